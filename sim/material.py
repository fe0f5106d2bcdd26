"""How the faces a reclaimer cut leaves behave: the material's kind, and the slides it makes.

A scenario's :class:`Material` says what the walls of a cut do once the wheel has passed
(the stacking, deposition at the angle of repose, is the same for every kind):

``repose`` (default)
    every cut's walls slump at once to the angle of repose: the avalanche relaxation of
    :mod:`sim.relaxation` with the critical drop ``tan(repose) * cell * DIST`` over the
    cut's footprint (:meth:`sim.world.World.settle_cut`).
``cohesive``
    a fresh face stands up to ``stand_angle_deg``: right after the cut, only what is
    steeper than that fails (the same relaxation with the stand angle's critical drop).
    With ``critical_height_m``, a face higher than that fails to the angle of repose
    instead; a face's height is the highest column on the footprint's rim (the columns
    just outside it) above the cutting envelope's lowest point (the wheel centre's height
    less the cutting radius, not below the ground).
``delayed``
    a face stands as cut; ``delay`` seconds after the cut's end (drawn per cut, uniform in
    ``failure_delay_s``, from the run's seed, stream ``"material"``) whatever is then
    steeper than the angle of repose around the cut's footprint fails, as one slide (the
    relaxation and composition routing of ``repose``, over the footprint's bbox).
``standing``
    no slide at all after cuts.

:class:`CutFaces` applies a material to a :class:`~sim.world.World` cut by cut and keeps
the record of every slide for ``truth.json`` (:meth:`CutFaces.truth`). Angles in
degrees, lengths in metres, times in UTC ns unless a name says ``_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from schemas.times import NS_PER_S
from sim.kinematics import Machine, wheel_centre
from sim.reclaiming import footprint_bbox
from sim.truth import CutTruth

if TYPE_CHECKING:   # only for the annotations: sim.scenario imports this module light
    from sim.world import World

__all__ = ["KINDS", "RNG_STREAM", "CutFaces", "Material"]

#: the kinds of material (see the module docstring)
KINDS = ("repose", "cohesive", "delayed", "standing")
#: the name of the run's random stream the delayed failures are drawn from (sim.rng)
RNG_STREAM = "material"


@dataclass(frozen=True)
class Material:
    """What a cut's faces do after the cut (see the module docstring).

    Parameters
    ----------
    kind : {"repose", "cohesive", "delayed", "standing"}
    stand_angle_deg : float
        ``cohesive``: the steepest a fresh face stands (deg, above the angle of repose,
        below 90).
    critical_height_m : float or None
        ``cohesive``: a face higher than this (m) fails to the angle of repose; None: no
        height limit.
    failure_delay_s : (float, float)
        ``delayed``: the range (s, lo <= hi, lo >= 0) each cut's failure is drawn from,
        after the cut's end.

    The angle of repose is the scenario's (``Scenario.repose_deg``): the pile is stacked
    and fails to it.
    """

    kind: str = "repose"
    stand_angle_deg: float = 50.0
    critical_height_m: float | None = None
    failure_delay_s: tuple[float, float] = (300.0, 3_600.0)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"material kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if not (math.isfinite(self.stand_angle_deg) and 0.0 < self.stand_angle_deg < 90.0):
            raise ValueError(f"stand_angle_deg must be in (0, 90), got {self.stand_angle_deg}")
        h = self.critical_height_m
        if h is not None and not (math.isfinite(h) and h > 0.0):
            raise ValueError(f"critical_height_m must be > 0 m or None, got {h}")
        delay = tuple(self.failure_delay_s)
        if (len(delay) != 2 or not all(math.isfinite(v) for v in delay)
                or not 0.0 <= delay[0] <= delay[1]):
            raise ValueError(f"failure_delay_s must be (lo, hi) seconds with 0 <= lo <= hi, "
                             f"got {self.failure_delay_s}")

    def check_repose(self, repose_deg: float) -> None:
        """ValueError unless a cohesive face stands steeper than ``repose_deg``."""
        if self.kind == "cohesive" and not self.stand_angle_deg > repose_deg:
            raise ValueError(f"a cohesive material's stand_angle_deg ({self.stand_angle_deg}) "
                             f"must be steeper than the angle of repose ({repose_deg})")

    def parameters(self, repose_deg: float) -> dict:
        """The parameters the kind uses, as ``truth.json`` gives them (None: not used)."""
        cohesive, delayed = self.kind == "cohesive", self.kind == "delayed"
        return {"kind": self.kind, "repose_deg": float(repose_deg),
                "stand_angle_deg": float(self.stand_angle_deg) if cohesive else None,
                "critical_height_m": (float(self.critical_height_m)
                                      if cohesive and self.critical_height_m is not None
                                      else None),
                "failure_delay_s": [float(v) for v in self.failure_delay_s] if delayed else None}


class CutFaces:
    """What the faces of each cut of a run do, per a :class:`Material`, and their record.

    Parameters
    ----------
    material : Material
    world : World
        The pile the cuts are made in (its angle of repose is the material's).
    machine : Machine
        The reclaimer (the cutting envelope's lowest point, for ``critical_height_m``).
    rng : numpy.random.Generator
        Draws each ``delayed`` cut's failure delay, in the order the cuts end.

    ``slides`` lists every slide (cut id, site time, volume moved m3, tonnes lost over the
    grid's border, the angle failed to; ``delay_s`` for a delayed failure, ``face_height_m``
    for a cohesive one with a height limit); ``failures`` every delayed cut's drawn delay,
    its due time and whether it happened within the run.
    """

    def __init__(self, material: Material, world: "World", machine: Machine,
                 rng: np.random.Generator):
        material.check_repose(world.repose_deg)
        self.material = material
        self.world = world
        self.machine = machine
        self.rng = rng
        self.slides: list[dict] = []
        self.failures: list[dict] = []

    def after_cut(self, cut_id: str, end_ns: int, parts: list[CutTruth]) -> int | None:
        """The walls of a finished cut (its sub-sweeps ``parts``, ended at ``end_ns``) do
        what the material does; returns the due time (ns) of a delayed failure to
        schedule (:meth:`fail`), else None. A cut that took nothing leaves no face."""
        kind = self.material.kind
        if kind == "standing" or not parts or sum(p.volume_m3 for p in parts) <= 0:
            return None
        if kind == "delayed":
            return self._draw_failure(cut_id, end_ns, parts)
        extra: dict = {}
        angle_deg = None
        if kind == "cohesive":
            angle_deg = self.material.stand_angle_deg
            if self.material.critical_height_m is not None:
                height_m = self.face_height_m(parts)
                extra["face_height_m"] = height_m
                if height_m > self.material.critical_height_m:
                    angle_deg = None   # the face is too high to stand: it fails to repose
        res = self.world.settle_cut(parts, angle_deg=angle_deg)   # None: to repose
        self._record(cut_id, end_ns, res, angle_deg, extra)
        return None

    def fail(self, t_ns: int, index: int) -> None:
        """The delayed failure ``index`` happens at ``t_ns``: whatever is steeper than the
        angle of repose around that cut's footprint fails, as one slide."""
        failure = self.failures[index]
        res = self.world.settle(bbox=tuple(failure["bbox"]))
        failure["happened"] = True
        self._record(failure["cut_id"], t_ns, res, None, {"delay_s": failure["delay_s"]})

    def pending_until_ns(self) -> int | None:
        """The latest due time (ns) of a delayed failure that has not happened, or None."""
        due = [f["due_ns"] for f in self.failures if not f["happened"]]
        return max(due) if due else None

    def face_height_m(self, parts: list[CutTruth]) -> float:
        """Height (m) of a cut's face: the highest column on the rim of its footprint
        above the cutting envelope's lowest point (not below the ground)."""
        footprint = np.logical_or.reduce([p.footprint for p in parts])
        rim = _dilate(footprint) & ~footprint
        surface = self.world.surface_z()
        top_m = float(surface[rim].max()) if rim.any() else float(surface[footprint].max())
        m = self.machine
        lowest_m = min(float(wheel_centre(m, p.travel_m, p.slew_start_rad, p.luff_rad)[2])
                       - m.cutting_radius_m for p in parts)
        return top_m - max(lowest_m, self.world.grid.ground_z_m)

    def truth(self) -> dict:
        """The material's parameters and every slide and delayed failure (truth.json)."""
        return {**self.material.parameters(self.world.repose_deg),
                "slides": [dict(s) for s in self.slides],
                "failures": [{k: v for k, v in f.items() if k != "bbox"}
                             for f in self.failures]}

    def _draw_failure(self, cut_id: str, end_ns: int, parts: list[CutTruth]) -> int:
        lo, hi = self.material.failure_delay_s
        delay_s = float(self.rng.uniform(lo, hi))
        due_ns = int(end_ns) + int(round(delay_s * NS_PER_S))
        footprint = np.logical_or.reduce([p.footprint for p in parts])
        self.failures.append({"cut_id": cut_id, "cut_end_ns": int(end_ns), "delay_s": delay_s,
                              "due_ns": due_ns, "happened": False,
                              "bbox": footprint_bbox(footprint)})
        return due_ns

    def _record(self, cut_id: str, t_ns: int, res: dict | None, angle_deg: float | None,
                extra: dict) -> None:
        if res is None:
            return
        self.slides.append({"cut_id": cut_id, "time_ns": int(t_ns),
                            "moved_m3": float(res["moved_m3"]),
                            "lost_tonnes": float(res["lost_tonnes"]),
                            "angle_deg": float(self.world.repose_deg if angle_deg is None
                                               else angle_deg), **extra})


def _dilate(mask: np.ndarray) -> np.ndarray:
    """``mask`` grown by one cell toward its 8 neighbours (``scipy.ndimage`` would make
    :mod:`sim.scenario`, which imports this module, load SciPy)."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    grown = out.copy()
    grown[:, 1:] |= out[:, :-1]
    grown[:, :-1] |= out[:, 1:]
    return grown
