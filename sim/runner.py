"""Runs a scenario: the world, its machines, emulated hardware and the laboratory in site time.

Output of one run (all deterministic for a given scenario, seed and noise seed; the
noise seed, by default the seed, draws only the sensors' noise, so another one measures
the same world again):

``events.jsonl``
    every event the yard publishes on Zenoh (declarations, clock, joint readings,
    stacking and reclaim events, lots, assays), as canonical JSON lines;
    with ``scan_events`` (below) also the scans and the scanner's poses;
``lms200.bin``
    the byte stream of the LMS200 scanner (0xB0 telegrams), as written to its
    pseudo-terminal;
``gnss.nmea``
    the GNSS receiver's GGA sentences, as written to its pseudo-terminal;
``truth.json`` / ``truth.npz``
    ground truth: the pile (surface, layer tops, parcels), every pass and cut, the
    true joints, scanner poses and antenna positions over time; with ``cut_surfaces``
    (CLI ``--truth-cut-surfaces``) also the true surface at each cut's start.
``survey-<YYYYmmddTHHMMSSZ>.laz`` / ``.json`` / ``.truth.npz``
    with ``drone_surveys`` (CLI ``--survey-at``): a drone survey of the true surface at
    each time and its truth (:mod:`sim.survey`); no other output changes.

Time is site time (UTC ns).  The site clock is published as ``clock`` events every
``clock_period_s``; at ``speed`` > 0 the run is paced against the wall clock
(``speed`` site seconds per wall second), at 0 it runs as fast as it can.  A ``clock``
event is also published where the yard starts or stops working (where a paced run
changes from ``speed`` to ``idle_speed`` or back), so that a service that dates its
readings between ticks has the corner of the site-time line; while a machine works the
ticks come every ``clock_busy_period_s`` if set, and a run that writes telegrams to a
scanner pty ticks right before each one.  A paced run that falls more than
``REBASE_S`` behind its schedule (a loaded machine) moves the schedule on rather than
catching up in a burst.

Scan events (``scan_events``, CLI ``--scan-events``).  A yard gets its ``scan`` events
from the scanner service (which decodes the LMS200 byte stream) and the scanner's
``frame_transform`` events from the localizer.  For testing consumers on a ledger built
from the simulator alone, the run can emit both itself, into every sink:

``"off"`` (default)
    none; every output is byte-identical to a run without the option.
``"truth"``
    per scan, one ``frame_transform`` (source ``<machine>.poses``, parent ``site``, child
    ``<machine>/scanner``) with the true scanner pose the scan was ray-cast from, and one
    ``scan`` (source ``<machine>.scanner``), both with the scan's valid time (the moment
    its telegram starts on the line, as the scanner service reconstructs it).
``"encoders"``
    the same, but the pose is the forward kinematics of the latest ``joint_reading``
    at or before the scan time (the encoders read at that very time are included): what a
    yard without a localizer would have.

The scan is the LMS200 telegram written to ``lms200.bin`` decoded and turned into a
``foxglove.LaserScan`` by :func:`services.scanner.scan_message` with the scanner
service's defaults (frame ``<machine>/scanner``, angles from the value count, ranges in
metres quantised to the telegram's unit, NaN for no-return and error codes).  Both
events are emitted after everything else the yard does at that instant (the frame
transform first); no random numbers are drawn for them, so the other streams do not
change.  Do not combine them with a scanner service or localizer on the same yard: the
ledger would get both versions (the localizer's transforms have source
``<machine>.localizer``; a scanner service's scans the same source, another epoch).

Cut faces: once the wheel has passed, a cut's walls do what the scenario's material does
(:mod:`sim.material`; the reclaim's handlers are :class:`sim.reclaim_run.ReclaimRun`): slump
to the angle of repose (the default), stand steeper, stand and fail later as one slide, or
stand. A run that ends on its own (no ``duration_h``) ends a minute after the last assay
or a minute after the last delayed failure, whichever is later.

Live mode (``live_at_ns``, CLI ``--live-at``; :mod:`sim.live`): the same world, fast-forwarded
without sensors or output to a live moment, then paced from a given wall-clock moment, with
every producer in a new epoch.

Adapters (``adapters``, CLI ``--adapters``): ``"sim"`` (default) publishes as above; ``"real"``
hands the machines', lab's and scanner's facts to a real yard's devices (:mod:`sim.adapters`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from devices import lms200
from devices.nmea import format_gga
from schemas.times import NS_PER_H, NS_PER_S
from security.event_keys import SigningKey
from services.scanner import default_frame_id, scan_field, scan_message
from sim import messages
from sim.encoders import EncoderModel
from sim.gnss import GnssModel
from sim.adapters import LMS511_FIELD_DEG, RealDevices, check_adapters
from sim.grades import ANALYTES, LabResult
from sim.live import (LATE_S, REBASE_S, LiveStart, Pacer, live_schedule0, live_start,
                      prefixed_assays, rates_of)
from sim.material import RNG_STREAM, CutFaces
from sim.motion import Motion, move_speed_m_s, patrol_legs, patrol_pose, scanner_pose
from sim.publish import JsonlSink, Producer, Sink
from sim.records import (
    LAB_WINDOW_FE, flow_grade, lab_schedule, lab_windows, write_truth)
from sim.reclaim_run import CUT_SUBSWEEPS, ReclaimRun
from sim.rng import named_rng
from sim.scanner import BEAM_ERROR_CODE, ScannerModel
from sim.scenario import Scenario
from sim.survey import DroneSurveys
from sim.timetable import CHUNK_S, Milestones, Queue, stacking_plan
from sim.world import Grid, World

__all__ = ["CUT_SUBSWEEPS", "LATE_S", "REBASE_S", "SCAN_EVENTS", "RunStats", "Simulation"]

#: values of ``Simulation.scan_events`` / ``--scan-events`` (see the module docstring)
SCAN_EVENTS = ("off", "truth", "encoders")

@dataclass
class RunStats:
    events: int = 0
    scans: int = 0
    gga: int = 0
    lms200_bytes: int = 0
    gnss_bytes: int = 0
    cuts: int = 0
    passes: int = 0
    assays: int = 0
    wall_s: float = 0.0
    site_s: float = 0.0
    dropped_pty_bytes: int = 0
    #: paced runs: events handled more than LATE_S (real time) behind their schedule,
    #: and the largest lag, real seconds (a slow step; beyond REBASE_S the schedule moves on)
    late_events: int = 0
    max_lag_s: float = 0.0
    #: times the schedule moved on (REBASE_S), and the real seconds it gave up in all
    rebases: int = 0
    given_up_s: float = 0.0
    #: live runs: the live moment (UTC ns), the wall seconds the fast-forward to it took,
    #: and how late (wall s) it was reached after its wall time (0: on time)
    live_at_ns: int | None = None
    fast_forward_wall_s: float = 0.0
    live_late_s: float = 0.0


@dataclass
class Simulation(ReclaimRun):
    """One run of a scenario.  ``run()`` does everything; see the module docstring."""

    scenario: Scenario
    seed: int
    out_dir: Path
    sinks: list[Sink] = field(default_factory=list)
    scanner_pty: object | None = None
    gnss_pty: object | None = None
    progress: Callable[[str], None] | None = None
    #: keep every scan's cast ranges and beam status (tests; memory grows with the run)
    record_scans: bool = False
    #: "off", "truth" or "encoders": emit ``scan`` and scanner ``frame_transform`` events
    #: (see the module docstring)
    scan_events: str = "off"
    #: keep the true surface at each cut's start (``cut_surface_z`` in truth.npz, float32,
    #: one (ny, nx) grid per cut in the order of truth.json's cuts): what the cut acted on;
    #: and the parcels as stacked, at the first cut's start (``first_cut_thickness`` m,
    #: float32, and ``first_cut_time_ns``, both (slots, ny, nx))
    cut_surfaces: bool = False
    #: the seed the sensors' noise is drawn from (scanner ranges and mixed pixels,
    #: encoders, GNSS); None: ``seed`` (set so on construction).  Another value
    #: measures the same world again (belt, stacking, reclaiming and the lab follow
    #: ``seed`` alone), so the spread of a projector's errors over noise seeds is what
    #: the measurement noise alone causes
    noise_seed: int | None = None
    #: source -> the key its events are signed with (sources not named: unsigned)
    signing_keys: dict[str, SigningKey] = field(default_factory=dict)
    #: "sim" or "real": who carries the machines', the lab's and the scanner's facts (see
    #: the module docstring); ``devices``: the real devices (made when not given)
    adapters: str = "sim"
    devices: RealDevices | None = None
    #: drone surveys of the true surface to take during the run (:mod:`sim.survey`)
    drone_surveys: DroneSurveys | None = None

    def __post_init__(self) -> None:
        sc = self.scenario
        if self.scan_events not in SCAN_EVENTS:
            raise ValueError(f"scan_events must be one of {', '.join(SCAN_EVENTS)}, "
                             f"got {self.scan_events!r}")
        self.real = check_adapters(self.adapters, self.scan_events, self.scanner_pty)
        if self.real and self.devices is None:
            self.devices = RealDevices(sc, self.out_dir).start()
        self.out_dir = Path(self.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = JsonlSink(self.out_dir / "events.jsonl")
        self._last_tick_ns = -1   # the newest clock event's site time
        self.producers = self._producers()
        margin = max(sc.pile_width_m * 0.25, 4 * sc.deposition_cell_m)
        self.grid = Grid.covering(sc.pile_origin_x_m - margin, sc.pile_origin_x_m + sc.pile_width_m + margin,
                                  sc.pile_origin_y_m - margin, sc.pile_origin_y_m + sc.pile_length_m + margin,
                                  sc.deposition_cell_m, ground_z_m=sc.ground_z_m)
        # a sixth grade channel carries the laboratory's Fe of the window each step of
        # belt flow falls in (LAB_WINDOW_FE): a cut's tonnage-weighted mean of it is the Fe
        # a projector with the true composition and true deposition times would report
        # from the assays, one grade per window
        self.world = World(self.grid, sc.repose_deg, analytes=ANALYTES + (LAB_WINDOW_FE,))
        self.machine = sc.machine
        self.noise_seed = self.seed if self.noise_seed is None else int(self.noise_seed)
        self.encoders = EncoderModel(rng=named_rng(self.noise_seed, "encoders"))
        self.gnss = GnssModel(sc.datum_lat_deg, sc.datum_lon_deg, sc.datum_alt_m,
                              rng=named_rng(self.noise_seed, "gnss"))
        # mm mode reaches 8 m: the laboratory pile (an LMS200's; an LMS511 sends mm always)
        self.unit_mm = sc.pile_width_m < 5.0 and not self.real
        fov, step = LMS511_FIELD_DEG if self.real else (sc.scan_fov_deg, sc.scan_step_deg)
        self.scanner = ScannerModel(fov_deg=fov, step_deg=step, any_step=self.real,
                                    max_range_m=8.0 if self.unit_mm else 80.0,
                                    unit_mm=self.unit_mm, rng=named_rng(self.noise_seed, "scanner"))
        if self.scan_events != "off":
            # the scanner service's defaults: frame from the source, field from the value
            # count (the scanner model only takes LMS200 fields, so they are the cast ones)
            self.scan_frame_id = default_frame_id(self.producers["scans"].source)
            self.scan_field = scan_field(self.scanner.n_beams)
        #: the latest encoder reading: (t_ns, travel m, slew rad, luff rad) as published
        self.last_reading: tuple[int, float, float, float] | None = None
        self.rng_belt = named_rng(self.seed, "belt")
        self.rng_stack = named_rng(self.seed, "stacking")
        self.faces = CutFaces(sc.material, self.world, self.machine,
                              named_rng(self.seed, RNG_STREAM))
        self.lms_file = (self.out_dir / "lms200.bin").open("wb")
        self.gnss_file = (self.out_dir / "gnss.nmea").open("wb")
        self.stats = RunStats()
        self.truth_joints: list[tuple[int, float, float, float]] = []
        self.truth_cut_surfaces: list[np.ndarray] = []
        self.truth_first_cut_parcels: dict[str, np.ndarray] = {}
        self.truth_scans: list[tuple] = []
        self.truth_antenna: list[tuple] = []
        self.passes: list[dict] = []
        self.cuts: list[dict] = []
        self.lab_results: list[LabResult] = []
        self.cast_scans: list[tuple[np.ndarray, np.ndarray]] = []
        self.motion = Motion(sc.start_ns, sc.start_ns, *([self._patrol_pose(sc.pile_origin_y_m)] * 2))

    def _producers(self) -> dict[str, Producer]:
        """One producer per source of the yard, all writing to events.jsonl and the sinks."""
        sc = self.scenario
        all_sinks = [self.jsonl, *self.sinks]
        epoch = sc.start_ns // NS_PER_S
        keys = self.signing_keys
        self.record_only = ("encoders", "stacker", "reclaimer", "lab") if self.real else ()
        yard = sc.yard_sources()
        if not sc.emits_clock:
            del yard["clock"]
        producers = {name: Producer(source, epoch,
                                    [self.jsonl] if name in self.record_only else all_sinks,
                                    keys.get(source)) for name, source in (
            *yard.items(), ("encoders", f"{sc.machine_id}.encoders"),
            ("stacker", f"{sc.stacker_id}.plc"), ("reclaimer", f"{sc.machine_id}.plc"))}
        if self.scan_events != "off":
            producers["scans"] = Producer(f"{sc.machine_id}.scanner", epoch, all_sinks)
            producers["poses"] = Producer(f"{sc.machine_id}.poses", epoch, all_sinks)
        return producers

    # -- geometry of the machines ---------------------------------------------------------

    @property
    def move_m_s(self) -> float:
        """Travel speed between cuts and on the patrol's run-on (m/s), see
        :func:`sim.motion.move_speed_m_s`."""
        return move_speed_m_s(self.machine)

    def _patrol_pose(self, travel_m: float) -> tuple[float, float, float]:
        return patrol_pose(self.scenario, self.machine, travel_m)

    def _scanner_pose(self, joints) -> tuple[np.ndarray, np.ndarray]:
        return scanner_pose(self.machine, self.scenario.scanner_offset_m, joints)

    # -- the run ----------------------------------------------------------------------------

    def run(self, *, duration_h: float | None = None, speed: float = 0.0,
            idle_speed: float = 0.0, live_at_ns: int | None = None,
            live_wall_s: float | None = None) -> RunStats:
        """Run the scenario until ``duration_h`` site hours (default: a minute after the
        last assay or after the last delayed failure of a cut's faces, if later), paced at
        ``speed`` site seconds per wall second (0: as fast as possible; ``idle_speed``
        while no machine moves); writes every output.  With ``live_at_ns`` (UTC ns) a live
        run: unpaced, without sensors and output up to then, paced from the wall time
        ``live_wall_s`` (Unix s; default: when it gets there) on (:mod:`sim.live`)."""
        sc = self.scenario
        self._wall0 = wall0 = time.monotonic()
        t0 = sc.start_ns
        plan = stacking_plan(sc)
        self.belts, results = lab_schedule(sc, plan, self.rng_belt)
        self.lab_results = prefixed_assays(results, sc.source_prefix)
        ms = Milestones.of(sc, plan, self.move_m_s, self.lab_results, duration_h)
        self.live = live_start(sc, ms.end_ns, live_at_ns, live_wall_s, speed)
        if self.live is not None and self.real:
            raise ValueError("a live run feeds no real devices: use adapters 'sim'")
        self.rates = rates_of(sc, self.live)
        self.pacer = Pacer(speed, idle_speed, self.stats)
        if self.live is None:
            self.pacer.start(wall0)
        else:
            self.stats.live_at_ns = self.live.at_ns
            for producer in self.producers.values():   # silent until the live moment
                producer.muted = self.live.at_ns > t0
        for msg in messages.declarations(sc, self.machine, t0):
            self.producers["config"].emit(msg)
        queue = self._schedule(plan, ms)
        self.stacking_until = ms.survey_end
        self.reclaiming = False
        self.lab_windows = lab_windows(self.lab_results, "Fe")
        # a run that ends on its own goes on past its delayed failures (sim.reclaim_run)
        self.end_ns, self.end_fixed = ms.end_ns, duration_h is not None
        self._work_through(queue)
        if self.drone_surveys is not None:   # those after the last event handled
            self.drone_surveys.take_due(self.end_ns + 1, self.world)
        self.stats.site_s = (self.end_ns - t0) / NS_PER_S
        self.stats.wall_s = time.monotonic() - wall0
        self._finish()
        return self.stats

    def _schedule(self, plan: list[dict], ms: Milestones) -> Queue:
        """The queue at the start: the live moment, lots, passes in chunks, assays, the
        first cut, the clock and sensors (from the live moment in a live run), and the
        survey after the last pass."""
        sc = self.scenario
        t0 = sc.start_ns
        queue = Queue()
        at = queue.at
        if self.live is not None:   # first of everything at its time
            at(self.live.at_ns, "live", self.live)
        for p in plan:
            first_of_lot = p is next(q for q in plan if q["lot_index"] == p["lot_index"])
            if first_of_lot:
                at(p["t0"] - 60 * NS_PER_S, "lot", p["lot"])
            at(p["t0"], "pass_start", p)
            n_chunks = max(1, round(sc.pass_duration_s / CHUNK_S))
            for k in range(n_chunks):
                at(p["t0"] + (p["t1"] - p["t0"]) * (k + 1) // n_chunks, "chunk", (p, k, n_chunks))
            at(p["t1"], "pass_end", p)
        for r in self.lab_results:
            at(r.reported_ns, "assay", r)
        at(ms.reclaim_start, "reclaim", (0, 0, None))
        sensors_from = t0 if self.live is None else self.live.at_ns
        if sc.emits_clock:
            at(sensors_from, "clock", int(sc.clock_period_s * NS_PER_S))
        at(sensors_from, "encoder", None)
        at(sensors_from, "gnss", None)
        at(sensors_from, "scan", None)
        last_forward = plan[-1]["y1"] >= plan[-1]["y0"]
        survey_to = sc.pile_origin_y_m + (0.0 if last_forward else sc.pile_length_m)
        at(ms.run_on_end, "patrol", (ms.survey_end, survey_to))
        return queue

    def _work_through(self, queue: Queue) -> None:
        """Handle the queue's events up to ``self.end_ns``, paced by ``self.pacer`` (see
        :meth:`run`)."""
        t0 = self.scenario.start_ns
        next_report = time.monotonic() + 10.0
        t_prev, busy = t0, None
        while queue:
            t, _, kind, payload = queue.pop()
            if t > self.end_ns:
                # telegrams of scans taken before the end are still on the wire: send them
                for t_late, _o, kind_late, data in sorted(queue.items + [(t, _, kind, payload)]):
                    if kind_late in ("telegram", "lms511"):
                        getattr(self, f"_on_{kind_late}")(t_late, data, queue.at)
                break
            if self.drone_surveys is not None:   # the world before anything at t happens
                self.drone_surveys.take_due(t, self.world)
            if self.progress is not None and time.monotonic() >= next_report:
                next_report = time.monotonic() + 10.0
                self.progress(f"site time {(t - t0) / NS_PER_H:6.2f} of "
                              f"{(self.end_ns - t0) / NS_PER_H:.2f} h: "
                              f"{self.jsonl.count:,} events, {self.stats.scans:,} scans, "
                              f"{self.stats.passes} passes, {self.stats.cuts} cuts")
            was_busy, busy = busy, self._busy(t_prev)
            if was_busy is not None and busy != was_busy:
                # a tick where the yard starts or stops working (a paced run changes pace
                # there), so that a service dating its readings between ticks (the
                # scanner) has the corner of the site-time line
                self._tick(t_prev)
            # pacing site time against the wall clock; idle stretches (no machine moves,
            # only late assays to wait for) run at idle_speed
            self.pacer.wait(t - t_prev, busy)
            t_prev = t
            getattr(self, f"_on_{kind}")(t, payload, queue.at)

    def _on_live(self, t: int, live: LiveStart, at) -> None:
        """The live moment: every producer muted so far restarts (epoch of its second,
        seq 0) and pacing starts at the live wall time (kept to: no rebase), or now."""
        for producer in self.producers.values():
            if producer.muted:
                producer.restart(live.epoch)
        self.stats.fast_forward_wall_s = time.monotonic() - self._wall0
        self.pacer.start(live_schedule0(live.wall_s, self.stats), rebase=live.wall_s is None)

    # -- handlers -------------------------------------------------------------------------------

    def _joints(self, t: int) -> tuple[float, float, float]:
        return self.motion.at(t)

    def _on_clock(self, t: int, period: int, at) -> None:
        self._tick(t)
        busy_s = self.scenario.clock_busy_period_s
        at(t + (int(busy_s * NS_PER_S) if busy_s and self._busy(t) else period), "clock", period)

    def _tick(self, t: int) -> None:
        """One ``clock`` event at site time ``t`` (never two at one time, never back; none
        without a clock or before the live moment)."""
        clock = self.producers.get("clock")
        if clock is not None and not clock.muted and t > self._last_tick_ns:
            self._last_tick_ns = t
            clock.emit(messages.clock(t))

    def _busy(self, t: int) -> bool:
        """Whether a machine works (full sensor rates) or the yard waits for assays."""
        return self.reclaiming or t < self.stacking_until

    def _period_ns(self, t: int, hz: float) -> int:
        return int(NS_PER_S / (hz if self._busy(t) else min(hz, self.scenario.idle_hz)))

    def _on_encoder(self, t: int, period: int, at) -> None:
        joints = self._joints(t)
        self.truth_joints.append((t, *joints))
        travel, slew, luff = self.encoders.read(t, *joints)
        msg = messages.joint_reading(self.scenario.machine_id, travel, slew, luff, t)
        self.producers["encoders"].emit(msg)
        self.last_reading = (t, msg.travel_m, msg.slew_rad, msg.luff_rad)
        if self.real:
            self.devices.encoder_sample(*self.last_reading)
        at(t + self._period_ns(t, self.rates.encoder_hz), "encoder", None)

    def _on_gnss(self, t: int, period: int, at) -> None:
        joints = np.asarray(self._joints(t))
        true = self.gnss.antenna_position(self.machine, joints)
        fix = self.gnss.fix(t, true)
        self.truth_antenna.append((t, *np.asarray(true, float).reshape(3)))
        sentence = format_gga(t, float(np.ravel(fix.lat_deg)[0]), float(np.ravel(fix.lon_deg)[0]),
                              int(np.ravel(fix.quality)[0]), int(np.ravel(fix.satellites)[0]),
                              float(np.ravel(fix.hdop)[0]), float(np.ravel(fix.alt_m)[0]))
        data = sentence.encode("ascii")
        self._write(self.gnss_file, self.gnss_pty, data)
        self.stats.gga += 1
        self.stats.gnss_bytes += len(data)
        at(t + self._period_ns(t, self.rates.gnss_hz), "gnss", None)

    def _on_scan(self, t: int, _payload, at) -> None:
        joints = self._joints(t)
        position, rotation = self._scanner_pose(joints)
        g = self.grid
        ranges, status = self.scanner.scan_with_status(self.world.surface_z(), g.origin_x_m,
                                                       g.origin_y_m, g.cell_m, position, rotation)
        if self.record_scans:
            self.cast_scans.append((ranges.copy(), status.copy()))
        if self.real:
            at(t + self.devices.lms.latency_ns, "lms511", (t, ranges))
        else:
            data = self._lms200_telegram(t, ranges, status, at)
        self.truth_scans.append((t, *position, *rotation.ravel()))
        self.stats.scans += 1
        if self.scan_events != "off":
            # queued at this very time: handled after everything already due now (the
            # encoders read at t among them), and nothing else moves in the queue
            at(t, "scan_events", (data, position, rotation))
        at(t + self._period_ns(t, self.rates.scan_hz), "scan", None)

    def _lms200_telegram(self, t: int, ranges: np.ndarray, status: np.ndarray, at) -> bytes:
        """The scan's LMS200 telegram, queued to leave its serial transfer time after ``t``."""
        values = lms200.ranges_to_values(ranges, unit_mm=self.unit_mm)
        values[status == BEAM_ERROR_CODE] = lms200.DAZZLE
        data = lms200.encode_measurement(values, unit_mm=self.unit_mm)
        # the telegram's last byte leaves the scanner its serial transfer time later
        transfer_ns = len(data) * 10 * NS_PER_S // self.scenario.scanner_baud
        at(t + transfer_ns, "telegram", data)
        self.stats.lms200_bytes += len(data)
        return data

    def _on_scan_events(self, t: int, payload, at) -> None:
        """The ``frame_transform`` and ``scan`` events of the scan taken at ``t``."""
        data, position, rotation = payload
        if self.scan_events == "encoders":
            if self.last_reading is None:  # cannot happen: the encoders read first at t0
                raise RuntimeError("a scan before the first encoder reading")
            position, rotation = self._scanner_pose(self.last_reading[1:])
        self.producers["poses"].emit(
            messages.scanner_transform(self.scenario.machine_id, position, rotation, t))
        ranges = lms200.decode_measurement(data).ranges_m
        self.producers["scans"].emit(scan_message(ranges, t, self.scan_frame_id, self.scan_field))

    def _on_telegram(self, t: int, data: bytes, at) -> None:
        if self.scanner_pty is not None and self._busy(t):
            # the clock ticks right before the telegram leaves: the scanner dates it
            # between the ticks around it, and casting the scan (most of a working site
            # second's compute) would otherwise sit between the tick and the telegram
            self._tick(t)
        self._write(self.lms_file, self.scanner_pty, data)

    def _on_lms511(self, t: int, payload, at) -> None:
        """Send the scan taken at ``payload[0]`` to the LMS511 (a tick first, as for a telegram)."""
        if self._busy(t):
            self._tick(t)
        self.devices.scan(*payload, self.scanner.angles_rad)

    def _on_lot(self, t: int, lot, at) -> None:
        self.producers["lims"].emit(messages.lot_declared(self.scenario, lot, t))

    def _on_pass_start(self, t: int, p: dict, at) -> None:
        self.producers["stacker"].emit(messages.stack_started(self.scenario, p, t))
        if self.real:
            self.devices.pass_started(t, p)
        # the reclaimer's scanner trails the stacker (sim.motion.patrol_legs)
        lag, run_on, start_end, far_end = patrol_legs(self.scenario, self.move_m_s, p)
        self.motion = Motion(t, t + lag, self.motion.at(t), self._patrol_pose(start_end))
        at(t + lag, "patrol", (p["t1"] + lag, p["y1"]))
        at(p["t1"] + lag, "patrol", (p["t1"] + lag + run_on, far_end))

    def _on_patrol(self, t: int, payload, at) -> None:
        """Move the scanner along the pile to ``target_y`` by ``t_end`` (payload)."""
        if self.reclaiming:
            return
        t_end, target_y = payload
        self.motion = Motion(t, t_end, self.motion.at(t), self._patrol_pose(target_y))

    def _on_chunk(self, t: int, payload, at) -> None:
        p, k, n = payload
        sc = self.scenario
        t_a = p["t0"] + (p["t1"] - p["t0"]) * k // n
        y_a = p["y0"] + (p["y1"] - p["y0"]) * k / n
        y_b = p["y0"] + (p["y1"] - p["y0"]) * (k + 1) / n
        x_c = sc.pile_origin_x_m + sc.pile_width_m / 2
        belt = self.belts[p["lot"].lot_id]
        windows = self.lab_windows.get(p["lot"].lot_id)
        planned_fe = p["lot"].mean_pct[ANALYTES.index("Fe")]   # a lot the lab never sampled
        grade = flow_grade(belt, windows, planned_fe)
        self.world.stack_pass(sc.pattern.lower(), y_a, y_b, x_c, sc.tonnes_per_pass / n, int(t_a), int(t),
                              p["deposit"], p["lot"].lot_id, grade,
                              sc.bulk_density_t_m3, rng=self.rng_stack,
                              jitter_m=0.02 * sc.pile_width_m, rate_cv=0.05)

    def _on_pass_end(self, t: int, p: dict, at) -> None:
        sc = self.scenario
        belt_tonnes = sc.tonnes_per_pass * (1.0 + self.rng_belt.normal(0.0, sc.belt_scale_error_frac))
        self.producers["stacker"].emit(messages.stack_ended(sc, p["pass_id"], belt_tonnes, t))
        if self.real:
            self.devices.pass_ended(t, belt_tonnes)
        self.passes.append({"pass_id": p["pass_id"], "lot_id": p["lot"].lot_id, "t0_ns": p["t0"],
                            "t1_ns": p["t1"], "true_tonnes": sc.tonnes_per_pass,
                            "belt_tonnes": belt_tonnes, "deposit": p["deposit"]})
        self.stats.passes += 1

    def _on_assay(self, t: int, r: LabResult, at) -> None:
        self.producers["lab"].emit(messages.assay(r))
        if self.real:
            self.devices.assay(t, r)
        self.stats.assays += 1

    # -- output -----------------------------------------------------------------------------

    def _write(self, file, pty, data: bytes) -> None:
        file.write(data)
        if pty is not None:
            pty.write(data)

    def _finish(self) -> None:
        self.jsonl.close()
        for sink in self.sinks:
            sink.close()
        self.lms_file.close()
        self.gnss_file.close()
        for pty in (self.scanner_pty, self.gnss_pty):
            if pty is not None:
                self.stats.dropped_pty_bytes += getattr(pty, "dropped_bytes", 0)
        self.stats.events = self.jsonl.count
        write_truth(self)
