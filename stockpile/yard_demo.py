"""The end-to-end demo: the simulated yard and every service as separate processes.

:func:`run_yard_demo` starts (through :class:`stockpile.orchestrate.Supervisor`)::

    zenoh router (this process, loopback)
      <- ledger service      stockpile service ledger --clock events
      <- localizer           stockpile service localizer --clock events
      <- simulator           stockpile sim --pty --zenoh   (waits for the services)
      <- scanner             stockpile service scanner --device <sim's LMS200 pty>
      <- gnss                stockpile service gnss --device <sim's GNSS pty>

(``adapters="real"``: the simulator serves its PLCs over OPC UA, the lab's LIMS files and
an LMS511 on TCP, and the PLC, lab and TCP scanner adapters carry them in instead:
:mod:`stockpile.demo_adapters`)

runs the scenario to its end, stops the producers, waits until the ledger holds
every event they say they published, stops the ledger, and checks the result
(:func:`check_exactly_once`, :func:`localizer_rmse`); then folds the ledger into the
layered model and sets it beside the simulator's truth (:func:`projector_vs_truth`).
Outputs in ``out_dir``: ``ledger.duckdb``, ``sim/`` (truth.json, truth.npz, the raw
streams), ``logs/``, ``summary.json``.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from schemas.events import decode_payload
from schemas.times import format_time_ns

from ledger import open_ledger
from projector.query import project
from services.ledger_client import LedgerClient
from sim.kinematics import Machine, wheel_centre
from sim.scenario import scenario_by_name
from stockpile.demo_adapters import (
    adapter_members, expected_counts, opcua_certificates, sim_options, start_adapters,
    wait_delivered)
from stockpile.demo_signing import money_sources, prepare_signing
from stockpile.demo_survey import reconcile_survey, say_survey, survey_time_ns
from stockpile.orchestrate import Supervisor, fresh_ledger_path

SITE_OF_SCENARIO = "capelambert"
MACHINE = "bwr1"


def _say(text: str) -> None:
    print(text, flush=True)


def wait_ledgered(client: LedgerClient, published: dict[str, tuple[int, int]],
                  timeout_s: float) -> dict[str, Any]:
    """Block until the ledger holds ``count`` events (or gaps) of every published source."""
    deadline = time.monotonic() + timeout_s
    while True:
        stats = client.stats()
        missing = {source: n - stats["per_source"].get(source, 0)
                   for source, (_epoch, n) in published.items()
                   if stats["per_source"].get(source, 0) < n}
        if not missing:
            return stats
        if stats.get("open_gaps", 0) and time.monotonic() > deadline - timeout_s / 2:
            return stats  # gaps are recorded: waiting longer will not fill them
        if time.monotonic() > deadline:
            raise TimeoutError(f"the ledger is still missing events after {timeout_s:g} s: {missing}")
        time.sleep(0.2)


def check_exactly_once(store, published: dict[str, tuple[int, int]]) -> list[dict[str, Any]]:
    """Per source: published count vs ledgered rows, duplicates, sequence coverage, gaps."""
    rows_by_source: dict[str, list[int]] = {}
    epochs: dict[str, set[int]] = {}
    for r in store.read():
        rows_by_source.setdefault(r.source, []).append(r.seq)
        epochs.setdefault(r.source, set()).add(r.epoch)
    gaps = store.gaps(open_only=True)
    report = []
    for source, (epoch, n) in sorted(published.items()):
        seqs = rows_by_source.get(source, [])
        report.append({
            "source": source, "published": n, "ledgered": len(seqs),
            "duplicates": len(seqs) - len(set(seqs)),
            "exact": sorted(seqs) == list(range(n)) and (n == 0 or epochs.get(source) == {epoch}),
            "open_gaps": [(g.first_seq, g.last_seq) for g in gaps if g.source == source],
        })
    unknown = sorted(set(rows_by_source) - set(published))
    for source in unknown:
        report.append({"source": source, "published": None, "ledgered": len(rows_by_source[source]),
                       "duplicates": 0, "exact": False, "open_gaps": []})
    return report


def _machine_from_ledger(store):

    for r in store.read(types=["machine_declared"]):
        msg = decode_payload("machine_declared", r.payload)
        if msg.machine_id == MACHINE:
            return Machine(**{f.name: getattr(msg, f.name) for f in fields(Machine)})
    raise LookupError(f"no machine_declared for {MACHINE}")


def _joints_of(store, type_name: str, source_suffix: str) -> np.ndarray:
    out = []
    for r in store.read(types=[type_name]):
        if not r.source.endswith(source_suffix):
            continue
        msg = decode_payload(type_name, r.payload)
        out.append((r.valid_time_ns, msg.travel_m, msg.slew_rad, msg.luff_rad))
    return np.asarray(out, dtype=np.float64).reshape(-1, 4)


def localizer_rmse(store, truth_npz: Path) -> dict[str, float]:
    """Wheel-centre RMSE (m) of the localizer's estimates and of the raw encoders vs truth.

    Truth joints are interpolated at each estimate's valid time; both sides go
    through the same forward kinematics (docs/domain.md §3).
    """

    machine = _machine_from_ledger(store)
    truth = np.load(truth_npz)["joints"]
    t_true = truth[:, 0]
    out: dict[str, float] = {}
    for label, type_name, suffix in (("localizer", "joint_estimate", ".localizer"),
                                     ("encoders", "joint_reading", ".encoders")):
        est = _joints_of(store, type_name, suffix)
        inside = (est[:, 0] >= t_true[0]) & (est[:, 0] <= t_true[-1]) if len(est) else []
        est = est[inside] if len(est) else est
        if len(est) == 0:
            continue
        true_j = [np.interp(est[:, 0], t_true, truth[:, k]) for k in (1, 2, 3)]
        c_true = np.asarray(wheel_centre(machine, *true_j))
        c_est = np.asarray(wheel_centre(machine, est[:, 1], est[:, 2], est[:, 3]))
        err = np.linalg.norm((c_est - c_true).reshape(3, -1), axis=0)
        out[f"{label}_rmse_m"] = float(np.sqrt(np.mean(err ** 2)))
        out[f"{label}_samples"] = int(len(est))
    return out


def scan_timing(store, truth_npz: Path) -> dict[str, float]:
    """Each ledgered scan's valid time minus its true scan time: median, p95, p99 of |error|, ms.

    The scanner publishes every intact telegram in order once its site clock is known,
    so the ledgered scans are the last ``n`` true scans, give or take the first few
    (dropped while the clock was unknown) and any lost to a bad CRC at the end; the
    alignment is the shift near the tail that makes the errors smallest.  Matching by
    order, not by the nearest true time, keeps an error larger than half the scan
    period visible.
    """
    true_t = np.sort(np.load(truth_npz)["scanner_poses"][:, 0]).astype(np.float64)
    t = np.asarray([r.valid_time_ns for r in store.read(types=["scan"])], dtype=np.float64)
    t.sort()
    n = len(t)
    if n == 0 or len(true_t) < n:
        return {}
    best = None
    tail = len(true_t) - n
    for shift in range(max(0, tail - 5), tail + 1):
        err_ms = (t - true_t[shift:shift + n]) / 1e6
        score = float(np.median(np.abs(err_ms)))
        if best is None or score < best[0]:
            best = (score, err_ms)
    err_ms = best[1]
    return {"scan_time_error_median_ms": float(np.median(err_ms)),
            "scan_time_abs_error_median_ms": float(np.median(np.abs(err_ms))),
            "scan_time_abs_error_p95_ms": float(np.percentile(np.abs(err_ms), 95)),
            "scan_time_abs_error_p99_ms": float(np.percentile(np.abs(err_ms), 99)),
            "scans": int(n)}


def pile_book(store) -> dict[str, Any]:
    """The pile by belt scales and assays as known at the end (beside the layered model).

    Tonnes in = stack passes' belt tonnes, out = reclaim cuts' belt tonnes.  Grade =
    the stacked tonnes weighted by each lot's mean assayed grade (FINAL over
    PROVISIONAL, superseded assays dropped), the lot's planned grade where unassayed.
    """
    passes_lot: dict[str, str] = {}
    stacked: dict[str, float] = {}
    lots: dict[str, dict[str, float]] = {}
    assays: dict[str, Any] = {}
    superseded: set[str] = set()
    reclaimed = 0.0
    for r in store.read(types=["lot_declared", "stack_started", "stack_ended", "reclaim_cut",
                               "assay"]):
        msg = decode_payload(r.type, r.payload)
        if r.type == "lot_declared":
            lots[msg.lot_id] = dict(msg.planned_grade)
        elif r.type == "stack_started":
            passes_lot[msg.pass_id] = msg.lot_id
        elif r.type == "stack_ended":
            lot = passes_lot.get(msg.pass_id, "?")
            stacked[lot] = stacked.get(lot, 0.0) + msg.tonnes
        elif r.type == "reclaim_cut":
            reclaimed += msg.tonnes
        elif r.type == "assay":
            assays[msg.assay_id] = msg
            if msg.supersedes:
                superseded.add(msg.supersedes)
    grade_by_lot: dict[str, dict[str, float]] = {}
    assayed_lots = set()
    for lot, planned in lots.items():
        current = [a for a in assays.values() if a.lot_id == lot and a.assay_id not in superseded]
        if current:
            assayed_lots.add(lot)
            keys = set().union(*(a.analytes.keys() for a in current))
            grade_by_lot[lot] = {k: float(np.mean([a.analytes[k] for a in current if k in a.analytes]))
                                 for k in keys}
        else:
            grade_by_lot[lot] = planned
    total_in = sum(stacked.values())
    grade: dict[str, float] = {}
    if total_in > 0:
        for analyte in ("Fe", "SiO2", "Al2O3", "P", "LOI"):
            w = [(t, grade_by_lot.get(lot, {}).get(analyte)) for lot, t in stacked.items()]
            w = [(t, g) for t, g in w if g is not None]
            if w:
                grade[analyte] = sum(t * g for t, g in w) / sum(t for t, _ in w)
    assayed = sum(t for lot, t in stacked.items() if lot in assayed_lots)
    return {"stacked_t": total_in, "reclaimed_t": reclaimed, "pile_t": total_in - reclaimed,
            "grade_pct": grade, "assayed_fraction": assayed / total_in if total_in else 0.0,
            "assays": len(assays), "superseded": len(superseded)}


def projector_vs_truth(store, truth: dict[str, Any]) -> dict[str, Any]:
    """The layered model as of the end (``stockpile project``) beside the simulator's truth.

    Pile tonnes, each cut's tonnes and Fe grade (all assays known), and what the fold's
    ground reference did: the scanner heights it corrected from the ground each scan
    saw (on the live path, the localizer's height error).
    """
    pile_id = truth["scenario"].get("pile_id", "P1")
    started = time.monotonic()
    state = project(store, pile_id)
    fold_s = time.monotonic() - started
    world_t = float(truth["world"]["tonnes"])
    true_cuts = {c["cut_id"]: c for c in truth["cuts"]}
    cuts = []
    for c in state.cuts:
        tc = true_cuts.get(c.cut_id)
        if tc is None or tc["true_tonnes"] <= 0:
            continue
        fe = c.grade.get("Fe", math.nan)
        cuts.append({"cut_id": c.cut_id, "tonnes": c.tonnes, "true_tonnes": tc["true_tonnes"],
                     "tonnes_error_pct": 100 * (c.tonnes / tc["true_tonnes"] - 1),
                     "fe_pct": fe, "true_fe_pct": tc["grade"]["Fe"],
                     "fe_error_pp": fe - tc["grade"]["Fe"]})
    counters = state.counters
    fused = counters.get("scans_fused", 0)
    return {"pile_id": pile_id, "fold_s": fold_s, "tonnes": state.tonnes,
            "true_tonnes": world_t,
            "tonnes_error_pct": 100 * (state.tonnes / world_t - 1) if world_t > 0 else math.nan,
            "flagged_tonnes": sum(d.tonnes for d in state.deposits if d.flagged),
            "cuts": cuts, "scans_fused": fused,
            "scans_ground_referenced": counters.get("scans_ground_referenced", 0),
            "ground_offset_mean_mm": counters.get("ground_offset_abs_sum_mm", 0) / max(fused, 1),
            "ground_offset_max_mm": counters.get("ground_offset_max_mm", 0)}


def _say_projector(result: dict[str, Any]) -> None:
    """Print :func:`projector_vs_truth`'s result: the pile, the height corrections, the cuts."""
    r = result
    _say(f"   pile {r['tonnes']:,.0f} t (true {r['true_tonnes']:,.0f} t, "
         f"{r['tonnes_error_pct']:+.2f} %); in flagged deposits {r['flagged_tonnes']:,.0f} t; "
         f"folded in {r['fold_s']:.0f} s")
    _say(f"   scanner heights referenced to the ground in {r['scans_ground_referenced']:,} of "
         f"{r['scans_fused']:,} scans: corrected by {r['ground_offset_mean_mm']:.0f} mm on "
         f"average (largest {r['ground_offset_max_mm']:,} mm), the localizer's error")
    if r["cuts"]:
        _say(f"   {'cut':<10} {'tonnes':>9} {'true':>9} {'error':>8}   {'Fe %':>6} {'true':>6} "
             f"{'error':>7}")
        for c in r["cuts"]:
            _say(f"   {c['cut_id']:<10} {c['tonnes']:>9,.1f} {c['true_tonnes']:>9,.1f} "
                 f"{c['tonnes_error_pct']:>+7.2f}%   {c['fe_pct']:>6.2f} "
                 f"{c['true_fe_pct']:>6.2f} {c['fe_error_pp']:>+6.2f}pp")


def _wait_recorded(recorder, events: int, timeout_s: float) -> None:
    """Block until the recorder's status line counts ``events`` recorded events."""
    deadline = time.monotonic() + timeout_s
    while True:
        counts = [int(r.get("recorded", 0)) for r in recorder.log_records()
                  if r.get("msg") == "status"]
        if counts and counts[-1] >= events:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"the recorder holds {counts[-1] if counts else 0} of {events} "
                               f"events after {timeout_s:g} s")
        time.sleep(0.2)


def _wait_done(sim, timeout_s: float, every_s: float = 15.0) -> str:
    """Wait for the simulator's ``done:`` line, echoing its latest progress line meanwhile."""
    deadline = time.monotonic() + timeout_s
    shown = ""
    while True:
        try:
            return sim.wait_stdout(lambda l: l.startswith("done:"),
                                   min(every_s, max(0.1, deadline - time.monotonic())))
        except TimeoutError:
            if time.monotonic() >= deadline:
                raise
        progress = [line.strip() for line in sim.log_path.read_text(errors="replace").splitlines()
                    if line.strip().startswith("site time")]
        if progress and progress[-1] != shown:
            shown = progress[-1]
            _say(f"   {shown}")


#: the process demo's children: certificate name -> role (also the event source they
#: publish under, for the publishing roles)
DEMO_MEMBERS = {"ledger": "ledger", "recorder": "recorder", f"{MACHINE}.localizer": "localizer",
                "sim": "replay", f"{MACHINE}.scanner": "scanner", f"{MACHINE}.gnss": "gnss"}


def _common(yard: Supervisor, site: str, name: str) -> list[str]:
    """Options every service child of the demo takes: site, status period, its link."""
    return ["--site", site, "--status-period", "5", *yard.client_args_for(name)]


def _start_services(yard: Supervisor, ledger_path: Path, site: str, record: Path | None,
                    signing: list[str]) -> None:
    """Start the ledger (``signing``: its signing options), the recorder (when ``record``
    is given) and the localizer."""
    yard.start("ledger", ["service", "ledger", "--ledger", str(ledger_path), "--clock", "events",
                          *signing, *_common(yard, site, "ledger")])
    yard.wait_live("ledger")
    if record is not None:
        yard.start("recorder", ["service", "recorder", "--out", str(record), "--clock", "events",
                                "--site", site, "--status-period", "1",
                                *yard.client_args_for("recorder")])
        yard.wait_live("recorder")
    yard.start("localizer", ["service", "localizer", "--machine", MACHINE,
                             *_common(yard, site, f"{MACHINE}.localizer")])


def _start_sim_and_sensors(yard: Supervisor, sim_dir: Path, *, site: str,
                           scenario: str, seed: int, speed: float, idle_speed: float,
                           duration_h: float | None, signing: list[str],
                           real: list[str] | None = None, survey_ns: int | None = None):
    """Start the simulator on pseudo-terminals and the scanner and GNSS services on its ports
    (``real``: the simulator's options of the real devices; then no serial scanner)."""
    live = f"stockpile/{site}/@live"
    sim_args = ["sim", "--scenario", scenario, "--seed", str(seed), "--out", str(sim_dir),
                "--pty", "--zenoh", "--speed", str(speed), "--idle-speed", str(idle_speed),
                "--wait-subscriber", "60", "--linger", "600",
                "--wait-live", f"{live}/scanner/**", "--wait-live", f"{live}/gnss/**",
                "--wait-live", f"{live}/localizer/**", *signing, *yard.client_args_for("sim"),
                *(real or [])]
    if duration_h is not None:
        sim_args += ["--duration", f"{duration_h * 3600:g}s"]
    if survey_ns is not None:
        sim_args += ["--survey-at", format_time_ns(survey_ns)]
    sim = yard.start("sim", sim_args)
    scanner_path = "LMS511 (TCP)"
    if real is None:
        scanner_path = sim.wait_stdout(lambda l: l.startswith("LMS200 scanner on"), 60).split()[-1]
        yard.start("scanner", ["service", "scanner", "--device", scanner_path, "--clock",
                               "events", "--source", f"{MACHINE}.scanner",
                               *_common(yard, site, f"{MACHINE}.scanner")])
    gnss_path = sim.wait_stdout(lambda l: l.startswith("GNSS receiver"), 60).split()[-1]
    yard.start("gnss", ["service", "gnss", "--device", gnss_path, "--clock", "events",
                        "--source", f"{MACHINE}.gnss", *_common(yard, site, f"{MACHINE}.gnss")])
    _say(f"   scanner on {scanner_path}, GNSS on {gnss_path}; simulating at {speed:g}x "
         f"({idle_speed:g}x while the yard waits for assays) ...")
    return sim


def _wait_sim_end(sim) -> tuple[str, float]:
    """Wait for the scenario's end; the simulator's pacing line and its largest lag (s)."""
    done_line = _wait_done(sim, 6 * 3600)
    _say(f"   simulator {done_line}")
    sim.wait_stdout(lambda l: l.strip().startswith("stacked"), 30)  # the pacing line is before it
    pacing = next((l.strip() for l in list(sim.stdout_lines) if l.strip().startswith("pacing:")),
                  "")
    if pacing:
        _say(f"   simulator {pacing}")
    lag = re.search(r"largest lag ([0-9.]+) s", pacing)
    return pacing, float(lag.group(1)) if lag else 0.0


def _drain_and_stop(yard: Supervisor, site: str, record: Path | None, declared: int = 0,
                    adapters: tuple[str, ...] = (), expected: dict[str, int] | None = None
                    ) -> tuple[dict[str, tuple[int, int]], dict[str, int | None]]:
    """Stop the producers, wait until the ledger holds all they published, stop the ledger.
    The recorder holds what went over Zenoh: all but the ``declared`` events written into
    the ledger before the services started.  The ``adapters`` (children) are stopped once
    the ledger holds the ``expected`` events per source, or after a minute.

    Returns what each source says it published ``{source: (epoch, count)}`` and each
    process's exit code.
    """
    for name in ("scanner", "gnss"):  # their ports went quiet: they end on their own
        if name not in adapters and yard.wait_exit(name, 30) is None:
            yard.stop(name)
    client = LedgerClient(yard.session, site, timeout_s=60)
    if adapters:
        short = wait_delivered(client, expected or {}, 60)
        _say(f"   the ledger lacks events the devices handed out: {short}" if short else
             "   the ledger holds every event the devices handed out")
        for name in adapters:
            yard.stop(name)
    published: dict[str, tuple[int, int]] = {}
    for name in dict.fromkeys(("sim", "scanner", "gnss", *adapters)):
        published.update(yard.children[name].published())
    wait_ledgered(client, published, 300)
    rc_localizer = yard.stop("localizer")
    published.update(yard.children["localizer"].published())
    wait_ledgered(client, published, 120)
    if record is not None:
        _wait_recorded(yard.children["recorder"], client.stats()["events"] - declared, 60)
        rc_recorder = yard.stop("recorder")
    rc = {"localizer": rc_localizer, "sim": yard.stop("sim"), "ledger": yard.stop("ledger")}
    if record is not None:
        rc["recorder"] = rc_recorder
    rc.update({n: yard.children[n].process.returncode for n in ("scanner", "gnss", *adapters)})
    return published, rc


def _check_ledger(ledger_path: Path, published: dict[str, tuple[int, int]],
                  sim_dir: Path) -> dict[str, Any]:
    """Everything the summary reports, read from the finished ledger and the simulator's truth."""
    with open_ledger(ledger_path, read_only=True) as store:
        checks = {"stats": store.stats(), "exact": check_exactly_once(store, published),
                  "verify": store.verify(), "gaps": store.gaps(open_only=True),
                  "quarantine": store.quarantine(), "book": pile_book(store),
                  "rmse": localizer_rmse(store, sim_dir / "truth.npz"),
                  "timing": scan_timing(store, sim_dir / "truth.npz"),
                  "truth": json.loads((sim_dir / "truth.json").read_text())}
        _say("\n== folding the ledger into the layered model (stockpile project) ...")
        checks["model"] = projector_vs_truth(store, checks["truth"])
    return checks


def _say_ledger(stats, exact: list[dict[str, Any]], verify, gaps, quarantine) -> None:
    """Print the events per type and the exactly-once check per source."""
    _say("\n== events per type in the ledger")
    for type_name, n in sorted(stats.per_type.items(), key=lambda kv: -kv[1]):
        _say(f"   {type_name:<16} {n:>8,}")
    _say("\n== exactly once: published by each source vs held by the ledger")
    for row in exact:
        mark = "ok" if row["exact"] and not row["open_gaps"] else "MISMATCH"
        _say(f"   {row['source']:<16} published {row['published'] or 0:>7,}  ledgered "
             f"{row['ledgered']:>7,}  duplicates {row['duplicates']}  {mark}")
    _say(f"   gaps open: {len(gaps)}; quarantined: {len(quarantine)}; chain "
         f"{'verified' if verify.ok else 'BROKEN'} ({verify.rows_checked:,} rows, "
         f"{verify.signatures:,} signatures checked)")
    for entry in quarantine[:5]:
        _say(f"   quarantined {entry.type} from {entry.source}: {entry.reason[:100]}")


def _vs(measured: float, true: float) -> str:
    return f"true {true:,.0f} t, {(measured / true - 1) * 100:+.2f} %" if true > 0 else \
        f"true {true:,.0f} t"


def _say_pile_book(book: dict[str, Any], truth: dict[str, Any]) -> None:
    """Print :func:`pile_book`'s result beside the simulator's truth."""
    _say("\n== the pile by belt scales and assays as known at the end")
    world = truth["world"]
    true_in = sum(p["true_tonnes"] for p in truth["passes"])
    true_out = sum(c["true_tonnes"] for c in truth["cuts"])
    _say(f"   stacked {book['stacked_t']:,.0f} t by the belt scales ({_vs(book['stacked_t'], true_in)}), "
         f"reclaimed {book['reclaimed_t']:,.0f} t ({_vs(book['reclaimed_t'], true_out)}), "
         f"pile {book['pile_t']:,.0f} t")
    _say(f"   the simulated pile holds {world['tonnes']:,.0f} t now, including any pass still "
         "running when the run ended")
    _say("   grade " + ", ".join(f"{k} {v:.2f} %" for k, v in book["grade_pct"].items())
         + f" (assayed fraction {book['assayed_fraction']:.2f}; truth Fe {world['grade']['Fe']:.2f} %, "
         f"SiO2 {world['grade']['SiO2']:.2f} %)")


def _say_localizer(rmse: dict[str, float], timing: dict[str, float], speed: float,
                   pacing: str) -> None:
    """Print the localizer's RMSE and the scans' timing error against the simulator's truth."""
    _say("\n== localizer against the simulator's truth (wheel centre)")
    if "localizer_rmse_m" in rmse:
        _say(f"   UKF {rmse['localizer_rmse_m']:.3f} m RMSE over {rmse['localizer_samples']:,} "
             f"estimates; encoders alone {rmse.get('encoders_rmse_m', float('nan')):.3f} m")
    else:
        _say("   no joint estimates in the ledger")
    if timing:
        _say(f"   scan valid times - true scan times over {timing['scans']:,} scans: median "
             f"{timing['scan_time_error_median_ms']:+.1f} ms, |error| median "
             f"{timing['scan_time_abs_error_median_ms']:.1f} ms, p95 "
             f"{timing['scan_time_abs_error_p95_ms']:.1f} ms, p99 "
             f"{timing['scan_time_abs_error_p99_ms']:.1f} ms site time "
             f"(at {speed:g}x a real-time delay of 1 ms is {speed:g} ms of site time)")
        if pacing:
            _say("   (the simulator fell behind its schedule at times, see its pacing line; it "
                 "then moves its schedule on, and a service that reads late on a busy machine "
                 "dates its scans late)")


def run_yard_demo(out_dir: Path, *, seed: int = 1, speed: float = 40.0, idle_speed: float = 2000.0,
                  duration_h: float | None = None, scenario: str = "demo",
                  site: str = SITE_OF_SCENARIO, record: Path | None = None,
                  insecure: bool = False, adapters: str = "sim") -> int:
    """Run the yard end to end; print the summary; return 0 when every check holds.
    ``adapters="real"``: through the PLC, lab and TCP scanner adapters (module docstring).

    The links are mutual TLS with the access control of each child's role, on a
    throw-away PKI in ``<out>/pki`` (plain TCP on loopback with ``insecure``).

    ``record`` (off by default) also runs ``stockpile service recorder`` writing the
    site's events to that MCAP file (site-clock log times); it is stopped once it holds
    as many events as the ledger.
    """
    started = time.monotonic()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    ledger_path = fresh_ledger_path(out_dir / "ledger.duckdb")
    sim_dir = out_dir / "sim"
    sc = scenario_by_name(scenario)
    real = adapters == "real"
    members = {} if insecure else {**DEMO_MEMBERS, **(adapter_members(
        sc.machine_id, sc.stacker_id) if real else {})}
    sim_opcua, adapter_opcua = opcua_certificates(out_dir) if real else ([], [])
    signing = prepare_signing(out_dir, ledger_path, money_sources(sc.machine_id, sc.stacker_id),
                              sc.start_ns)
    survey_ns = survey_time_ns(sc, seed, duration_h)
    with Supervisor(out_dir, site=site, members=members) as yard:
        link = "plain TCP" if insecure else f"mutual TLS, access by role, PKI in {yard.pki}"
        _say(f"== the yard as processes: zenoh router on {yard.endpoint} (loopback, scouting "
             f"off, {link}); logs in {yard.logs}")
        _say(f"   signed events: assays, lots, stacking and reclaim events and the yard's "
             f"declarations, keys in {out_dir / 'keys'}; the ledger requires them")
        _start_services(yard, ledger_path, site, record, signing.ledger_args)
        sim = _start_sim_and_sensors(yard, sim_dir, site=site, scenario=scenario,
                                     seed=seed, speed=speed, idle_speed=idle_speed,
                                     duration_h=duration_h, signing=signing.sim_args,
                                     survey_ns=survey_ns,
                                     real=sim_options(site, sc.machine_id, sc.stacker_id,
                                                      sim_opcua) if real else None)
        names = start_adapters(yard, sim, machine=sc.machine_id, stacker=sc.stacker_id,
                               keys=out_dir / "keys" / "sources", opcua=adapter_opcua,
                               common=lambda name: _common(yard, site, name)) if real else []
        pacing, sim_max_lag_s = _wait_sim_end(sim)
        expected = expected_counts(sim, sc.machine_id, sc.stacker_id) if real else None
        declared = sum(n for _epoch, n in signing.published.values())
        published, rc = _drain_and_stop(yard, site, record, declared, tuple(names), expected)
        published.update(signing.published)

    c = _check_ledger(ledger_path, published, sim_dir)
    stats, exact, verify, gaps, quarantine = (c["stats"], c["exact"], c["verify"], c["gaps"],
                                              c["quarantine"])
    book, rmse, timing, model = c["book"], c["rmse"], c["timing"], c["model"]
    _say_ledger(stats, exact, verify, gaps, quarantine)
    _say_pile_book(book, c["truth"])
    _say_localizer(rmse, timing, speed, pacing)
    _say("\n== the layered model as of the end (stockpile project) against the simulator's truth")
    _say_projector(model)
    survey = None
    if survey_ns is not None:
        _say("\n== the drone survey against the model (stockpile survey import, audit survey)")
        survey = reconcile_survey(ledger_path, sim_dir, model["pile_id"], survey_ns)
        say_survey(survey, ledger_path, model["pile_id"])
    ok = (verify.ok and not gaps and all(r["exact"] and not r["open_gaps"] for r in exact)
          and all(code == 0 for code in rc.values()))
    summary = {"ok": ok, "exit_codes": rc, "published": published, "exactly_once": exact,
               "signed_events": verify.signatures,
               "per_type": stats.per_type, "open_gaps": len(gaps), "quarantined": len(quarantine),
               "verify_ok": verify.ok, "pile_book": book, "projector": model, "survey": survey,
               "localizer": rmse,
               "scan_timing": timing, "speed": speed, "sim_pacing": pacing,
               "sim_max_lag_s": sim_max_lag_s, "wall_s": time.monotonic() - started}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=list))
    _say(f"\n{'all checks hold' if ok else 'CHECKS FAILED'}: exit codes {rc}; "
         f"done in {time.monotonic() - started:.0f} s -> {out_dir}/summary.json")
    _say(f"Try:\n  stockpile ledger stats --ledger {ledger_path}\n"
         f"  stockpile project --ledger {ledger_path} --pile {model['pile_id']}\n"
         f"  stockpile ledger export --ledger {ledger_path} --types reclaim_cut assay")
    return 0 if ok else 1
