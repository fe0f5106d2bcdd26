"""Machine PLC tags over OPC UA: the tag map (``plc.toml``) and the state machine that turns
time-ordered tag samples into the yard's events.  Pure: no OPC UA library here.

The map names, per machine (``[machines.<id>]``, the id is the events' ``machine_id``),
the OPC UA node of each tag (``ns=2;s=...``, ``nsu=URI;s=...``, ``i=``, ``g=``, ``b=``
identifiers) and how to read it:

=================  ===================================================================
key / table        meaning
=================  ===================================================================
``kind``           ``"reclaimer"`` (works while ``reclaiming``: cuts) or ``"stacker"``
                   (works while ``stacking``: passes)
``travel``,        encoders: ``node``, ``scale`` (unit per raw count, non-zero), ``offset``,
``slew``,          ``unit`` (``m``/``mm`` travel, ``rad``/``deg`` slew and luff); value =
``luff``           raw * scale + offset.  All three or none (a reclaimer needs them)
``state``          ``node`` and ``[...state.values]``: raw value -> ``stacking``,
                   ``reclaiming``, ``travelling``, ``idle`` or ``fault``
``ids``            nodes of ``pile_id`` and ``pass_id`` + ``lot_id`` (stacker) or
                   ``cut_id`` + ``bench_id`` (reclaimer), read at the start
``pass``           stacker: ``start_y``, ``end_y`` (scaled, lengths), ``pattern``
``cut``            reclaimer, optional: the cut plan, ``travel``, ``luff``, ``slew_start``,
                   ``slew_end`` (scaled); else the encoders at the cut's start and end
``totaliser``      optional: ``node``, ``unit`` (``t``/``kg``), ``scale`` (unit per raw
                   count), ``rollover`` (the raw value it wraps at; 0: never)
=================  ===================================================================

:class:`MachineTracker` is fed one machine's samples ``(source time ns, tag, value,
good)`` in time order (see its docstring for the rules) and returns what to publish.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from schemas import pb
from schemas.events import set_timestamp_ns

__all__ = [
    "STATES", "KINDS", "MapError", "NodeRef", "Scaled", "Totaliser", "MachineMap", "PlcMap",
    "parse_node_id", "load_map", "parse_map", "Publish", "Note", "MachineTracker",
]

#: the machine states a map's state values name
STATES = ("stacking", "reclaiming", "travelling", "idle", "fault")
#: machine kind -> the state in which it works (a pass or a cut is open)
KINDS = {"stacker": "stacking", "reclaimer": "reclaiming"}
#: unit -> (metres or radians) per unit
LENGTH_UNITS = {"m": 1.0, "mm": 0.001}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
MASS_UNITS_T = {"t": 1.0, "kg": 0.001}
JOINTS = ("travel", "slew", "luff")
#: ids each kind needs; the first names the activity (a pass or a cut)
IDS = {"stacker": ("pass_id", "pile_id", "lot_id"), "reclaimer": ("cut_id", "pile_id", "bench_id")}
PLAN = {"stacker": ("start_y", "end_y"), "reclaimer": ("travel", "luff", "slew_start", "slew_end")}
PATTERNS = ("CHEVRON", "WINDROW", "CONE_SHELL", "STRATA")
PATTERN_KEY = {"stacker": ("pattern",), "reclaimer": ()}
#: decimals tonnes are rounded to (a gram: below any belt scale, above float noise)
TONNES_DECIMALS = 6

_NODE_ID = re.compile(r"(?:(ns)=(\d+);|(nsu)=([^;]+);)?([isgb])=(.+)", re.S)


class MapError(ValueError):
    """A bad tag map: the message is one line naming the file and the key."""


@dataclass(frozen=True)
class NodeRef:
    """An OPC UA node id as written in the map: ``kind`` ``i`` (numeric), ``s``
    (string), ``g`` (GUID) or ``b`` (opaque, base64), the ``identifier`` as written, and
    ``ns=`` (``namespace_index``) or ``nsu=`` (``namespace_uri``, resolved against the
    server's namespace array)."""

    kind: str
    identifier: str
    namespace_index: int = 0
    namespace_uri: str | None = None

    def __str__(self) -> str:
        prefix = (f"nsu={self.namespace_uri};" if self.namespace_uri is not None
                  else f"ns={self.namespace_index};" if self.namespace_index else "")
        return f"{prefix}{self.kind}={self.identifier}"


def parse_node_id(text: str) -> NodeRef:
    """A :class:`NodeRef` from ``[ns=N;|nsu=URI;](i|s|g|b)=ID``; ValueError otherwise."""
    match = _NODE_ID.fullmatch(text.strip()) if isinstance(text, str) else None
    if match is None:
        raise ValueError(f"{text!r} is not an OPC UA node id ([ns=N;|nsu=URI;]s=NAME, i=N ...)")
    _, ns, _, uri, kind, ident = match.groups()
    if kind == "i" and not ident.isdigit():
        raise ValueError(f"{text!r}: a numeric identifier (i=) must be digits")
    return NodeRef(kind, ident, int(ns) if ns else 0, uri)


@dataclass(frozen=True)
class Scaled:
    """An analogue tag: raw value -> metres or radians (``raw * scale + offset`` in ``unit``)."""
    node: NodeRef
    scale: float
    offset: float
    unit: str

    def si(self, raw: float) -> float:
        """Metres or radians of a raw value (``deg`` through :func:`math.radians`)."""
        value = float(raw) * self.scale + self.offset
        if self.unit == "deg":
            return math.radians(value)
        return value * (LENGTH_UNITS.get(self.unit) or ANGLE_UNITS[self.unit])

    def raw(self, si_value: float, whole: bool = True) -> int | float:
        """The raw value of a value in metres or radians (the inverse of :meth:`si`): the
        nearest count, or with ``whole=False`` the exact quotient (a REAL tag)."""
        value = (math.degrees(si_value) if self.unit == "deg"
                 else si_value / (LENGTH_UNITS.get(self.unit) or ANGLE_UNITS[self.unit]))
        raw = (value - self.offset) / self.scale
        return round(raw) if whole else raw


@dataclass(frozen=True)
class Totaliser:
    """A belt-scale totaliser: raw counts of ``scale`` ``unit`` each, wrapping at ``rollover``."""
    node: NodeRef
    unit: str
    scale: float
    rollover: int = 0

    @property
    def tonnes_per_count(self) -> float:
        return self.scale * MASS_UNITS_T[self.unit]


@dataclass(frozen=True)
class MachineMap:
    """One machine's tags (see the module docstring)."""
    machine_id: str
    kind: str
    state_node: NodeRef
    state_values: dict[str, str]
    ids: dict[str, NodeRef]
    encoders: dict[str, Scaled] = field(default_factory=dict)
    plan: dict[str, Scaled] = field(default_factory=dict)
    totaliser: Totaliser | None = None
    pattern: str = ""

    @property
    def working_state(self) -> str:
        return KINDS[self.kind]

    def tags(self) -> dict[str, NodeRef]:
        """Tag name -> node: ``travel`` ..., ``state``, the ids, ``plan.<name>``,
        ``totaliser``."""
        tags: dict[str, NodeRef] = {name: s.node for name, s in self.encoders.items()}
        tags["state"] = self.state_node
        tags.update(self.ids)
        tags.update({f"plan.{name}": s.node for name, s in self.plan.items()})
        if self.totaliser is not None:
            tags["totaliser"] = self.totaliser.node
        return tags

    def state_raw(self, name: str) -> str:
        """The first raw value the map gives for state ``name`` (the simulator writes it)."""
        for raw, state in self.state_values.items():
            if state == name:
                return raw
        raise KeyError(f"{self.machine_id}: the map gives no value for state {name!r}")


@dataclass(frozen=True)
class PlcMap:
    """Every machine of a map, and which node is which (machine, tag)."""
    machines: dict[str, MachineMap]
    path: str = ""

    def nodes(self) -> dict[NodeRef, tuple[str, str]]:
        return {node: (m.machine_id, tag) for m in self.machines.values()
                for tag, node in m.tags().items()}


# -- parsing -------------------------------------------------------------------------------


def load_map(path: str | Path) -> PlcMap:
    """Read and check a ``plc.toml``; :class:`MapError` (one line) when it is bad."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MapError(f"{path}: cannot read the map: {exc}") from None
    return parse_map(text, str(path))


def parse_map(text: str, name: str = "plc.toml") -> PlcMap:
    """A :class:`PlcMap` from TOML text; :class:`MapError` naming ``name`` and the line
    (TOML syntax) or the key (content)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        where = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        line = f":{where.group(1)}" if where else ""
        raise MapError(f"{name}{line}: {str(exc).split(' (at line')[0]}") from None
    reader = _Reader(name)
    unknown = set(data) - {"machines"}
    if unknown:
        reader.fail(sorted(unknown)[0], "unknown key (the map has [machines.<id>] tables)")
    machines = reader.table(data, "machines", "machines")
    if not machines:
        reader.fail("machines", "no machine is mapped")
    out = {mid: _machine(reader, mid, reader.table(machines, mid, f"machines.{mid}"))
           for mid in machines}
    seen: dict[NodeRef, str] = {}
    for m in out.values():
        for tag, node in m.tags().items():
            key = f"machines.{m.machine_id}.{tag}"
            if node in seen:
                reader.fail(key, f"node {node} is also {seen[node]}")
            seen[node] = key
    return PlcMap(out, name)


class _Reader:
    """Typed look-ups that fail with ``<file>: <key>: <reason>``."""

    def __init__(self, name: str) -> None:
        self.name = name

    def fail(self, key: str, reason: str):
        raise MapError(f"{self.name}: {key}: {reason}")

    def table(self, data: dict, name: str, key: str, required: bool = True) -> dict:
        value = data.get(name)
        if value is None and not required:
            return {}
        if not isinstance(value, dict):
            self.fail(key, "missing table" if value is None else "must be a table")
        return value

    def node(self, data: Any, key: str) -> NodeRef:
        text = data.get("node") if isinstance(data, dict) else data
        if not isinstance(text, str):
            self.fail(key, "needs a node id (node = \"nsu=URI;s=NAME\")")
        try:
            return parse_node_id(text)
        except ValueError as exc:
            self.fail(key, str(exc))

    def number(self, data: dict, name: str, key: str, default: float | None = None,
               positive: bool = False, nonzero: bool = False) -> float:
        value = data.get(name, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(f"{key}.{name}", "must be a finite number")
        if (positive and not value > 0) or (nonzero and value == 0):
            self.fail(f"{key}.{name}", f"must be {'> 0' if positive else 'non-zero'}, got {value}")
        return float(value)

    def choice(self, data: dict, name: str, key: str, options, default: str | None = None) -> str:
        value = data.get(name, default)
        if value not in options:
            self.fail(f"{key}.{name}", f"must be one of {', '.join(options)}, got {value!r}")
        return value

    def scaled(self, data: Any, key: str, units: dict[str, float]) -> Scaled:
        if not isinstance(data, dict):
            self.fail(key, "must be a table with node, scale, offset, unit")
        self.only(data, key, {"node", "scale", "offset", "unit"})
        return Scaled(self.node(data, key), self.number(data, "scale", key, nonzero=True),
                      self.number(data, "offset", key, 0.0), self.choice(data, "unit", key, units))

    def only(self, data: dict, key: str, allowed: set[str]) -> None:
        extra = sorted(set(data) - allowed)
        if extra:
            self.fail(f"{key}.{extra[0]}", f"unknown key (expected {', '.join(sorted(allowed))})")


def _machine(r: _Reader, mid: str, data: dict) -> MachineMap:
    key = f"machines.{mid}"
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", mid):
        r.fail(key, "a machine id is letters, digits, _ and - (it names the event sources)")
    r.only(data, key, {"kind", "travel", "slew", "luff", "state", "ids", "pass", "cut",
                       "totaliser"})
    kind = r.choice(data, "kind", key, tuple(KINDS))
    encoders = {}
    for joint in JOINTS:
        if joint in data:
            units = LENGTH_UNITS if joint == "travel" else ANGLE_UNITS
            encoders[joint] = r.scaled(data[joint], f"{key}.{joint}", units)
    if encoders and len(encoders) != 3:
        r.fail(f"{key}.{next(j for j in JOINTS if j not in encoders)}",
               "map all three encoders (travel, slew, luff) or none")
    if kind == "reclaimer" and not encoders:
        r.fail(f"{key}.travel", "a reclaimer needs its travel, slew and luff encoders")
    state = r.table(data, "state", f"{key}.state")
    r.only(state, f"{key}.state", {"node", "values"})
    values = r.table(state, "values", f"{key}.state.values")
    for raw, name in values.items():
        if name not in STATES:
            r.fail(f"{key}.state.values.{raw}", f"must be one of {', '.join(STATES)}, got {name!r}")
    if KINDS[kind] not in values.values():
        r.fail(f"{key}.state.values", f"no value means {KINDS[kind]!r} (when the {kind} works)")
    ids_data = r.table(data, "ids", f"{key}.ids")
    r.only(ids_data, f"{key}.ids", set(IDS[kind]))
    ids = {name: r.node(ids_data.get(name), f"{key}.ids.{name}") for name in IDS[kind]}
    plan_key, other = ("pass", "cut") if kind == "stacker" else ("cut", "pass")
    if other in data:
        r.fail(f"{key}.{other}", f"a {kind} has no [{other}] table")
    plan_data = r.table(data, plan_key, f"{key}.{plan_key}", required=kind == "stacker")
    r.only(plan_data, f"{key}.{plan_key}", {*PLAN[kind], *PATTERN_KEY[kind]})
    plan, pattern = {}, ""
    if plan_data:
        for name in PLAN[kind]:
            units = LENGTH_UNITS if name in ("start_y", "end_y", "travel") else ANGLE_UNITS
            plan[name] = r.scaled(plan_data.get(name), f"{key}.{plan_key}.{name}", units)
    if kind == "stacker":
        pattern = r.choice(plan_data, "pattern", f"{key}.pass", PATTERNS)
    totaliser = None
    if "totaliser" in data:
        t = r.table(data, "totaliser", f"{key}.totaliser")
        r.only(t, f"{key}.totaliser", {"node", "unit", "scale", "rollover"})
        rollover = t.get("rollover", 0)
        if isinstance(rollover, bool) or not isinstance(rollover, int) or rollover < 0:
            r.fail(f"{key}.totaliser.rollover", "must be an integer >= 0 (0: never wraps)")
        totaliser = Totaliser(r.node(t, f"{key}.totaliser"),
                              r.choice(t, "unit", f"{key}.totaliser", MASS_UNITS_T),
                              r.number(t, "scale", f"{key}.totaliser", positive=True), rollover)
    return MachineMap(mid, kind, r.node(state, f"{key}.state"), dict(values), ids, encoders,
                      plan, totaliser, pattern)


# -- the state machine ---------------------------------------------------------------------


@dataclass(frozen=True)
class Publish:
    """An event to publish: ``stream`` is ``"encoders"`` (joint readings) or ``"plc"``."""
    stream: str
    message: Any


@dataclass(frozen=True)
class Note:
    """A line to log: ``level``, ``msg`` and its fields."""
    level: str
    msg: str
    fields: dict


@dataclass
class _Activity:
    """An open pass or cut."""
    activity_id: str
    start_ns: int
    ids: dict[str, str]
    geometry: dict[str, float]
    tonnes: float = 0.0
    bad_samples: int = 0
    left_ns: int | None = None   # when the machine last left its working state (a fault)


class MachineTracker:
    """One machine's samples in, events out.

    Samples come in source-time order (:meth:`feed`); the samples of one source time are
    an *instant*.  An instant is handled once a later sample arrives (or on :meth:`flush`):
    its good values first, then the machine's state:

    - a sample at or before the last handled instant is stale (a repeat after a
      reconnect): counted in ``stale_samples``, not used;
    - a sample with bad or uncertain status is counted in ``bad_samples`` and not used:
      the tag keeps its last good value; an encoder stays bad until a good sample, and no
      ``JointReading`` is published while one is (``withheld_readings``); the open pass or
      cut (else the one the instant opens) counts it in its ``bad_samples``;
    - an instant with an encoder sample publishes one ``JointReading`` with the latest
      good joints (metres, radians);
    - totaliser deltas accrue to the open pass or cut; a decrease is a wrap when the
      counter went past ``rollover`` by less than half of it, else a reset to 0 (each
      logged); tonnes are rounded to :data:`TONNES_DECIMALS`;
    - the pass or cut named by the activity id is open while the state is the working one
      (stacking or reclaiming) with a non-empty id.  It ends when the state becomes
      anything but the working state or ``fault``, or the id changes; a fault pauses it
      (it ends at the fault's start unless the machine resumes with the same id).  A
      stacker publishes ``StackStarted`` at the start and ``StackEnded`` at the end, a
      reclaimer one ``ReclaimCut`` at the end.
    """

    def __init__(self, machine: MachineMap) -> None:
        self.machine = machine
        self.counters: dict[str, int] = {}
        self._pending_ns: int | None = None
        self._pending: list[tuple[str, Any, bool]] = []
        self._closed_ns: int | None = None
        self._raw: dict[str, Any] = {}          # last good raw value per tag
        self._bad_joints: set[str] = set()
        self._state: str | None = None
        self._total_raw: float | None = None
        self._activity: _Activity | None = None

    @property
    def pending_ns(self) -> int | None:
        """Source time of the instant not handled yet (None: none)."""
        return self._pending_ns

    @property
    def open_activity(self) -> str | None:
        """Id of the open pass or cut (None: none)."""
        return self._activity.activity_id if self._activity else None

    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def feed(self, t_ns: int, tag: str, value: Any, good: bool) -> list[Publish | Note]:
        """One sample (source time ns, tag name of the map, raw value, status good?)."""
        self._count("samples")
        if self._closed_ns is not None and t_ns <= self._closed_ns:
            self._count("stale_samples")
            return []
        if self._pending_ns is None or t_ns == self._pending_ns:
            self._pending_ns = t_ns
            self._pending.append((tag, value, good))
            return []
        if t_ns < self._pending_ns:   # later than anything handled: handled on its own now
            return self._handle(t_ns, [(tag, value, good)])
        out = self.flush()
        self._pending_ns, self._pending = t_ns, [(tag, value, good)]
        return out

    def flush(self) -> list[Publish | Note]:
        """Handle the pending instant now (no later sample is coming for a while)."""
        if self._pending_ns is None:
            return []
        t_ns, samples = self._pending_ns, self._pending
        self._pending_ns, self._pending = None, []
        return self._handle(t_ns, samples)

    def _handle(self, t_ns: int, samples: list[tuple[str, Any, bool]]) -> list[Publish | Note]:
        self._closed_ns = t_ns if self._closed_ns is None else max(self._closed_ns, t_ns)
        out: list[Publish | Note] = []
        was_open = self._activity
        bad, encoder_update = 0, False
        for tag, value, good in samples:
            encoder_update |= tag in JOINTS
            if not good:
                bad += 1
                self._bad_joints |= {tag} & set(JOINTS)
                continue
            self._bad_joints.discard(tag)
            self._apply(t_ns, tag, value, out)
        if bad:
            self._count("bad_samples", bad)
            if was_open is not None:
                was_open.bad_samples += bad
        if encoder_update and self.machine.encoders:
            self._reading(t_ns, out)
        self._transition(t_ns, out)
        if bad and was_open is None and self._activity is not None:
            self._activity.bad_samples += bad
        return out

    def _apply(self, t_ns: int, tag: str, value: Any, out: list) -> None:
        if tag == "state":
            name = self.machine.state_values.get(_state_key(value))
            if name is None:
                self._count("unmapped_states")
                out.append(Note("warning", "unmapped state value", {
                    "machine": self.machine.machine_id, "value": value, "t_ns": t_ns}))
                return
            self._state = name
        elif tag == "totaliser":
            self._totalise(t_ns, value, out)
        self._raw[tag] = value

    def _totalise(self, t_ns: int, value: Any, out: list) -> None:
        totaliser = self.machine.totaliser
        raw, previous = float(value), self._total_raw
        self._total_raw = raw
        if previous is None:
            return
        counts = raw - previous
        if counts < 0:
            rollover = totaliser.rollover
            wrapped = rollover - previous + raw
            if rollover and wrapped <= rollover / 2:
                counts, what = wrapped, "wrapped"
            else:
                counts, what = raw, "reset"
            self._count(f"totaliser_{what}")
            out.append(Note("info", f"totaliser {what}", {
                "machine": self.machine.machine_id, "from_raw": previous, "to_raw": raw,
                "rollover": rollover, "tonnes": counts * totaliser.tonnes_per_count,
                "t_ns": t_ns}))
        if self._activity is not None:
            self._activity.tonnes += counts * totaliser.tonnes_per_count

    def _joints_si(self) -> dict[str, float] | None:
        if self._bad_joints or any(j not in self._raw for j in JOINTS):
            return None
        return {j: self.machine.encoders[j].si(self._raw[j]) for j in JOINTS}

    def _reading(self, t_ns: int, out: list) -> None:
        joints = self._joints_si()
        if joints is None:
            self._count("withheld_readings")
            return
        msg = pb.JointReading(machine_id=self.machine.machine_id, travel_m=joints["travel"],
                              slew_rad=joints["slew"], luff_rad=joints["luff"])
        set_timestamp_ns(msg.time, t_ns)
        self._count("readings")
        out.append(Publish("encoders", msg))

    def _transition(self, t_ns: int, out: list) -> None:
        m, act = self.machine, self._activity
        working = self._state == m.working_state
        activity_id = str(self._raw.get(IDS[m.kind][0], "")).strip()
        if working and activity_id:
            wanted = activity_id
        elif self._state == "fault" and act is not None:
            wanted = act.activity_id
        else:
            wanted = None
        if act is not None:
            if not working and act.left_ns is None:
                act.left_ns = t_ns
            elif working and wanted == act.activity_id:
                act.left_ns = None
            if wanted != act.activity_id:
                self._end(act, t_ns if act.left_ns is None else act.left_ns, out)
                self._activity = None
        if wanted is not None and self._activity is None:
            self._start(wanted, t_ns, out)
        elif working and not activity_id:
            self._count("missing_ids")

    def _geometry(self, names: tuple[str, ...], out: list, t_ns: int) -> dict[str, float]:
        """The plan's values (or, for a reclaimer without one, the encoders) now."""
        m = self.machine
        if m.plan:
            values = {n: m.plan[n].si(self._raw[f"plan.{n}"]) for n in names
                      if f"plan.{n}" in self._raw}
        else:
            joints = self._joints_si() or {}
            values = {n: joints[n.split("_")[0]] for n in names if n.split("_")[0] in joints}
        missing = [n for n in names if n not in values]
        if missing:
            self._count("unknown_geometry")
            out.append(Note("warning", "geometry unknown, written as 0", {
                "machine": m.machine_id, "missing": ",".join(missing), "t_ns": t_ns}))
        return {n: values.get(n, 0.0) for n in names}

    def _start(self, activity_id: str, t_ns: int, out: list) -> None:
        m = self.machine
        ids = {name: str(self._raw.get(name, "")).strip() for name in IDS[m.kind]}
        names = ("start_y", "end_y") if m.kind == "stacker" else ("travel", "luff", "slew_start")
        act = _Activity(activity_id, t_ns, ids, self._geometry(names, out, t_ns))
        self._activity = act
        self._count("started")
        if m.kind == "stacker":
            msg = pb.StackStarted(pile_id=ids["pile_id"], pass_id=activity_id,
                                  lot_id=ids["lot_id"], machine_id=m.machine_id,
                                  pattern=getattr(pb, m.pattern),
                                  start_y_m=act.geometry["start_y"], end_y_m=act.geometry["end_y"])
            set_timestamp_ns(msg.time, t_ns)
            out.append(Publish("plc", msg))

    def _end(self, act: _Activity, end_ns: int, out: list) -> None:
        m = self.machine
        tonnes = max(0.0, round(act.tonnes, TONNES_DECIMALS))
        self._count("ended")
        if m.kind == "stacker":
            msg = pb.StackEnded(pile_id=act.ids["pile_id"], pass_id=act.activity_id,
                                tonnes=tonnes, bad_samples=act.bad_samples)
            set_timestamp_ns(msg.time, end_ns)
        else:
            end = self._geometry(("slew_end",), out, end_ns)
            msg = pb.ReclaimCut(pile_id=act.ids["pile_id"], cut_id=act.activity_id,
                                bench_id=act.ids["bench_id"], machine_id=m.machine_id,
                                travel_m=act.geometry["travel"], luff_rad=act.geometry["luff"],
                                slew_start_rad=act.geometry["slew_start"],
                                slew_end_rad=end["slew_end"], tonnes=tonnes,
                                bad_samples=act.bad_samples)
            set_timestamp_ns(msg.start_time, act.start_ns)
            set_timestamp_ns(msg.end_time, end_ns)
        if act.bad_samples:
            out.append(Note("warning", "flagged: bad samples", {
                "machine": m.machine_id, "id": act.activity_id, "bad_samples": act.bad_samples}))
        out.append(Publish("plc", msg))


def _state_key(value: Any) -> str:
    """The map key of a raw state value: integers (also whole floats) as digits, booleans
    as ``true``/``false``, strings stripped."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value).strip()
