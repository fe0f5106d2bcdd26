"""Scanner heights referenced to the declared ground (``projector.ground`` and the
fold's ``ground_reference``).

The kernels are checked on synthetic scans whose ground offset is known by construction;
the fold is checked on the short simulated yard with a slowly varying error added to
every scanner pose's height, against the simulator's own pile volume.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from projector import fold as F
from projector.ground import scan_ground_offsets, smooth_offsets
from ledger.records import RecordedEvent
from schemas.events import Event, decode_payload
from schemas.jsonl import decode_line

import targets

SD = 0.015          # point height noise (m)
SE_FACTOR = 1.2533  # median's standard error over the mean's for Gaussian noise


def _scans(rng: np.random.Generator, offsets_m: np.ndarray, n_ground: int = 60,
           n_layer: int = 120, layer_m: float = 0.3) -> np.ndarray:
    """Scans (S, 361) of a pile on ground at 0: ``n_ground`` ground points, a flat layer of
    ``n_layer`` points ``layer_m`` above the ground (more points than the ground has), a
    ridge up to 2 m; every point of scan s shifted by ``offsets_m[s]``; a few NaN."""
    s = offsets_m.size
    z = np.empty((s, 361))
    z[:, :n_ground] = 0.0
    z[:, n_ground:n_ground + n_layer] = layer_m
    rest = 361 - n_ground - n_layer
    z[:, n_ground + n_layer:] = np.linspace(0.05, 2.0, rest)
    z += offsets_m[:, None] + rng.normal(0.0, SD, z.shape)
    z[:, 5] = np.nan
    return z


def test_each_scans_offset_is_its_grounds_level_not_the_material_on_it():
    seed = 20261127
    print("seed", seed)
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-0.4, 0.4, 200)
    z = _scans(rng, offsets)
    est, n = scan_ground_offsets(z, np.ones(z.shape, bool), 0.0, window_m=2 * SD,
                                 min_points=15, max_offset_m=1.0)
    assert np.all(np.isfinite(est))
    se = SE_FACTOR * SD / np.sqrt(n)
    assert np.all(np.abs(est - offsets) <= 4.5 * se), np.max(np.abs(est - offsets) / se)
    # the window holds the ground's points within 2 sd: about 95 % of them, never the layer
    assert np.all((n >= 45) & (n <= 60))
    # no bias toward the ground's low tail (the search starts there): the mean error over
    # 200 scans is within 4 standard errors of the mean
    err = est - offsets
    assert abs(err.mean()) <= 4 * err.std() / math.sqrt(err.size)


def test_scans_without_enough_ground_or_beyond_reach_have_no_offset():
    rng = np.random.default_rng(7)
    offsets = np.array([0.0, 0.0, 0.9, 0.0])
    z = _scans(rng, offsets)
    cand = np.ones(z.shape, bool)
    cand[1, :60] = False                       # scan 1's ground is not a candidate
    z[3, :50] = np.nan                         # scan 3 sees 10 ground points only
    est, n = scan_ground_offsets(z, cand, 0.0, window_m=2 * SD, min_points=15,
                                 max_offset_m=0.2)
    assert np.isfinite(est[0]) and abs(est[0]) < 0.01
    # scan 1: the lowest candidates are the layer, 0.3 m up: beyond max_offset_m
    # scan 2: its ground is 0.9 m off, beyond reach; scan 3: too few points
    assert np.all(np.isnan(est[1:])) and np.all(n[1:] == 0)
    with pytest.raises(ValueError):
        scan_ground_offsets(z, cand[:, :10], 0.0, window_m=0.03, min_points=15,
                            max_offset_m=0.2)
    with pytest.raises(ValueError):
        scan_ground_offsets(z, cand, 0.0, window_m=0.0, min_points=15, max_offset_m=0.2)


def test_smoothed_offsets_are_the_windows_median_and_carry_its_standard_error():
    rng = np.random.default_rng(11)
    t = np.sort(rng.integers(0, 20 * 10**9, 60))
    off = rng.normal(0.05, 0.01, 60)
    off[rng.random(60) < 0.3] = np.nan
    off[10:20] = np.nan
    t[10:20] = 100 * 10**9 + np.arange(10)      # ten scans far from any offset
    n = rng.integers(20, 60, 60)
    half = 10**9
    got, se = smooth_offsets(t, off, n, half_window_ns=half, point_sd_m=SD)
    for i in range(60):                          # brute force, one scan at a time
        inside = [j for j in range(60) if abs(int(t[j]) - int(t[i])) <= half
                  and np.isfinite(off[j])]
        if not inside:
            assert np.isnan(got[i]) and np.isnan(se[i])
            continue
        assert got[i] == pytest.approx(float(np.median(off[inside])), abs=1e-15)
        assert se[i] == pytest.approx(SE_FACTOR * SD / math.sqrt(sum(n[j] for j in inside)))
    assert np.all(np.isnan(got[10:20]))
    with pytest.raises(ValueError):
        smooth_offsets(t, off[:5], n, half_window_ns=half, point_sd_m=SD)


def _with_height_error(event: Event, t0_ns: int) -> Event:
    """The event, with a scanner pose's height off by 8 cm +- 6 cm (a 90 s period)."""
    if event.type != "frame_transform":
        return event
    msg = decode_payload(event.type, event.payload)
    if not msg.child_frame_id.endswith("/scanner"):
        return event
    s = (event.valid_time_ns - t0_ns) / 1e9
    msg.translation.z += 0.08 + 0.06 * math.sin(2 * math.pi * s / 90.0)
    return Event(event.type, event.source, event.epoch, event.seq, event.valid_time_ns,
                 msg.SerializeToString(), event.recorded_time_ns)


def _fold_volume_m3(events: list[Event], **config) -> tuple[float, dict[str, int]]:
    state = F.initial_state(F.FoldConfig("P1", **config))
    order = sorted(range(len(events)), key=lambda i: (events[i].valid_time_ns, i))
    for i in order:
        e = events[i]
        F.apply(state, RecordedEvent(i, e.type, e.source, e.epoch, e.seq, e.valid_time_ns,
                                     e.valid_time_ns, e.payload, b"", b""))
    F.flush(state)
    return state.stack.total_volume_m3(), state.counters


@pytest.fixture(scope="module")
def drift_folds(small_yard_sim) -> dict:
    """The short yard folded three times: poses with a drifting height error, as posed and
    referenced to the ground, and the true poses; each volume's error against the truth's."""
    events = [decode_line(line)
              for line in (small_yard_sim / "events.jsonl").read_text().splitlines()]
    truth_m3 = json.loads((small_yard_sim / "truth.json").read_text())["world"]["volume_m3"]
    t0 = min(e.valid_time_ns for e in events)
    drifting = [_with_height_error(e, t0) for e in events]
    as_posed, _ = _fold_volume_m3(drifting, ground_reference=False)
    referenced, counters = _fold_volume_m3(drifting)
    posed_true, true_counters = _fold_volume_m3(events)
    err = {k: 100 * (v / truth_m3 - 1) for k, v in
           (("as posed", as_posed), ("referenced", referenced), ("true poses", posed_true))}
    print({k: f"{v:+.2f} %" for k, v in err.items()})
    return {"err": err, "counters": counters, "true_counters": true_counters}


def test_a_drifting_scanner_height_is_corrected_by_the_ground_it_sees(drift_folds):
    err, counters = drift_folds["err"], drift_folds["counters"]
    true_counters = drift_folds["true_counters"]
    print({k: f"{v:+.2f} %" for k, v in err.items()})
    assert err["as posed"] > 10.0                # every point 2-14 cm high
    # what the ground reference leaves of the drift: the referenced volume against the
    # true poses' (measured +0.84 points, before and after the grazing test of
    # projector.profile; the referenced volume met 0.3 % at +0.07 % only while the true
    # poses read -0.77 %: docs/fidelity.md, "The pile's volume")
    assert err["referenced"] - err["true poses"] <= 1.0
    # the pile's tonnes target (measured +0.60 %)
    assert abs(err["referenced"]) <= 1.0
    # the true poses meet the volume target (below): this guards the figure
    assert abs(err["true poses"]) <= 1.0
    fused = counters["scans_fused"]
    assert counters["scans_ground_referenced"] >= 0.8 * fused
    # the offsets applied are the error added: 8 cm on average
    assert 0.07 <= counters["ground_offset_abs_sum_mm"] / 1e3 / fused <= 0.09
    # true poses: nothing applied (the deadband)
    assert true_counters.get("ground_offset_abs_sum_mm", 0) <= 0.002 * 1e3 * fused


def test_the_true_poses_volume_meets_the_target(drift_folds):
    """Measured -0.24 % (-0.77 % before returns mixed on a grazing run were dropped)."""
    err = drift_folds["err"]["true poses"]
    print(f"true poses: {err:+.2f} % (target <= {targets.VOLUME_NOISY_PCT} %)")
    assert abs(err) <= targets.VOLUME_NOISY_PCT
