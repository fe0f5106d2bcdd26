"""``stockpile survey import``: a LAS/LAZ file into one ``survey`` event, in bounded memory.

The file is read in chunks (``laspy``'s ``chunk_iterator``), each chunk converted from the
file's CRS (its header's, or the one given) to the site frame (:class:`geo.site_crs.
SiteCrs` with the site's declared datum) and binned into the pile's grid (the projector's
own grid for the pile's declaration: :mod:`surveys.grid`).  Memory is a chunk plus the
grid, whatever the file's size; the file's sha256 is taken in the same pass.

The event's identity is ``(survey.import, the survey's time in whole seconds, 0)``: the
same file imported again is a duplicate, another file at the same time a conflict.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from geo.site_crs import SiteCrs
from projector import fold as F
from schemas.events import decode_payload, make_event
from schemas.times import NS_PER_S
from surveys.grid import CellAccumulator, survey_message

__all__ = ["SOURCE", "SurveyImport", "import_survey"]

#: the source of every imported survey
SOURCE = "survey.import"
#: points read at a time
CHUNK_POINTS = 1_000_000


@dataclass(frozen=True)
class SurveyImport:
    """What an import did: the ledger's outcome and the survey's figures."""

    outcome: str             # appended, duplicate, conflict, rejected
    reason: str
    survey_id: str
    points: int
    points_in_grid: int
    cells: int
    crs_epsg: int
    sha256_hex: str


def _declarations(store, pile_id: str, time_ns: int):
    """The site's last declaration and the pile's grid, as of the survey's time."""
    site, pile = None, None
    for record in store.as_of(time_ns, 2**63 - 1, types=["site_declared", "pile_declared"]):
        msg = decode_payload(record.type, record.payload)
        if record.type == "site_declared":
            site = msg
        elif msg.pile_id == pile_id and pile is None:
            pile = record
    if site is None:
        raise ValueError("the ledger declares no site before the survey's time")
    if pile is None:
        raise ValueError(f"pile {pile_id!r} is not declared before the survey's time")
    state = F.initial_state(pile_id)
    F.apply(state, pile)
    return site, state.pile.geometry


def _file_crs(header, epsg: int | None) -> int:
    if epsg:
        return int(epsg)
    try:
        crs = header.parse_crs()
    except Exception as exc:  # noqa: BLE001 - laspy raises several kinds for a bad VLR
        raise ValueError(f"the file's CRS cannot be read ({exc}): give it with --crs EPSG") \
            from None
    code = crs.to_epsg() if crs is not None else None
    if not code:
        raise ValueError("the file names no EPSG CRS: give it with --crs EPSG")
    return int(code)


def import_survey(path: str | Path, store, pile_id: str, time_ns: int, *,
                  epsg: int | None = None, provider: str = "", accuracy_m: float = 0.0,
                  survey_id: str | None = None, chunk_points: int = CHUNK_POINTS,
                  progress: Callable[[int, int], None] | None = None) -> SurveyImport:
    """Read ``path`` and append its ``survey`` event to ``store``.

    ``progress(points_read, points_total)`` is called after each chunk.  Raises ValueError
    for a file or a ledger that cannot give a survey (no site, no pile, no CRS, no point
    in the pile's grid); the ledger's own refusal is the returned outcome.
    """
    import laspy

    path = Path(path)
    site, geometry = _declarations(store, pile_id, time_ns)
    digest = hashlib.sha256()
    with open(path, "rb") as raw:
        for block in iter(lambda: raw.read(1 << 20), b""):
            digest.update(block)
    acc = CellAccumulator(geometry)
    with laspy.open(path) as reader:
        code = _file_crs(reader.header, epsg)
        frame = SiteCrs(site.datum_lat_deg, site.datum_lon_deg, site.datum_alt_m, code)
        total = int(reader.header.point_count)
        for points in reader.chunk_iterator(chunk_points):
            acc.add(*frame.to_site(points.x, points.y, points.z))
            if progress is not None:
                progress(acc.points, total)
    sid = survey_id or f"{pile_id}-{time_ns // NS_PER_S}"
    msg = survey_message(acc, time_ns=time_ns, survey_id=sid, pile_id=pile_id,
                         provider=provider, accuracy_m=accuracy_m,
                         source_sha256=digest.digest(), crs_epsg=code)
    event = make_event(msg, source=SOURCE, epoch=time_ns // NS_PER_S, seq=0)
    result = store.append([event])
    outcome = result.outcomes[0]
    reason = f"{outcome.code}: {outcome.detail}" if outcome.code else ""
    return SurveyImport(outcome.status, reason, sid, acc.points, acc.points_in_grid,
                        int(msg.nx * msg.ny), code, digest.hexdigest())
