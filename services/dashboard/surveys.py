"""The pile's surveys on the dashboard: where a survey and the model differ.

:class:`SurveyMaps` takes the pile's ``survey`` records as they are read and, at the next
update, reconciles each one (:func:`audit.surveys.reconcile_survey`: the model as of the
survey's time, as known when the survey was recorded) against a ledger it is given.
For each survey it logs, at the survey's valid time and the record's ``ledger_seq``:

- ``/surveys/difference``: a heat map with one pixel per cell, viewed from above (east to
  the right, north up, in the site frame). Each pixel is survey minus model: red where
  the survey is higher (the model is short), blue where it is lower. The scale is
  symmetric, to the 98th percentile of ``|difference|`` (at least 5 cm). Cells with no
  survey point are transparent;
- ``/surveys/difference_m``: the same values (m, float32, NaN for no point), as a tensor
  (rows y from north, columns x from west);
- ``/surveys/report``: a table of every survey reconciled so far (volumes m3, the
  difference in m3, t and %), and one ``/log`` line each.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from audit.surveys import reconcile_survey
from schemas.events import decode_payload
from services.dashboard.recorder import iso, rr
from services.dashboard.style import colour_map

__all__ = ["SurveyMaps", "heat_map"]

#: the heat map's scale is at least +/- this much (m)
MIN_SCALE_M = 0.05


def heat_map(cells_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(RGBA image (ny, nx, 4) uint8, values (ny, nx) float32, scale m)`` of per-cell
    differences ``cells_m`` (m, (nx, ny), NaN: none): north up, east to the right, blue at
    ``-scale``, red at ``+scale``, transparent where NaN."""
    cells_m = np.asarray(cells_m, np.float64)
    if cells_m.ndim != 2:
        raise ValueError(f"cells_m must be 2-D (nx, ny), got shape {cells_m.shape}")
    values = cells_m.T[::-1, :]
    finite = np.isfinite(values)
    scale = MIN_SCALE_M
    if finite.any():
        scale = max(MIN_SCALE_M, float(np.percentile(np.abs(values[finite]), 98)))
    rgb = colour_map(values.ravel(), -scale, scale).reshape(values.shape + (3,))
    alpha = np.where(finite, 255, 0).astype(np.uint8)[..., None]
    return np.concatenate([rgb, alpha], axis=2), values.astype(np.float32), scale


class SurveyMaps:
    """The surveys of one pile: read, reconciled at the next update, logged.

    Parameters
    ----------
    out : Recorder
    pile_id : str

    ``source`` (set by the dashboard's driver) returns the ledger to fold from: the
    store offline, a :class:`services.ledger_client.RemoteLedger` live; None: the
    surveys are only listed in ``/log``.
    """

    def __init__(self, out, pile_id: str) -> None:
        self.out, self.pile_id = out, pile_id
        self.source: Callable[[], Any] | None = None
        self.pending: list = []
        self.rows: list[str] = []

    def add(self, record) -> bool:
        """Take a ``survey`` record; True if it is this pile's (reconciled at the next
        :meth:`log_pending`)."""
        msg = decode_payload(record.type, record.payload)
        if msg.pile_id != self.pile_id:
            return False
        self.pending.append(record)
        return True

    def log_pending(self) -> int:
        """Reconcile and log the surveys read since the last call; returns how many were
        logged.  A survey that cannot be reconciled gets a WARN line, not an exception."""
        done = 0
        pending, self.pending = self.pending, []
        for record in pending:
            sid = decode_payload(record.type, record.payload).survey_id
            if self.source is None:
                self.out.text(f"survey {sid} read; no ledger to reconcile it against", "WARN",
                              valid_ns=record.valid_time_ns, seq=record.global_seq)
                continue
            try:
                report = reconcile_survey(self.source(), record, record.recorded_time_ns,
                                          then=False)
            except Exception as exc:  # noqa: BLE001 - a survey must not stop the dashboard
                self.out.text(f"survey {sid} could not be reconciled: {exc}", "WARN",
                              valid_ns=record.valid_time_ns, seq=record.global_seq)
                continue
            self._log(record, report)
            done += 1
        return done

    def _log(self, record, r) -> None:
        rerun = rr()
        image, values, scale = heat_map(r.cells_m)
        self.out.at(record.valid_time_ns, record.global_seq)
        self.out.log("/surveys/difference", rerun.Image(image, color_model="RGBA"))
        self.out.log("/surveys/difference_m", rerun.Tensor(values, dim_names=["y", "x"]))
        pct = f"{r.diff_now_pct:+.2f} %" if math.isfinite(r.diff_now_pct) else "-"
        self.rows.append(f"| {r.survey_id} | {iso(r.time_ns)} | {r.area_m2:,.0f} | "
                         f"{r.survey_m3:,.1f} | {r.model_now_m3:,.1f} | {r.diff_now_m3:+,.1f} | "
                         f"{r.diff_now_t:+,.0f} | {pct} |")
        self.out.log("/surveys/report", rerun.TextDocument(
            "| survey | time | area m2 | survey m3 | model m3 | survey - model m3 | t | % |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|\n" + "\n".join(self.rows)
            + f"\n\nThe map: survey minus model per {r.cell_m:g} m cell, red where the survey "
            f"is higher, blue lower, to +/- {scale:.2f} m.", media_type="text/markdown"))
        self.out.text(f"survey {r.survey_id} at {iso(r.time_ns)}: survey {r.survey_m3:,.1f} m3, "
                      f"model {r.model_now_m3:,.1f} m3, difference {r.diff_now_m3:+,.1f} m3 "
                      f"({pct})", valid_ns=record.valid_time_ns, seq=record.global_seq)
