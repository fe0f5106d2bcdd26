"""Simulator scenarios: the yard, its pile, machines, lots and timetable as data.

===================  =====================================================================
scenario             what it is
===================  =====================================================================
``demo``             a small pile (60 m), 8 chevron layers from 3 lots, one reclaim bench,
                     assays arriving 2-6 h late; the default behind ``make demo``
``full-scale``       the thesis' 220 m pile, ~30 m high, tens of layers, several benches
``bench-scale``      the thesis' laboratory pile in metres (Table 4.1 sizes), two reclaims of
                     10 and 5 cuts (§5.3.4)
``load``             the demo pile with every sensor at its maximum rate (reliability tests)
``cohesive``         the demo with cohesive ore: a cut's faces stand at up to 50 deg
``delayed``          the demo with faces that stand as cut and fail to repose 5-60 min later
``standing``         the demo with faces that never slide
``two-bed-stack``    bed A of a two-bed blending yard: the full-scale pile at y 0-220 m,
                     sources ``bedA.*``, the yard's clock; starts 12 h after bed B, so it is
                     stacking (about 9.5 h in) when bed B starts reclaiming
``two-bed-reclaim``  bed B: the same pile at y 300-520 m along the same rail (pile ``B``,
                     machines ``bwr2``/``stk2``, lots ``*-B``), sources ``bedB.*``, no clock
===================  =====================================================================

The two-bed scenarios are meant to run as two ``stockpile sim`` processes on one site:
history at the full-scale rates (scan 2 Hz, encoders 2 Hz, GNSS 1 Hz), and from a live
moment (``--live-at``, :mod:`sim.live`) the rates of ``live_rates`` (an LMS200 at 75 Hz,
GNSS at 10 Hz, encoders at 50 Hz; 75 telegrams of 412 bytes a second are 309 kbit/s, within
the scanner's 500 kbaud line).

The material (:class:`sim.material.Material`) says what a cut's faces do after the cut;
every scenario but ``cohesive``, ``delayed`` and ``standing`` slumps them at once to the
angle of repose.

Lengths in metres, times in seconds of site time unless a name says otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from schemas.events import is_valid_source
from sim.grades import LotSpec, table_5_4_lots
from sim.kinematics import BENCH_SCALE, FULL_SCALE, Machine
from sim.material import Material

#: 2026-11-01T00:00:00Z, the default start of every scenario.
DEFAULT_START_NS = 1_793_491_200_000_000_000


@dataclass(frozen=True)
class Scenario:
    """Everything that defines one simulated yard session."""

    name: str
    site_id: str = "capelambert"
    datum_lat_deg: float = -20.659739
    datum_lon_deg: float = 117.078497
    datum_alt_m: float = 5.0
    #: the mine grid's projected CRS (EPSG; 7850: GDA2020 / MGA zone 50, the Pilbara's)
    crs_epsg: int = 7850
    start_ns: int = DEFAULT_START_NS

    # the pile (site ENU; the pile's long axis is +y, along the rail)
    pile_id: str = "P1"
    pile_origin_x_m: float = 10.0
    pile_origin_y_m: float = 0.0
    pile_length_m: float = 60.0
    pile_width_m: float = 40.0
    ground_z_m: float = 0.0
    surface_cell_m: float = 0.25      # the product's surface grid (declared)
    voxel_m: float = 1.0              # the product's voxels (declared)
    bulk_density_t_m3: float = 2.4
    repose_deg: float = 37.0
    deposition_cell_m: float = 0.25   # the simulator's own fine grid
    #: what a cut's faces do after the cut (default: slump at once to ``repose_deg``)
    material: Material = field(default_factory=Material)

    # machines: one bucket-wheel reclaimer that also carries the scanner and GNSS
    machine_id: str = "bwr1"
    stacker_id: str = "stk1"
    machine: Machine = field(default_factory=lambda: replace(FULL_SCALE, rail_x_m=-25.0))
    scanner_offset_m: tuple[float, float, float] = (0.0, 0.0, 3.0)  # from the wheel centre

    # stacking
    lots: tuple[LotSpec, ...] = field(default_factory=lambda: tuple(table_5_4_lots()[:3]))
    passes_per_lot: int = 3
    tonnes_per_pass: float = 1_800.0
    pass_duration_s: float = 300.0
    pass_gap_s: float = 60.0
    pattern: str = "CHEVRON"
    belt_scale_error_frac: float = 0.007

    # reclaiming
    cuts_per_bench: tuple[int, ...] = (10,)   # one entry per bench
    bench_heights_m: tuple[float, ...] | None = None  # wheel-centre heights; None: from crest
    cut_duration_s: float = 120.0
    landing_min_slew_deg: float = 0.0  # land where the cut meets a face this wide in slew
    first_bench_below_crest_m: float = 3.0  # wheel centre height below the pile's crest
    bench_step_m: float = 4.0

    # laboratory
    assay_window_s: float = 1200.0
    assay_delay_h: tuple[float, float] = (2.0, 6.0)

    # sensors
    scan_hz: float = 5.0
    scan_fov_deg: float = 100.0
    scan_step_deg: float = 0.5
    scanner_baud: int = 500_000  # RS-422; a telegram reaches the pty its transfer time after the scan
    gnss_hz: float = 1.0
    encoder_hz: float = 10.0
    clock_period_s: float = 10.0
    #: the clock's period while a machine works (None: ``clock_period_s``); a service
    #: dating its readings between ticks follows a paced run's unsteady pace closer
    clock_busy_period_s: float | None = None
    idle_hz: float = 0.1   # every sensor's rate cap while no machine moves (late assays)
    #: (scan_hz, gnss_hz, encoder_hz) of a live run from its live moment on (``--live-at``);
    #: None: ``scan_hz``, ``gnss_hz``, ``encoder_hz`` throughout
    live_rates: tuple[float, float, float] | None = None

    # the yard's sources
    #: non-empty: the yard-wide sources are ``<prefix>.config``, ``<prefix>.clock``,
    #: ``<prefix>.lims`` and ``<prefix>.lab`` (not ``yard.config``, ``sim.clock``, ``lims``,
    #: ``lab1``) and the lab's assay ids ``<prefix>-AS-00001`` ..., so that two runs on one
    #: site (two beds) publish under sources and assay ids of their own
    source_prefix: str = ""
    #: whether the run publishes ``clock`` events (a yard has one clock: False for every
    #: run on a site but one)
    emits_clock: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.material, Material):
            raise TypeError("material must be a sim.material.Material")
        self.material.check_repose(self.repose_deg)
        if self.source_prefix and not is_valid_source(f"{self.source_prefix}.config"):
            raise ValueError(f"source_prefix must be letters, digits, '.', '_' or '-', "
                             f"starting with a letter or digit, got {self.source_prefix!r}")
        if self.live_rates is not None and not (
                len(self.live_rates) == 3
                and all(math.isfinite(hz) and hz > 0 for hz in self.live_rates)):
            raise ValueError(f"live_rates must be three rates > 0 Hz (scan, gnss, encoder), "
                             f"got {self.live_rates!r}")

    def yard_sources(self) -> dict[str, str]:
        """The yard-wide sources (``config``, ``clock``, ``lims``, ``lab``) -> their names:
        ``yard.config``, ``sim.clock``, ``lims``, ``lab1``, or ``<source_prefix>.<kind>``."""
        if self.source_prefix:
            return {kind: f"{self.source_prefix}.{kind}" for kind in ("config", "clock", "lims", "lab")}
        return {"config": "yard.config", "clock": "sim.clock", "lims": "lims", "lab": "lab1"}

    @property
    def benches(self) -> int:
        return len(self.cuts_per_bench)

    @property
    def lot_count(self) -> int:
        return len(self.lots)

    @property
    def stacking_s(self) -> float:
        n = self.lot_count * self.passes_per_lot
        return n * self.pass_duration_s + (n - 1) * self.pass_gap_s


def demo() -> Scenario:
    # the lab composites one-minute increments (a cross-belt sampler's cadence): the
    # belt grade drifts within a pass, and a cut at the pile's end takes the part of
    # each pass stacked there, so a grade per pass could not say what a cut delivered
    return Scenario(name="demo", assay_window_s=60.0, clock_busy_period_s=1.0)


def load() -> Scenario:
    return replace(demo(), name="load", scan_hz=75.0, scan_step_deg=0.25, gnss_hz=10.0,
                   encoder_hz=50.0, clock_period_s=0.1)


def full_scale() -> Scenario:
    # 220 m long, ~60 m wide base, ~30 m high at 37 deg: 12 lots x 3 passes
    lots = tuple(replace(lot, lot_id=f"{lot.lot_id}{k}") for k in range(3)
                 for lot in table_5_4_lots())
    return Scenario(
        name="full-scale", pile_length_m=220.0, pile_width_m=70.0, pile_origin_x_m=10.0,
        lots=lots, passes_per_lot=3, tonnes_per_pass=22_000.0, pass_duration_s=1_800.0,
        pass_gap_s=300.0, cuts_per_bench=(12, 12, 12), cut_duration_s=240.0,
        landing_min_slew_deg=30.0,
        first_bench_below_crest_m=4.0, bench_step_m=6.0, deposition_cell_m=0.5,
        scan_hz=2.0, encoder_hz=2.0)


def bench_scale() -> Scenario:
    # the thesis' laboratory pile (Table 4.1): about 1.2 m long, 0.25 m high, in metres;
    # two reclaims of 10 and 5 cuts at the bench heights of §5.3.4
    # the lab weighs the same material the pile is built of (1.65 t/m3, a laboratory
    # sand), so its assays report that density; it takes a sample every 30 s of feed (a
    # cut of the 1.2 m pile's end takes a few seconds of each layer's feed)
    lots = tuple(replace(lot, bulk_density_t_m3=1.65) for lot in table_5_4_lots("LAYER")[:4])
    return Scenario(
        name="bench-scale", pile_length_m=1.2, pile_width_m=0.8, pile_origin_x_m=0.0,
        pile_origin_y_m=0.0, surface_cell_m=0.005, voxel_m=0.02, deposition_cell_m=0.005,
        machine=replace(BENCH_SCALE, rail_x_m=0.0), scanner_offset_m=(0.0, 0.0, 0.03),
        lots=lots, passes_per_lot=1, tonnes_per_pass=0.03, pass_duration_s=300.0,
        pass_gap_s=60.0, cuts_per_bench=(10, 5), bench_heights_m=(0.15297, 0.08929),
        cut_duration_s=60.0,
        first_bench_below_crest_m=0.02, bench_step_m=0.06, bulk_density_t_m3=1.65,
        scan_hz=5.0, assay_window_s=30.0)


def cohesive() -> Scenario:
    # cohesive fines: a fresh face stands up to 50 deg (between repose and vertical: the
    # wheel's steeper face fails partly), only what is steeper fails
    return replace(demo(), name="cohesive", material=Material("cohesive", stand_angle_deg=50.0))


def delayed() -> Scenario:
    # faces stand as cut and each fails to repose as one slide 5 to 60 min after its cut
    # (cuts end about 4.4 min apart: several fail separately within the reclaim)
    return replace(demo(), name="delayed",
                   material=Material("delayed", failure_delay_s=(300.0, 3_600.0)))


def standing() -> Scenario:
    # faces never slide (lump ore that holds a cut face)
    return replace(demo(), name="standing", material=Material("standing"))


#: an LMS200 at 75 Hz, GNSS at 10 Hz, encoders at 50 Hz: the two-bed yard's live rates
TWO_BED_LIVE_RATES = (75.0, 10.0, 50.0)
#: bed B's pile starts this far along the rail (m), 80 m beyond bed A's 220 m pile
BED_B_ORIGIN_Y_M = 300.0
#: bed A starts this long after bed B (ns): stacking about 9.5 h in when B starts reclaiming
BED_A_DELAY_NS = 12 * 3600 * 1_000_000_000


def two_bed_stack() -> Scenario:
    # bed A: being stacked while bed B is reclaimed; it publishes the yard's clock
    return replace(full_scale(), name="two-bed-stack", pile_id="A", machine_id="bwr1",
                   stacker_id="stk1", pile_origin_y_m=0.0, source_prefix="bedA",
                   emits_clock=True, start_ns=DEFAULT_START_NS + BED_A_DELAY_NS,
                   live_rates=TWO_BED_LIVE_RATES)


def two_bed_reclaim() -> Scenario:
    # bed B: beyond bed A along the same rail, its own machines, lots and sources, no clock
    lots = tuple(replace(lot, lot_id=f"{lot.lot_id}-B") for lot in full_scale().lots)
    return replace(full_scale(), name="two-bed-reclaim", pile_id="B", machine_id="bwr2",
                   stacker_id="stk2", pile_origin_y_m=BED_B_ORIGIN_Y_M, lots=lots,
                   source_prefix="bedB", emits_clock=False, start_ns=DEFAULT_START_NS,
                   live_rates=TWO_BED_LIVE_RATES)


SCENARIOS = {"demo": demo, "full-scale": full_scale, "bench-scale": bench_scale, "load": load,
             "cohesive": cohesive, "delayed": delayed, "standing": standing,
             "two-bed-stack": two_bed_stack, "two-bed-reclaim": two_bed_reclaim}


def scenario_by_name(name: str) -> Scenario:
    try:
        return SCENARIOS[name]()
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}") from None
