"""What the localizer reads and publishes: fixes in the site frame, estimates as messages.

:func:`fix_enu_m` and :func:`fix_covariance_m2` turn a ``foxglove.LocationFix`` into the
site ENU position and covariance the filter fuses; :func:`estimate_messages` turns an
estimate into the ``joint_estimate`` and the two ``frame_transform`` messages
(``<machine>/wheel``, ``<machine>/scanner``) the localizer service publishes, the poses by
:mod:`projector.kinematics`.
"""

from __future__ import annotations

import numpy as np
import pymap3d
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

from schemas import pb
from schemas.events import set_timestamp_ns
from projector.kinematics import (MachineGeometry, scanner_pose, wheel_centre_m,
                                  wheel_quaternion_xyzw)

__all__ = ["fix_enu_m", "fix_covariance_m2", "estimate_messages", "VERTICAL_FACTOR"]

#: vertical / horizontal sd of a fix that carries no covariance
VERTICAL_FACTOR = 1.7


def fix_enu_m(fix, datum: tuple[float, float, float]) -> np.ndarray:
    """A ``foxglove.LocationFix`` position in the site ENU frame (3,) (m)."""
    e, n, u = pymap3d.geodetic2enu(fix.latitude, fix.longitude, fix.altitude, *datum)
    return np.array([float(e), float(n), float(u)])


def fix_covariance_m2(fix, default_sd_m: float) -> np.ndarray:
    """The fix's ENU covariance (3, 3) in m^2, or a default when it carries none.

    ``position_covariance_type`` UNKNOWN (0), a covariance that is not 9 finite values,
    or one with a non-positive diagonal gives ``diag(sd^2, sd^2, (1.7 sd)^2)``;
    DIAGONAL_KNOWN keeps only the diagonal.
    """
    c = np.asarray(fix.position_covariance, float)
    kind = int(fix.position_covariance_type)
    if kind == 0 or c.size != 9 or not np.all(np.isfinite(c)):
        return np.diag([default_sd_m ** 2, default_sd_m ** 2,
                        (VERTICAL_FACTOR * default_sd_m) ** 2])
    c = c.reshape(3, 3)
    if not np.all(np.diag(c) > 0):
        return np.diag([default_sd_m ** 2, default_sd_m ** 2,
                        (VERTICAL_FACTOR * default_sd_m) ** 2])
    if kind == 2:  # DIAGONAL_KNOWN
        c = np.diag(np.diag(c))
    return 0.5 * (c + c.T)


def _timestamp(message, name: str, t_ns: int):
    set_timestamp_ns(getattr(message, name), t_ns)
    return message


def estimate_messages(machine_id: str, geometry: MachineGeometry, t_ns: int, joints,
                      joint_cov, position_cov_m2) -> list:
    """The ``joint_estimate`` and the two ``frame_transform`` messages of one estimate.

    Parameters
    ----------
    machine_id : str
    geometry : MachineGeometry
    t_ns : int
        Valid time (UTC ns).
    joints : array_like (3,)
        (travel m, slew rad, luff rad).
    joint_cov, position_cov_m2 : array_like (3, 3)
        Joint covariance and wheel-centre covariance (m^2).
    """
    j = np.asarray(joints, float)
    est = pb.JointEstimate(machine_id=machine_id, travel_m=float(j[0]), slew_rad=float(j[1]),
                           luff_rad=float(j[2]))
    est.covariance.extend(float(v) for v in np.asarray(joint_cov, float).reshape(9))
    est.position_covariance_m2.extend(float(v) for v in
                                      np.asarray(position_cov_m2, float).reshape(9))
    _timestamp(est, "time", t_ns)
    out = [est]
    centre = wheel_centre_m(geometry, j)
    q_wheel = wheel_quaternion_xyzw(float(j[1]))
    scanner_p, scanner_q = scanner_pose(geometry, j)
    for child, p, q in ((f"{machine_id}/wheel", centre, q_wheel),
                        (f"{machine_id}/scanner", scanner_p, scanner_q)):
        ft = FrameTransform(parent_frame_id="site", child_frame_id=child)
        ft.translation.x, ft.translation.y, ft.translation.z = (float(v) for v in p)
        ft.rotation.x, ft.rotation.y, ft.rotation.z, ft.rotation.w = (float(v) for v in q)
        out.append(_timestamp(ft, "timestamp", t_ns))
    return out
