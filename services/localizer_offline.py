"""The product's localizer over a recorded run (``events.jsonl``, ``gnss.nmea``), no transport.

A yard's scans are placed by the localizer's poses: the gnss service turns NMEA GGA into
``location_fix`` events, the localizer fuses them with the encoders' ``joint_reading``
events and publishes ``joint_estimate`` and ``frame_transform``.  The same two steps:

- :func:`gnss_fixes`: the GGA sentences as the gnss service reads them in the process
  demo (``--clock events``): each fix's time of day joined to the date nearest "now" by
  :func:`services.gnss.gga_time_ns`, "now" being the site clock the ``clock`` events
  give (the newest tick at or before the previous fix; the first tick for the first);
  a fix dated before the first tick is dropped, as the service drops a fix read before
  it knows the site clock; source ``<machine>.gnss``, frame ``<machine>/gnss``, the
  service's default range errors.
- :func:`localize_run`: the declarations, the readings and those fixes, in valid-time
  order (readings before fixes at one time, as the service's reorder buffer orders
  them), through :class:`services.localizer.Localizer` with the service's
  :class:`~services.localizer.Config` defaults; returns the events it published, as
  source ``<machine>.localizer``, numbered densely from 0 in one epoch and unsigned, as
  the service's publisher numbers them.  As the service, it smooths each estimate with
  the fixes of the next ``Config.smooth_lag_s`` site seconds
  (:mod:`services.localizer_smoother`); the estimates still held at the run's end are
  smoothed over the rest of it, as the service does when it stops.
- :func:`ledger_input_lines` and :func:`write_ledger_input`: the run's ledger input on
  that path: its JSON lines without the simulator's true scanner poses (``frame_transform``
  of source ``<machine>.poses``), each localizer event after the reading it was
  estimated at.

A service's epoch is the wall clock at its start; here it is the run's first valid
time (ns), so the same run always gives the same events.
"""

from __future__ import annotations

import bisect
import json
import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from devices import nmea
from schemas.events import Event, decode_payload, make_event
from schemas.jsonl import decode_line, event_line
from services import gnss
from services.localizer import Config, Localizer

__all__ = ["INPUT_TYPES", "gnss_fixes", "localize_run", "ledger_input_lines",
           "write_ledger_input"]

#: the recorded event types the offline localizer reads (``clock`` dates the fixes)
INPUT_TYPES = ("site_declared", "machine_declared", "joint_reading", "clock")
#: order at one valid time: declarations, then readings before fixes (the service's heap)
_RANK = {"site_declared": 0, "machine_declared": 0, "joint_reading": 1, "location_fix": 2}


def _count_into(counts: dict[str, int]) -> Callable[..., None]:
    def count(name: str, n: int = 1) -> None:
        counts[name] = counts.get(name, 0) + n
    return count


def _ignore(msg: str, **fields) -> None:
    """The default log: the offline run reports through its counters."""


def gnss_fixes(nmea_bytes: bytes, clock_ns: Sequence[int], *, machine_id: str, epoch: int,
               counts: dict[str, int] | None = None) -> list[Event]:
    """The ``location_fix`` events the gnss service publishes for a GGA byte stream.

    ``clock_ns``: valid times of the run's ``clock`` events (UTC ns); ``machine_id``
    names source ``<machine>.gnss`` and frame ``<machine>/gnss``; ``counts`` is filled
    with the service's counters (``published``, ``no_fix``, ``unparseable``, ``non_gga``,
    ``waiting_for_clock``, ``checksum_errors``).  Returns the fixes in stream order,
    sequence numbers from 0; ValueError for fixes without a ``clock`` event to date them.
    """
    count = _count_into({} if counts is None else counts)
    reader = nmea.NmeaReader()
    sentences = reader.feed(bytes(nmea_bytes))
    count("checksum_errors", reader.checksum_errors)
    ticks = sorted(int(t) for t in clock_ns)
    source, frame_id = f"{machine_id}.gnss", f"{machine_id}/gnss"
    out: list[Event] = []
    previous_ns: int | None = None
    for sentence in sentences:
        gga = _fix_of(sentence, count)
        if gga is None:
            continue
        if not ticks:
            raise ValueError("GNSS fixes but no clock event: the fixes cannot be dated "
                             "(the gnss service dates them by the site clock)")
        now_ns = ticks[0] if previous_ns is None else \
            ticks[bisect.bisect_right(ticks, previous_ns) - 1]
        t_ns = gnss.gga_time_ns(gga.time_of_day_s, now_ns)
        if t_ns < ticks[0]:
            count("waiting_for_clock")
            continue
        uere_m = gnss.uere_for_quality(gga.quality, gnss.DEFAULT_UERE_M,
                                       gnss.DEFAULT_AUTONOMOUS_UERE_M)
        message = gnss.fix_message(gga, t_ns, frame_id, uere_m)
        out.append(make_event(message, source=source, epoch=epoch, seq=len(out)))
        count("published")
        previous_ns = t_ns
    return out


def _fix_of(sentence: str, count: Callable[..., None]) -> nmea.Gga | None:
    """A GGA sentence with a position and a time of day, or None (counted as the service
    counts it, :func:`services.gnss.read_gga`)."""
    gga, skipped, _error = gnss.read_gga(sentence)
    if gga is None:
        count(skipped)
        return None
    if not gga.time_of_day_s >= 0:      # no time of day: nothing to date it by
        count("unparseable")
        return None
    return gga


def localize_run(events: Iterable[Event], nmea_bytes: bytes, *, machine_id: str = "bwr1",
                 config: Config | None = None, epoch: int | None = None,
                 counts: dict[str, int] | None = None,
                 log: Callable[..., None] | None = None) -> list[Event]:
    """Run :class:`services.localizer.Localizer` over a recorded run.

    Parameters
    ----------
    events : iterable of Event
        The run's events: the declarations, the machine's ``joint_reading`` and the
        ``clock`` events are used, the rest ignored.
    nmea_bytes : bytes
        The GNSS receiver's GGA stream, dated by :func:`gnss_fixes`.
    machine_id : str
        The reclaimer (when ``config`` is given: its ``machine_id``).
    config : Config, optional
        The localizer's options; default the service's defaults.
    epoch : int, optional
        Epoch of the fixes and the published events; default the run's first valid time (ns).
    counts : dict, optional
        Filled with the localizer's status counters and the gnss service's (``gnss_`` prefix).
    log : callable(msg, **fields), optional
        The localizer's log lines (default: none).

    Returns
    -------
    list of Event
        ``joint_estimate`` and ``frame_transform`` events (``<machine>/wheel``,
        ``<machine>/scanner``) of source ``<machine>.localizer``, in publication order.

    Raises
    ------
    ValueError
        No ``site_declared`` event, no ``machine_declared`` event of the machine, no
        ``joint_reading`` of the machine, fixes without clock events, or no estimate
        published.
    """
    config = Config(machine_id=machine_id) if config is None else config
    machine_id = config.machine_id
    inputs, ticks = _inputs(events, machine_id)
    epoch = min(e.valid_time_ns for e in inputs) if epoch is None else int(epoch)
    counters: dict[str, int] = {}
    gnss_counts: dict[str, int] = {}
    fixes = gnss_fixes(nmea_bytes, ticks, machine_id=machine_id, epoch=epoch,
                       counts=gnss_counts)
    count = _count_into(counters)
    for name, n in gnss_counts.items():
        count(f"gnss_{name}", n)
    merged = sorted(enumerate([*inputs, *fixes]),
                    key=lambda pair: (pair[1].valid_time_ns, _RANK[pair[1].type], pair[0]))
    published: list = []
    localizer = Localizer(config, published.append, count, log or _ignore)
    for _arrival, event in merged:
        localizer.handle(event, now_s=0.0)
        localizer.release(now_s=math.inf)   # in time order: every measurement is due now
    localizer.release(now_s=math.inf, flush=True)
    if counts is not None:
        counts.update(counters)
    if not published:
        raise ValueError(f"the localizer published no estimate for {machine_id} "
                         f"(counters: {dict(sorted(counters.items()))})")
    source = f"{machine_id}.localizer"
    return [make_event(m, source=source, epoch=epoch, seq=seq)
            for seq, m in enumerate(published)]


def _inputs(events: Iterable[Event], machine_id: str) -> tuple[list[Event], list[int]]:
    """The declarations and the machine's readings, and the clock's valid times (ns);
    ValueError when the site, the machine or its readings are missing."""
    inputs: list[Event] = []
    ticks: list[int] = []
    site = machine = readings = 0
    for event in events:
        if event.type == "clock":
            ticks.append(event.valid_time_ns)
        elif event.type in _RANK and event.type != "location_fix":
            if event.type == "site_declared":
                site += 1
            elif decode_payload(event.type, event.payload).machine_id == machine_id:
                machine += event.type == "machine_declared"
                readings += event.type == "joint_reading"
            inputs.append(event)
    if not site:
        raise ValueError("no site_declared event: the localizer needs the site's datum")
    if not machine:
        raise ValueError(f"no machine_declared event for {machine_id}: the localizer needs "
                         "its geometry")
    if not readings:
        raise ValueError(f"no joint_reading of {machine_id}: nothing to localise")
    return inputs, ticks


# -- the run's ledger input on the localizer's path --------------------------------------------


def _head(line: str) -> dict | None:
    """The JSON object of a line, or None when it is not one (passed on as it is)."""
    try:
        value = json.loads(line)
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def _is_reading_of(head: dict, machine_id: str) -> bool:
    body = head.get("body")
    return (head.get("type") == "joint_reading" and isinstance(body, dict)
            and body.get("machine_id") == machine_id)


def ledger_input_lines(lines: Iterable[str], localized: Sequence[Event], *,
                       machine_id: str) -> Iterator[str]:
    """The run's JSON lines on the localizer's path, without line ends.

    Every line as it is, except the simulator's true scanner poses (``frame_transform``
    of source ``<machine>.poses``); after each ``joint_reading`` of the machine, the
    localizer's events (``localized``, in publication order) with a valid time at or
    before the reading's, as canonical lines (:func:`schemas.jsonl.event_line`): the
    earliest a live localizer publishes them.  The rest follow the last line.
    """
    poses = f"{machine_id}.poses"
    ordered = sorted(localized, key=lambda e: e.valid_time_ns)   # stable: publication order
    i = 0
    for line in lines:
        line = line.rstrip("\r\n")
        head = _head(line)
        if head is not None and head.get("type") == "frame_transform" \
                and head.get("source") == poses:
            continue
        yield line
        if head is not None and _is_reading_of(head, machine_id):
            t_ns = head.get("valid_time_ns")
            while i < len(ordered) and isinstance(t_ns, int) \
                    and ordered[i].valid_time_ns <= t_ns:
                yield event_line(ordered[i])
                i += 1
    for event in ordered[i:]:
        yield event_line(event)


def _recorded_inputs(events_path: Path) -> Iterator[Event]:
    """The events of a JSON lines file the localizer reads (:data:`INPUT_TYPES`)."""
    with events_path.open(encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            head = _head(line)
            if head is None or head.get("type") not in INPUT_TYPES:
                continue
            event = decode_line(line, where=f"{events_path}:{n}")
            if isinstance(event, Event):
                yield event


def write_ledger_input(events_path: str | Path, nmea_path: str | Path, out_path: str | Path,
                       *, machine_id: str = "bwr1",
                       counts: dict[str, int] | None = None,
                       config: Config | None = None) -> int:
    """Write a run's ledger input on the localizer's path (:func:`ledger_input_lines`).

    ``events_path``: the run's ``events.jsonl``; ``nmea_path``: its ``gnss.nmea``;
    ``out_path``: written beside itself, then renamed (never left half written);
    ``counts``: filled as by :func:`localize_run`; ``config``: the localizer's options
    (:func:`localize_run`).  Returns how many localizer events were written;
    ValueError from :func:`localize_run`, OSError from the files.
    """
    events_path, out_path = Path(events_path), Path(out_path)
    localized = localize_run(_recorded_inputs(events_path), Path(nmea_path).read_bytes(),
                             machine_id=machine_id, counts=counts, config=config)
    partial = out_path.with_name(out_path.name + ".partial")
    with events_path.open(encoding="utf-8") as src, partial.open("w", encoding="utf-8") as dst:
        for line in ledger_input_lines(src, localized, machine_id=machine_id):
            dst.write(line + "\n")
    os.replace(partial, out_path)
    return len(localized)
