"""The localizer's scanner poses against the simulator's, by phase of a kept run.

    .venv/bin/python bench/pose_error.py /tmp/pt/demo-seed1
    .venv/bin/python bench/pose_error.py /tmp/pt/demo-seed1 --along 0,3,6,10,20,40,60

Reads a run kept by ``bench/projector_truth.py --keep`` (the folder holding
``events.jsonl`` with the simulator's true scanner poses, ``events-localizer.jsonl``
with the localizer's, and ``truth.json``), puts the localizer's scanner position at
each true pose's time (linear between its estimates) and prints the error (east,
north, up; m): its mean (the slow part a scan's surface is shifted by) and sd, over the
whole run, before the first cut (the stacking phase) by where along the rail the
scanner stood, during each cut and in the minute after it, and per two minutes before
the first cut.  North is along the rail (the pile's length), east across it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def scanner_positions(path: Path, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (ns, (N,)) and positions (m, (N, 3)) of the scanner frames of ``source``
    in a JSON lines file, sorted by time."""
    t, p = [], []
    needle = f'"source":"{source}"'
    with path.open(encoding="utf-8") as f:
        for line in f:
            if needle not in line or '"frame_transform"' not in line:
                continue
            event = json.loads(line)
            body = event["body"]
            if not body.get("child_frame_id", "").endswith("/scanner"):
                continue
            tr = body.get("translation", {})
            t.append(event["valid_time_ns"])
            p.append([tr.get("x", 0.0), tr.get("y", 0.0), tr.get("z", 0.0)])
    t_ns, xyz = np.asarray(t, np.int64), np.asarray(p, float).reshape(-1, 3)
    order = np.argsort(t_ns, kind="stable")
    return t_ns[order], xyz[order]


def _line(name: str, err: np.ndarray) -> str:
    if len(err) == 0:
        return f"{name:<30} no scans"
    mean, sd = err.mean(axis=0), err.std(axis=0)
    return (f"{name:<30} {len(err):>6}  mean {mean[0]:+.3f} {mean[1]:+.3f} {mean[2]:+.3f}"
            f"  sd {sd[0]:.3f} {sd[1]:.3f} {sd[2]:.3f}")


def report(run: Path, machine_id: str, along_m: list[float]) -> None:
    """Print the scanner's error by phase (see the module docstring)."""
    truth = json.loads((run / "truth.json").read_text())
    t_true, p_true = scanner_positions(run / "events.jsonl", f"{machine_id}.poses")
    t_loc, p_loc = scanner_positions(run / "events-localizer.jsonl", f"{machine_id}.localizer")
    if len(t_true) == 0 or len(t_loc) == 0:
        raise ValueError("no true or no localizer scanner poses in the run")
    est = np.stack([np.interp(t_true, t_loc, p_loc[:, k]) for k in range(3)], axis=1)
    err = est - p_true
    cuts = truth["cuts"]
    first_cut = cuts[0]["t0_ns"] if cuts else int(t_true[-1]) + 1
    print(f"scanner position error, localizer - truth (m: east, north, up), {run}")
    print(f"{'':<30} {'scans':>6}  {'mean e/n/u':<22}  sd e/n/u")
    print(_line("whole run", err))
    before = t_true < first_cut
    print(_line("before the first cut", err[before]))
    y = p_true[:, 1]
    for lo, hi in zip(along_m[:-1], along_m[1:]):
        print(_line(f"  scanner north {lo:g}..{hi:g} m", err[before & (y >= lo) & (y < hi)]))
    for cut in cuts:
        during = (t_true >= cut["t0_ns"]) & (t_true <= cut["t1_ns"])
        after = (t_true > cut["t1_ns"]) & (t_true <= cut["t1_ns"] + 60 * 10**9)
        print(_line(f"during {cut['cut_id']}", err[during]))
        print(_line("  the minute after it", err[after]))
    print("before the first cut, per two minutes (mean error; scanner north, m):")
    minute = (t_true - t_true[0]) // (60 * 10**9)
    for m in np.unique(minute[before] // 2 * 2):
        sel = before & (minute // 2 * 2 == m)
        e = err[sel].mean(axis=0)
        print(f"  {int(m):>4} min  {e[0]:+.3f} {e[1]:+.3f} {e[2]:+.3f}   north {y[sel].mean():6.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a run folder kept by projector_truth.py --keep")
    ap.add_argument("--machine", default="bwr1", help="the reclaimer (default bwr1)")
    ap.add_argument("--along", default="-5,0,3,6,10,20,40,60,70",
                    help="bin edges along the rail for the stacking phase (m)")
    args = ap.parse_args(argv)
    try:
        along = [float(v) for v in args.along.split(",")]
        report(args.run, args.machine, along)
    except (OSError, ValueError, KeyError) as exc:
        print(f"pose_error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
