"""The dashboard's catch-up over a ledger whose pile it has nothing to draw for.

A dashboard started for a pile the ledger has not declared (yet) has no geometry to log.
It must still wait for a reason or ``every_s`` of valid time between attempts, as after
an update, and not summarise the whole fold at every record.  The records are the small
yard's (``test_audit``), fed as the live catch-up feeds them.
"""

from __future__ import annotations

import pytest

from ledger import open_ledger
from services.dashboard.config import Config
from services.dashboard.core import Dashboard, feed
from services.dashboard.viewer import make_recording
from test_audit import PILE, audit_ledger


@pytest.fixture(scope="module")
def records(small_yard_sim, tmp_path_factory):
    path = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())[0]
    with open_ledger(path, read_only=True) as store:
        return list(store.read(0, store.head().global_seq + 1))


def _catch_up(records, pile_id: str, tmp_path) -> tuple[Dashboard, int]:
    """Feed every record as the live catch-up does; returns the dashboard and how many
    summaries of the fold it computed."""
    config = Config(site="test", pile_id=pile_id, rrd=str(tmp_path / f"{pile_id}.rrd"))
    rec, _uri = make_recording(config)
    dash = Dashboard(rec, pile_id, config)
    projection = dash.tracker.projection
    calls = [0]
    summary = projection.summary

    def counted():
        calls[0] += 1
        return summary()
    projection.summary = counted
    feed(dash, records, updates=True)
    return dash, calls[0]


def test_an_undeclared_pile_is_not_summarised_at_every_record(records, tmp_path):
    dash, calls = _catch_up(records, "NOT-DECLARED", tmp_path)
    assert dash.updates == 0
    boundaries = sum(1 for a, b in zip(records, records[1:])
                     if b.recorded_time_ns > a.recorded_time_ns)
    print(f"{len(records):,} records, {boundaries:,} recorded-time boundaries, "
          f"{calls} summaries")
    assert boundaries > 500
    assert calls <= 50


def test_the_declared_pile_is_still_drawn(records, tmp_path):
    dash, calls = _catch_up(records, PILE, tmp_path)
    assert dash.updates > 0 and dash.last_state is not None
    assert dash.last_state.geometry is not None
    assert calls >= dash.updates
