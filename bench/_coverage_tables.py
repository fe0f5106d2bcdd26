"""Coverage of the standard deviations: z-scores of a projection's cuts and pile against
the simulator's truth, and the table of how often they lie within 1 and 2 sd (targets
about 68 % and 95 %; accepted 60-76 % and 90-98 %).  Shared by ``bench/coverage.py`` and
``bench/projector_truth.py --matrix``.
"""

from __future__ import annotations

import math

import numpy as np

FIGURES = ("cut tonnes", "cut Fe", "pile tonnes", "pile Fe")


def z_rows(p, truth: dict) -> dict[str, list[tuple]]:
    """Per figure, ``(label, ours, truth, sd, z)`` of a projection's cuts and pile (``p``:
    a :class:`projector.query.PileState`; ``truth``: the simulator's ``truth.json``)."""
    out: dict[str, list[tuple]] = {f: [] for f in FIGURES}

    def add(figure, label, ours, true, sd):
        z = (ours - true) / sd if sd > 0 else math.nan
        out[figure].append((label, ours, true, sd, z))

    ours = {c.cut_id: c for c in p.cuts}
    for c in truth["cuts"]:
        mine = ours.get(c["cut_id"])
        if mine is None:
            continue
        add("cut tonnes", c["cut_id"], mine.tonnes, c["true_tonnes"], mine.tonnes_sd)
        add("cut Fe", c["cut_id"], mine.grade.get("Fe", math.nan), c["grade"]["Fe"],
            mine.grade_sd.get("Fe", math.nan))
    world = truth["world"]
    add("pile tonnes", "pile", p.tonnes, world["tonnes"], p.tonnes_sd)
    add("pile Fe", "pile", p.grade.get("Fe", math.nan), world["grade"]["Fe"],
        p.grade_sd.get("Fe", math.nan))
    return out


def coverage(zs: list[float]) -> dict:
    """n, share within 1 and 2 sd (%), mean and rms z of finite z values."""
    z = np.array([v for v in zs if math.isfinite(v)])
    if z.size == 0:
        return {"n": 0, "within_1sd_pct": math.nan, "within_2sd_pct": math.nan,
                "mean_z": math.nan, "rms_z": math.nan}
    return {"n": int(z.size), "within_1sd_pct": float(np.mean(np.abs(z) <= 1) * 100),
            "within_2sd_pct": float(np.mean(np.abs(z) <= 2) * 100),
            "mean_z": float(z.mean()), "rms_z": float(np.sqrt(np.mean(z * z)))}


def verdict(c: dict) -> str:
    if c["n"] == 0:
        return "-"
    ok = 60 <= c["within_1sd_pct"] <= 76 and 90 <= c["within_2sd_pct"] <= 98
    return "PASS" if ok else "MISS"


def print_table(scenario: str, rows: dict[str, list[tuple]], runs: int) -> dict:
    """The coverage table of one scenario; ``rows``: per figure, ``(run, label, ours,
    truth, sd, z)``."""
    print(f"\n== {scenario}: {runs} runs")
    print(f"{'figure':<12} {'n':>5} {'within 1 sd':>12} {'within 2 sd':>12} {'mean z':>8} "
          f"{'rms z':>7} {'median sd':>10} {'median |err|':>12}  verdict")
    table = {}
    for figure in FIGURES:
        c = coverage([r[5] for r in rows[figure]])
        sds = [r[4] for r in rows[figure] if math.isfinite(r[4])]
        c["median_sd"] = float(np.median(sds)) if sds else math.nan
        errs = [abs(r[2] - r[3]) for r in rows[figure] if math.isfinite(r[2] - r[3])]
        c["median_abs_err"] = float(np.median(errs)) if errs else math.nan
        table[figure] = c
        print(f"{figure:<12} {c['n']:>5} {c['within_1sd_pct']:>11.1f}% "
              f"{c['within_2sd_pct']:>11.1f}% {c['mean_z']:>+8.2f} {c['rms_z']:>7.2f} "
              f"{c['median_sd']:>10.3g} {c['median_abs_err']:>12.3g}  {verdict(c)}")
    return table
