"""``stockpile service scanner``: LMS200 telegrams through a real pty, scans out on Zenoh.

The service runs as a separate process reading a :class:`PtyDevice` with pyserial; the test
holds a real Zenoh router session on a free loopback port (scouting off) with an
``AdvancedSubscriber`` (history and recovery, as the ledger subscribes), and waits on
conditions (the service's liveliness token, N samples, log lines), never on sleeps.

Random data is seeded from the run's seed (``--seed N`` or ``STOCKPILE_TEST_SEED=N``
reproduces a run; the seed is printed, and written into a failing test's report).
"""

from __future__ import annotations

import math
import select
import subprocess
import sys
import time

import numpy as np
import pytest

from schemas.times import parse_time_ns
from schemas.events import (
    make_event,
    timestamp_ns,
)
from schemas.validate import check_event
from services import scanner as S
from devices import lms200 as L
from services.service import SiteTime, parse_logfmt
from sim.pty import PtyDevice
from sim.scanner import beam_angles_rad
from tests.zenoh_helpers import (
    EventSink,
    SiteClock,
    client_args,
    log_lines,
    open_router,
    stockpile,
    stop,
    wait_liveliness,
    wait_until,
)
from seeding import session_seed

SEED = session_seed()
#: the random tests here draw from the run's seed (tests/seeding.py)
pytestmark = pytest.mark.seeded
SITE = "scantest"
TIMEOUT_S = 20.0  # generous: each wait normally takes well under a second
#: value count -> (fov deg, step deg) of every LMS200 field
FIELDS = {401: (100.0, 0.25), 361: (180.0, 0.5), 181: (180.0, 1.0), 201: (100.0, 0.5),
          101: (100.0, 1.0)}


def _rng(test_name: str) -> np.random.Generator:
    print(f"{test_name}: seed {SEED} (--seed {SEED} reproduces it)")
    return np.random.default_rng(SEED)


def _random_values(rng: np.random.Generator, count: int) -> np.ndarray:
    """Range codes: distances, plus about 5 % error codes (no return, dazzle, over range)."""
    values = rng.integers(0, L.MAX_RANGE_VALUE + 1, size=count).astype(np.uint16)
    errors = rng.random(count) < 0.05
    values[errors] = rng.choice([L.NO_RETURN, L.DAZZLE, L.OVER_RANGE], size=int(errors.sum()))
    return values


def _without_stx(values: np.ndarray) -> np.ndarray:
    """The range codes with each byte 0x02 (STX) made 0x06 (a range a little longer)."""
    lo, hi = values & 0xFF, values >> 8
    lo = np.where(lo == L.STX, 0x06, lo)
    hi = np.where(hi == L.STX, 0x06, hi)
    return ((hi << 8) | lo).astype(np.uint16)


def _garbage(rng: np.random.Generator, max_len: int) -> bytes:
    """Line noise without 0x02 (so every CRC error in a test is one the test planted)."""
    noise = rng.integers(0, 256, size=int(rng.integers(1, max_len + 1))).astype(np.uint8)
    noise[noise == L.STX] = 0x55
    return noise.tobytes()


# -------------------------------------------------------------------------- Zenoh side


@pytest.fixture()
def router():
    session, endpoint = open_router()
    try:
        yield session, endpoint
    finally:
        session.close()


def _start_scanner(dev: PtyDevice, endpoint: str, tmp_path, *extra: str) -> subprocess.Popen:
    return stockpile("service", "scanner", "--device", dev.path, "--site", SITE,
                     "--status-period", "0.5", *client_args(endpoint), *extra,
                     stderr_path=tmp_path / "scanner.log")


def _one(lines: list[dict], msg: str) -> dict:
    found = [line for line in lines if line.get("msg") == msg]
    assert len(found) == 1, f"expected one {msg!r} line, got {found}"
    return found[0]


# -------------------------------------------------------------------------- end to end


def test_intact_telegrams_published_once_in_order_and_bad_bytes_counted(router, tmp_path):
    session, endpoint = router
    rng = _rng("scanner garbage and crc")
    counts = list(FIELDS)
    corrupt = {4, 11, 17}  # one flipped bit in a data byte: a CRC error each
    truncated = 8          # only its first half is sent: the next telegram completes the
                           # candidate, whose CRC fails (one more CRC error)
    scans, flipped = [], {}
    for i in range(24):
        count = counts[i % len(counts)]
        while True:
            values = _random_values(rng, count)
            if i in corrupt or i == truncated:
                values = _without_stx(values)
            unit_mm = bool(rng.integers(0, 2))
            telegram = L.encode_measurement(values, unit_mm=unit_mm)
            if i in corrupt:
                data = bytearray(telegram)
                k = 7 + int(rng.integers(0, 2 * len(values)))  # inside the range values
                data[k] ^= 1 << int(rng.integers(0, 8))
                flipped[i] = bytes(data)
                sent = flipped[i]
            else:
                sent = telegram[:len(telegram) // 2] if i == truncated else telegram
            # a failed candidate's data and CRC hold no 0x02: the reader resumes its search
            # inside it, and a candidate found there would count (or hide) one more CRC
            # error than the test planted (TelegramReader's echoes), whatever the seed
            if i not in corrupt and i != truncated or L.STX not in sent[7:]:
                break
        scans.append((values, unit_mm, telegram))
    false_candidate = bytes([L.STX, 0x80, 0x05, 0x00, 0xB0, 0x01, 0x00, 0x00, 0x10, 0x00, 0x00])
    assert L.crc16(false_candidate[:-2]) != 0  # noise that looks like a telegram, bad CRC
    ack = L.encode_frame(L.ADDRESS_SCANNER, bytes([0xA0, 0x00, 0x10]))  # not 0xB0

    chunks: list[bytes] = []
    expected = []
    for i, (values, unit_mm, telegram) in enumerate(scans):
        chunks.append(_garbage(rng, 30))
        if i == 14:
            chunks += [false_candidate, _garbage(rng, 10), ack]
        if i in corrupt:
            chunks.append(flipped[i])
        elif i == truncated:
            chunks.append(telegram[:len(telegram) // 2])
        else:
            chunks.append(telegram)
            expected.append((values, unit_mm, telegram))
    assert len(expected) == 20
    # the stream ends with an intact telegram: nothing is left pending in the reader
    intact_bytes = sum(len(t) for _, _, t in expected) + len(ack)
    total_bytes = sum(len(c) for c in chunks)

    sink = EventSink(session, SITE, "scan", S.DEFAULT_SOURCE, TIMEOUT_S)
    with PtyDevice(write_timeout_s=TIMEOUT_S) as dev:
        process = _start_scanner(dev, endpoint, tmp_path)
        try:
            wait_liveliness(session, f"stockpile/{SITE}/@live/scanner/**", TIMEOUT_S)
            first_write_ns = time.time_ns()
            for chunk in chunks:
                dev.write(chunk)
            got = sink.wait_for(len(expected), process)
            received_ns = time.time_ns()
            rc = stop(process)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        assert dev.dropped_bytes == 0
    sink.close()

    assert rc == 0
    assert len(got) == len(expected)  # nothing extra arrived after the last expected scan
    assert [e.seq for e in got] == list(range(len(expected)))
    assert len({e.epoch for e in got}) == 1
    # valid time: the pty delivers bursts faster than the line rate, so a read may hold the
    # whole stream, and the service spreads it back over its line time; never later than
    # its arrival (the exact arithmetic is the next tests' and the unit tests' business)
    line_time_ns = S.transfer_time_ns(total_bytes, S.DEFAULT_BAUD)
    assert all(first_write_ns - line_time_ns <= e.valid_time_ns <= received_ns for e in got), (
        [(e.valid_time_ns - first_write_ns) // 1000 for e in got])
    for event, (values, unit_mm, _telegram) in zip(got, expected):
        assert event.type == "scan" and event.source == "bwr1.scanner"
        msg = check_event(event)  # the ledger would accept it
        fov, step = FIELDS[len(values)]
        angles = beam_angles_rad(fov, step)
        assert msg.frame_id == "bwr1/scanner"
        assert msg.start_angle == angles[0] and msg.end_angle == angles[-1]
        ranges = np.asarray(msg.ranges)
        np.testing.assert_array_equal(ranges, L.values_to_ranges_m(values, unit_mm))
        assert np.array_equal(np.isnan(ranges), values >= L.ERROR_CODE_MIN)
        assert len(msg.intensities) == 0

    lines = log_lines(tmp_path / "scanner.log")
    assert not (tmp_path / "scanner.log").read_text().count("Traceback")
    published = _one(lines, "published")
    assert published["source"] == "bwr1.scanner"
    assert int(published["count"]) == len(got)
    assert int(published["epoch"]) == got[0].epoch
    stopped = _one(lines, "stopped")
    assert stopped["reason"] == "SIGTERM"
    assert int(stopped["published"]) == len(got)
    assert int(stopped["crc_errors"]) == len(corrupt) + 1 + 1  # corrupt + truncated + false
    assert int(stopped["other_telegrams"]) == 1
    assert int(stopped["garbage_bytes"]) == total_bytes - intact_bytes
    assert int(stopped["telegrams"]) == len(expected) + 1
    assert "waiting_for_clock" not in stopped and "bad_telegrams" not in stopped


def _read_command(dev: PtyDevice, want: int, timeout_s: float = TIMEOUT_S) -> bytes:
    """Bytes the service wrote to the device (host -> scanner), waiting on the master fd."""
    got = b""
    deadline = time.monotonic() + timeout_s
    while len(got) < want:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"only {got.hex()} arrived from the service"
        select.select([dev.fileno()], [], [], remaining)
        got += dev.read()
    return got


def test_valid_time_is_arrival_minus_transfer_and_field_comes_from_the_count(router, tmp_path):
    """At 9600 baud a 401-value telegram takes 846 ms on the line: well beyond the tolerance."""
    session, endpoint = router
    baud = 9600
    tolerance_ns = 200_000_000
    rng = _rng("scanner valid time")
    sink = EventSink(session, SITE, "scan", S.DEFAULT_SOURCE, TIMEOUT_S)
    writes: list[tuple[int, int, np.ndarray]] = []  # (wall ns after the write, bytes, values)
    dev = PtyDevice(write_timeout_s=TIMEOUT_S)
    process = _start_scanner(dev, endpoint, tmp_path, "--baud", str(baud), "--send-start")
    try:
        wait_liveliness(session, f"stockpile/{SITE}/@live/scanner/**", TIMEOUT_S)
        # --send-start: the start-continuous command, once, before any answer
        assert _read_command(dev, len(L.START_CONTINUOUS)) == L.START_CONTINUOUS
        for i, count in enumerate(FIELDS):
            values = _random_values(rng, count)
            telegram = L.encode_measurement(values)
            dev.write(telegram)
            writes.append((time.time_ns(), len(telegram), values))
            sink.wait_for(i + 1, process)  # one telegram per read: nothing behind it
        # the device goes away (the pty closes): the service stops by itself, cleanly
        dev.close()
        rc = process.wait(TIMEOUT_S)
    finally:
        dev.close()
        if process.poll() is None:
            process.kill()
            process.wait()
        sink.close()
    assert rc == 0
    got = sink.events
    assert len(got) == len(FIELDS)
    for event, (written_ns, n_bytes, values), (fov, step) in zip(got, writes, FIELDS.values()):
        msg = check_event(event)
        transfer_ns = n_bytes * 10 * 1_000_000_000 // baud
        assert transfer_ns > tolerance_ns
        expected_ns = written_ns - transfer_ns
        assert abs(timestamp_ns(msg.timestamp) - expected_ns) < tolerance_ns, (
            f"{len(values)} values: valid time {timestamp_ns(msg.timestamp) - expected_ns} ns "
            "from write - transfer")
        angles = beam_angles_rad(fov, step)
        assert len(msg.ranges) == len(values) == len(angles)
        assert msg.start_angle == angles[0] and msg.end_angle == angles[-1]
    lines = log_lines(tmp_path / "scanner.log")
    assert any(line.get("msg") == "device closed" for line in lines)
    assert int(_one(lines, "published")["count"]) == len(FIELDS)
    assert _one(lines, "stopped")["reason"] == "done"


def test_site_clock_waits_for_the_clock_then_maps_arrival_onto_site_time(router, tmp_path):
    """``--clock site``: a scan before the first clock event is dropped and counted; after
    it, valid time = site time of the arrival - transfer time."""
    session, endpoint = router
    baud = 9600
    tolerance_ns = 200_000_000
    site0_ns = parse_time_ns("2030-03-31T12:00:00Z")  # far from the wall clock
    log = tmp_path / "scanner.log"
    telegram = L.encode_measurement(_random_values(_rng("scanner site clock"), 201))
    sink = EventSink(session, SITE, "scan", S.DEFAULT_SOURCE, TIMEOUT_S)
    dev = PtyDevice(write_timeout_s=TIMEOUT_S)
    process = _start_scanner(dev, endpoint, tmp_path, "--clock", "site", "--baud", str(baud),
                             "--status-period", "0.2")
    try:
        wait_liveliness(session, f"stockpile/{SITE}/@live/scanner/**", TIMEOUT_S)
        dev.write(telegram)  # no clock yet: its valid time is unknown
        wait_until(lambda: any(line.get("waiting_for_clock") == "1" for line in log_lines(log)),
                   TIMEOUT_S, "the scan counted as waiting_for_clock")
        with SiteClock(session, SITE, site0_ns) as clock:
            wait_until(lambda: any(line.get("msg") == "site clock ready"
                                   for line in log_lines(log)),
                       TIMEOUT_S, "the service to follow the site clock")
            dev.write(telegram)
            written_site_ns = clock.site_ns(time.monotonic_ns())
            got = sink.wait_for(1, process)
        rc = stop(process)
    finally:
        dev.close()
        if process.poll() is None:
            process.kill()
            process.wait()
        sink.close()
    assert rc == 0 and len(got) == 1
    transfer_ns = S.transfer_time_ns(len(telegram), baud)
    expected_ns = written_site_ns - transfer_ns
    assert abs(timestamp_ns(check_event(got[0]).timestamp) - expected_ns) < tolerance_ns
    stopped = _one(log_lines(log), "stopped")
    assert int(stopped["waiting_for_clock"]) == 1 and int(stopped["published"]) == 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_site_time_follows_a_change_of_pace_at_once(seed):
    """The demo's simulator runs at 40x while a machine moves and 2000x while none does
    (30 site seconds between cuts).  Clock ticks every 10 site seconds, delivered up to
    2 ms late: right after the switch back to 40x, site time read 0.1 s (local) after
    the newest tick is that tick + 4 s.  A line fitted across the switch was 17 s off."""
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    clock = SiteTime("site")
    local_s, site_ns = 100.0, 1_800_000_000_000_000_000
    steps = [(0.25, 40.0)] * 30 + [(0.005, 2000.0)] * 3 + [(0.25, 40.0)] * 3
    for local_step_s, speed in steps:
        local_s += local_step_s
        site_ns += int(round(local_step_s * speed * 1e9))
        clock.observe(local_s + abs(rng.normal(0.0, 0.002)), site_ns)
    expected_ns = site_ns + int(0.1 * 40.0 * 1e9)
    assert abs(clock.at(local_s + 0.1) - expected_ns) < 0.3e9   # 0.3 site s = 7.5 ms local
    assert clock.speed == pytest.approx(40.0, rel=0.05)
    # a burst (ticks delivered together) neither starts a new pace nor spoils the line
    for _ in range(3):
        site_ns += 10 * 10**9
        clock.observe(local_s + 0.25 + 1e-5 * _, site_ns)
    assert clock.speed == pytest.approx(40.0, rel=0.5)
    # a tick repeated or delivered late changes nothing
    before = clock.at(local_s + 1.0)
    clock.observe(local_s + 0.9, site_ns - 30 * 10**9)
    clock.observe(local_s + 0.95, site_ns)
    assert clock.at(local_s + 1.0) == before
    with pytest.raises(ValueError):
        SiteTime("site", pace_change=1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_site_time_between_ticks_follows_a_pace_the_line_has_not_seen(seed):
    """A simulator at 40x that falls behind (10x for a while) and catches up (400x):
    readings placed between the ticks around them stay within the ticks' delivery jitter
    (times the pace) of the true site time; the fitted line, extrapolating from the ticks
    before, is seconds off right after each change."""
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    clock = SiteTime("site")
    jitter_s = 0.001
    # the true schedule: (local s, site ns) corners of a piecewise-linear map
    corners = [(100.0, 1_800_000_000_000_000_000)]
    for local_step_s, speed in [(5.0, 40.0), (2.0, 10.0), (0.5, 400.0), (5.0, 40.0)]:
        m0, s0 = corners[-1]
        corners.append((m0 + local_step_s, s0 + int(round(local_step_s * speed * 1e9))))
    local = np.array([m for m, _ in corners])
    site = np.array([s for _, s in corners], dtype=np.float64)
    tick_local = np.arange(local[0], local[-1], 0.25)   # a tick every 10 site s at 40x
    for m in tick_local:
        clock.observe(m + abs(rng.normal(0.0, jitter_s)), int(np.interp(m, local, site)))
    readings = rng.uniform(local[0] + 0.3, tick_local[-1] - 0.3, 400)
    truth = np.interp(readings, local, site)
    placed = np.array([clock.interpolate(m) for m in readings], dtype=np.float64)
    # a tick delivered up to ~4 jitter sds late, at 400x: 1.6 s; at 40x 0.16 s
    err_s = np.abs(placed - truth) / 1e9
    assert np.median(err_s) < 0.1 and err_s.max() < 2.0, (np.median(err_s), err_s.max())
    # the fitted line, read right after the pace changes, is off by far more
    after = np.array([local[1] + 0.2, local[2] + 0.2, local[3] + 0.2])
    line_err = []
    for m_read in after:
        line = SiteTime("site")
        for m in tick_local[tick_local < m_read]:
            line.observe(m, int(np.interp(m, local, site)))
        line_err.append(float(abs(line.at(m_read) - np.interp(m_read, local, site)) / 1e9))
    print("between ticks: median %.3f s, max %.3f s; fitted line after the changes: %s"
          % (np.median(err_s), err_s.max(), [round(e, 2) for e in line_err]))
    assert max(line_err) > 2 * err_s.max(), line_err
    # none before the first tick or after the newest one; wall mode is the wall clock
    assert clock.interpolate(tick_local[0] - 1.0) is None
    assert clock.interpolate(tick_local[-1] + 1.0) is None
    wall = SiteTime("wall")
    now = time.monotonic()
    assert abs(wall.interpolate(now) - time.time_ns()) < 1e9


def test_a_device_that_cannot_be_opened_is_one_error_line_and_exit_2(tmp_path):
    missing = tmp_path / "no-such-tty"
    run = subprocess.run([sys.executable, "-m", "stockpile.cli", "service", "scanner",
                          "--device", str(missing), "--mode", "client", "--connect",
                          "tcp/127.0.0.1:9"], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    line = parse_logfmt(lines[0])
    assert line["level"] == "error" and line["msg"] == "cannot open device"
    assert line["device"] == str(missing)


# -------------------------------------------------------------------------- pure parts


@pytest.mark.parametrize("count", list(FIELDS))
def test_default_field_matches_the_simulator_beam_angles(count):
    fov, step = FIELDS[count]
    angles = beam_angles_rad(fov, step)
    geometry = S.scan_field(count)
    assert geometry.count == count == len(angles)
    assert geometry.start_angle_rad == angles[0]
    assert geometry.end_angle_rad == angles[-1]
    assert math.isclose(geometry.end_angle_rad, math.radians(fov / 2), abs_tol=1e-12)
    # one of fov/step given: the other follows from the count; both given: must agree
    assert S.scan_field(count, fov_deg=fov) == geometry
    assert S.scan_field(count, resolution_deg=step) == geometry
    assert S.scan_field(count, fov_deg=fov, resolution_deg=step) == geometry


def test_field_options_that_do_not_fit_the_count_are_refused():
    with pytest.raises(ValueError, match="no LMS200 configuration"):
        S.scan_field(400)
    with pytest.raises(ValueError, match="do not fit"):
        S.scan_field(401, fov_deg=100.0, resolution_deg=0.5)
    assert S.scan_field(91, fov_deg=90.0).end_angle_rad == math.radians(45.0)


def test_scan_message_passes_the_ledger_checks():
    values = np.array([0, 1000, L.NO_RETURN, L.DAZZLE, 8182] + [500] * 96, dtype=np.uint16)
    ranges = L.values_to_ranges_m(values, unit_mm=True)
    msg = S.scan_message(ranges, 1_793_491_200_123_456_789, "bwr1/scanner", S.scan_field(101))
    event = make_event(msg, source="bwr1.scanner", epoch=1, seq=0)
    checked = check_event(event)
    assert event.valid_time_ns == 1_793_491_200_123_456_789
    assert list(checked.ranges)[:2] == [0.0, 1.0] and math.isnan(checked.ranges[2])
    assert checked.pose.orientation.w == 1.0
    with pytest.raises(ValueError):
        S.scan_message(ranges[:-1], 0, "bwr1/scanner", S.scan_field(101))


def test_valid_time_subtracts_line_time_and_never_goes_back_past_the_previous_read():
    # 812 bytes at 500 kbaud: 16.24 ms
    assert S.transfer_time_ns(812, 500_000) == 16_240_000
    assert S.scan_valid_time_ns(10**18, 0, 812, 500_000) == 10**18 - 16_240_000
    # 100 bytes arrived behind it: its last byte came 2 ms before the read
    assert S.scan_valid_time_ns(10**18, 100, 812, 500_000) == 10**18 - 18_240_000
    # ... but not before the previous read
    assert (S.scan_valid_time_ns(10**18, 100, 812, 500_000, not_before_ns=10**18 - 1_000_000)
            == 10**18 - 17_240_000)


def test_telegram_end_offsets_find_each_telegram_behind_garbage():
    a = L.encode_measurement(np.arange(101))
    b = L.encode_measurement(np.arange(101) + 1)
    window = b"\x00\x01" + a + b"\xff" * 5 + b + b"\x02\x80"
    reader = L.TelegramReader()
    telegrams = reader.feed(window)
    assert telegrams == [a, b]
    ends = S.telegram_end_offsets(window, telegrams)
    assert ends == [2 + len(a), 2 + len(a) + 5 + len(b)]
    # the same telegram twice in a row ends twice
    assert S.telegram_end_offsets(a + a, [a, a]) == [len(a), 2 * len(a)]


def test_config_defaults_and_refusals():
    config = S.Config(device="/dev/null")
    assert config.frame_id == "bwr1/scanner" and config.baud == 500_000
    assert S.Config(device="/dev/null", source="bwr2.scanner.left").frame_id == "bwr2/scanner.left"
    assert S.Config(device="/dev/null", frame_id="x").frame_id == "x"
    for bad in ({"baud": 0}, {"source": "bad source"}, {"clock": "gps"}, {"fov_deg": -1.0},
                {"resolution_deg": float("nan")}):
        with pytest.raises(ValueError):
            S.Config(device="/dev/null", **bad)
