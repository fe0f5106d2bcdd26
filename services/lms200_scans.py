"""What the scanner service makes of an LMS200 telegram, without I/O: angles, time, message.

:func:`scan_field` gives the angles of a scan of ``count`` values (:class:`ScanField`,
the Foxglove ``LaserScan`` / ROS convention, as :mod:`sim.scanner` computes them);
:func:`transfer_time_ns`, :func:`telegram_end_offsets` and :func:`scan_valid_time_ns`
date a scan by when its first byte went on the serial line; :func:`scan_message` builds
the ``foxglove.LaserScan``.  :mod:`services.scanner` is the service that uses them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

from devices import lms200
from schemas.events import set_timestamp_ns
from schemas.times import NS_PER_S

__all__ = ["BITS_PER_BYTE", "ScanField", "scan_field", "transfer_time_ns",
           "telegram_end_offsets", "scan_valid_time_ns", "scan_message"]

#: Bits on the line per byte: start bit, 8 data bits, stop bit (8N1).
BITS_PER_BYTE = 10
#: tolerance when checking that a field of view is a whole number of steps, degrees
_FIELD_TOLERANCE_DEG = 1e-6


@dataclass(frozen=True)
class ScanField:
    """Angles of one scan, radians (Foxglove ``LaserScan``: bearing about +z from +x).

    Attributes
    ----------
    start_angle_rad, end_angle_rad : float
        Bearing of the first and the last value.
    count : int
        Values per scan.
    """

    start_angle_rad: float
    end_angle_rad: float
    count: int


def scan_field(count: int, fov_deg: float | None = None,
               resolution_deg: float | None = None) -> ScanField:
    """The angles of a scan of ``count`` values.

    Beam ``k`` has bearing ``-fov/2 + k * step`` (the simulator's
    :func:`sim.scanner.beam_angles_rad`, computed the same way so the angles
    agree to the last bit).

    Parameters
    ----------
    count : int
        Values in the telegram.
    fov_deg, resolution_deg : float, optional
        Field of view and step, degrees.  Both None: the LMS200 field for the count
        (:func:`devices.lms200.field_for_count`).  One given: the other follows
        from ``fov = (count - 1) * step``.  Both given: they must agree with the count.

    Returns
    -------
    ScanField

    Raises
    ------
    ValueError
        If the count is not an LMS200 count (nothing given), or does not fit the given
        field: ``fov != (count - 1) * step``.
    """
    if count < 2:
        raise ValueError(f"a scan needs at least 2 values, got {count}")
    if fov_deg is None and resolution_deg is None:
        fov_deg, resolution_deg = lms200.field_for_count(count)
    elif fov_deg is None:
        fov_deg = resolution_deg * (count - 1)
    elif resolution_deg is None:
        resolution_deg = fov_deg / (count - 1)
    elif abs(resolution_deg * (count - 1) - fov_deg) > _FIELD_TOLERANCE_DEG:
        raise ValueError(f"{count} values do not fit a {fov_deg:g} deg field at "
                         f"{resolution_deg:g} deg steps (that needs "
                         f"{round(fov_deg / resolution_deg) + 1} values)")
    start = math.radians(-0.5 * fov_deg)
    end = math.radians(-0.5 * fov_deg + resolution_deg * (count - 1))
    return ScanField(start_angle_rad=start, end_angle_rad=end, count=int(count))


def transfer_time_ns(n_bytes: int, baud: int) -> int:
    """Time the line takes to carry ``n_bytes`` bytes at ``baud`` (8N1: 10 bits a byte), ns."""
    return n_bytes * BITS_PER_BYTE * NS_PER_S // baud


def telegram_end_offsets(window: bytes, telegrams: list[bytes]) -> list[int]:
    """Where each telegram ends in the bytes the reader held plus the bytes just read.

    Parameters
    ----------
    window : bytes
        The reader's unconsumed bytes before the feed followed by the bytes fed.
    telegrams : list of bytes
        What :meth:`TelegramReader.feed` returned for them, in order.

    Returns
    -------
    list of int
        Offset just past each telegram in ``window``.  The reader returns the first
        CRC-valid candidate at or after the previous telegram's end, so the first match
        of its bytes from there is the telegram itself.  A telegram not found (which the
        reader's contract rules out) is taken to end at the window's end.
    """
    ends: list[int] = []
    pos = 0
    for telegram in telegrams:
        start = window.find(telegram, pos)
        end = len(window) if start < 0 else start + len(telegram)
        ends.append(end)
        pos = end if start >= 0 else pos
    return ends


def scan_valid_time_ns(window_end_ns: int, bytes_behind: int, telegram_bytes: int,
                       baud: int, not_before_ns: int | None = None) -> int:
    """Valid time of a scan: when its first byte went on the line.

    Parameters
    ----------
    window_end_ns : int
        Time the last byte read so far arrived (site time, UTC ns).
    bytes_behind : int
        Bytes that arrived after the telegram's last byte, up to that moment.
    telegram_bytes : int
        The telegram's length in bytes.
    baud : int
        Line rate.
    not_before_ns : int, optional
        Earliest possible arrival of the telegram's last byte (the previous read, UTC ns):
        the line-rate estimate is not taken back past it.

    Returns
    -------
    int
        ``max(window_end_ns - transfer_time(bytes_behind), not_before_ns)
        - transfer_time(telegram_bytes)``, UTC ns.
    """
    last_byte_ns = window_end_ns - transfer_time_ns(bytes_behind, baud)
    if not_before_ns is not None and last_byte_ns < not_before_ns:
        last_byte_ns = not_before_ns
    return last_byte_ns - transfer_time_ns(telegram_bytes, baud)


def scan_message(ranges_m: np.ndarray, valid_time_ns: int, frame_id: str,
                 geometry: ScanField) -> LaserScan:
    """A ``foxglove.LaserScan`` for one measurement.

    Parameters
    ----------
    ranges_m : numpy.ndarray of float, shape (n,)
        Ranges, metres; NaN for no return / error codes.
    valid_time_ns : int
        The scan's valid time, UTC ns (its ``timestamp``).
    frame_id : str
        Scanner frame.
    geometry : ScanField
        Start and end angles (``geometry.count`` must equal n).

    Returns
    -------
    LaserScan
        With an identity pose (the scan origin is the frame origin) and no intensities.
    """
    if ranges_m.shape != (geometry.count,):
        raise ValueError(f"{ranges_m.shape[0]} ranges for a {geometry.count}-value field")
    msg = LaserScan(frame_id=frame_id, start_angle=geometry.start_angle_rad,
                    end_angle=geometry.end_angle_rad)
    set_timestamp_ns(msg.timestamp, valid_time_ns)
    msg.pose.orientation.w = 1.0
    msg.ranges.extend(ranges_m.tolist())
    return msg
