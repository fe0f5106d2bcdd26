"""Validation of events at the ledger boundary.

:func:`check_event` decodes an :class:`~schemas.events.Event` and either returns
its message or raises :class:`InvalidEvent` with a machine-readable ``code`` (one
of :data:`REASON_CODES`) and a human-readable ``detail``.  It is pure: the checks
that need ledger state (duplicates, conflicts, unknown lots) live in the ledger.
"""

from __future__ import annotations

import math
import operator
from functools import lru_cache

import numpy as np
from google.protobuf import unknown_fields
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import DecodeError, Message

from schemas.events import (
    EVENT_TYPES,
    MAX_COUNTER,
    Event,
    is_valid_source,
    payload_valid_time_ns,
)
from schemas.analytes import AnalytePolicy, spellings as analyte_spellings
from schemas.packed import packed_doubles, packed_tail
from schemas.times import MAX_TIME_NS, MIN_TIME_NS, NS_PER_S

#: Every reason the ledger can give for refusing an event.
REASON_CODES: dict[str, str] = {
    "bad_identity": "source, epoch or sequence malformed or out of range",
    "bad_key": "Zenoh key expression is not a stockpile event key",
    "bad_attachment": "Zenoh attachment missing or malformed",
    "unsigned": "a type the site signs arrived without a signature",
    "bad_signature": "the signature does not hold for this event and key",
    "unknown_key": "signed with a key no admin declared",
    "revoked_key": "signed with a key revoked before the event's valid time",
    "key_not_valid": "the event's valid time lies outside its key's validity period",
    "key_role": "the key's role may not produce this event type",
    "malformed": "input line is not a valid event record",
    "unknown_type": "event type is not in the schema",
    "undecodable": "payload does not parse as the type's protobuf message",
    "valid_time_mismatch": "valid time differs from the payload's own timestamp",
    "non_finite": "NaN or infinity where a number is required",
    "out_of_range": "a value outside its physical or declared range",
    "missing_field": "a required identifier is empty",
    "ranges_angles_mismatch": "number of scan ranges inconsistent with its angles",
    "negative_tonnes": "a tonnage below zero",
    "analyte_out_of_range": "an analyte outside 0-100 mass %",
    "analyte_sum": "analytes summing to more than 100 mass %",
    "unknown_analyte": "an analyte not on the site's declared list, or one analyte named twice",
    "unknown_enum": "an enum value that is unspecified or not in the schema",
    "conflict": "same (source, epoch, seq) as a stored event, different payload",
    "recorded_time_backwards": "a preserved recorded time earlier than the ledger head",
    # what an import line can be besides an event (schemas.jsonl.decode_line, ledger.importing)
    "not_utf8": "input line is not UTF-8 text",
    "lone_surrogate": "a \\u escape of half a UTF-16 surrogate pair, which no text can hold",
    "too_large": "a number with more digits than a line may carry",
    "too_deep": "JSON nested deeper than a line may be",
    "unstorable": "the store refused the line as an event; kept as raw bytes only",
}

#: Analytes may sum to 100 % plus this rounding allowance (mass %, absolute).
ANALYTE_SUM_TOLERANCE_PCT = 0.1

#: widest field of view a scan may cover, degrees (one turn), and the allowance on it for
#: the rounding of the angles, radians
MAX_SCAN_FIELD_DEG = 360.0
#: the largest code of EPSG's registry (its codes run 1024-32767)
MAX_EPSG = 32767
_FIELD_TOLERANCE_RAD = 1e-9

# Times are stored as signed 64-bit UTC nanoseconds: MIN_TIME_NS .. MAX_TIME_NS (schemas.times).


def is_time_ns(value: object) -> bool:
    """Whether ``value`` is an integer time that fits in signed 64-bit nanoseconds."""
    return (isinstance(value, int) and not isinstance(value, bool)
            and MIN_TIME_NS <= value <= MAX_TIME_NS)

#: Identifiers that must not be empty, per event type.
REQUIRED_IDS: dict[str, tuple[str, ...]] = {
    "frame_transform": ("child_frame_id",),
    "joint_reading": ("machine_id",),
    "joint_estimate": ("machine_id",),
    "site_declared": ("site_id",),
    "pile_declared": ("pile_id",),
    "machine_declared": ("machine_id",),
    "lot_declared": ("lot_id",),
    "stack_started": ("pile_id", "pass_id", "lot_id"),
    "stack_ended": ("pile_id", "pass_id"),
    "reclaim_cut": ("pile_id", "cut_id"),
    "assay": ("assay_id", "lot_id"),
    "source_key_declared": ("key_id", "role", "name"),
    "source_key_revoked": ("key_id",),
    "survey": ("survey_id", "pile_id"),
}

#: Enum fields that must hold a defined, non-zero value.
REQUIRED_ENUMS: dict[str, tuple[str, ...]] = {
    "machine_declared": ("kind",),
    "stack_started": ("pattern",),
    "assay": ("status",),
}

#: Repeated double fields in which NaN is allowed (a NaN range means "no return");
#: the generic walk skips them and the type's own check reads them from the wire.
NAN_ALLOWED: frozenset[tuple[str, str]] = frozenset(
    {("foxglove.LaserScan", "ranges"), ("foxglove.LaserScan", "intensities")}
)


class InvalidEvent(ValueError):
    """An event refused at the ledger boundary.

    Attributes
    ----------
    code : str
        One of :data:`REASON_CODES`.
    detail : str
        What exactly is wrong, for people.
    """

    def __init__(self, code: str, detail: str) -> None:
        assert code in REASON_CODES, code
        super().__init__(f"{code}: {detail}")
        self.code = code
        self.detail = detail


_KNOWN_SOURCES: set[str] = set()  # sources already seen valid (bounded cache)


def shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to about ``limit`` characters; a huge integer by its size in bits
    (``repr`` of one with more than 4,300 digits raises)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 96:
        return f"an integer of {value.bit_length():,} bits"
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def check_identity(event: Event) -> None:
    """Raise :class:`InvalidEvent` unless type, source, epoch and seq are well formed.

    Epoch and seq must lie in [0, 2^63), valid and recorded time in signed 64 bits (what
    the store holds); anything else, however large, is ``bad_identity``.
    """
    if event.type not in EVENT_TYPES:
        raise InvalidEvent("unknown_type", f"unknown event type {shown(event.type)}")
    source = event.source
    if source not in _KNOWN_SOURCES:
        if type(source) is not str or not is_valid_source(source):
            raise InvalidEvent("bad_identity", f"bad source {shown(source)}")
        if len(_KNOWN_SOURCES) < 100_000:
            _KNOWN_SOURCES.add(source)
    epoch, seq = event.epoch, event.seq
    if type(epoch) is not int or not 0 <= epoch <= MAX_COUNTER:
        raise InvalidEvent("bad_identity", f"epoch {shown(epoch)} is not in [0, 2^63)")
    if type(seq) is not int or not 0 <= seq <= MAX_COUNTER:
        raise InvalidEvent("bad_identity", f"seq {shown(seq)} is not in [0, 2^63)")
    valid = event.valid_time_ns
    if type(valid) is not int or not MIN_TIME_NS <= valid <= MAX_TIME_NS:
        raise InvalidEvent("bad_identity",
                           f"valid_time_ns {shown(valid)} is not a signed 64-bit integer")
    if event.recorded_time_ns is not None and not is_time_ns(event.recorded_time_ns):
        raise InvalidEvent("bad_identity", f"recorded_time_ns {shown(event.recorded_time_ns)} "
                           "is not a signed 64-bit integer")
    if not isinstance(event.payload, (bytes, bytearray, memoryview)):
        raise InvalidEvent("undecodable", "payload is not bytes")


def check_event(event: Event) -> Message:
    """Decode and validate one event; return its protobuf message.

    Raises
    ------
    InvalidEvent
        With the first problem found; ``code`` is one of :data:`REASON_CODES`.
    """
    check_identity(event)
    cls = EVENT_TYPES[event.type]
    try:
        message = cls.FromString(bytes(event.payload))
    except DecodeError as exc:
        raise InvalidEvent("undecodable", f"payload is not a {cls.DESCRIPTOR.full_name}: {exc}") from None
    if len(unknown_fields.UnknownFieldSet(message)):
        raise InvalidEvent(
            "undecodable",
            f"payload has fields unknown to {cls.DESCRIPTOR.full_name} (wrong type or schema?)",
        )
    _compiled(cls.DESCRIPTOR).check(message)
    payload_time = payload_valid_time_ns(event.type, message)
    if payload_time != event.valid_time_ns:
        raise InvalidEvent(
            "valid_time_mismatch",
            f"valid_time_ns {event.valid_time_ns} but payload says {payload_time}",
        )
    for name in REQUIRED_IDS.get(event.type, ()):
        if not getattr(message, name):
            raise InvalidEvent("missing_field", f"{name} is empty")
    for name in REQUIRED_ENUMS.get(event.type, ()):
        if getattr(message, name) == 0:
            raise InvalidEvent("unknown_enum", f"{name} is unspecified")
    check = _TYPE_CHECKS.get(event.type)
    if check is _check_scan:
        _check_scan(message, bytes(event.payload))
    elif check is not None:
        check(message)
    return message


# --- per-type compiled checks: finiteness, enums, timestamps ---------------------------
#
# For each message type the fields to check are found once from its descriptor,
# following singular sub-messages (so ``rotation.w`` of a FrameTransform is one dotted
# path), and read with one ``operator.attrgetter`` call.  The fast path for doubles
# is one ``sum``: it is finite exactly when no value is NaN or infinite (barring an
# overflow of the sum, which the exact per-field pass then clears).


def _tuple_getter(paths: list[str]):
    """A callable giving the values at the dotted ``paths`` as one tuple, in order.

    Paths that share a sub-message (``rotation.x``, ``rotation.w``) are read through it
    once: each read of a sub-message makes a new Python object for it.
    """
    if not paths:
        return lambda message: ()
    groups: list[tuple[str, list[str]]] = []    # (sub-message path, leaf names), in order
    for path in paths:
        parent, _, leaf = path.rpartition(".")
        if groups and groups[-1][0] == parent:
            groups[-1][1].append(leaf)
        else:
            groups.append((parent, [leaf]))
    if len(groups) == 1 and not groups[0][0] or len(paths) == 1:
        return _flat_getter(paths)
    steps = [(operator.attrgetter(parent) if parent else None, _flat_getter(leaves))
             for parent, leaves in groups]

    def getter(message):
        values: tuple = ()
        for sub, leaves in steps:
            values += leaves(sub(message) if sub is not None else message)
        return values
    return getter


def _flat_getter(paths: list[str]):
    getter = operator.attrgetter(*paths)
    if len(paths) == 1:
        return lambda message: (getter(message),)
    return getter


class _CompiledChecks:
    """Everything the generic checks read from one message type, as dotted paths."""

    def __init__(self, descriptor: Descriptor) -> None:
        self.name = descriptor.full_name
        doubles: list[str] = []
        repeated: list[str] = []
        maps: list[str] = []
        enums: list[tuple[str, frozenset[int], str]] = []
        timestamps: list[str] = []
        self._collect(descriptor, "", doubles, repeated, maps, enums, timestamps, depth=0)
        self.double_paths, self.repeated_paths, self.map_paths = doubles, repeated, maps
        self.enum_paths, self.timestamp_paths = enums, timestamps
        self.get_doubles = _tuple_getter(doubles)
        self.get_repeated = _tuple_getter(repeated)
        self.get_maps = _tuple_getter(maps)
        self.get_enums = _tuple_getter([e[0] for e in enums])
        self.get_timestamps = _tuple_getter(timestamps)

    def _collect(self, descriptor, prefix, doubles, repeated, maps, enums, timestamps, depth):
        if depth > 8:
            raise ValueError(f"{descriptor.full_name} nests too deeply to validate")
        for field in descriptor.fields:
            path = prefix + field.name
            if (descriptor.full_name, field.name) in NAN_ALLOWED:
                continue  # checked by the type's own check
            if field.type in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
                (repeated if field.is_repeated else doubles).append(path)
            elif field.type == FieldDescriptor.TYPE_ENUM and not field.is_repeated:
                values = frozenset(field.enum_type.values_by_number)
                enums.append((path, values, field.enum_type.full_name))
            elif field.type == FieldDescriptor.TYPE_MESSAGE and not field.is_repeated:
                sub = field.message_type
                if sub.full_name == "google.protobuf.Timestamp":
                    timestamps.append(path)
                else:
                    self._collect(sub, path + ".", doubles, repeated, maps, enums, timestamps,
                                  depth + 1)
            elif field.type == FieldDescriptor.TYPE_MESSAGE and field.message_type.GetOptions().map_entry:
                if field.message_type.fields_by_name["value"].type == FieldDescriptor.TYPE_DOUBLE:
                    maps.append(path)

    def check(self, message: Message) -> None:
        values = self.get_doubles(message)
        if values and not math.isfinite(sum(values)):
            for path, value in zip(self.double_paths, values):
                if not math.isfinite(value):
                    raise InvalidEvent("non_finite", f"{self.name}.{path} is not finite")
        if self.repeated_paths:     # (most types have none: skip the getter's call)
            self._check_repeated(message)
        if self.map_paths:
            self._check_maps(message)
        if self.enum_paths:
            self._check_enums(message)
        for path, ts in zip(self.timestamp_paths, self.get_timestamps(message)):
            nanos = ts.nanos
            if not 0 <= nanos < NS_PER_S or not is_time_ns(ts.seconds * NS_PER_S + nanos):
                raise InvalidEvent(
                    "out_of_range",
                    f"{self.name}.{path} is not a timestamp between 1677-09-21 and 2262-04-11")

    def _check_repeated(self, message: Message) -> None:
        for path, items in zip(self.repeated_paths, self.get_repeated(message)):
            if items and not math.isfinite(sum(items)):
                for index, value in enumerate(items):
                    if not math.isfinite(value):
                        raise InvalidEvent("non_finite", f"{self.name}.{path}[{index}] is not finite")

    def _check_maps(self, message: Message) -> None:
        for path, mapping in zip(self.map_paths, self.get_maps(message)):
            for key, value in mapping.items():
                if not math.isfinite(value):
                    raise InvalidEvent("non_finite", f"{self.name}.{path}[{key!r}] is not finite")

    def _check_enums(self, message: Message) -> None:
        for (path, allowed, enum_name), value in zip(self.enum_paths, self.get_enums(message)):
            if value not in allowed:
                raise InvalidEvent("unknown_enum", f"{self.name}.{path} = {value} is not a {enum_name}")


@lru_cache(maxsize=None)
def _compiled(descriptor: Descriptor) -> _CompiledChecks:
    return _CompiledChecks(descriptor)


# --- per-type semantic checks ----------------------------------------------------------


def _require(condition: bool, code: str, detail: str) -> None:
    if not condition:
        raise InvalidEvent(code, detail)


def check_analytes(grades, field: str) -> None:
    """Each analyte in [0, 100] mass %, their sum <= 100 (+ rounding tolerance)."""
    total = 0.0
    for name, value in grades.items():
        _require(bool(name), "analyte_out_of_range", f"{field} has an unnamed analyte")
        _require(0.0 <= value <= 100.0, "analyte_out_of_range", f"{field}[{name!r}] = {value} %")
        total += value
    _require(
        total <= 100.0 + ANALYTE_SUM_TOLERANCE_PCT,
        "analyte_sum",
        f"{field} sums to {total:.3f} % (> 100 %)",
    )


#: Event types that name analytes (:func:`check_analyte_names`).
ANALYTE_TYPES: frozenset[str] = frozenset({"assay", "lot_declared"})


def check_analyte_names(type_name: str, message, policy: AnalytePolicy) -> tuple[str, ...]:
    """The analyte names of an assay or lot plan checked against the site's ``policy``
    (:mod:`schemas.analytes`): the unknown names to flag, sorted (empty for other types).

    Raises :class:`InvalidEvent` (``unknown_analyte``) for a name that cannot be an
    analyte, for two spellings of one analyte, and under the ``quarantine`` policy for an
    unknown name."""
    if type_name == "assay":
        grades, field = message.analytes, "analytes"
    elif type_name == "lot_declared":
        grades, field = message.planned_grade, "planned_grade"
    else:
        return ()
    unknown, problems = analyte_spellings(grades, policy)
    _require(not problems, "unknown_analyte", f"{field}: {problems[0] if problems else ''}")
    _require(not unknown or policy.unknown != "quarantine", "unknown_analyte",
             f"{field} names {', '.join(map(repr, unknown))}, not on the declared list "
             f"({','.join(policy.declared)})")
    return tuple(unknown)


_LASER_SCAN_RANGES = 6
_LASER_SCAN_INTENSITIES = 7


_MAX_FIELD_RAD = math.radians(MAX_SCAN_FIELD_DEG)


def _check_scan(m, payload: bytes) -> None:
    """A scan's geometry (any scanner: the step is what its angles and count make it) and
    its ranges.  A ``LaserScan`` carries no step of its own: beam ``k`` lies at
    ``start_angle + k * step`` with ``step = (end_angle - start_angle) / (n - 1)``, so the
    count matches the angles when that step is finite and > 0 and the field
    ``end_angle - start_angle`` is > 0 and at most one turn (360 deg)."""
    n = len(m.ranges)
    span = m.end_angle - m.start_angle
    if n < 2:
        raise InvalidEvent("ranges_angles_mismatch", f"a scan needs at least 2 ranges, got {n}")
    if not span > 0:
        raise InvalidEvent("ranges_angles_mismatch", "end_angle must be greater than start_angle")
    if not span <= _MAX_FIELD_RAD + _FIELD_TOLERANCE_RAD:
        raise InvalidEvent("ranges_angles_mismatch",
                           f"{n} ranges over {math.degrees(span):.3f} deg: a field wider than "
                           f"{MAX_SCAN_FIELD_DEG:g} deg")
    step = span / (n - 1)
    if not (math.isfinite(step) and step > 0):
        raise InvalidEvent("ranges_angles_mismatch",
                           f"{n} ranges over {span!r} rad give a step of {step!r} rad")
    n_intensities = len(m.intensities)
    if n_intensities not in (0, n):
        raise InvalidEvent("ranges_angles_mismatch", f"{n_intensities} intensities for {n} ranges")
    arrays = None
    if not n_intensities:
        ranges = packed_tail(payload, _LASER_SCAN_RANGES, n, m.ranges)
        if ranges is not None:
            arrays = [ranges, np.empty(0)]
    if arrays is None:
        arrays = packed_doubles(payload, _LASER_SCAN_RANGES, _LASER_SCAN_INTENSITIES)
    if arrays is None:
        arrays = [np.asarray(m.ranges, dtype=np.float64), np.asarray(m.intensities, dtype=np.float64)]
    for values, name, lowest in zip(arrays, ("ranges", "intensities"), (0.0, -math.inf)):
        if not len(values):
            continue
        # NaN ("no return") is allowed; fmin/fmax ignore it.  All-NaN gives NaN: fine.
        low, high = np.fmin.reduce(values), np.fmax.reduce(values)
        if high == math.inf or low == -math.inf:
            raise InvalidEvent("non_finite", f"{name} holds an infinity")
        if low < lowest:
            raise InvalidEvent("out_of_range", f"negative value in {name}")


def _check_location_fix(m) -> None:
    _require(-90.0 <= m.latitude <= 90.0, "out_of_range", f"latitude {m.latitude}")
    _require(-180.0 <= m.longitude <= 180.0, "out_of_range", f"longitude {m.longitude}")
    _require(len(m.position_covariance) in (0, 9), "out_of_range",
             f"position_covariance has {len(m.position_covariance)} values, expected 9")


def _check_frame_transform(m) -> None:
    q = m.rotation
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    _require(abs(norm - 1.0) <= 1e-3, "out_of_range", f"rotation quaternion norm {norm:.6f} != 1")


def _check_joint_estimate(m) -> None:
    for name in ("covariance", "position_covariance_m2"):
        _require(len(getattr(m, name)) in (0, 9), "out_of_range",
                 f"{name} has {len(getattr(m, name))} values, expected 9")


def _check_site(m) -> None:
    _require(-90.0 <= m.datum_lat_deg <= 90.0, "out_of_range", f"datum_lat_deg {m.datum_lat_deg}")
    _require(-180.0 <= m.datum_lon_deg <= 180.0, "out_of_range", f"datum_lon_deg {m.datum_lon_deg}")
    _require(m.crs_epsg == 0 or 1024 <= m.crs_epsg <= MAX_EPSG, "out_of_range",
             f"crs_epsg {m.crs_epsg} is not an EPSG code (1024-{MAX_EPSG}, or 0 for none)")


def _check_pile(m) -> None:
    _require(m.length_m > 0 and m.width_m > 0, "out_of_range", "length_m and width_m must be > 0")
    _require(m.cell_m >= 0 and m.voxel_m >= 0, "out_of_range", "cell_m and voxel_m must be >= 0")
    _require(m.default_bulk_density_t_m3 > 0, "out_of_range",
             f"default_bulk_density_t_m3 {m.default_bulk_density_t_m3} must be > 0")


def _check_machine(m) -> None:
    for name in ("l2_m", "l3_m", "l4_m", "l5_m", "wheel_radius_m", "cutting_radius_m", "bucket_width_m"):
        _require(getattr(m, name) >= 0, "out_of_range", f"{name} must be >= 0")


def _check_lot(m) -> None:
    _require(m.planned_tonnes >= 0, "negative_tonnes", f"planned_tonnes {m.planned_tonnes}")
    check_analytes(m.planned_grade, "planned_grade")


def _check_stack_ended(m) -> None:
    _require(m.tonnes >= 0, "negative_tonnes", f"tonnes {m.tonnes}")


def _check_reclaim_cut(m) -> None:
    _require(m.tonnes >= 0, "negative_tonnes", f"tonnes {m.tonnes}")
    _require(
        (m.start_time.seconds, m.start_time.nanos) <= (m.end_time.seconds, m.end_time.nanos),
        "out_of_range", "start_time is after end_time",
    )


def _check_assay(m) -> None:
    check_analytes(m.analytes, "analytes")
    _require(0.0 <= m.moisture_pct <= 100.0, "out_of_range", f"moisture_pct {m.moisture_pct}")
    _require(m.bulk_density_t_m3 >= 0, "out_of_range", f"bulk_density_t_m3 {m.bulk_density_t_m3}")
    _require(
        (m.window_start.seconds, m.window_start.nanos) <= (m.window_end.seconds, m.window_end.nanos),
        "out_of_range", "window_start is after window_end",
    )
    _require(m.supersedes != m.assay_id, "out_of_range", "an assay cannot supersede itself")
    for name, sd in m.repeatability_pp.items():
        _require(name in m.analytes, "out_of_range",
                 f"repeatability_pp[{name!r}] names an analyte the assay does not report")
        _require(0.0 < sd <= 100.0, "out_of_range", f"repeatability_pp[{name!r}] = {sd} pp")


def _check_source_key(m) -> None:
    _require(len(m.public_key) == 32, "out_of_range",
             f"public_key is {len(m.public_key)} bytes, an Ed25519 key is 32")
    _require(
        (m.valid_from.seconds, m.valid_from.nanos) < (m.valid_until.seconds, m.valid_until.nanos),
        "out_of_range", "valid_from is not before valid_until")


#: the most cells a survey's grid part may have (a 1 km x 1 km pile at 0.25 m)
MAX_SURVEY_CELLS = 16_000_000


def _check_survey(m) -> None:
    _require(m.cell_m > 0 and m.nx >= 1 and m.ny >= 1, "out_of_range",
             "cell_m must be > 0 and nx, ny >= 1")
    _require(m.nx * m.ny <= MAX_SURVEY_CELLS, "out_of_range",
             f"{m.nx} x {m.ny} cells, more than {MAX_SURVEY_CELLS}")
    _require(len(m.heights_m) == 4 * m.nx * m.ny and len(m.counts) == 2 * m.nx * m.ny,
             "out_of_range", f"heights_m ({len(m.heights_m)} bytes) and counts "
             f"({len(m.counts)} bytes) must hold nx * ny = {m.nx * m.ny} cells")
    _require(len(m.source_sha256) == 32, "out_of_range",
             f"source_sha256 is {len(m.source_sha256)} bytes, a sha256 is 32")
    _require(m.accuracy_m >= 0, "out_of_range", f"accuracy_m {m.accuracy_m} must be >= 0")
    _require(m.points_in_grid <= m.points, "out_of_range",
             "points_in_grid must not exceed points")


_TYPE_CHECKS = {
    "scan": _check_scan,
    "location_fix": _check_location_fix,
    "frame_transform": _check_frame_transform,
    "joint_estimate": _check_joint_estimate,
    "site_declared": _check_site,
    "pile_declared": _check_pile,
    "machine_declared": _check_machine,
    "lot_declared": _check_lot,
    "stack_ended": _check_stack_ended,
    "reclaim_cut": _check_reclaim_cut,
    "assay": _check_assay,
    "source_key_declared": _check_source_key,
    "survey": _check_survey,
}
