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
"""

from __future__ import annotations

import heapq
import json
import math
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from scipy.spatial.transform import Rotation

from schemas import pb
from schemas.events import set_timestamp_ns
from devices import lms200
from devices.nmea import format_gga
from services.scanner import default_frame_id, scan_field, scan_message
from sim import sensors
from sim.grades import ANALYTES, NS_PER_S, BeltGrade, LabModel, LabResult
from sim.kinematics import FULL_SCALE, boom_radius_m, envelope_floor_z, wheel_centre
from sim.publish import JsonlSink, Producer, Sink
from sim.scenario import Scenario
from sim.world import Grid, World

#: Rotation of the scanner frame in the wheel frame: looking straight down, scan plane
#: containing the boom (scanner x = down, y = along the boom, z = x cross y).
SCANNER_IN_WHEEL = np.array([[0.0, 1.0, 0.0],
                             [0.0, 0.0, -1.0],
                             [-1.0, 0.0, 0.0]])

#: The world's extra grade channel: the laboratory's Fe (mass %) of the assay window each
#: piece of belt flow falls in (see Simulation.__init__); cut records give its mean as
#: ``lab_window_fe_pct``.
LAB_WINDOW_FE = "Fe@lab-window"
CHUNK_S = 30.0           # stacking is released in chunks of this much site time
CUT_SUBSWEEPS = 8        # a cut removes material in this many steps of its slew
MOVE_SPEED_M_S = 0.5     # travel speed between cuts and while patrolling (full-scale machine)
PATROL_LAG_S = 2 * CHUNK_S  # the scanner trails the stacker by this much while it stacks
SLEW_STEP_RAD = math.radians(0.5)
#: values of ``Simulation.scan_events`` / ``--scan-events`` (see the module docstring)
SCAN_EVENTS = ("off", "truth", "encoders")


def _rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def wheel_rotation(slew_rad: float) -> np.ndarray:
    """Rotation of the wheel frame in the site frame: x along the boom (horizontal), z up."""
    c, s = math.sin(slew_rad), math.cos(slew_rad)  # boom direction (sin slew, cos slew, 0)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Motion:
    """Linear joint motion between two times (travel m, slew rad, luff rad)."""

    t0_ns: int
    t1_ns: int
    start: tuple[float, float, float]
    end: tuple[float, float, float]

    def at(self, t_ns: int) -> tuple[float, float, float]:
        if self.t1_ns <= self.t0_ns:
            return self.end
        w = min(max((t_ns - self.t0_ns) / (self.t1_ns - self.t0_ns), 0.0), 1.0)
        return tuple(a + (b - a) * w for a, b in zip(self.start, self.end))  # type: ignore[return-value]


#: a paced event handled this much (real seconds) behind schedule counts as late
LATE_S = 0.005
#: a paced run that falls further behind than this (real seconds) gives the lost time up:
#: its schedule moves on (site time runs slower for a moment) rather than catching up in a
#: burst, in which telegrams and clock ticks arrive together and a service that maps
#: arrival onto site time dates them seconds off
REBASE_S = 0.05


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


@dataclass
class Simulation:
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

    def __post_init__(self) -> None:
        sc = self.scenario
        if self.scan_events not in SCAN_EVENTS:
            raise ValueError(f"scan_events must be one of {', '.join(SCAN_EVENTS)}, "
                             f"got {self.scan_events!r}")
        self.out_dir = Path(self.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = JsonlSink(self.out_dir / "events.jsonl")
        self._last_tick_ns = -1   # the newest clock event's site time
        all_sinks = [self.jsonl, *self.sinks]
        epoch = sc.start_ns // NS_PER_S
        self.producers = {name: Producer(source, epoch, all_sinks) for name, source in (
            ("config", "yard.config"), ("clock", "sim.clock"),
            ("encoders", f"{sc.machine_id}.encoders"), ("stacker", f"{sc.stacker_id}.plc"),
            ("reclaimer", f"{sc.machine_id}.plc"), ("lims", "lims"), ("lab", "lab1"))}
        if self.scan_events != "off":
            self.producers["scans"] = Producer(f"{sc.machine_id}.scanner", epoch, all_sinks)
            self.producers["poses"] = Producer(f"{sc.machine_id}.poses", epoch, all_sinks)
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
        self.encoders = sensors.EncoderModel(rng=_rng(self.noise_seed, "encoders"))
        self.gnss = sensors.GnssModel(sc.datum_lat_deg, sc.datum_lon_deg, sc.datum_alt_m,
                                      rng=_rng(self.noise_seed, "gnss"))
        self.unit_mm = sc.pile_width_m < 5.0  # mm mode reaches 8 m: the laboratory pile
        self.scanner = sensors.ScannerModel(fov_deg=sc.scan_fov_deg, step_deg=sc.scan_step_deg,
                                            max_range_m=8.0 if self.unit_mm else 80.0,
                                            unit_mm=self.unit_mm,
                                            rng=_rng(self.noise_seed, "scanner"))
        if self.scan_events != "off":
            # the scanner service's defaults: frame from the source, field from the value
            # count (the scanner model only takes LMS200 fields, so they are the cast ones)
            self.scan_frame_id = default_frame_id(self.producers["scans"].source)
            self.scan_field = scan_field(self.scanner.n_beams)
        #: the latest encoder reading: (t_ns, travel m, slew rad, luff rad) as published
        self.last_reading: tuple[int, float, float, float] | None = None
        self.rng_belt = _rng(self.seed, "belt")
        self.rng_stack = _rng(self.seed, "stacking")
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

    # -- geometry of the machines ---------------------------------------------------------

    def _expected_crest_m(self) -> float:
        sc = self.scenario
        volume = sc.lot_count * sc.passes_per_lot * sc.tonnes_per_pass / sc.bulk_density_t_m3
        tan = math.tan(math.radians(sc.repose_deg))
        h = math.sqrt(volume / sc.pile_length_m * tan)
        return sc.ground_z_m + min(h, sc.pile_width_m / 2 * tan)

    @property
    def move_m_s(self) -> float:
        """Travel speed between cuts and on the patrol's run-on (m/s): MOVE_SPEED_M_S for
        the full-scale machine, scaled down with the boom for a smaller one (a laboratory
        model crossing its 1.2 m pile in 2 s would scan its end slope once)."""
        return MOVE_SPEED_M_S * min(1.0, self.machine.l5_m / FULL_SCALE.l5_m)

    def _patrol_pose(self, travel_m: float) -> tuple[float, float, float]:
        """Joints that hold the wheel above the pile's centre line, clear of the crest."""
        sc, m = self.scenario, self.machine
        clearance = max(0.5 * self._expected_crest_m(), 3 * m.cutting_radius_m)
        z = self._expected_crest_m() + clearance
        sin_luff = (z - m.rail_z_m - m.pivot_height_m) / m.l5_m
        luff = math.asin(min(max(sin_luff, -0.95), 0.95))
        rho = float(boom_radius_m(m, luff))
        x_c = sc.pile_origin_x_m + sc.pile_width_m / 2
        slew = math.asin(min(max((x_c - m.rail_x_m) / rho, -1.0), 1.0))
        return (travel_m - rho * math.cos(slew), slew, luff)

    def _scanner_pose(self, joints) -> tuple[np.ndarray, np.ndarray]:
        centre = wheel_centre(self.machine, *joints)
        r_wheel = wheel_rotation(joints[1])
        position = centre + r_wheel @ np.asarray(self.scenario.scanner_offset_m)
        return position, r_wheel @ SCANNER_IN_WHEEL

    # -- declarations -----------------------------------------------------------------------

    def _declare(self, t: int) -> None:
        sc, m = self.scenario, self.machine
        emit = self.producers["config"].emit
        site = pb.SiteDeclared(site_id=sc.site_id, datum_lat_deg=sc.datum_lat_deg,
                               datum_lon_deg=sc.datum_lon_deg, datum_alt_m=sc.datum_alt_m)
        emit(_stamp(site, "time", t))
        pile = pb.PileDeclared(pile_id=sc.pile_id, origin_x_m=sc.pile_origin_x_m,
                               origin_y_m=sc.pile_origin_y_m, length_m=sc.pile_length_m,
                               width_m=sc.pile_width_m, ground_z_m=sc.ground_z_m,
                               cell_m=sc.surface_cell_m, voxel_m=sc.voxel_m,
                               default_bulk_density_t_m3=sc.bulk_density_t_m3)
        emit(_stamp(pile, "time", t))
        quat = Rotation.from_matrix(SCANNER_IN_WHEEL).as_quat()  # x, y, z, w
        for machine_id, kind in ((sc.machine_id, pb.BUCKET_WHEEL_RECLAIMER), (sc.stacker_id, pb.STACKER)):
            msg = pb.MachineDeclared(
                machine_id=machine_id, kind=kind, rail_x_m=m.rail_x_m, rail_z_m=m.rail_z_m,
                l2_m=m.l2_m, l3_m=m.l3_m, l4_m=m.l4_m, l5_m=m.l5_m, wheel_radius_m=m.wheel_radius_m,
                cutting_radius_m=m.cutting_radius_m, wheel_tilt_rad=m.wheel_tilt_rad,
                bucket_width_m=m.bucket_width_m, fall_angle_rad=m.fall_angle_rad)
            if machine_id == sc.machine_id:
                msg.scanner.parent_frame_id = f"{machine_id}/wheel"
                msg.scanner.child_frame_id = f"{machine_id}/scanner"
                msg.scanner.translation.x, msg.scanner.translation.y, msg.scanner.translation.z = sc.scanner_offset_m
                (msg.scanner.rotation.x, msg.scanner.rotation.y, msg.scanner.rotation.z,
                 msg.scanner.rotation.w) = (float(v) for v in quat)
            emit(_stamp(msg, "time", t))

    # -- the timetable ----------------------------------------------------------------------

    def _stacking_plan(self) -> list[dict]:
        sc = self.scenario
        t = sc.start_ns + 300 * NS_PER_S
        plan = []
        n = 0
        for lot_index, lot in enumerate(sc.lots):
            for p in range(sc.passes_per_lot):
                t0, t1 = t, t + int(sc.pass_duration_s * NS_PER_S)
                forward = n % 2 == 0
                plan.append({"pass_id": f"{lot.lot_id}-P{p + 1}", "lot": lot, "lot_index": lot_index,
                             "t0": t0, "t1": t1, "deposit": n,
                             "y0": sc.pile_origin_y_m + (0.1 if forward else 0.9) * sc.pile_length_m,
                             "y1": sc.pile_origin_y_m + (0.9 if forward else 0.1) * sc.pile_length_m})
                t = t1 + int(sc.pass_gap_s * NS_PER_S)
                n += 1
        return plan

    def run(self, *, duration_h: float | None = None, speed: float = 0.0,
            idle_speed: float = 0.0) -> RunStats:
        sc = self.scenario
        wall0 = time.monotonic()
        t0 = sc.start_ns
        self._declare(t0)
        plan = self._stacking_plan()
        belts = {}
        counter = [0]
        lab = LabModel(window_s=sc.assay_window_s, delay_h=sc.assay_delay_h)
        for lot_index, lot in enumerate(sc.lots):
            spans = [p for p in plan if p["lot_index"] == lot_index]
            belt = BeltGrade(lot, spans[0]["t0"], spans[-1]["t1"], self.rng_belt)
            belts[lot.lot_id] = belt
            for p in spans:
                self.lab_results += lab.assays(belt, p["t0"], p["t1"], self.rng_belt, counter)
        self.lab_results.sort(key=lambda r: (r.reported_ns, r.assay_id))
        # the scanner runs on over the last pass's far end after the stacker stops, then
        # surveys the finished pile end to end (a scan line per surface cell, at most at
        # the travel speed) before the first cut
        run_on_end = plan[-1]["t1"] + int((PATROL_LAG_S + sc.pile_length_m / self.move_m_s)
                                          * NS_PER_S)
        survey_m_s = min(self.move_m_s, sc.surface_cell_m * sc.scan_hz)
        survey_end = run_on_end + int(sc.pile_length_m / survey_m_s * NS_PER_S)
        reclaim_start = max(plan[-1]["t1"] + int(600 * NS_PER_S), survey_end + int(30 * NS_PER_S))
        end_ns = (max(r.reported_ns for r in self.lab_results) if self.lab_results else reclaim_start)
        end_ns += 60 * NS_PER_S
        if duration_h is not None:
            end_ns = t0 + int(duration_h * 3600 * NS_PER_S)

        # the queue of things to do, in site time: (t_ns, order, kind, payload)
        queue: list[tuple[int, int, str, object]] = []
        order = [0]

        def at(t_ns: int, kind: str, payload: object = None) -> None:
            order[0] += 1
            heapq.heappush(queue, (int(t_ns), order[0], kind, payload))

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
        at(reclaim_start, "reclaim", (0, 0, None))
        at(t0, "clock", int(sc.clock_period_s * NS_PER_S))
        at(t0, "encoder", None)
        at(t0, "gnss", None)
        at(t0, "scan", None)
        last_forward = plan[-1]["y1"] >= plan[-1]["y0"]
        survey_to = sc.pile_origin_y_m + (0.0 if last_forward else sc.pile_length_m)
        at(run_on_end, "patrol", (survey_end, survey_to))
        self.stacking_until = survey_end
        self.reclaiming = False
        self.belts = belts
        self.lab_windows = _lab_windows(self.lab_results, "Fe")

        next_report = time.monotonic() + 10.0
        t_prev, wall_due, schedule0, busy = t0, 0.0, wall0, None
        while queue:
            t, _, kind, payload = heapq.heappop(queue)
            if t > end_ns:
                # telegrams of scans taken before the end are still on the wire: send them
                for t_late, _o, kind_late, data in sorted(queue + [(t, _, kind, payload)]):
                    if kind_late == "telegram":
                        self._on_telegram(t_late, data, at)
                break
            if self.progress is not None and time.monotonic() >= next_report:
                next_report = time.monotonic() + 10.0
                self.progress(f"site time {(t - t0) / 3.6e12:6.2f} of {(end_ns - t0) / 3.6e12:.2f} h: "
                              f"{self.jsonl.count:,} events, {self.stats.scans:,} scans, "
                              f"{self.stats.passes} passes, {self.stats.cuts} cuts")
            was_busy, busy = busy, self._busy(t_prev)
            if was_busy is not None and busy != was_busy:
                # a tick where the yard starts or stops working (a paced run changes pace
                # there), so that a service dating its readings between ticks (the
                # scanner) has the corner of the site-time line
                self._tick(t_prev)
            if speed > 0:
                # pacing site time against the wall clock; idle stretches (no machine
                # moves, only late assays to wait for) run at idle_speed
                rate = idle_speed if (idle_speed and not busy) else speed
                wall_due += (t - t_prev) / NS_PER_S / rate
                lag = wall_due - (time.monotonic() - schedule0)
                if lag > 0:
                    time.sleep(lag)
                elif -lag > LATE_S:
                    self.stats.late_events += 1
                    self.stats.max_lag_s = max(self.stats.max_lag_s, -lag)
                    if -lag > REBASE_S:
                        schedule0 -= lag          # lag < 0: the schedule moves on by it
                        self.stats.rebases += 1
                        self.stats.given_up_s -= lag
            t_prev = t
            getattr(self, f"_on_{kind}")(t, payload, at)
        self.stats.site_s = (end_ns - t0) / NS_PER_S
        self.stats.wall_s = time.monotonic() - wall0
        self._finish()
        return self.stats

    # -- handlers -------------------------------------------------------------------------------

    def _joints(self, t: int) -> tuple[float, float, float]:
        return self.motion.at(t)

    def _on_clock(self, t: int, period: int, at) -> None:
        self._tick(t)
        busy_s = self.scenario.clock_busy_period_s
        at(t + (int(busy_s * NS_PER_S) if busy_s and self._busy(t) else period), "clock", period)

    def _tick(self, t: int) -> None:
        """One ``clock`` event at site time ``t`` (never two at one time, never back)."""
        if t > self._last_tick_ns:
            self._last_tick_ns = t
            self.producers["clock"].emit(_stamp(pb.Clock(), "time", t))

    def _busy(self, t: int) -> bool:
        """Whether a machine works (full sensor rates) or the yard waits for assays."""
        return self.reclaiming or t < self.stacking_until

    def _period_ns(self, t: int, hz: float) -> int:
        return int(NS_PER_S / (hz if self._busy(t) else min(hz, self.scenario.idle_hz)))

    def _on_encoder(self, t: int, period: int, at) -> None:
        joints = self._joints(t)
        self.truth_joints.append((t, *joints))
        travel, slew, luff = self.encoders.read(t, *joints)
        msg = pb.JointReading(machine_id=self.scenario.machine_id, travel_m=float(travel),
                              slew_rad=float(slew), luff_rad=float(luff))
        self.producers["encoders"].emit(_stamp(msg, "time", t))
        self.last_reading = (t, msg.travel_m, msg.slew_rad, msg.luff_rad)
        at(t + self._period_ns(t, self.scenario.encoder_hz), "encoder", None)

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
        at(t + self._period_ns(t, self.scenario.gnss_hz), "gnss", None)

    def _on_scan(self, t: int, _payload, at) -> None:
        sc = self.scenario
        joints = self._joints(t)
        position, rotation = self._scanner_pose(joints)
        g = self.grid
        ranges, status = self.scanner.scan_with_status(self.world.surface_z(), g.origin_x_m,
                                                       g.origin_y_m, g.cell_m, position, rotation)
        if self.record_scans:
            self.cast_scans.append((ranges.copy(), status.copy()))
        values = lms200.ranges_to_values(ranges, unit_mm=self.unit_mm)
        values[status == sensors.BEAM_ERROR_CODE] = lms200.DAZZLE
        data = lms200.encode_measurement(values, unit_mm=self.unit_mm)
        # the telegram's last byte leaves the scanner its serial transfer time later
        transfer_ns = len(data) * 10 * NS_PER_S // sc.scanner_baud
        at(t + transfer_ns, "telegram", data)
        self.truth_scans.append((t, *position, *rotation.ravel()))
        self.stats.scans += 1
        self.stats.lms200_bytes += len(data)
        if self.scan_events != "off":
            # queued at this very time: handled after everything already due now (the
            # encoders read at t among them), and nothing else moves in the queue
            at(t, "scan_events", (data, position, rotation))
        at(t + self._period_ns(t, sc.scan_hz), "scan", None)

    def _on_scan_events(self, t: int, payload, at) -> None:
        """The ``frame_transform`` and ``scan`` events of the scan taken at ``t``."""
        data, position, rotation = payload
        if self.scan_events == "encoders":
            if self.last_reading is None:  # cannot happen: the encoders read first at t0
                raise RuntimeError("a scan before the first encoder reading")
            position, rotation = self._scanner_pose(self.last_reading[1:])
        quat = Rotation.from_matrix(rotation).as_quat()  # x, y, z, w
        if quat[3] < 0:
            quat = -quat
        ft = FrameTransform(parent_frame_id="site",
                            child_frame_id=f"{self.scenario.machine_id}/scanner")
        ft.translation.x, ft.translation.y, ft.translation.z = (float(v) for v in position)
        ft.rotation.x, ft.rotation.y, ft.rotation.z, ft.rotation.w = (float(v) for v in quat)
        self.producers["poses"].emit(_stamp(ft, "timestamp", t))
        ranges = lms200.decode_measurement(data).ranges_m
        self.producers["scans"].emit(scan_message(ranges, t, self.scan_frame_id, self.scan_field))

    def _on_telegram(self, t: int, data: bytes, at) -> None:
        if self.scanner_pty is not None and self._busy(t):
            # the clock ticks right before the telegram leaves: the scanner dates it
            # between the ticks around it, and casting the scan (about 4 ms, most of a
            # working site second's compute) would otherwise sit between the tick and the
            # telegram: 0.16 s of site time late at the demo's 40x
            self._tick(t)
        self._write(self.lms_file, self.scanner_pty, data)

    def _on_lot(self, t: int, lot, at) -> None:
        msg = pb.LotDeclared(lot_id=lot.lot_id, origin=lot.origin,
                             planned_tonnes=self.scenario.passes_per_lot * self.scenario.tonnes_per_pass)
        msg.planned_grade.update(lot.planned_grade())
        self.producers["lims"].emit(_stamp(msg, "time", t))

    def _on_pass_start(self, t: int, p: dict, at) -> None:
        sc = self.scenario
        msg = pb.StackStarted(pile_id=sc.pile_id, pass_id=p["pass_id"], lot_id=p["lot"].lot_id,
                              machine_id=sc.stacker_id, pattern=getattr(pb, sc.pattern),
                              start_y_m=p["y0"], end_y_m=p["y1"])
        self.producers["stacker"].emit(_stamp(msg, "time", t))
        # The reclaimer patrols along the pile with the scanner, trailing the stacker by
        # up to PATROL_LAG_S so that it sees every stretch after the pass laid its layer there
        # (a scanner that met the stacker half way would see half the pile before each
        # pass and could not tell two passes' layers apart there): it waits at the end
        # the pass starts from, follows the stacker to the pass's last position, then
        # runs on over the far end's slope.
        forward = p["y1"] >= p["y0"]
        y_lo, y_hi = sc.pile_origin_y_m, sc.pile_origin_y_m + sc.pile_length_m
        start_end, far_end = (y_lo, y_hi) if forward else (y_hi, y_lo)
        # the run over the far end's slope ends before the next pass starts pouring
        run_on_s = abs(far_end - p["y1"]) / self.move_m_s
        lag_s = max(min(PATROL_LAG_S, sc.pass_gap_s - run_on_s - 10.0), CHUNK_S + 5.0)
        lag, run_on = int(lag_s * NS_PER_S), int(run_on_s * NS_PER_S)
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

        def grade(tt: int) -> np.ndarray:
            return np.append(belt.at(tt), _window_value(windows, tt) if windows else planned_fe)

        self.world.stack_pass(sc.pattern.lower(), y_a, y_b, x_c, sc.tonnes_per_pass / n, int(t_a), int(t),
                              p["deposit"], p["lot"].lot_id, grade,
                              sc.bulk_density_t_m3, rng=self.rng_stack,
                              jitter_m=0.02 * sc.pile_width_m, rate_cv=0.05)

    def _on_pass_end(self, t: int, p: dict, at) -> None:
        sc = self.scenario
        belt_tonnes = sc.tonnes_per_pass * (1.0 + self.rng_belt.normal(0.0, sc.belt_scale_error_frac))
        msg = pb.StackEnded(pile_id=sc.pile_id, pass_id=p["pass_id"], tonnes=round(belt_tonnes, 1))
        self.producers["stacker"].emit(_stamp(msg, "time", t))
        self.passes.append({"pass_id": p["pass_id"], "lot_id": p["lot"].lot_id, "t0_ns": p["t0"],
                            "t1_ns": p["t1"], "true_tonnes": sc.tonnes_per_pass,
                            "belt_tonnes": belt_tonnes, "deposit": p["deposit"]})
        self.stats.passes += 1

    def _on_assay(self, t: int, r: LabResult, at) -> None:
        msg = pb.Assay(assay_id=r.assay_id, lot_id=r.lot_id, moisture_pct=r.moisture_pct,
                       bulk_density_t_m3=r.bulk_density_t_m3, status=getattr(pb, r.status),
                       supersedes=r.supersedes, lab_id=r.lab_id)
        msg.analytes.update(r.analytes_pct)
        _stamp(msg, "window_start", r.window_start_ns)
        _stamp(msg, "window_end", r.window_end_ns)
        _stamp(msg, "reported_time", r.reported_ns)
        self.producers["lab"].emit(msg)
        self.stats.assays += 1

    # -- reclaiming -----------------------------------------------------------------------------

    def _bench_luff(self, bench: int) -> float:
        sc, m = self.scenario, self.machine
        crest = float(np.max(self.world.surface_z()))
        z = crest - sc.first_bench_below_crest_m - bench * sc.bench_step_m
        if sc.bench_heights_m is not None:
            z = sc.ground_z_m + sc.bench_heights_m[bench]
        z = max(z, sc.ground_z_m + m.cutting_radius_m * 0.98)
        return math.asin((z - m.rail_z_m - m.pivot_height_m) / m.l5_m)

    def _slew_range(self, travel: float, luff: float) -> tuple[float, float] | None:
        """Slew angles (0.5 deg steps) where the envelope meets material at this travel."""
        m, g = self.machine, self.grid
        x, y = np.meshgrid(g.x_centres, g.y_centres)
        floor = envelope_floor_z(m, x, y, travel, luff, 0.0, math.pi)
        surface = self.world.surface_z()
        material = self.world.thickness() > 0.01 * m.cutting_radius_m  # not bare ground
        hit = material & np.isfinite(floor) & (surface > floor + 0.01 * m.cutting_radius_m)
        if not hit.any():
            return None
        theta = np.arctan2(x[hit] - m.rail_x_m, y[hit] - travel)
        lo = math.floor(theta.min() / SLEW_STEP_RAD) * SLEW_STEP_RAD
        hi = math.ceil(theta.max() / SLEW_STEP_RAD) * SLEW_STEP_RAD
        return lo, hi

    def _on_reclaim(self, t: int, state, at) -> None:
        """Plan and start the next cut (state = bench, cut index, travel of the last cut)."""
        sc, m = self.scenario, self.machine
        bench, cut, travel = state
        if bench >= sc.benches:
            self.reclaiming = False
            return
        self.reclaiming = True
        luff = self._bench_luff(bench)
        rho = float(boom_radius_m(m, luff))
        if travel is None:  # landing: approach from the low-y end until the wheel meets the pile
            travel = sc.pile_origin_y_m - rho - m.cutting_radius_m
            limit = sc.pile_origin_y_m + sc.pile_length_m
            min_face = math.radians(sc.landing_min_slew_deg)
            while travel < limit:
                slews = self._slew_range(travel, luff)
                if slews is not None and slews[1] - slews[0] >= min_face:
                    break
                travel += m.cut_depth_m
            travel += 0.5 * m.cutting_radius_m  # land into the bank, not on its toe
        else:
            travel += m.cut_depth_m
        slews = self._slew_range(travel, luff)
        if slews is None or cut >= sc.cuts_per_bench[bench]:
            at(t + int(120 * NS_PER_S), "reclaim", (bench + 1, 0, None))
            return
        lo, hi = slews if cut % 2 == 0 else slews[::-1]
        current = self.motion.at(t)
        move_s = abs(travel - current[0]) / self.move_m_s + 20.0
        t_start = t + int(move_s * NS_PER_S)
        self.motion = Motion(t, t_start, current, (travel, lo, luff))
        at(t_start, "cut_start", {"bench": bench, "cut": cut, "travel": travel, "luff": luff,
                                  "slew_start": lo, "slew_end": hi, "t0": t_start,
                                  "t1": t_start + int(sc.cut_duration_s * NS_PER_S), "parts": []})

    def _on_cut_start(self, t: int, c: dict, at) -> None:
        if self.cut_surfaces:
            if not self.truth_cut_surfaces:
                # the layers as stacked, before any cut or its slump moved them
                parcels = self.world.parcels()
                self.truth_first_cut_parcels = {
                    "first_cut_thickness": parcels["thickness"].astype(np.float32),
                    "first_cut_time_ns": parcels["time_ns"]}
            self.truth_cut_surfaces.append(self.world.surface_z().astype(np.float32))
        self.motion = Motion(c["t0"], c["t1"], (c["travel"], c["slew_start"], c["luff"]),
                             (c["travel"], c["slew_end"], c["luff"]))
        for k in range(CUT_SUBSWEEPS):
            at(c["t0"] + (c["t1"] - c["t0"]) * (k + 1) // CUT_SUBSWEEPS, "cut_part", (c, k))

    def _on_cut_part(self, t: int, payload, at) -> None:
        c, k = payload
        a = c["slew_start"] + (c["slew_end"] - c["slew_start"]) * k / CUT_SUBSWEEPS
        b = c["slew_start"] + (c["slew_end"] - c["slew_start"]) * (k + 1) / CUT_SUBSWEEPS
        truth = self.world.reclaim_cut(self.machine, c["travel"], c["luff"], a, b, int(t),
                                       relax=False)
        c["parts"].append(truth)
        if k == CUT_SUBSWEEPS - 1:
            # the walls of the whole cut slump once the wheel has passed
            self.world.settle_cut(c["parts"])
            self._finish_cut(t, c, at)

    def _finish_cut(self, t: int, c: dict, at) -> None:
        sc = self.scenario
        tonnes = sum(p.tonnes for p in c["parts"])
        grade = {}
        for a in self.world.analytes:   # the analytes and the lab's channel
            mass = sum(p.tonnes * p.grade[a] for p in c["parts"] if p.tonnes > 0)
            grade[a] = mass / tonnes if tonnes > 0 else float("nan")
        lab_fe = grade.pop(LAB_WINDOW_FE)
        by_lot: dict[str, float] = {}
        for p in c["parts"]:
            for lot, tn in p.tonnes_by_lot.items():
                by_lot[str(lot)] = by_lot.get(str(lot), 0.0) + tn
        by_deposit: dict[str, float] = {}
        for p in c["parts"]:
            for dep, tn in p.tonnes_by_deposit.items():
                by_deposit[str(dep)] = by_deposit.get(str(dep), 0.0) + tn
        belt = tonnes * (1.0 + self.rng_belt.normal(0.0, sc.belt_scale_error_frac)) if tonnes > 0 else 0.0
        cut_id = f"B{c['bench'] + 1}-C{c['cut'] + 1:02d}"
        msg = pb.ReclaimCut(pile_id=sc.pile_id, cut_id=cut_id, bench_id=f"B{c['bench'] + 1}",
                            machine_id=sc.machine_id, travel_m=c["travel"], luff_rad=c["luff"],
                            slew_start_rad=c["slew_start"], slew_end_rad=c["slew_end"],
                            tonnes=round(belt, 1))
        _stamp(msg, "start_time", c["t0"])
        _stamp(msg, "end_time", c["t1"])
        self.producers["reclaimer"].emit(msg)
        self.cuts.append({"cut_id": cut_id, "t0_ns": c["t0"], "t1_ns": c["t1"], "travel_m": c["travel"],
                          "luff_rad": c["luff"], "slew_start_rad": c["slew_start"],
                          "slew_end_rad": c["slew_end"], "true_tonnes": tonnes,
                          "true_volume_m3": sum(p.volume_m3 for p in c["parts"]), "belt_tonnes": belt,
                          "slump_m3": sum(p.slump_m3 for p in c["parts"]),
                          "grade": grade, "lab_window_fe_pct": lab_fe, "tonnes_by_lot": by_lot,
                          "tonnes_by_deposit": by_deposit})
        self.stats.cuts += 1
        at(t + int(30 * NS_PER_S), "reclaim", (c["bench"], c["cut"] + 1, c["travel"]))

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
        world = self.world
        truth = {
            "scenario": {k: (v if isinstance(v, (int, float, str, bool, type(None))) else str(v))
                         for k, v in asdict(self.scenario).items() if k not in ("lots", "machine")},
            "machine": asdict(self.machine),
            "seed": self.seed,
            "noise_seed": self.noise_seed,
            "stats": asdict(self.stats),
            "passes": self.passes,
            "cuts": self.cuts,
            "assays": [asdict(r) for r in self.lab_results],
            "world": world.summary(),
        }
        truth["world"].pop("cuts", None)  # per sub-sweep; the per-cut totals are in "cuts"
        (self.out_dir / "truth.json").write_text(json.dumps(_clean(truth), indent=1, sort_keys=True))
        arrays = {"surface_z": world.surface_z(), "layer_tops": world.layer_surfaces(),
                  "x_centres": world.grid.x_centres, "y_centres": world.grid.y_centres,
                  "joints": np.asarray(self.truth_joints, dtype=np.float64).reshape(-1, 4),
                  "scanner_poses": np.asarray(self.truth_scans, dtype=np.float64).reshape(-1, 13),
                  "antenna_enu": np.asarray(self.truth_antenna, dtype=np.float64).reshape(-1, 4)}
        if self.cut_surfaces:
            # a run stopped mid-cut has a surface for a cut it did not finish: not kept
            arrays["cut_surface_z"] = np.asarray(self.truth_cut_surfaces[:len(self.cuts)],
                                                 np.float32).reshape(-1, *arrays["surface_z"].shape)
            arrays.update(self.truth_first_cut_parcels)
        parcels = world.parcels()
        arrays.update(thickness=parcels["thickness"], time_ns=parcels["time_ns"],
                      grade=parcels["grade"], density_t_m3=parcels["density_t_m3"])
        np.savez_compressed(self.out_dir / "truth.npz", **arrays)


def _lab_windows(results: list[LabResult], analyte: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per lot, the laboratory's final value of ``analyte`` (mass %) per sampling window:
    (window starts in UTC ns, values), in time order (a FINAL replaces the PROVISIONAL
    result of its window)."""
    final = {(r.lot_id, r.window_start_ns): r.analytes_pct[analyte]
             for r in results if r.status == "FINAL"}
    by_lot: dict[str, list[tuple[int, float]]] = {}
    for (lot, start_ns), value in sorted(final.items()):
        by_lot.setdefault(lot, []).append((start_ns, value))
    return {lot: (np.array([t for t, _ in rows], np.int64), np.array([v for _, v in rows]))
            for lot, rows in by_lot.items()}


def _window_value(windows: tuple[np.ndarray, np.ndarray], time_ns: int) -> float:
    """The value of the window that holds ``time_ns`` (the first or last beyond the ends)."""
    starts, values = windows
    i = int(np.searchsorted(starts, time_ns, side="right")) - 1
    return float(values[min(max(i, 0), len(values) - 1)])


def _stamp(message, field_name: str, t_ns: int):
    set_timestamp_ns(getattr(message, field_name), int(t_ns))
    return message


def _clean(value):
    """NaN/inf -> None, numpy scalars -> Python, recursively (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    return value
