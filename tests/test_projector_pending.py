"""Waiting scans are passed over only when one can be fused: the same pile, far fewer passes.

A live yard's poses come a smoothing lag (60 s) after their scans, so the live fold keeps
a minute of scans waiting; a pass over all of them at every scan and pose made the live
projector's summaries quadratic in that minute.  The fold now passes over them only when a
scan or a pose makes one ready (``ProjectorState.pending_settled``).  The short simulated
yard is replayed as the projector service receives it (its frame transforms recorded 60 s
late, ``LiveProjection`` with the service's reorder window), once with the check and once
with a pass at every scan and pose (the fold before it): the summaries are identical.
"""

from __future__ import annotations

import numpy as np
import pytest

import projector.fold as F
import projector.scans as scans_module
from schemas.jsonl import decode_line
from schemas.times import NS_PER_S as S
from services.projector_service import LiveProjection
from services.service import LIVE_REORDER_S
from test_projector_fold import _ledger

LAG_NS = 60 * S


@pytest.fixture(scope="module")
def records(small_yard_sim):
    events = [decode_line(line) for line in
              (small_yard_sim / "events.jsonl").read_text().splitlines()]
    delays = [LAG_NS if e.type == "frame_transform" else 0 for e in events]
    store = _ledger(events, delays)
    out = list(store.read())
    store.close()
    assert sum(r.type == "scan" for r in out) > 500
    return out


def _replay(records, monkeypatch, every_pass: bool):
    passes = []
    ready_scans = scans_module._ready_scans

    def counted(state, until_ns, final):
        passes.append(len(state.pending))
        return ready_scans(state, until_ns, final)

    apply = F.apply
    broken = []

    def checked(state, event):
        apply(state, event)
        # the invariant the skip rests on: settled means no waiting scan has its pose
        if state.pending_settled and any(scans_module.scan_is_ready(state, s)
                                         for s in state.pending):
            broken.append(event.global_seq)

    with monkeypatch.context() as m:
        m.setattr(scans_module, "_ready_scans", counted)
        if not every_pass:
            m.setattr(F, "apply", checked)
        if every_pass:
            m.setattr(F, "note_pending", lambda state, scan: (
                state.pending.append(scan), setattr(state, "pending_settled", False)))
            m.setattr(F, "note_pose", lambda state, frame, t_ns, new:
                      setattr(state, "pending_settled", False))
        projection = LiveProjection("P1", int(LIVE_REORDER_S * S))
        summaries = []
        for k, record in enumerate(records):
            projection.add(record)
            projection.advance()
            if k % 2000 == 1999:
                summaries.append(projection.summary())
        summaries.append(projection.summary())
    assert not broken, f"settled with a ready scan waiting after records {broken[:5]}"
    return summaries, passes


def test_the_same_summaries_with_far_fewer_passes(records, monkeypatch):
    settled, passes = _replay(records, monkeypatch, every_pass=False)
    every, passes_before = _replay(records, monkeypatch, every_pass=True)
    assert len(settled) == len(every) > 3
    for a, b in zip(settled, every):
        assert a.tonnes == b.tonnes and a.volume_m3 == b.volume_m3
        assert a.counters == b.counters
        np.testing.assert_array_equal(a.elevation_m, b.elevation_m)
        np.testing.assert_array_equal(a.state.stack.surfaces(), b.state.stack.surfaces())
    assert settled[-1].counters.get("scans_fused", 0) > 500
    # scans waited for their poses, and were passed over far less often
    assert max(passes_before) > 100
    work, work_before = sum(passes), sum(passes_before)
    print(f"passes {len(passes)} over {work} waiting scans; before {len(passes_before)} "
          f"over {work_before}")
    assert work * 5 < work_before
