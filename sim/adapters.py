"""The simulated yard's devices for the real adapters (``stockpile sim --adapters real``).

With ``Simulation(adapters="real")`` the runner does not publish the machines' and the
laboratory's facts itself; it hands them to the devices a real yard has, and the
product's adapters carry them into the yard:

* the reclaimer's joint encoders, the stacker's passes and the reclaimer's cuts go to an
  OPC UA server (:class:`sim.opcua_server.PlcServer`, the tags of ``sim/plc_map.toml``,
  the map ``docs/plc.example.toml`` shows; read by ``stockpile service plc``);
* the laboratory's results go as LIMS CSV exports into a drop folder
  (:class:`sim.lims.LimsDropWriter`, map :data:`sim.lims.MAP_TOML`; read by
  ``stockpile service lab``);
* the scans go to an emulated SICK LMS511 on loopback TCP (:class:`sim.lms511.Lms511Server`,
  CoLa-B, a 190 deg field at 0.5 deg steps; read by ``stockpile service scanner --tcp``).

:class:`RealDevices` opens, drives and closes the three.  The runner still writes every
fact to ``events.jsonl`` (the record of the run, not published), but publishes only the
lots, the yard's declarations and the clock.  A scan is sent when site time reaches its
scan time plus the LMS511's latency, after a clock tick (as an LMS200 telegram is);
``lms200.bin`` stays empty.  ``Simulation`` makes and starts the devices when not given
them; the caller closes them (``sim.devices.close()``) once the adapters have read all.
"""

from __future__ import annotations

import shutil
import socket
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from devices.opcua_tags import load_map
from schemas.times import NS_PER_S
from sim.grades import LabResult
from sim.lims import LimsDropWriter, write_map
from sim.lms511 import Lms511Server
from sim.opcua_server import PlcServer
from sim.scenario import Scenario

__all__ = ["ADAPTER_MODES", "PLC_MAP", "LMS511_FIELD_DEG", "LMS511_SCAN_HZ", "RealDevices",
           "check_adapters", "free_port"]

#: values of ``Simulation.adapters`` / ``--adapters``
ADAPTER_MODES = ("sim", "real")
#: the PLC tag map the simulated PLCs serve (its machines are the scenarios' bwr1, stk1)
PLC_MAP = Path(__file__).with_name("plc_map.toml")  # docs/plc.example.toml, packaged
#: the emulated LMS511's field and angular step, degrees
LMS511_FIELD_DEG = (190.0, 0.5)
#: the scan frequency the LMS511's telegrams state, Hz (its latency is one period)
LMS511_SCAN_HZ = 25.0


def check_adapters(adapters: str, scan_events: str, scanner_pty: object | None) -> bool:
    """Whether ``adapters`` is ``"real"``; ValueError for another mode than
    :data:`ADAPTER_MODES`, or for real devices with scan events or an LMS200 pty."""
    if adapters not in ADAPTER_MODES:
        raise ValueError(f"adapters must be one of {', '.join(ADAPTER_MODES)}, got {adapters!r}")
    real = adapters == "real"
    if real and (scan_events != "off" or scanner_pty is not None):
        raise ValueError("adapters 'real' sends the scans to the LMS511: no scan events, "
                         "no LMS200 pty")
    return real


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (bound and released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


@dataclass
class RealDevices:
    """The OPC UA PLC server, the LIMS drop folder and the LMS511 of one run.

    Parameters
    ----------
    scenario : Scenario
        The run's scenario (its machine and stacker ids must be the map's).
    out_dir : Path
        The run's folder: ``plc.toml`` and ``lims.toml`` (the maps the adapters read) are
        written there, and the drop folder is ``lims-drop/`` unless ``lims_dir`` is given.
    plc_port, lms_port : int
        Loopback ports of the OPC UA server and the LMS511 (0: a free one).
    lims_dir : Path, optional
        The LIMS drop folder.
    certificate, private_key : Path, optional
        The OPC UA server's application certificate and key (``Basic256Sha256``
        ``SignAndEncrypt``); without them the server offers no security (loopback only).
    corrupt_rate : float
        Fraction of LMS511 telegrams corrupted (needs ``rng`` when > 0).
    rng : numpy.random.Generator, optional
        The LMS511's fault stream.
    """

    scenario: Scenario
    out_dir: Path
    plc_port: int = 0
    lms_port: int = 0
    lims_dir: Path | None = None
    certificate: Path | None = None
    private_key: Path | None = None
    corrupt_rate: float = 0.0
    rng: np.random.Generator | None = None

    def __post_init__(self) -> None:
        sc = self.scenario
        self.out_dir = Path(self.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.plc_map_path = self.out_dir / "plc.toml"
        shutil.copyfile(PLC_MAP, self.plc_map_path)
        plc_map = load_map(self.plc_map_path)
        missing = {sc.machine_id, sc.stacker_id} - set(plc_map.machines)
        if missing:
            raise ValueError(f"the PLC map {PLC_MAP} has no machine {sorted(missing)[0]!r}")
        self.lims_map_path = write_map(self.out_dir / "lims.toml")
        self.lims_dir = Path(self.lims_dir or self.out_dir / "lims-drop")
        # the PLCs' state at start (idle, no ids, 0 t) is stamped a second before the first
        # encoder sample, so that sample is newer than it (an adapter handles each instant once)
        self.plc = PlcServer(plc_map, port=self.plc_port or free_port(),
                             certificate=self.certificate, private_key=self.private_key,
                             start_ns=sc.start_ns - NS_PER_S)
        self.lims = LimsDropWriter(self.lims_dir)
        self.lms = Lms511Server("127.0.0.1", self.lms_port, "cola-b",
                                scan_frequency_hz=LMS511_SCAN_HZ, corrupt_rate=self.corrupt_rate,
                                rng=self.rng)
        self.started = False
        #: what the devices handed out: encoder samples, passes, cuts, assays, scans sent
        self.counts = {"encoder_samples": 0, "passes": 0, "cuts": 0, "assays": 0,
                       "scans_sent": 0, "scans_corrupted": 0}

    def start(self) -> RealDevices:
        """Start the OPC UA server and the LMS511 (both listen once this returns)."""
        self.plc.start()
        try:
            self.lms.start()
        except BaseException:
            self.plc.stop()
            raise
        self.started = True
        return self

    def close(self) -> None:
        """Stop both servers."""
        if self.started:
            self.lms.close()
            self.plc.stop()
            self.started = False

    # -- what the runner hands over ---------------------------------------------------------

    def encoder_sample(self, t_ns: int, travel_m: float, slew_rad: float, luff_rad: float) -> None:
        """One reading of the reclaimer's encoders (m, rad, rad) at site time ``t_ns``."""
        self.plc.encoder_sample(t_ns, travel_m, slew_rad, luff_rad,
                                machine=self.scenario.machine_id)
        self.counts["encoder_samples"] += 1

    def pass_started(self, t_ns: int, p: dict) -> None:
        """The stacker starts pass ``p`` (a pass as the runner plans it)."""
        sc = self.scenario
        self.plc.pass_started(t_ns, pass_id=p["pass_id"], lot_id=p["lot"].lot_id,
                              pile_id=sc.pile_id, start_y_m=p["y0"], end_y_m=p["y1"],
                              machine=sc.stacker_id)

    def pass_ended(self, t_ns: int, belt_tonnes: float) -> None:
        """The stacker's pass ends with ``belt_tonnes`` on its belt scale."""
        self.plc.pass_ended(t_ns, belt_tonnes, machine=self.scenario.stacker_id)
        self.counts["passes"] += 1

    def cut_started(self, t_ns: int, c: dict, cut_id: str) -> None:
        """The reclaimer starts cut ``c`` (a cut as the runner plans it)."""
        sc = self.scenario
        self.plc.cut_started(t_ns, cut_id=cut_id, bench_id=f"B{c['bench'] + 1}",
                             pile_id=sc.pile_id, travel_m=c["travel"], luff_rad=c["luff"],
                             slew_start_rad=c["slew_start"], slew_end_rad=c["slew_end"],
                             machine=sc.machine_id)

    def cut_ended(self, t_ns: int, belt_tonnes: float) -> None:
        """The reclaimer's cut ends with ``belt_tonnes`` on its belt scale."""
        self.plc.cut_ended(t_ns, belt_tonnes, machine=self.scenario.machine_id)
        self.counts["cuts"] += 1

    def assay(self, t_ns: int, result: LabResult) -> None:
        """The laboratory reports ``result`` at site time ``t_ns``: one LIMS export file."""
        self.lims.write(t_ns, [result])
        self.counts["assays"] += 1

    def scan(self, t_ns: int, ranges_m: np.ndarray, angles_rad: np.ndarray) -> None:
        """The scan taken at ``t_ns`` (ranges m, NaN: no return; beam bearings rad, evenly
        stepped), sent now (at ``t_ns`` + the LMS511's latency)."""
        start, step = float(angles_rad[0]), float(angles_rad[1] - angles_rad[0])
        sent = self.lms.send_scan(t_ns, ranges_m, start, step)
        if sent.sent:
            self.counts["scans_sent"] += 1
            self.counts["scans_corrupted"] += bool(sent.fault)

    def summary(self) -> str:
        """One line: what went through the devices."""
        c = self.counts
        return (f"devices: {c['encoder_samples']:,} encoder samples, {c['passes']} passes and "
                f"{c['cuts']} cuts over OPC UA; {c['assays']} assays in LIMS files; "
                f"{c['scans_sent']:,} LMS511 telegrams sent ({c['scans_corrupted']} corrupted)")
