"""The yard's events as the simulator emits them: protobuf messages with their times.

Builders for every message a simulated yard publishes (declarations, lots, stacking and
reclaim events, joint readings, assays, clock ticks, and the scanner's poses of the
``scan_events`` option), each stamped with its site time (UTC ns). The runner hands them
to its :class:`~sim.publish.Producer`\\ s; nothing here draws random numbers.
"""

from __future__ import annotations

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from scipy.spatial.transform import Rotation

from schemas import pb
from schemas.events import set_timestamp_ns
from sim.grades import LabResult, LotSpec
from sim.kinematics import Machine
from sim.motion import SCANNER_IN_WHEEL
from sim.scenario import Scenario


def stamp(message, field_name: str, t_ns: int):
    """Set the timestamp field ``field_name`` of ``message`` to ``t_ns``; returns it."""
    set_timestamp_ns(getattr(message, field_name), int(t_ns))
    return message


def declarations(sc: Scenario, m: Machine, t: int) -> list:
    """The site, the pile and both machines (the reclaimer with its scanner mount)."""
    site = pb.SiteDeclared(site_id=sc.site_id, datum_lat_deg=sc.datum_lat_deg,
                           datum_lon_deg=sc.datum_lon_deg, datum_alt_m=sc.datum_alt_m,
                           crs_epsg=sc.crs_epsg)
    out = [stamp(site, "time", t)]
    pile = pb.PileDeclared(pile_id=sc.pile_id, origin_x_m=sc.pile_origin_x_m,
                           origin_y_m=sc.pile_origin_y_m, length_m=sc.pile_length_m,
                           width_m=sc.pile_width_m, ground_z_m=sc.ground_z_m,
                           cell_m=sc.surface_cell_m, voxel_m=sc.voxel_m,
                           default_bulk_density_t_m3=sc.bulk_density_t_m3)
    out.append(stamp(pile, "time", t))
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
            msg.scanner.translation.x, msg.scanner.translation.y, msg.scanner.translation.z = \
                sc.scanner_offset_m
            (msg.scanner.rotation.x, msg.scanner.rotation.y, msg.scanner.rotation.z,
             msg.scanner.rotation.w) = (float(v) for v in quat)
        out.append(stamp(msg, "time", t))
    return out


def clock(t: int):
    return stamp(pb.Clock(), "time", t)


def lot_declared(sc: Scenario, lot: LotSpec, t: int):
    msg = pb.LotDeclared(lot_id=lot.lot_id, origin=lot.origin,
                         planned_tonnes=sc.passes_per_lot * sc.tonnes_per_pass)
    msg.planned_grade.update(lot.planned_grade())
    return stamp(msg, "time", t)


def stack_started(sc: Scenario, p: dict, t: int):
    """``p`` is a pass of :func:`sim.timetable.stacking_plan`."""
    msg = pb.StackStarted(pile_id=sc.pile_id, pass_id=p["pass_id"], lot_id=p["lot"].lot_id,
                          machine_id=sc.stacker_id, pattern=getattr(pb, sc.pattern),
                          start_y_m=p["y0"], end_y_m=p["y1"])
    return stamp(msg, "time", t)


def stack_ended(sc: Scenario, pass_id: str, belt_tonnes: float, t: int):
    msg = pb.StackEnded(pile_id=sc.pile_id, pass_id=pass_id, tonnes=round(belt_tonnes, 1))
    return stamp(msg, "time", t)


def reclaim_cut(sc: Scenario, c: dict, cut_id: str, belt_tonnes: float):
    """``c`` is a cut as the runner plans it (bench, travel, luff, slews, t0, t1)."""
    msg = pb.ReclaimCut(pile_id=sc.pile_id, cut_id=cut_id, bench_id=f"B{c['bench'] + 1}",
                        machine_id=sc.machine_id, travel_m=c["travel"], luff_rad=c["luff"],
                        slew_start_rad=c["slew_start"], slew_end_rad=c["slew_end"],
                        tonnes=round(belt_tonnes, 1))
    stamp(msg, "start_time", c["t0"])
    stamp(msg, "end_time", c["t1"])
    return msg


def assay(r: LabResult):
    msg = pb.Assay(assay_id=r.assay_id, lot_id=r.lot_id, moisture_pct=r.moisture_pct,
                   bulk_density_t_m3=r.bulk_density_t_m3, status=getattr(pb, r.status),
                   supersedes=r.supersedes, lab_id=r.lab_id)
    msg.analytes.update(r.analytes_pct)
    msg.repeatability_pp.update({a: sd for a, sd in r.repeatability_pct.items()
                                 if a in r.analytes_pct})
    stamp(msg, "window_start", r.window_start_ns)
    stamp(msg, "window_end", r.window_end_ns)
    stamp(msg, "reported_time", r.reported_ns)
    return msg


def joint_reading(machine_id: str, travel_m, slew_rad, luff_rad, t: int):
    msg = pb.JointReading(machine_id=machine_id, travel_m=float(travel_m),
                          slew_rad=float(slew_rad), luff_rad=float(luff_rad))
    return stamp(msg, "time", t)


def scanner_transform(machine_id: str, position, rotation, t: int):
    """The scanner's pose (position (3,) m, rotation (3, 3)) as a site -> scanner
    ``FrameTransform`` (quaternion with w >= 0)."""
    quat = Rotation.from_matrix(rotation).as_quat()  # x, y, z, w
    if quat[3] < 0:
        quat = -quat
    ft = FrameTransform(parent_frame_id="site", child_frame_id=f"{machine_id}/scanner")
    ft.translation.x, ft.translation.y, ft.translation.z = (float(v) for v in position)
    ft.rotation.x, ft.rotation.y, ft.rotation.z, ft.rotation.w = (float(v) for v in quat)
    return stamp(ft, "timestamp", t)
