"""A yard with several scanners: each scan is placed by its own scanner's poses.

A blending yard has a machine per bed, each with a scanner and its own pose track
(``FrameTransform`` site -> ``<machine>/scanner``).  The fold keeps one track per
scanner frame (:class:`projector.state.PoseTrack`); a pile's projector also sees the
other bed's scans, whose points fall outside its footprint and change nothing.
"""

from __future__ import annotations

import numpy as np

from ledger import open_ledger
from projector.query import project
from schemas.events import (
    Event,
    decode_payload,
    make_event,
    set_timestamp_ns,
    timestamp_ns,
)
from schemas.jsonl import decode_line

PILE = "P1"
#: the second machine's scans and poses, this long after the first's (so the two
#: tracks interleave in the ledger, never at the same time)
OFFSET_NS = 37_000_000


def _events(small_yard_sim) -> list[Event]:
    return [decode_line(line) for line in
            (small_yard_sim / "events.jsonl").read_text().splitlines()]


def _shifted(event: Event, machine: str, dy_m: float, frame: str | None = None) -> Event:
    """A copy of a scan or scanner pose as another machine's: frame ``<machine>/scanner``
    (or ``frame``), ``OFFSET_NS`` later, a pose moved ``dy_m`` along the rail."""
    msg = decode_payload(event.type, event.payload)
    frame = frame or f"{machine}/scanner"
    if event.type == "scan":
        msg.frame_id = frame
        set_timestamp_ns(msg.timestamp, timestamp_ns(msg.timestamp) + OFFSET_NS)
        source = f"{machine}.scanner"
    else:
        msg.child_frame_id = frame
        msg.translation.y += dy_m
        set_timestamp_ns(msg.timestamp, timestamp_ns(msg.timestamp) + OFFSET_NS)
        source = f"{machine}.poses"
    return make_event(msg, source=source, epoch=event.epoch, seq=event.seq)


def _is_scanner_pose(event: Event) -> bool:
    return event.type == "frame_transform" and decode_payload(
        event.type, event.payload).child_frame_id.endswith("/scanner")


def _fold(events: list[Event]):
    """The pile as of the end, everything known, from a ledger holding ``events`` in
    valid-time order (recorded at their valid time)."""
    store = open_ledger(":memory:")
    ordered = sorted(events, key=lambda e: e.valid_time_ns)
    store.append([Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload,
                        e.valid_time_ns) for e in ordered])
    try:
        return project(store, PILE)
    finally:
        store.close()


def _every_other_pose(events: list[Event]) -> list[Event]:
    """Every other scanner pose left out: most scans then fall between two poses of
    their scanner (as with a localizer's own rate), not on one."""
    kept, k = [], 0
    for e in events:
        if _is_scanner_pose(e):
            k += 1
            if k % 2:
                continue
        kept.append(e)
    return kept


def test_a_second_scanner_elsewhere_changes_nothing_in_this_pile(small_yard_sim):
    events = _every_other_pose(_events(small_yard_sim))
    alone = _fold(events)
    # the same machine's scans and poses again, as a second machine 1 km along the rail
    # (another bed): its points miss this pile's footprint
    other = [_shifted(e, "bwr9", 1000.0) for e in events
             if e.type == "scan" or _is_scanner_pose(e)]
    assert len(other) > 100
    both = _fold(events + other)
    assert both.counters["scans_fused"] == 2 * alone.counters["scans_fused"] > 0
    assert both.counters["points_fused"] > alone.counters["points_fused"]
    assert both.counters.get("poses_out_of_order", 0) == 0
    # the fold fuses its waiting scans in batches, which the other scanner's scans fill
    # sooner: the same scans of this pile are fused in other batches, to a hair
    assert abs(both.tonnes / alone.tonnes - 1) < 1e-3 and alone.tonnes > 0
    assert abs(both.volume_m3 / alone.volume_m3 - 1) < 1e-3
    moved = np.abs(np.nan_to_num(both.state.stack.surface() - alone.state.stack.surface()))
    assert np.quantile(moved, 0.99) < 0.02, np.quantile(moved, 0.99)


def test_the_second_scanner_is_placed_by_its_own_poses(small_yard_sim):
    events = _events(small_yard_sim)
    alone = _fold(events)
    base = [e for e in events if e.type != "scan" and not _is_scanner_pose(e)]
    poses = [e for e in events if _is_scanner_pose(e)]
    # the pile scanned by the second machine only, two tracks in the ledger: one where
    # the scans were taken and one 1 km away
    scans = [_shifted(e, "bwr9", 0.0) for e in events if e.type == "scan"]
    own_near = [_shifted(e, "bwr9", 0.0) for e in poses]
    own_far = [_shifted(e, "bwr9", 1000.0) for e in poses]
    first_far = [_shifted(e, "bwr1", 1000.0) for e in poses]
    # its own track where it stood (the first machine's far away): the pile is seen
    seen = _fold(base + scans + own_near + first_far)
    # its own track far away (the first machine's where the scans were taken): unseen
    unseen = _fold(base + scans + own_far + poses)
    assert abs(seen.volume_m3 / alone.volume_m3 - 1) < 0.01
    assert unseen.volume_m3 < 0.5 * alone.volume_m3


def test_one_scanner_whose_poses_name_another_frame_is_still_placed(small_yard_sim):
    events = _events(small_yard_sim)
    alone = _fold(events)
    renamed = [make_event(_renamed(e), source=e.source, epoch=e.epoch, seq=e.seq)
               if _is_scanner_pose(e) else e for e in events]
    again = _fold(renamed)
    assert again.tonnes == alone.tonnes > 0
    np.testing.assert_array_equal(again.state.stack.surface(), alone.state.stack.surface())


def _renamed(event: Event):
    msg = decode_payload(event.type, event.payload)
    msg.child_frame_id = "rig/scanner"
    return msg
