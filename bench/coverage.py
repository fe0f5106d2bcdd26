"""Calibration of the standard deviations: how often the truth lies within 1 and 2 sd.

    .venv/bin/python bench/coverage.py --scenario demo --runs 20 --keep /tmp/cov
    .venv/bin/python bench/coverage.py --scenario demo --runs 20 --keep /tmp/cov \\
        --set unseen_sd_m=0.3 --set corr_cells=20          # the kept folds, another config

Each run is one draw of the simulator, as ``bench/projector_truth.py`` runs it
(``stockpile sim --scan-events truth``, the scans placed by the localizer's poses unless
``--poses truth``), imported by ``stockpile ledger import --clock events``'s code into an
in-memory ledger (the same events and recorded times as its DuckDB file, faster), then
:func:`projector.query.project` with everything known.  A draw is a world seed
(``--first-seed`` onwards: the belt's grades, the lab's errors and the sensors' noise) or,
with ``--noise-draws N``, N draws of the sensors' noise on each world (``stockpile sim
--noise-seed``: the same world measured again).  For every cut and the pile it forms
``z = (ours - truth) / sd`` of the tonnes and of Fe, with the truth from the simulator's
``truth.json`` (a cut's ``true_tonnes`` and ``grade``, the world's ``tonnes`` and
``grade`` at the end), and prints per scenario and figure: the number of figures, the
share within 1 sd and within 2 sd (targets about 68 % and 95 %; accepted 60-76 % and
90-98 %), the mean z (a bias shows as a mean away from 0), the rms z (1 for a
calibrated sd), and the median sd beside the median absolute error (for a normal error,
the median |error| is 0.67 sd).

The folded state of each run is kept beside it (``<run>.state.pkl``, with the grade
inputs), so ``--set NAME=VALUE`` (fields of :class:`projector.uncertainty.UncertaintyConfig`)
recomputes the figures of kept runs without folding again.  ``--duration`` (site hours)
stops each run early: the demo's cuts all end by about 1.25 h, before most assays arrive
(the cuts are then graded from the lots' plans).
"""

from __future__ import annotations

import argparse
import ast
import json
import pickle
import sys
import tempfile
import time
from dataclasses import fields
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))   # projector_truth
sys.path.insert(0, str(ROOT))             # before bench/: its projector.py is not the package

from _coverage_tables import FIGURES, print_table, z_rows  # noqa: E402
from projector_truth import POSES, ledger_input, run_name, simulate  # noqa: E402
from ledger import open_ledger  # noqa: E402
from ledger.clock import EventClock  # noqa: E402
from ledger.importing import import_lines  # noqa: E402
from projector.query import grade_inputs, project, summarise  # noqa: E402
from projector.uncertainty import UncertaintyConfig  # noqa: E402

def parse_set(items: list[str]) -> UncertaintyConfig:
    """An :class:`UncertaintyConfig` from ``NAME=VALUE`` items (a Python literal each)."""
    names = {f.name for f in fields(UncertaintyConfig)}
    kwargs = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or name not in names:
            raise SystemExit(f"--set wants NAME=VALUE with NAME one of {', '.join(sorted(names))}"
                             f", got {item!r}")
        kwargs[name] = ast.literal_eval(value)
    return UncertaintyConfig(**kwargs)


def folded(scenario: str, seed: int, noise_seed: int | None, out: Path, duration_h,
           poses: str) -> tuple:
    """``(folded state, lots, assays, valid ns, known ns, truth)`` of one run, from its kept
    pickle or simulated, imported and folded now (then kept)."""
    cache = out / f"{run_name(scenario, seed, noise_seed)}-{poses}.state.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    sim_dir, truth = simulate(scenario, seed, out, duration_h, noise_seed=noise_seed)
    # the in-memory ledger, imported by `stockpile ledger import --clock events`'s code
    with open_ledger(":memory:", EventClock()) as store, \
            open(ledger_input(sim_dir, truth, poses), "rb") as lines:
        import_lines(store, lines)
        p = project(store, truth["scenario"].get("pile_id", "P1"))
        lots, assays = grade_inputs(store, p.valid_time_ns, p.known_time_ns)
    kept = (p.state, lots, assays, p.valid_time_ns, p.known_time_ns, truth)
    cache.write_bytes(pickle.dumps(kept, protocol=5))
    return kept


def z_scores(kept: tuple, config: UncertaintyConfig) -> dict[str, list[tuple]]:
    """Per figure, ``(label, ours, truth, sd, z)`` of one run's cuts and pile."""
    state, lots, assays, v, k, truth = kept
    return z_rows(summarise(state, lots, assays, valid_time_ns=v, known_time_ns=k,
                            uncertainty=config), truth)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", action="append",
                    help="a simulator scenario (repeatable; default demo)")
    ap.add_argument("--runs", type=int, default=20, help="worlds per scenario (default 20)")
    ap.add_argument("--first-seed", type=int, default=1, help="the first world's seed")
    ap.add_argument("--noise-draws", type=int, default=1, metavar="N",
                    help="draws of the sensors' noise per world (default 1: the seed's own)")
    ap.add_argument("--duration", type=float, default=None, help="site hours (default: all)")
    ap.add_argument("--poses", choices=tuple(POSES), default="localizer")
    ap.add_argument("--keep", metavar="DIR", help="keep (and reuse) the runs in DIR")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="an UncertaintyConfig field (repeatable)")
    ap.add_argument("--json", metavar="FILE", help="also write every z and the tables here")
    args = ap.parse_args(argv)
    config = parse_set(args.set)
    print(f"uncertainty config: {config}", flush=True)
    result = {"config": repr(config), "scenarios": {}}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.keep or tmp)
        out.mkdir(parents=True, exist_ok=True)
        for scenario in args.scenario or ["demo"]:
            rows: dict[str, list[tuple]] = {f: [] for f in FIGURES}
            draws = [(s, None if d == 0 else 1000 * d + s)
                     for s in range(args.first_seed, args.first_seed + args.runs)
                     for d in range(args.noise_draws)]
            t0 = time.perf_counter()
            for i, (seed, noise) in enumerate(draws, 1):
                kept = folded(scenario, seed, noise, out, args.duration, args.poses)
                for figure, found in z_scores(kept, config).items():
                    rows[figure] += [(f"seed{seed}-noise{noise or seed}", *r) for r in found]
                n_cuts = len(rows["cut tonnes"])
                print(f"  {scenario} run {i}/{len(draws)} (seed {seed}, noise "
                      f"{noise or seed}): {n_cuts} cuts so far, "
                      f"{time.perf_counter() - t0:.0f} s", flush=True)
            table = print_table(scenario, rows, len(draws))
            result["scenarios"][scenario] = {"table": table, "rows": rows}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
