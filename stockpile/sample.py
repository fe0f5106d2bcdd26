"""A generated sample yard session, as canonical JSON lines in arrival order.

Until the yard simulator exists this is the embedded default behind ``make demo``.
It is small (about 12,000 events over 6 simulated hours) but exercises everything
the ledger does: declarations, stacking passes, sensor streams, reclaim cuts, a
site clock, assays that arrive hours late (one before its lot is declared, one
superseded), and bad input (malformed lines, an infinite scan range, a conflicting
retransmission, an exact retransmission, a dropped sequence number).

Lines are in *arrival* order; recorded time comes from the ``clock`` events
(import with ``--clock events``).  Deterministic for a given seed.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from google.protobuf.message import Message

from schemas import pb
from schemas.events import make_event, set_timestamp_ns
from schemas.jsonl import encode_line

#: 2026-11-01T00:00:00Z
SESSION_START_NS = 1_793_491_200_000_000_000
S = 1_000_000_000  # ns per second

ANALYTES = ("Fe", "SiO2", "Al2O3", "P", "LOI")
#: planned grades of the sample's lots, mass % (magnitudes of thesis Table 5.4)
LOT_GRADES = {
    "LOT-A": {"Fe": 62.4, "SiO2": 3.9, "Al2O3": 2.2, "P": 0.08, "LOI": 5.1},
    "LOT-B": {"Fe": 60.8, "SiO2": 5.6, "Al2O3": 2.6, "P": 0.10, "LOI": 5.6},
    "LOT-C": {"Fe": 63.1, "SiO2": 3.2, "Al2O3": 1.9, "P": 0.07, "LOI": 4.8},
}


@dataclass
class _Stream:
    source: str
    epoch: int
    seq: int = 0


@dataclass
class SampleSession:
    """The generated lines plus what was planted in them, for the demo's report."""

    lines: list[str] = field(default_factory=list)
    planted: dict[str, int] = field(default_factory=dict)
    start_ns: int = SESSION_START_NS
    end_ns: int = SESSION_START_NS


def _stamp(message: Message, name: str, t_ns: int) -> Message:
    set_timestamp_ns(getattr(message, name), t_ns)
    return message


def generate_sample(seed: int = 7, hours: float = 6.0) -> SampleSession:
    """Generate the sample session; see the module docstring."""
    rng = random.Random(seed)
    t0 = SESSION_START_NS
    end = t0 + int(hours * 3600 * S)
    arrivals: list[tuple[int, int, Message, _Stream]] = []  # (arrival ns, order, msg, stream)
    order = 0

    def emit(arrival_ns: int, message: Message, stream: _Stream) -> None:
        nonlocal order
        arrivals.append((arrival_ns, order, message, stream))
        order += 1

    config = _Stream("yard.config", 1)
    clock = _Stream("sim.clock", 1)
    joints = _Stream("bwr1.encoders", 1)
    poses = _Stream("bwr1.localizer", 1)
    scanner = _Stream("bwr1.scanner", 1)
    belt = _Stream("stacker1.belt", 1)
    reclaimer = _Stream("bwr1.control", 1)
    lab = _Stream("lab1", 1)

    emit(t0, _stamp(pb.SiteDeclared(site_id="demo", datum_lat_deg=-20.3, datum_lon_deg=118.6,
                                     datum_alt_m=6.0), "time", t0), config)
    emit(t0, _stamp(pb.PileDeclared(pile_id="P1", origin_x_m=0.0, origin_y_m=0.0, length_m=220.0,
                                    width_m=60.0, ground_z_m=0.0, cell_m=0.25, voxel_m=1.0,
                                    default_bulk_density_t_m3=2.4), "time", t0), config)
    machine = pb.MachineDeclared(
        machine_id="bwr1", kind=pb.BUCKET_WHEEL_RECLAIMER, rail_x_m=-10.0, rail_z_m=0.0,
        l2_m=6.0, l3_m=5.0, l4_m=5.0, l5_m=50.0, wheel_radius_m=7.0, cutting_radius_m=10.0,
        wheel_tilt_rad=math.radians(5), bucket_width_m=1.2, fall_angle_rad=math.radians(15))
    machine.scanner.parent_frame_id = "bwr1/wheel"
    machine.scanner.child_frame_id = "bwr1/scanner"
    machine.scanner.translation.z = 3.0
    machine.scanner.rotation.w = 1.0
    emit(t0, _stamp(machine, "time", t0), config)

    # stacking: three lots, two passes each, over the first 3 hours
    pass_length_s = 1800
    lot_times = {}
    for i, (lot, grade) in enumerate(LOT_GRADES.items()):
        declared = t0 + (i * 2 * pass_length_s + 60) * S
        lot_times[lot] = declared
        lot_msg = pb.LotDeclared(lot_id=lot, origin=f"pit-{i + 1}", planned_tonnes=24_000.0)
        lot_msg.planned_grade.update(grade)
        # LOT-C's first assay arrives before LOT-C is declared: it will be flagged
        emit(declared, _stamp(lot_msg, "time", declared), config)
        for p in range(2):
            start = declared + (p * pass_length_s + 30) * S
            stop = start + (pass_length_s - 60) * S
            pass_id = f"{lot}-pass{p + 1}"
            emit(start, _stamp(pb.StackStarted(pile_id="P1", pass_id=pass_id, lot_id=lot,
                                               machine_id="stacker1", pattern=pb.CHEVRON,
                                               start_y_m=10.0, end_y_m=210.0), "time", start), belt)
            tonnes = 12_000.0 * rng.uniform(0.99, 1.01)
            emit(stop, _stamp(pb.StackEnded(pile_id="P1", pass_id=pass_id, tonnes=tonnes),
                              "time", stop), belt)
            # one assay per pass, reported 2-4 hours after its window closed
            late = int(rng.uniform(2.0, 4.0) * 3600 * S)
            assay = pb.Assay(assay_id=f"{pass_id}-A", lot_id=lot, status=pb.PROVISIONAL,
                             lab_id="lab1", moisture_pct=rng.uniform(4, 7),
                             bulk_density_t_m3=rng.uniform(2.3, 2.5))
            for a in ANALYTES:
                assay.analytes[a] = round(grade[a] * rng.uniform(0.97, 1.03), 3)
            _stamp(assay, "window_start", start)
            _stamp(assay, "window_end", stop)
            arrival = stop + late
            if lot == "LOT-C" and p == 0:
                arrival = declared - 120 * S  # before its lot: accepted and flagged
                _stamp(assay, "window_start", declared - 600 * S)
                _stamp(assay, "window_end", declared - 300 * S)
            _stamp(assay, "reported_time", arrival)
            emit(arrival, assay, lab)
            if lot == "LOT-A" and p == 0:
                final = pb.Assay()
                final.CopyFrom(assay)
                final.assay_id = f"{pass_id}-A-final"
                final.status = pb.FINAL
                final.supersedes = assay.assay_id
                final.analytes["Fe"] = round(final.analytes["Fe"] - 0.4, 3)
                _stamp(final, "reported_time", arrival + 3600 * S)
                emit(arrival + 3600 * S, final, lab)

    # reclaiming: a bench of cuts in the last two hours
    for c in range(8):
        start = t0 + int((4 * 3600 + c * 600) * S)
        stop = start + 480 * S
        cut = pb.ReclaimCut(pile_id="P1", cut_id=f"B1-C{c + 1}", bench_id="B1", machine_id="bwr1",
                            travel_m=20.0 + 1.08 * c, luff_rad=math.radians(-8),
                            slew_start_rad=math.radians(30), slew_end_rad=math.radians(80),
                            tonnes=rng.uniform(1400, 1700))
        _stamp(cut, "start_time", start)
        _stamp(cut, "end_time", stop)
        emit(stop, cut, reclaimer)

    # sensors and the clock
    for t in range(t0, end + 1, 10 * S):
        emit(t, _stamp(pb.Clock(), "time", t), clock)
    for k, t in enumerate(range(t0, end, 5 * S)):
        travel = 20.0 + 10.0 * math.sin(k / 400.0)
        slew = math.radians(55.0 + 25.0 * math.sin(k / 37.0))
        luff = math.radians(-8.0)
        emit(t, _stamp(pb.JointReading(machine_id="bwr1", travel_m=travel + rng.gauss(0, 0.002),
                                       slew_rad=slew, luff_rad=luff), "time", t), joints)
        pose = FrameTransform(parent_frame_id="site", child_frame_id="bwr1/wheel")
        rho = 5.0 + 50.0 * math.cos(luff)
        pose.translation.x = -10.0 + rho * math.sin(slew)
        pose.translation.y = travel + rho * math.cos(slew)
        pose.translation.z = 11.0 + 50.0 * math.sin(luff)
        pose.rotation.z, pose.rotation.w = math.sin(slew / 2), math.cos(slew / 2)
        emit(t, _stamp(pose, "timestamp", t), poses)
    for t in range(t0, end, 30 * S):
        scan = LaserScan(frame_id="bwr1/scanner", start_angle=math.radians(-50),
                         end_angle=math.radians(50))
        for i in range(401):
            r = 25.0 + 8.0 * math.cos(math.radians(-50 + i * 0.25)) + rng.gauss(0, 0.015)
            scan.ranges.append(r if rng.random() > 0.01 else math.nan)
        emit(t, _stamp(scan, "timestamp", t), scanner)

    # at equal arrival times the clock ticks first, so nothing is recorded before the clock
    arrivals.sort(key=lambda a: (a[0], a[3] is not clock, a[1]))
    session = SampleSession(start_ns=t0, end_ns=end)
    planted = {"malformed_lines": 0, "bad_scans": 0, "conflicts": 0, "retransmissions": 0,
               "dropped": 0}
    for arrival, _, message, stream in arrivals:
        event = make_event(message, source=stream.source, epoch=stream.epoch, seq=stream.seq)
        stream.seq += 1
        if stream is joints and event.seq == 1000:
            planted["dropped"] += 1  # lost on the network: leaves a gap in the ledger
            continue
        line = encode_line(event.type, event.source, event.epoch, event.seq,
                           event.valid_time_ns, event.payload)
        session.lines.append(line)
        if stream is scanner and event.seq == 100:
            # a scanner glitch: an infinite range (quarantined)
            bad = LaserScan()
            bad.CopyFrom(message)
            bad.ranges[200] = math.inf
            bad_event = make_event(bad, source=stream.source, epoch=stream.epoch, seq=stream.seq)
            stream.seq += 1
            session.lines.append(encode_line(bad_event.type, bad_event.source, bad_event.epoch,
                                             bad_event.seq, bad_event.valid_time_ns,
                                             bad_event.payload))
            planted["bad_scans"] += 1
        if stream is poses and event.seq == 2000:
            session.lines.append(line)  # an exact retransmission: a duplicate, no-op
            planted["retransmissions"] += 1
            # a conflicting retransmission: same identity, different payload
            rival = FrameTransform()
            rival.CopyFrom(message)
            rival.translation.x += 0.5
            session.lines.append(encode_line(event.type, event.source, event.epoch, event.seq,
                                             event.valid_time_ns, rival.SerializeToString()))
            planted["conflicts"] += 1
        if stream is joints and event.seq == 3000:
            session.lines.append('{"type": "joint_reading", "source": "bwr1.encoders", ')
            session.lines.append("garbage from a half-written file")
            planted["malformed_lines"] += 2
    session.planted = planted
    return session

