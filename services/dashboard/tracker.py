"""What the dashboard knows from the records read so far, before anything is logged.

:class:`PileTracker` takes committed ledger records in global order: it feeds the live
projection (:class:`services.projector_service.LiveProjection`) and keeps the position
read (seq K, recorded and valid time), the reclaimers and their latest wheel poses, the
scanner's recent poses and the latest scan, the reclaim cuts' messages, the assays by id,
each analyte's range of grades (the colour scales) and the reasons an update is due.  It
logs nothing: :meth:`PileTracker.add` returns the log lines a record gives.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from projector.kinematics import Reclaimer
from projector.grades import coerce_time_ns
from schemas.analytes import canonical_grades
from schemas.events import decode_payload
from schemas.times import NS_PER_H
from services.dashboard.pose import quat_matrix, wheel_from_scanner
from services.projector_service import LiveProjection

#: record types that change what is drawn in 3D
GEOMETRY_TYPES = ("scan", "frame_transform", "stack_started", "stack_ended",
                  "reclaim_cut", "pile_declared", "machine_declared", "survey")
#: a machine's scanner poses kept for georeferencing its latest scan
SCANNER_POSES_KEPT = 64


@dataclass
class MachineState:
    """A declared bucket-wheel reclaimer and its latest wheel pose."""

    machine_id: str
    reclaimer: Any
    wheel_radius_m: float
    mount: tuple[np.ndarray, np.ndarray] | None   # scanner in wheel: (R, t)
    pose: tuple[int, np.ndarray, np.ndarray] | None = None   # (t, centre, R) of the wheel
    logged_pose_ns: int | None = None
    rail_logged: bool = False


class PileTracker:
    """The records read so far, as the dashboard needs them (see the module docstring).

    Parameters
    ----------
    pile_id : str
    reorder_ns : int
        The live fold's reorder window, site ns.
    """

    def __init__(self, pile_id: str, reorder_ns: int) -> None:
        self.pile_id = pile_id
        self.projection = LiveProjection(pile_id, reorder_ns)
        self.max_valid_ns = -(2 ** 62)
        self.known_ns = -(2 ** 62)
        self.seq = -1
        self.machines: dict[str, MachineState] = {}
        self.scanner_poses: dict[str, deque] = {}
        self.latest_scan = None
        self.cut_msgs: dict[str, Any] = {}
        self.assays_by_id: dict[str, Any] = {}
        self.grade_range: dict[str, list[float]] = {}
        #: why the next update is due now ("cut", "assay", "lot", "pass", "pile", "end")
        self.reasons: set[str] = set()
        self.assay_version = 0
        #: the surface and voxels must be redrawn (a geometry record since the last redraw)
        self.geometry_dirty = True

    @property
    def valid_ns(self) -> int:
        """The newest valid time read, or K if later (an update's V is at least this)."""
        return max(self.max_valid_ns, self.known_ns)

    def colour_range(self, analyte: str) -> tuple[float, float]:
        """``(lo, hi)`` % of an analyte's colour scale: the grades seen, padded."""
        lo, hi = self.grade_range.get(analyte, (math.nan, math.nan))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return 0.0, 1.0
        pad = max(0.05 * (hi - lo), 1e-3 * max(abs(hi), 1.0))
        return lo - pad, hi + pad

    # -- records ------------------------------------------------------------------------

    def add(self, record) -> list[tuple[str, str]]:
        """Take one committed record (global order); returns its ``(text, level)`` log lines."""
        self.projection.add(record)
        self.seq = max(self.seq, record.global_seq)
        self.known_ns = max(self.known_ns, record.recorded_time_ns)
        self.max_valid_ns = max(self.max_valid_ns, record.valid_time_ns)
        kind = record.type
        if kind in GEOMETRY_TYPES:
            self.geometry_dirty = True
        if kind == "frame_transform":
            self._on_pose(decode_payload(kind, record.payload))
        elif kind == "scan":
            self.latest_scan = record   # decoded only if it is still the latest at an update
        elif kind == "machine_declared":
            self._on_machine(decode_payload(kind, record.payload))
        elif kind == "pile_declared":
            if decode_payload(kind, record.payload).pile_id == self.pile_id:
                self.reasons.add("pile")
        elif kind == "reclaim_cut":
            return self._on_cut(decode_payload(kind, record.payload))
        elif kind == "assay":
            return self._on_assay(record, decode_payload(kind, record.payload))
        elif kind == "lot_declared":
            return self._on_lot(decode_payload(kind, record.payload))
        elif kind in ("stack_started", "stack_ended"):
            return self._on_pass(kind, decode_payload(kind, record.payload))
        return []

    def _widen_range(self, grade: dict[str, float]) -> None:
        for a, v in grade.items():
            if math.isfinite(v):
                r = self.grade_range.setdefault(a, [v, v])
                r[0], r[1] = min(r[0], v), max(r[1], v)

    def _on_cut(self, msg) -> list[tuple[str, str]]:
        if msg.pile_id != self.pile_id:
            return []
        self.cut_msgs[msg.cut_id] = msg
        self.reasons.add("cut")
        return [(f"cut {msg.cut_id} (bench {msg.bench_id}) ended: belt scale "
                 f"{msg.tonnes:,.1f} t", "INFO")]

    def _on_lot(self, msg) -> list[tuple[str, str]]:
        self._widen_range(canonical_grades(msg.planned_grade))
        self.assay_version += 1
        self.reasons.add("lot")
        return [(f"lot {msg.lot_id} declared: {msg.planned_tonnes:,.0f} t planned, "
                 + ", ".join(f"{k} {v:.2f} %" for k, v in msg.planned_grade.items()), "INFO")]

    def _on_pass(self, kind: str, msg) -> list[tuple[str, str]]:
        if msg.pile_id != self.pile_id:
            return []
        self.reasons.add("pass")
        text = (f"stacking pass {msg.pass_id} started (lot {msg.lot_id})"
                if kind == "stack_started"
                else f"stacking pass {msg.pass_id} ended: belt scale {msg.tonnes:,.1f} t")
        return [(text, "INFO")]

    def _on_assay(self, record, msg) -> list[tuple[str, str]]:
        self.assay_version += 1
        self.reasons.add("assay")
        self._widen_range(canonical_grades(msg.analytes))
        late_h = (record.recorded_time_ns - coerce_time_ns(msg.window_end)) / NS_PER_H
        status = {1: "PROVISIONAL", 2: "FINAL"}.get(int(msg.status), str(msg.status))
        unknown = "unknown_lot" in (getattr(record, "flags", ()) or ())
        lines = [(
            f"assay {msg.assay_id} ({status}) for lot {msg.lot_id} from {msg.lab_id or record.source}"
            f" arrived {late_h:.2f} h after its window: "
            + ", ".join(f"{k} {v:.2f} %" for k, v in msg.analytes.items())
            + (" (lot not declared)" if unknown else ""),
            "WARN" if unknown else "INFO")]
        if msg.supersedes:
            old = self.assays_by_id.get(msg.supersedes)
            change = ""
            if old is not None:
                change = ": " + ", ".join(
                    f"{k} {old.analytes[k]:.2f} -> {v:.2f} %" for k, v in msg.analytes.items()
                    if k in old.analytes and abs(v - old.analytes[k]) > 1e-12)
            lines.append((f"assay {msg.supersedes} superseded by {msg.assay_id} ({status})"
                          + change, "WARN"))
        self.assays_by_id[msg.assay_id] = msg
        return lines

    def _on_machine(self, msg) -> None:
        if int(msg.kind) != 1:   # BUCKET_WHEEL_RECLAIMER
            return
        mount = None
        if msg.HasField("scanner"):
            t = msg.scanner.translation
            r = msg.scanner.rotation
            mount = (quat_matrix((r.x, r.y, r.z, r.w)), np.array([t.x, t.y, t.z]))
        self.machines[msg.machine_id] = MachineState(
            msg.machine_id, Reclaimer.from_message(msg), float(msg.wheel_radius_m) or 0.0, mount)

    def _on_pose(self, msg) -> None:
        if msg.parent_frame_id != "site" or "/" not in msg.child_frame_id:
            return
        machine_id, frame = msg.child_frame_id.split("/", 1)
        t = coerce_time_ns(msg.timestamp)
        p = np.array([msg.translation.x, msg.translation.y, msg.translation.z])
        q = (msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w)
        if frame == "scanner":
            poses = self.scanner_poses.setdefault(machine_id, deque(maxlen=SCANNER_POSES_KEPT))
            poses.append((t, p, q))
        m = self.machines.get(machine_id)
        if m is None:
            return
        if frame == "wheel":
            pose = (t, p, quat_matrix(q))
        elif frame == "scanner" and m.mount is not None:
            centre, r_site_wheel = wheel_from_scanner(p, q, m.mount)
            pose = (t, centre, r_site_wheel)
        else:
            return
        if m.pose is None or pose[0] >= m.pose[0]:
            m.pose = pose
