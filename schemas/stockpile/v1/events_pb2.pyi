import datetime

from google.protobuf import timestamp_pb2 as _timestamp_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MachineKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MACHINE_KIND_UNSPECIFIED: _ClassVar[MachineKind]
    BUCKET_WHEEL_RECLAIMER: _ClassVar[MachineKind]
    STACKER: _ClassVar[MachineKind]

class StackPattern(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STACK_PATTERN_UNSPECIFIED: _ClassVar[StackPattern]
    CHEVRON: _ClassVar[StackPattern]
    WINDROW: _ClassVar[StackPattern]
    CONE_SHELL: _ClassVar[StackPattern]
    STRATA: _ClassVar[StackPattern]

class AssayStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ASSAY_STATUS_UNSPECIFIED: _ClassVar[AssayStatus]
    PROVISIONAL: _ClassVar[AssayStatus]
    FINAL: _ClassVar[AssayStatus]
MACHINE_KIND_UNSPECIFIED: MachineKind
BUCKET_WHEEL_RECLAIMER: MachineKind
STACKER: MachineKind
STACK_PATTERN_UNSPECIFIED: StackPattern
CHEVRON: StackPattern
WINDROW: StackPattern
CONE_SHELL: StackPattern
STRATA: StackPattern
ASSAY_STATUS_UNSPECIFIED: AssayStatus
PROVISIONAL: AssayStatus
FINAL: AssayStatus

class Vector3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Quaternion(_message.Message):
    __slots__ = ("x", "y", "z", "w")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    W_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    w: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., w: _Optional[float] = ...) -> None: ...

class Mount(_message.Message):
    __slots__ = ("parent_frame_id", "child_frame_id", "translation", "rotation")
    PARENT_FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    CHILD_FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TRANSLATION_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    parent_frame_id: str
    child_frame_id: str
    translation: Vector3
    rotation: Quaternion
    def __init__(self, parent_frame_id: _Optional[str] = ..., child_frame_id: _Optional[str] = ..., translation: _Optional[_Union[Vector3, _Mapping]] = ..., rotation: _Optional[_Union[Quaternion, _Mapping]] = ...) -> None: ...

class SiteDeclared(_message.Message):
    __slots__ = ("time", "site_id", "datum_lat_deg", "datum_lon_deg", "datum_alt_m", "crs_epsg")
    TIME_FIELD_NUMBER: _ClassVar[int]
    SITE_ID_FIELD_NUMBER: _ClassVar[int]
    DATUM_LAT_DEG_FIELD_NUMBER: _ClassVar[int]
    DATUM_LON_DEG_FIELD_NUMBER: _ClassVar[int]
    DATUM_ALT_M_FIELD_NUMBER: _ClassVar[int]
    CRS_EPSG_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    site_id: str
    datum_lat_deg: float
    datum_lon_deg: float
    datum_alt_m: float
    crs_epsg: int
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., site_id: _Optional[str] = ..., datum_lat_deg: _Optional[float] = ..., datum_lon_deg: _Optional[float] = ..., datum_alt_m: _Optional[float] = ..., crs_epsg: _Optional[int] = ...) -> None: ...

class PileDeclared(_message.Message):
    __slots__ = ("time", "pile_id", "origin_x_m", "origin_y_m", "length_m", "width_m", "ground_z_m", "cell_m", "voxel_m", "default_bulk_density_t_m3", "survey_rebase")
    TIME_FIELD_NUMBER: _ClassVar[int]
    PILE_ID_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_X_M_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_Y_M_FIELD_NUMBER: _ClassVar[int]
    LENGTH_M_FIELD_NUMBER: _ClassVar[int]
    WIDTH_M_FIELD_NUMBER: _ClassVar[int]
    GROUND_Z_M_FIELD_NUMBER: _ClassVar[int]
    CELL_M_FIELD_NUMBER: _ClassVar[int]
    VOXEL_M_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_BULK_DENSITY_T_M3_FIELD_NUMBER: _ClassVar[int]
    SURVEY_REBASE_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    pile_id: str
    origin_x_m: float
    origin_y_m: float
    length_m: float
    width_m: float
    ground_z_m: float
    cell_m: float
    voxel_m: float
    default_bulk_density_t_m3: float
    survey_rebase: bool
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., pile_id: _Optional[str] = ..., origin_x_m: _Optional[float] = ..., origin_y_m: _Optional[float] = ..., length_m: _Optional[float] = ..., width_m: _Optional[float] = ..., ground_z_m: _Optional[float] = ..., cell_m: _Optional[float] = ..., voxel_m: _Optional[float] = ..., default_bulk_density_t_m3: _Optional[float] = ..., survey_rebase: _Optional[bool] = ...) -> None: ...

class MachineDeclared(_message.Message):
    __slots__ = ("time", "machine_id", "kind", "rail_x_m", "rail_z_m", "l2_m", "l3_m", "l4_m", "l5_m", "wheel_radius_m", "cutting_radius_m", "wheel_tilt_rad", "bucket_width_m", "fall_angle_rad", "scanner")
    TIME_FIELD_NUMBER: _ClassVar[int]
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    RAIL_X_M_FIELD_NUMBER: _ClassVar[int]
    RAIL_Z_M_FIELD_NUMBER: _ClassVar[int]
    L2_M_FIELD_NUMBER: _ClassVar[int]
    L3_M_FIELD_NUMBER: _ClassVar[int]
    L4_M_FIELD_NUMBER: _ClassVar[int]
    L5_M_FIELD_NUMBER: _ClassVar[int]
    WHEEL_RADIUS_M_FIELD_NUMBER: _ClassVar[int]
    CUTTING_RADIUS_M_FIELD_NUMBER: _ClassVar[int]
    WHEEL_TILT_RAD_FIELD_NUMBER: _ClassVar[int]
    BUCKET_WIDTH_M_FIELD_NUMBER: _ClassVar[int]
    FALL_ANGLE_RAD_FIELD_NUMBER: _ClassVar[int]
    SCANNER_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    machine_id: str
    kind: MachineKind
    rail_x_m: float
    rail_z_m: float
    l2_m: float
    l3_m: float
    l4_m: float
    l5_m: float
    wheel_radius_m: float
    cutting_radius_m: float
    wheel_tilt_rad: float
    bucket_width_m: float
    fall_angle_rad: float
    scanner: Mount
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., machine_id: _Optional[str] = ..., kind: _Optional[_Union[MachineKind, str]] = ..., rail_x_m: _Optional[float] = ..., rail_z_m: _Optional[float] = ..., l2_m: _Optional[float] = ..., l3_m: _Optional[float] = ..., l4_m: _Optional[float] = ..., l5_m: _Optional[float] = ..., wheel_radius_m: _Optional[float] = ..., cutting_radius_m: _Optional[float] = ..., wheel_tilt_rad: _Optional[float] = ..., bucket_width_m: _Optional[float] = ..., fall_angle_rad: _Optional[float] = ..., scanner: _Optional[_Union[Mount, _Mapping]] = ...) -> None: ...

class JointReading(_message.Message):
    __slots__ = ("time", "machine_id", "travel_m", "slew_rad", "luff_rad")
    TIME_FIELD_NUMBER: _ClassVar[int]
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    TRAVEL_M_FIELD_NUMBER: _ClassVar[int]
    SLEW_RAD_FIELD_NUMBER: _ClassVar[int]
    LUFF_RAD_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    machine_id: str
    travel_m: float
    slew_rad: float
    luff_rad: float
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., machine_id: _Optional[str] = ..., travel_m: _Optional[float] = ..., slew_rad: _Optional[float] = ..., luff_rad: _Optional[float] = ...) -> None: ...

class JointEstimate(_message.Message):
    __slots__ = ("time", "machine_id", "travel_m", "slew_rad", "luff_rad", "covariance", "position_covariance_m2")
    TIME_FIELD_NUMBER: _ClassVar[int]
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    TRAVEL_M_FIELD_NUMBER: _ClassVar[int]
    SLEW_RAD_FIELD_NUMBER: _ClassVar[int]
    LUFF_RAD_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    POSITION_COVARIANCE_M2_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    machine_id: str
    travel_m: float
    slew_rad: float
    luff_rad: float
    covariance: _containers.RepeatedScalarFieldContainer[float]
    position_covariance_m2: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., machine_id: _Optional[str] = ..., travel_m: _Optional[float] = ..., slew_rad: _Optional[float] = ..., luff_rad: _Optional[float] = ..., covariance: _Optional[_Iterable[float]] = ..., position_covariance_m2: _Optional[_Iterable[float]] = ...) -> None: ...

class LotDeclared(_message.Message):
    __slots__ = ("time", "lot_id", "origin", "planned_tonnes", "planned_grade")
    class PlannedGradeEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    TIME_FIELD_NUMBER: _ClassVar[int]
    LOT_ID_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_FIELD_NUMBER: _ClassVar[int]
    PLANNED_TONNES_FIELD_NUMBER: _ClassVar[int]
    PLANNED_GRADE_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    lot_id: str
    origin: str
    planned_tonnes: float
    planned_grade: _containers.ScalarMap[str, float]
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., lot_id: _Optional[str] = ..., origin: _Optional[str] = ..., planned_tonnes: _Optional[float] = ..., planned_grade: _Optional[_Mapping[str, float]] = ...) -> None: ...

class StackStarted(_message.Message):
    __slots__ = ("time", "pile_id", "pass_id", "lot_id", "machine_id", "pattern", "start_y_m", "end_y_m")
    TIME_FIELD_NUMBER: _ClassVar[int]
    PILE_ID_FIELD_NUMBER: _ClassVar[int]
    PASS_ID_FIELD_NUMBER: _ClassVar[int]
    LOT_ID_FIELD_NUMBER: _ClassVar[int]
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    PATTERN_FIELD_NUMBER: _ClassVar[int]
    START_Y_M_FIELD_NUMBER: _ClassVar[int]
    END_Y_M_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    pile_id: str
    pass_id: str
    lot_id: str
    machine_id: str
    pattern: StackPattern
    start_y_m: float
    end_y_m: float
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., pile_id: _Optional[str] = ..., pass_id: _Optional[str] = ..., lot_id: _Optional[str] = ..., machine_id: _Optional[str] = ..., pattern: _Optional[_Union[StackPattern, str]] = ..., start_y_m: _Optional[float] = ..., end_y_m: _Optional[float] = ...) -> None: ...

class StackEnded(_message.Message):
    __slots__ = ("time", "pile_id", "pass_id", "tonnes", "bad_samples")
    TIME_FIELD_NUMBER: _ClassVar[int]
    PILE_ID_FIELD_NUMBER: _ClassVar[int]
    PASS_ID_FIELD_NUMBER: _ClassVar[int]
    TONNES_FIELD_NUMBER: _ClassVar[int]
    BAD_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    pile_id: str
    pass_id: str
    tonnes: float
    bad_samples: int
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., pile_id: _Optional[str] = ..., pass_id: _Optional[str] = ..., tonnes: _Optional[float] = ..., bad_samples: _Optional[int] = ...) -> None: ...

class ReclaimCut(_message.Message):
    __slots__ = ("pile_id", "cut_id", "bench_id", "machine_id", "start_time", "end_time", "travel_m", "luff_rad", "slew_start_rad", "slew_end_rad", "tonnes", "bad_samples")
    PILE_ID_FIELD_NUMBER: _ClassVar[int]
    CUT_ID_FIELD_NUMBER: _ClassVar[int]
    BENCH_ID_FIELD_NUMBER: _ClassVar[int]
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    START_TIME_FIELD_NUMBER: _ClassVar[int]
    END_TIME_FIELD_NUMBER: _ClassVar[int]
    TRAVEL_M_FIELD_NUMBER: _ClassVar[int]
    LUFF_RAD_FIELD_NUMBER: _ClassVar[int]
    SLEW_START_RAD_FIELD_NUMBER: _ClassVar[int]
    SLEW_END_RAD_FIELD_NUMBER: _ClassVar[int]
    TONNES_FIELD_NUMBER: _ClassVar[int]
    BAD_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    pile_id: str
    cut_id: str
    bench_id: str
    machine_id: str
    start_time: _timestamp_pb2.Timestamp
    end_time: _timestamp_pb2.Timestamp
    travel_m: float
    luff_rad: float
    slew_start_rad: float
    slew_end_rad: float
    tonnes: float
    bad_samples: int
    def __init__(self, pile_id: _Optional[str] = ..., cut_id: _Optional[str] = ..., bench_id: _Optional[str] = ..., machine_id: _Optional[str] = ..., start_time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., end_time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., travel_m: _Optional[float] = ..., luff_rad: _Optional[float] = ..., slew_start_rad: _Optional[float] = ..., slew_end_rad: _Optional[float] = ..., tonnes: _Optional[float] = ..., bad_samples: _Optional[int] = ...) -> None: ...

class Assay(_message.Message):
    __slots__ = ("assay_id", "lot_id", "window_start", "window_end", "analytes", "moisture_pct", "bulk_density_t_m3", "status", "supersedes", "lab_id", "reported_time", "repeatability_pp")
    class AnalytesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    class RepeatabilityPpEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    ASSAY_ID_FIELD_NUMBER: _ClassVar[int]
    LOT_ID_FIELD_NUMBER: _ClassVar[int]
    WINDOW_START_FIELD_NUMBER: _ClassVar[int]
    WINDOW_END_FIELD_NUMBER: _ClassVar[int]
    ANALYTES_FIELD_NUMBER: _ClassVar[int]
    MOISTURE_PCT_FIELD_NUMBER: _ClassVar[int]
    BULK_DENSITY_T_M3_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    SUPERSEDES_FIELD_NUMBER: _ClassVar[int]
    LAB_ID_FIELD_NUMBER: _ClassVar[int]
    REPORTED_TIME_FIELD_NUMBER: _ClassVar[int]
    REPEATABILITY_PP_FIELD_NUMBER: _ClassVar[int]
    assay_id: str
    lot_id: str
    window_start: _timestamp_pb2.Timestamp
    window_end: _timestamp_pb2.Timestamp
    analytes: _containers.ScalarMap[str, float]
    moisture_pct: float
    bulk_density_t_m3: float
    status: AssayStatus
    supersedes: str
    lab_id: str
    reported_time: _timestamp_pb2.Timestamp
    repeatability_pp: _containers.ScalarMap[str, float]
    def __init__(self, assay_id: _Optional[str] = ..., lot_id: _Optional[str] = ..., window_start: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., window_end: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., analytes: _Optional[_Mapping[str, float]] = ..., moisture_pct: _Optional[float] = ..., bulk_density_t_m3: _Optional[float] = ..., status: _Optional[_Union[AssayStatus, str]] = ..., supersedes: _Optional[str] = ..., lab_id: _Optional[str] = ..., reported_time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., repeatability_pp: _Optional[_Mapping[str, float]] = ...) -> None: ...

class Clock(_message.Message):
    __slots__ = ("time",)
    TIME_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class SourceKeyDeclared(_message.Message):
    __slots__ = ("time", "key_id", "public_key", "role", "name", "valid_from", "valid_until")
    TIME_FIELD_NUMBER: _ClassVar[int]
    KEY_ID_FIELD_NUMBER: _ClassVar[int]
    PUBLIC_KEY_FIELD_NUMBER: _ClassVar[int]
    ROLE_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    VALID_FROM_FIELD_NUMBER: _ClassVar[int]
    VALID_UNTIL_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    key_id: str
    public_key: bytes
    role: str
    name: str
    valid_from: _timestamp_pb2.Timestamp
    valid_until: _timestamp_pb2.Timestamp
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., key_id: _Optional[str] = ..., public_key: _Optional[bytes] = ..., role: _Optional[str] = ..., name: _Optional[str] = ..., valid_from: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., valid_until: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class SourceKeyRevoked(_message.Message):
    __slots__ = ("time", "key_id", "reason")
    TIME_FIELD_NUMBER: _ClassVar[int]
    KEY_ID_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    key_id: str
    reason: str
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., key_id: _Optional[str] = ..., reason: _Optional[str] = ...) -> None: ...

class Survey(_message.Message):
    __slots__ = ("time", "survey_id", "pile_id", "provider", "accuracy_m", "source_sha256", "crs_epsg", "origin_x_m", "origin_y_m", "cell_m", "ix0", "iy0", "nx", "ny", "heights_m", "counts", "points", "points_in_grid")
    TIME_FIELD_NUMBER: _ClassVar[int]
    SURVEY_ID_FIELD_NUMBER: _ClassVar[int]
    PILE_ID_FIELD_NUMBER: _ClassVar[int]
    PROVIDER_FIELD_NUMBER: _ClassVar[int]
    ACCURACY_M_FIELD_NUMBER: _ClassVar[int]
    SOURCE_SHA256_FIELD_NUMBER: _ClassVar[int]
    CRS_EPSG_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_X_M_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_Y_M_FIELD_NUMBER: _ClassVar[int]
    CELL_M_FIELD_NUMBER: _ClassVar[int]
    IX0_FIELD_NUMBER: _ClassVar[int]
    IY0_FIELD_NUMBER: _ClassVar[int]
    NX_FIELD_NUMBER: _ClassVar[int]
    NY_FIELD_NUMBER: _ClassVar[int]
    HEIGHTS_M_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    POINTS_IN_GRID_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    survey_id: str
    pile_id: str
    provider: str
    accuracy_m: float
    source_sha256: bytes
    crs_epsg: int
    origin_x_m: float
    origin_y_m: float
    cell_m: float
    ix0: int
    iy0: int
    nx: int
    ny: int
    heights_m: bytes
    counts: bytes
    points: int
    points_in_grid: int
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., survey_id: _Optional[str] = ..., pile_id: _Optional[str] = ..., provider: _Optional[str] = ..., accuracy_m: _Optional[float] = ..., source_sha256: _Optional[bytes] = ..., crs_epsg: _Optional[int] = ..., origin_x_m: _Optional[float] = ..., origin_y_m: _Optional[float] = ..., cell_m: _Optional[float] = ..., ix0: _Optional[int] = ..., iy0: _Optional[int] = ..., nx: _Optional[int] = ..., ny: _Optional[int] = ..., heights_m: _Optional[bytes] = ..., counts: _Optional[bytes] = ..., points: _Optional[int] = ..., points_in_grid: _Optional[int] = ...) -> None: ...
