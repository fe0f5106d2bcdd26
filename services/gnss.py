"""``stockpile service gnss``: read NMEA GGA from a GNSS receiver's serial port, publish fixes.

The service opens the receiver's serial port with pyserial (a real port, or the simulator's
pseudo-terminal), splits the byte stream into checksum-valid sentences with
:class:`devices.nmea.NmeaReader`, parses GGA sentences with
:func:`~devices.nmea.parse_gga` and publishes every fix as one ``location_fix``
event (``foxglove.LocationFix``) on ``stockpile/<site>/@v1/location_fix/<source>`` through the
shared :class:`~services.service.EventPublisher`.

Nothing in the stream stops it; what is not published is counted in the status counters
(the periodic ``status`` line and the final ``stopped`` line):

=======================  ========================================================  ======
counter                  meaning                                                   error?
=======================  ========================================================  ======
``sentences``            checksum-valid sentences of any type                      no
``published``            fixes published                                           no
``checksum_errors``      candidate sentences with a wrong or missing checksum      yes
``garbage_bytes``        bytes outside any sentence (a byte count)                 no [1]_
``unparseable``          checksum-valid GGA sentences with missing or bad fields   yes
``non_gga``              valid sentences of other types (RMC, GSA, ...)            no
``no_fix``               GGA with quality 0 (the receiver has no position)         no
``no_geoid_separation``  fixes without a geoid separation: published with the      no
                         altitude above mean sea level as the height
``waiting_for_clock``    fixes dropped in ``--clock site`` mode before the first   no
                         ``clock`` event (the date is unknown)
=======================  ========================================================  ======

.. [1] ``garbage_bytes`` is reported but not summed into ``errors``, which counts events.

The published fix:

- ``timestamp`` (the valid time, :func:`gga_time_ns`): GGA carries only the UTC time of day;
  it is joined to the date of "now" (site time, :class:`~services.service.SiteTime`), taking
  the previous, same or next day, whichever puts it closest to now, so a fix from 23:59:59.9
  read just after midnight keeps its date.
- ``latitude`` / ``longitude`` in degrees; ``altitude`` is the height above the WGS84
  ellipsoid (as ``sensor_msgs/NavSatFix``): GGA's altitude above mean sea level plus the
  geoid separation (:func:`ellipsoidal_height_m`).  The simulator's receiver writes its
  ellipsoidal height with separation 0, so its height comes back unchanged.
- ``position_covariance`` (ENU, row-major, m^2; :func:`position_covariance_m2`): diagonal,
  horizontal sigma ``HDOP * UERE``, vertical sigma twice that, where the UERE follows the
  fix quality: ``--uere-m`` for differential and RTK fixes (quality 2, 4, 5),
  ``--autonomous-uere-m`` for autonomous and estimated fixes (quality 1, 6; Table 3.2's
  2.5 m at HDOP 1.33);
  ``position_covariance_type = DIAGONAL_KNOWN``.

The service stops on SIGINT/SIGTERM (exit 0), when the device goes away (logged as
``device closed``, exit 0), and exits 2 with one ``cannot open device`` line when the port
cannot be opened.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field

import serial
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

from common.options import add_clock
from schemas.events import is_valid_source, set_timestamp_ns
from schemas.times import NS_PER_DAY, NS_PER_S
from devices import nmea
from services.serial_device import DevicePipeline, run_serial_service
from services.service import (
    DEFAULT_SITE,
    DEFAULT_STATUS_PERIOD_S,
    ServiceRuntime,
    SiteTime,
    Stopper,
    ZenohOptions,
)

__all__ = [
    "SERVICE", "DEFAULT_BAUD", "DEFAULT_SOURCE", "DEFAULT_FRAME_ID", "DEFAULT_UERE_M",
    "DEFAULT_AUTONOMOUS_UERE_M", "AUTONOMOUS_QUALITIES", "uere_for_quality",
    "VERTICAL_SIGMA_FACTOR", "READ_TIMEOUT_S", "ERROR_KEYS", "NS_PER_DAY", "Config",
    "gga_time_ns", "ellipsoidal_height_m", "position_covariance_m2", "fix_message", "read_gga",
    "add_arguments", "config_from_args", "main",
]

SERVICE = "gnss"
#: Default line rate, baud (bits per second).
DEFAULT_BAUD = 38_400
DEFAULT_SOURCE = "bwr1.gnss"
DEFAULT_FRAME_ID = "bwr1/gnss"
#: Default user-equivalent range error, metres (1 sigma).
DEFAULT_UERE_M = 0.5
#: Default UERE of an autonomous (quality 1) or estimated (6) fix, metres (1 sigma):
#: 2.5 m horizontal at the nominal HDOP of 4/3 (thesis Table 3.2).
DEFAULT_AUTONOMOUS_UERE_M = 1.875
#: GGA fix qualities without differential corrections.
AUTONOMOUS_QUALITIES = frozenset({1, 6})
#: Vertical sigma as a multiple of the horizontal sigma.
VERTICAL_SIGMA_FACTOR = 2.0
#: Longest wait of one serial read, seconds (how often the stop flag is checked).
READ_TIMEOUT_S = 0.1
#: Status counters summed into the status line's ``errors``.
ERROR_KEYS = ("checksum_errors", "unparseable")


# -- configuration ------------------------------------------------------------------------


@dataclass(frozen=True)
class Config:
    """Options of one GNSS service.

    Attributes
    ----------
    device : str
        Serial port of the receiver.
    site : str
        Site id: keys are ``stockpile/<site>/@v1/...``.
    zenoh : ZenohOptions
        Session options.
    status_period_s : float
        Seconds between status lines (0: none).
    baud : int
        Line rate, baud (bits per second).
    source : str
        Event source, e.g. ``bwr1.gnss``.
    frame_id : str
        ``LocationFix.frame_id`` (the antenna's frame).
    clock : str
        ``"wall"`` or ``"site"`` (follow the ``clock`` events).
    uere_m : float
        User-equivalent range error of a differential or RTK fix, metres (1 sigma);
        horizontal sigma = HDOP * UERE.
    autonomous_uere_m : float
        The same for an autonomous or estimated fix (quality 1 or 6), metres.
    read_timeout_s : float
        Longest wait of one serial read, seconds.
    """

    device: str
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    baud: int = DEFAULT_BAUD
    source: str = DEFAULT_SOURCE
    frame_id: str = DEFAULT_FRAME_ID
    clock: str = "wall"
    uere_m: float = DEFAULT_UERE_M
    autonomous_uere_m: float = DEFAULT_AUTONOMOUS_UERE_M
    read_timeout_s: float = READ_TIMEOUT_S

    def __post_init__(self) -> None:
        if not self.device:
            raise ValueError("a device is required (--device PATH)")
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError(f"baud must be a positive integer, got {self.baud!r}")
        if not is_valid_source(self.source):
            raise ValueError(f"bad source name {self.source!r}")
        if self.clock not in ("wall", "site"):
            raise ValueError(f"clock must be 'wall' or 'site', got {self.clock!r}")
        for name in ("uere_m", "autonomous_uere_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):  # R = 0 would break the filter
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not self.read_timeout_s > 0:
            raise ValueError(f"read_timeout_s must be > 0, got {self.read_timeout_s}")


# -- pure parts: time, height, covariance, message ----------------------------------------


def gga_time_ns(time_of_day_s: float, now_ns: int) -> int:
    """Join a GGA time of day to the date that puts it closest to ``now_ns``.

    Parameters
    ----------
    time_of_day_s : float
        UTC seconds since midnight (from the sentence; may exceed 86400 in a leap second).
    now_ns : int
        Current site time, UTC ns.

    Returns
    -------
    int
        UTC ns on the day before, of, or after ``now_ns``'s date, whichever is closest to
        ``now_ns`` (the earlier on a tie), so a fix taken just before midnight and read
        just after it keeps its date, and the reverse.

    Raises
    ------
    ValueError
        If the time of day is not finite or negative.
    """
    if not (math.isfinite(time_of_day_s) and time_of_day_s >= 0):
        raise ValueError(f"time of day must be finite and >= 0, got {time_of_day_s}")
    tod_ns = round(time_of_day_s * NS_PER_S)
    midnight = now_ns // NS_PER_DAY * NS_PER_DAY
    candidates = (midnight - NS_PER_DAY + tod_ns, midnight + tod_ns,
                  midnight + NS_PER_DAY + tod_ns)
    return min(candidates, key=lambda t: (abs(t - now_ns), t))


def ellipsoidal_height_m(gga: nmea.Gga) -> float:
    """Height above the WGS84 ellipsoid: altitude above MSL + geoid separation (0 if empty)."""
    sep = gga.geoid_sep_m if math.isfinite(gga.geoid_sep_m) else 0.0
    return gga.altitude_m + sep


def position_covariance_m2(hdop: float, uere_m: float) -> list[float]:
    """Diagonal ENU position covariance, row-major 3 x 3, m^2.

    Horizontal sigma ``hdop * uere_m`` on east and north, vertical sigma
    :data:`VERTICAL_SIGMA_FACTOR` times that.
    """
    h2 = (hdop * uere_m) ** 2
    v2 = (VERTICAL_SIGMA_FACTOR * hdop * uere_m) ** 2
    return [h2, 0.0, 0.0, 0.0, h2, 0.0, 0.0, 0.0, v2]


def uere_for_quality(quality: int, uere_m: float, autonomous_uere_m: float) -> float:
    """The UERE (m) for a GGA fix quality: autonomous for 1 and 6, differential otherwise."""
    return autonomous_uere_m if quality in AUTONOMOUS_QUALITIES else uere_m


def fix_message(gga: nmea.Gga, valid_time_ns: int, frame_id: str, uere_m: float) -> LocationFix:
    """A ``foxglove.LocationFix`` from one GGA fix (quality > 0).

    Parameters
    ----------
    gga : Gga
        A parsed fix with a position.
    valid_time_ns : int
        Its time, UTC ns (:func:`gga_time_ns`).
    frame_id : str
        The antenna's frame.
    uere_m : float
        User-equivalent range error, metres.
    """
    msg = LocationFix(frame_id=frame_id, latitude=gga.lat_deg, longitude=gga.lon_deg,
                      altitude=ellipsoidal_height_m(gga),
                      position_covariance_type=LocationFix.PositionCovarianceType.DIAGONAL_KNOWN)
    set_timestamp_ns(msg.timestamp, valid_time_ns)
    msg.position_covariance.extend(position_covariance_m2(gga.hdop, uere_m))
    return msg


# -- command line -------------------------------------------------------------------------


def read_gga(sentence: str) -> tuple[nmea.Gga | None, str | None, str | None]:
    """A checksum-valid sentence as the service reads it: ``(gga, None, None)`` for a GGA
    with a position, else ``(None, counter, error)``: ``counter`` is ``non_gga``,
    ``unparseable`` (``error``: the parser's message) or ``no_fix``."""
    kind = sentence[1:sentence.find(",")] if "," in sentence else sentence[1:]
    if not kind.endswith("GGA"):
        return None, "non_gga", None
    try:
        gga = nmea.parse_gga(sentence)
    except nmea.NmeaError as exc:
        return None, "unparseable", str(exc)
    if gga.quality == 0:
        return None, "no_fix", None
    return gga, None, None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the GNSS service's own options (the shared ones come from ``service_cli``)."""
    parser.add_argument("--device", required=True, metavar="PATH",
                        help="serial port of the GNSS receiver")
    parser.add_argument("--baud", type=int, default=DEFAULT_BAUD,
                        help=f"line rate, baud (default {DEFAULT_BAUD})")
    parser.add_argument("--source", default=DEFAULT_SOURCE,
                        help=f"event source (default {DEFAULT_SOURCE})")
    parser.add_argument("--frame-id", default=DEFAULT_FRAME_ID,
                        help=f"LocationFix frame id (default {DEFAULT_FRAME_ID})")
    add_clock(parser, events_as="site",
              help="site time: the machine's UTC clock (wall) or the simulator's clock events")
    parser.add_argument("--uere-m", type=float, default=DEFAULT_UERE_M, metavar="M",
                        help="user-equivalent range error of a differential/RTK fix "
                        f"(quality 2, 4, 5) for the covariance, metres (default {DEFAULT_UERE_M})")
    parser.add_argument("--autonomous-uere-m", type=float, default=DEFAULT_AUTONOMOUS_UERE_M,
                        metavar="M", help="the same for an autonomous fix (quality 1, 6), "
                        f"metres (default {DEFAULT_AUTONOMOUS_UERE_M})")


def config_from_args(args: argparse.Namespace) -> Config:
    """A :class:`Config` from parsed arguments (raises ValueError on bad values)."""
    return Config(device=args.device, site=args.site, zenoh=ZenohOptions.from_args(args),
                  status_period_s=args.status_period, baud=args.baud, source=args.source,
                  frame_id=args.frame_id, clock=args.clock, uere_m=args.uere_m,
                  autonomous_uere_m=args.autonomous_uere_m)


# -- the service --------------------------------------------------------------------------


class _FixPipeline(DevicePipeline):
    """Bytes in, fixes out: the NMEA reader, the date logic and the counters."""

    def __init__(self, config: Config, runtime: ServiceRuntime, site_time: SiteTime) -> None:
        super().__init__(runtime, site_time, config.source, "location_fix")
        self.config = config
        self.reader = nmea.NmeaReader()

    def start(self, port: serial.Serial) -> None:
        config = self.config
        self.runtime.log("reading", device=config.device, baud=config.baud, source=config.source,
                         frame_id=config.frame_id, clock=config.clock, uere_m=config.uere_m,
                         epoch=self.publisher.epoch)

    def feed(self, data: bytes, arrived_s: float) -> None:
        """Bytes that arrived at local monotonic time ``arrived_s``."""
        sentences = self.reader.feed(data)
        self.sync_counters(self.reader, "checksum_errors", "garbage_bytes")
        if sentences:
            self.status.add("sentences", len(sentences))
        for sentence in sentences:
            self._sentence(sentence, arrived_s)

    def _sentence(self, sentence: str, arrived_s: float) -> None:
        gga, skipped, error = read_gga(sentence)
        if gga is None:
            if skipped == "unparseable" and self.status.get("unparseable") == 0:
                self.runtime.log("unparseable GGA", level="warning", error=error)
            self.status.add(skipped)
            return
        now_ns = self.site_ns(arrived_s)
        if now_ns is None:
            self.status.add("waiting_for_clock")
            return
        if not math.isfinite(gga.geoid_sep_m):
            self.status.add("no_geoid_separation")
        msg = fix_message(gga, gga_time_ns(gga.time_of_day_s, now_ns), self.config.frame_id,
                          uere_for_quality(gga.quality, self.config.uere_m,
                                           self.config.autonomous_uere_m))
        self.publisher.publish(msg)
        self.status.add("published")


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the GNSS service until the device ends or SIGINT/SIGTERM.

    Returns
    -------
    int
        0 on a clean stop (signal or device closed), 2 if the device cannot be opened or
        the Zenoh session cannot start.
    """
    return run_serial_service(SERVICE, config, error_keys=ERROR_KEYS, stopper=stopper,
                              make_pipeline=lambda runtime, site_time:
                              _FixPipeline(config, runtime, site_time))
