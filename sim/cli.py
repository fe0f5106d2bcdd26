"""``stockpile sim``: run a simulated yard and its emulated hardware."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import threading
from common.options import add_duration, non_negative_float, positive_float
from dataclasses import replace
from pathlib import Path

import zenoh

from schemas.times import format_time_ns, parse_time_ns
from security.event_keys import load_signing_key
from services.service import Stopper, log
from services.zenoh_config import DEFAULT_LISTEN, add_zenoh_arguments, config_from_args
from sim.adapters import ADAPTER_MODES, RealDevices
from sim.live import live_start, milestones
from sim.publish import ZenohSink
from sim.pty import PtyDevice
from sim.runner import Simulation
from sim.scenario import SCENARIOS, scenario_by_name
from sim.survey import (DEFAULT_DENSITY_PER_M2, DEFAULT_SD_HORIZONTAL_M, DEFAULT_SD_VERTICAL_M,
                        DroneSurveys, survey_stem)


def _wait_liveliness(session, key: str, timeout_s: float) -> bool:
    seen = threading.Event()
    sub = session.liveliness().declare_subscriber(key, lambda _s: seen.set(), history=True)
    try:
        return seen.wait(timeout_s)
    finally:
        sub.undeclare()


def load_source_keys(directory: str | Path) -> dict:
    """source -> signing key, for every ``SOURCE.sign.key`` in ``directory``."""
    folder = Path(directory)
    if not folder.is_dir():
        raise ValueError(f"--signing-keys: no directory {folder}")
    return {path.name[:-len(".sign.key")]: load_signing_key(path)
            for path in sorted(folder.glob("*.sign.key"))}


def site_time_ns(text: str) -> int:
    """argparse type: an absolute site time, ISO-8601 or integer UTC ns (as ``--valid-time``)."""
    try:
        return parse_time_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def unix_seconds(text: str) -> float:
    """argparse type: a finite wall-clock time, Unix seconds."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of Unix seconds: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"not a finite number of Unix seconds: {text!r}")
    return value


def check_live(args: argparse.Namespace, scenario) -> None:
    """One-line usage errors for ``--live-at`` and ``--live-wall`` (before anything opens)."""
    fail = args._parser.error
    if args.live_wall is not None and args.live_at is None:
        fail("--live-wall needs --live-at")
    if args.live_wall is not None and not args.speed > 0:
        fail("--live-wall paces the run: it needs --speed > 0")
    if args.live_at is None:
        return
    if args.adapters != "sim":
        fail("--live-at runs with --adapters sim only")
    end_ns = milestones(scenario, args.seed, _duration_h(args))["end_ns"]
    try:
        live_start(scenario, end_ns, args.live_at, args.live_wall, args.speed)
    except ValueError as exc:
        fail(f"--live-at: {exc}")


#: the packages a drone survey (``--survey-at``) needs (the [sim] extra has them)
SURVEY_IMPORTS = ("laspy", "lazrs", "pyproj")


def check_surveys(args: argparse.Namespace, scenario) -> None:
    """One-line usage errors for ``--survey-at`` (before anything opens): every time
    between the run's start and end, no two in one second, laspy, lazrs and pyproj installed."""
    fail = args._parser.error
    if not args.survey_at:
        for flag, given in (("--survey-density", args.survey_density),
                            ("--survey-seed", args.survey_seed)):
            if given is not None:
                fail(f"{flag} needs --survey-at")
        return
    if args.survey_density is not None and not math.isfinite(args.survey_density):
        fail(f"--survey-density must be finite, got {args.survey_density}")
    missing = [name for name in SURVEY_IMPORTS if importlib.util.find_spec(name) is None]
    if missing:
        fail(f"--survey-at needs laspy, lazrs and pyproj ({', '.join(missing)} missing): "
             "pip install 'stockpile-ledger[sim]'")
    end_ns = milestones(scenario, args.seed, _duration_h(args))["end_ns"]
    for t in args.survey_at:
        if not scenario.start_ns <= t <= end_ns:
            fail(f"--survey-at {format_time_ns(t)}: not between the run's start "
                 f"{format_time_ns(scenario.start_ns)} and end {format_time_ns(end_ns)}")
    stems = [survey_stem(t) for t in args.survey_at]
    if len(set(stems)) != len(stems):
        fail("--survey-at: two surveys in one second of site time (one file name)")


def _drone_surveys(args: argparse.Namespace, scenario, out: Path) -> DroneSurveys | None:
    """The run's drone surveys (``--survey-at``), each reported on stdout; None: none."""
    if not args.survey_at:
        return None
    seed = args.seed if args.survey_seed is None else args.survey_seed
    density = DEFAULT_DENSITY_PER_M2 if args.survey_density is None else args.survey_density
    return DroneSurveys(args.survey_at, out, scenario, seed, density,
                        report=lambda line: print(line, flush=True))


def _duration_h(args: argparse.Namespace) -> float | None:
    return None if args.duration is None else args.duration / 3600.0


def run_sim(args: argparse.Namespace) -> int:
    scenario = scenario_by_name(args.scenario)
    if args.assay_window is not None:
        if not (args.assay_window > 0 and math.isfinite(args.assay_window)):
            raise ValueError(f"--assay-window must be > 0 seconds, got {args.assay_window}")
        scenario = replace(scenario, assay_window_s=args.assay_window)
    if args.milestones:
        print(json.dumps(milestones(scenario, args.seed, _duration_h(args))), flush=True)
        return 0
    check_live(args, scenario)
    check_surveys(args, scenario)
    out = Path(args.out or f"sim-out/{args.scenario}-seed{args.seed}")
    sinks: list = []
    ptys: dict[str, object] = {}
    session = None
    devices = _open_devices(args, scenario, out)
    if args.pty:
        ptys = {"gnss": PtyDevice()} if devices else {"scanner": PtyDevice(), "gnss": PtyDevice()}
        if "scanner" in ptys:
            print(f"LMS200 scanner on {ptys['scanner'].path}", flush=True)
        print(f"GNSS receiver  on {ptys['gnss'].path}", flush=True)
    if args.zenoh:
        session = zenoh.open(config_from_args(args))
        sink = ZenohSink(session, scenario.site_id)
        sinks.append(sink)
        endpoints = args.listen or ([args._listen_default] if args._listen_default else [])
        print(f"publishing stockpile/{scenario.site_id}/@v1/** on zenoh "
              f"(listen {', '.join(endpoints) or '-'}; connect {', '.join(args.connect) or '-'})",
              flush=True)
        if args.wait_subscriber:
            print(f"waiting up to {args.wait_subscriber:g} s for a subscriber ...", flush=True)
            # the run's first event after its start: the clock, or an encoder reading
            first = (("clock", scenario.yard_sources()["clock"]) if scenario.emits_clock
                     else ("joint_reading", f"{scenario.machine_id}.encoders"))
            if not sink.wait_for_subscriber(*first, args.wait_subscriber):
                raise OSError("no zenoh subscriber matched the site's events in time")
        for key in args.wait_live:
            print(f"waiting up to {args.wait_live_timeout:g} s for {key} ...", flush=True)
            if not _wait_liveliness(session, key, args.wait_live_timeout):
                raise OSError(f"no liveliness token {key} appeared in time")
    if devices is not None and args.wait_lms511 > 0:
        print(f"waiting up to {args.wait_lms511:g} s for a client to turn the LMS511's "
              "output on ...", flush=True)
        if not devices.lms.wait_streaming(args.wait_lms511):
            raise OSError("no client turned the LMS511's scan output on in time")
    noise = "" if args.noise_seed is None else f", sensor noise seed {args.noise_seed}"
    print(f"simulating scenario {scenario.name!r}, seed {args.seed}{noise} -> {out}", flush=True)
    try:
        keys = load_source_keys(args.signing_keys) if args.signing_keys else {}
        sim = Simulation(scenario, args.seed, out, sinks=sinks, scanner_pty=ptys.get("scanner"),
                         gnss_pty=ptys.get("gnss"), scan_events=args.scan_events,
                         cut_surfaces=args.truth_cut_surfaces, noise_seed=args.noise_seed,
                         signing_keys=keys, adapters=args.adapters, devices=devices,
                         drone_surveys=_drone_surveys(args, scenario, out),
                         progress=lambda line: print(f"  {line}", file=sys.stderr, flush=True))
        if args.live_at is not None:
            print(f"fast-forwarding to the live moment {args.live_at} (UTC ns)"
                  + ("" if args.live_wall is None else f", live at wall {args.live_wall:.3f}"),
                  flush=True)
        stats = sim.run(duration_h=_duration_h(args), speed=args.speed,
                        idle_speed=args.idle_speed, live_at_ns=args.live_at,
                        live_wall_s=args.live_wall)
        for pty in ptys.values():  # the devices go quiet: their readers see the end
            pty.close()
        if session is not None:
            for name, producer in sim.producers.items():  # logged before the done line
                if name in sim.record_only:   # the devices' facts: the adapters publish them
                    continue
                log("sim", "published", source=producer.source, epoch=producer.epoch,
                    count=producer.seq)
        _print_summary(stats, out)
        if devices is not None:
            print(f"  {devices.summary()}", flush=True)
        if session is not None:
            if args.linger > 0:
                # keep the publishers' caches up until told to stop, so a ledger that
                # missed something can still recover it
                Stopper().wait(args.linger)
    finally:
        for pty in ptys.values():
            pty.close()
        if devices is not None:   # after the linger: the adapters have read everything
            devices.close()
        if session is not None:
            session.close()
    return 0


def _open_devices(args: argparse.Namespace, scenario, out: Path) -> RealDevices | None:
    """With ``--adapters real``: start the OPC UA PLC server and the LMS511, make the LIMS
    drop folder, and print where they are (the demo reads these lines); else None."""
    if args.adapters != "real":
        for flag, given in (("--plc-port", args.plc_port), ("--lms511-port", args.lms511_port),
                            ("--lims-dir", args.lims_dir), ("--opcua-cert", args.opcua_cert),
                            ("--opcua-key", args.opcua_key), ("--wait-lms511", args.wait_lms511)):
            if given:
                raise ValueError(f"{flag} is for --adapters real")
        return None
    if args.scan_events != "off":
        raise ValueError("--adapters real sends the scans to the LMS511: no --scan-events")
    devices = RealDevices(scenario, out, plc_port=args.plc_port, lms_port=args.lms511_port,
                          lims_dir=Path(args.lims_dir) if args.lims_dir else None,
                          certificate=args.opcua_cert, private_key=args.opcua_key).start()
    security = "Basic256Sha256 SignAndEncrypt" if args.opcua_cert else "no security"
    print(f"OPC UA server on {devices.plc.endpoint} ({security}; map {devices.plc_map_path})",
          flush=True)
    print(f"LIMS drop folder {devices.lims_dir} (map {devices.lims_map_path})", flush=True)
    print(f"LMS511 on tcp 127.0.0.1:{devices.lms.port} (cola-b)", flush=True)
    return devices


def _print_summary(stats, out: Path) -> None:
    """The run's summary on stdout (flushed: a supervisor waits for the ``done:`` line)."""
    truth = json.loads((out / "truth.json").read_text())
    world = truth["world"]
    print(f"done: {stats.site_s / 3600:.2f} site h in {stats.wall_s:.1f} s wall "
          f"({stats.events:,} events = {stats.events / max(stats.wall_s, 1e-9):,.0f}/s; "
          f"{stats.scans:,} scans, {stats.gga:,} GGA sentences)")
    if stats.live_at_ns is not None:
        print(f"  live from {stats.live_at_ns} (UTC ns) after a {stats.fast_forward_wall_s:.1f} s "
              f"fast-forward; {stats.live_late_s:.3f} s late")
    if stats.late_events:
        print(f"  pacing: {stats.late_events:,} events handled > 5 ms behind schedule "
              f"(largest lag {stats.max_lag_s:.2f} s real); device bytes and clock events "
              f"were late with them; the schedule moved on {stats.rebases:,} times, giving up "
              f"{stats.given_up_s:.1f} s real")
    print(f"  stacked {sum(p['true_tonnes'] for p in truth['passes']):,.3f} t in {stats.passes} passes; "
          f"reclaimed {sum(c['true_tonnes'] for c in truth['cuts']):,.3f} t in {stats.cuts} cuts; "
          f"{stats.assays} assays")
    repose = world.get("repose_angle_estimate_deg")
    print(f"  pile now {world['tonnes']:,.3f} t, {world['volume_m3']:,.3f} m3, "
          f"max height {world['max_height_m']:.3f} m, repose "
          + (f"{repose:.1f} deg" if repose is not None else "- (no pile yet)"))
    print(f"  files: events.jsonl, lms200.bin, gnss.nmea, truth.json, truth.npz in {out}")
    sys.stdout.flush()


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("sim", help="run the yard simulator (ground truth + emulated hardware)",
                              description="Run a simulated stockyard: stacking, reclaiming, "
                              "the laboratory, and the LMS200 scanner, GNSS receiver and encoders "
                              "with their errors. Writes events, raw device streams and truth.")
    p.add_argument("--scenario", choices=sorted(SCENARIOS), default="demo", help="default demo")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--noise-seed", type=int, metavar="N",
                   help="draw the sensors' noise (scanner, encoders, GNSS) from this seed: the "
                   "same world (belt, stacking, cuts, lab: --seed) measured again "
                   "(default: --seed)")
    p.add_argument("--assay-window", type=float, metavar="SECONDS",
                   help="the lab's sampling window (default: the scenario's: demo 60 s, bench-scale "
                   "30 s, full-scale 1200 s)")
    add_duration(p, "--duration", bare_unit="h",
                 help="stop after this much site time, with a unit: 90min, 2h ... (default: "
                 "until the last assay; a bare number, read as site hours, is deprecated)")
    p.add_argument("--idle-speed", type=non_negative_float, default=0.0, metavar="X",
                   help="with --speed: site seconds per wall second while no machine moves "
                   "(waiting for late assays); default: the same as --speed")
    p.add_argument("--speed", type=non_negative_float, default=0.0, metavar="X",
                   help="site seconds per wall second (default 0 = as fast as possible)")
    p.add_argument("--out", metavar="DIR", help="output folder (default sim-out/SCENARIO-seedN)")
    p.add_argument("--pty", action="store_true",
                   help="also write the scanner and GNSS streams to pseudo-terminals (paths printed)")
    p.add_argument("--zenoh", action="store_true", help="also publish the events on zenoh")
    p.add_argument("--signing-keys", metavar="DIR",
                   help="sign each source's events with DIR/SOURCE.sign.key where that file "
                   "exists (stockpile keys new --name SOURCE)")
    p.add_argument("--scan-events", choices=("off", "truth", "encoders"), default="off",
                   help="also emit, per scan, a 'scan' event (source MACHINE.scanner, as the "
                   "scanner service decodes the LMS200 telegram) and the scanner's "
                   "'frame_transform' (source MACHINE.poses, site -> MACHINE/scanner) at the "
                   "scan time, so a ledger needs no scanner or localizer service: truth = the "
                   "true scanner pose, encoders = forward kinematics of the latest encoder "
                   "reading; default off (no such events)")
    p.add_argument("--adapters", choices=ADAPTER_MODES, default="sim",
                   help="sim (default): publish every event; real: serve the machines' PLCs "
                   "over OPC UA, write the lab's results as LIMS files and send the scans "
                   "to an emulated LMS511 on TCP, for stockpile service plc, lab and "
                   "scanner --tcp (the lots, declarations and clock are still published; "
                   "with --pty only the GNSS pty)")
    p.add_argument("--plc-port", type=int, default=0, metavar="PORT",
                   help="with --adapters real: the OPC UA server's loopback port (default: a "
                   "free one)")
    p.add_argument("--lms511-port", type=int, default=0, metavar="PORT",
                   help="with --adapters real: the LMS511's loopback port (default: a free one)")
    p.add_argument("--lims-dir", metavar="DIR",
                   help="with --adapters real: the LIMS drop folder (default OUT/lims-drop)")
    p.add_argument("--opcua-cert", metavar="FILE",
                   help="with --adapters real: the OPC UA server's application certificate "
                   "(with --opcua-key: Basic256Sha256 SignAndEncrypt only; default: no "
                   "security, loopback)")
    p.add_argument("--opcua-key", metavar="FILE", help="its private key (PEM)")
    p.add_argument("--wait-lms511", type=float, default=0.0, metavar="SECONDS",
                   help="with --adapters real: start only once a client turned the LMS511's "
                   "output on (give up after SECONDS)")
    p.add_argument("--truth-cut-surfaces", action="store_true",
                   help="also keep the true surface at each cut's start in truth.npz "
                   "(cut_surface_z) and the parcels as stacked at the first cut's start "
                   "(first_cut_thickness, first_cut_time_ns; for "
                   "bench/projector_truth.py --explain)")
    p.add_argument("--wait-subscriber", type=float, default=0.0, metavar="SECONDS",
                   help="with --zenoh: start only once a subscriber listens (give up after SECONDS)")
    p.add_argument("--wait-live", action="append", default=[], metavar="KEY",
                   help="with --zenoh: start only once a liveliness token matching KEY exists "
                   "(e.g. stockpile/demo/@live/scanner/**; repeatable)")
    p.add_argument("--wait-live-timeout", type=float, default=60.0, metavar="S",
                   help="how long --wait-live waits, seconds (default 60)")
    p.add_argument("--live-at", type=site_time_ns, metavar="T",
                   help="live mode: the world as a plain run of the same scenario and seed, "
                   "fast-forwarded (no sensors, nothing published) to site time T "
                   "(ISO-8601 or integer UTC ns, between the start and the end), then paced "
                   "at --speed with the scenario's live sensor rates; every source starts a "
                   "new epoch (T's second) at seq 0 and the declarations are not repeated")
    p.add_argument("--live-wall", type=unix_seconds, metavar="UNIX_S",
                   help="with --live-at and --speed: the wall-clock time (Unix seconds) site "
                   "time T happens at; the run waits for it after the fast-forward, then maps "
                   "site time t to UNIX_S + (t - T) / speed (without --idle-speed) and keeps "
                   "to it (behind, it catches up rather than moving its schedule on), so runs "
                   "given the same T and UNIX_S keep in step; reached late, it starts at once "
                   "and says how late on stderr")
    p.add_argument("--survey-at", type=site_time_ns, action="append", default=[], metavar="T",
                   help="when site time reaches T (ISO-8601 or integer UTC ns, between the "
                   "start and the end), write a drone survey of the true surface: "
                   "OUT/survey-<YYYYmmddTHHMMSSZ>.laz (mine grid, the scenario's EPSG), "
                   ".json (its truth: time, seed, noise, true volume) and .truth.npz (the "
                   "true surface); changes no other output (repeatable)")
    p.add_argument("--survey-density", type=positive_float, metavar="PER_M2",
                   help=f"--survey-at's points per square metre (default "
                   f"{DEFAULT_DENSITY_PER_M2:g}; noise sd {DEFAULT_SD_VERTICAL_M:g} m "
                   f"vertical, {DEFAULT_SD_HORIZONTAL_M:g} m horizontal)")
    p.add_argument("--survey-seed", type=int, metavar="N",
                   help="draw --survey-at's points and noise from this seed (default: --seed)")
    p.add_argument("--milestones", action="store_true",
                   help="print the run's timetable as one JSON object (UTC ns: start_ns, "
                   "stacking_end_ns, survey_end_ns, reclaim_start_ns, first_cut_start_ns = "
                   "null as the first cut is planned on the true pile, default_end_ns, "
                   "end_ns with --duration) and exit without simulating")
    p.add_argument("--linger", type=float, default=0.0, metavar="S",
                   help="with --zenoh: after the run keep publishing caches up for S seconds or "
                   "until SIGTERM (a ledger can still recover missed events)")
    add_zenoh_arguments(p, listen_default=DEFAULT_LISTEN)
    p.set_defaults(func=run_sim, _parser=p)


