"""A kept run with its true scanner poses moved along the rail by Gauss-Markov noise.

    .venv/bin/python bench/along_rail_noise.py /work/ptm/demo-seed2 --sd-m 0.1 --tau-s 60 \\
        --seed 7 --out /tmp/smear/gm10
    .venv/bin/python bench/projector_truth.py --scenario demo --seed 2 --poses truth \\
        --keep /tmp/smear/gm10

Reads a run kept by ``bench/projector_truth.py --keep`` and writes a copy of it to
``OUT/<run name>``: the same scans, truth and sensor streams (hard links), and
``events.jsonl`` with each scanner pose's north coordinate (along the rail, the
pile's length) moved by a first-order Gauss-Markov error of sd ``--sd-m`` (m) and
correlation time ``--tau-s`` (s), drawn from ``--seed``.  Nothing else changes, so
projecting the copy on the true-pose path measures what an along-rail pose error alone
does to each cut (docs/fidelity.md, "The first cut").
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

#: the run's files other than events.jsonl, linked unchanged
LINKED = ("gnss.nmea", "lms200.bin", "truth.json", "truth.npz")
POSE_SOURCE = '"bwr1.poses"'


def perturb(src: Path, dst: Path, sd_m: float, tau_s: float, seed: int) -> int:
    """Write ``dst`` (a run folder) from ``src`` with the along-rail error; the poses moved."""
    if sd_m < 0 or tau_s <= 0:
        raise ValueError("--sd-m must be >= 0 and --tau-s > 0")
    dst.mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        if (src / name).exists() and not (dst / name).exists():
            os.link(src / name, dst / name)
    rng = np.random.default_rng(seed)
    error_m, last_s, moved = 0.0, None, 0
    with open(src / "events.jsonl") as lines, open(dst / "events.jsonl", "w") as out:
        for line in lines:
            if POSE_SOURCE in line and '"frame_transform"' in line:
                event = json.loads(line)
                t_s = event["valid_time_ns"] / 1e9
                if last_s is None:
                    error_m = rng.normal(0.0, sd_m)
                else:
                    a = math.exp(-(t_s - last_s) / tau_s)
                    error_m = a * error_m + rng.normal(0.0, sd_m * math.sqrt(max(1 - a * a, 0)))
                last_s = t_s
                translation = event["body"].setdefault("translation", {})
                translation["y"] = translation.get("y", 0.0) + error_m
                line = json.dumps(event, separators=(",", ":")) + "\n"
                moved += 1
            out.write(line)
    return moved


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder kept by projector_truth.py --keep")
    ap.add_argument("--sd-m", type=float, required=True, help="the error's sd, m")
    ap.add_argument("--tau-s", type=float, required=True, help="its correlation time, s")
    ap.add_argument("--seed", type=int, required=True, help="the draw")
    ap.add_argument("--out", type=Path, required=True, help="the folder to write the run in")
    args = ap.parse_args(argv)
    try:
        moved = perturb(args.run, args.out / args.run.name, args.sd_m, args.tau_s, args.seed)
    except (OSError, ValueError) as exc:
        print(f"along_rail_noise: {exc}", file=sys.stderr)
        return 2
    print(f"{moved:,} scanner poses moved; written {args.out / args.run.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
