"""``stockpile service gnss``: NMEA GGA through a real pty, location fixes out on Zenoh.

The service runs as a separate process reading a :class:`PtyDevice` with pyserial; the test
holds a real Zenoh router session on a free loopback port (scouting off) with an
``AdvancedSubscriber`` (history and recovery, as the ledger subscribes), and waits on
conditions (the service's liveliness token, N samples, log lines), never on sleeps.
``--clock site`` is driven by ``clock`` events the test publishes like the simulator does.

Random data is seeded
from the run's seed (``--seed N`` or ``STOCKPILE_TEST_SEED=N`` reproduces a run; the seed is
printed, and written into a failing test's report).
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from schemas.times import parse_time_ns as parse_time
from schemas.events import (
    make_event,
    timestamp_ns,
)
from schemas.validate import check_event
from services import gnss as G
from devices import nmea as N
from services.service import parse_logfmt
from sim.pty import PtyDevice
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
SITE = "gnsstest"
TIMEOUT_S = 20.0  # generous: each wait normally takes well under a second
NS_PER_CS = 10_000_000
#: half a unit of the sentence's last digit of latitude / longitude (1e-7 arc-minute), deg
ANGLE_TOLERANCE_DEG = 0.5e-7 / 60 + 1e-12
LIVE_KEY = f"stockpile/{SITE}/@live/gnss/**"


def _rng(test_name: str) -> np.random.Generator:
    print(f"{test_name}: seed {SEED} (--seed {SEED} reproduces it)")
    return np.random.default_rng(SEED)


def _sentence(body: str) -> bytes:
    """A framed sentence with a correct checksum."""
    return f"${body}*{N.nmea_checksum(body)}\r\n".encode("ascii")


def _bad_checksum(sentence: str) -> bytes:
    star = sentence.rindex("*")
    wrong = f"{int(sentence[star + 1:star + 3], 16) ^ 0x5A:02X}"
    return (sentence[:star + 1] + wrong + "\r\n").encode("ascii")


# -------------------------------------------------------------------------- Zenoh side


@pytest.fixture()
def router():
    session, endpoint = open_router()
    try:
        yield session, endpoint
    finally:
        session.close()


def _start_gnss(dev: PtyDevice, endpoint: str, log: Path, *extra: str) -> subprocess.Popen:
    return stockpile("service", "gnss", "--device", dev.path, "--site", SITE,
                     "--status-period", "0.2", *client_args(endpoint), *extra,
                     stderr_path=log)


def _one(lines: list[dict], msg: str) -> dict:
    found = [line for line in lines if line.get("msg") == msg]
    assert len(found) == 1, f"expected one {msg!r} line, got {found}"
    return found[0]


def _kill(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.kill()
        process.wait()


# -------------------------------------------------------------------------- end to end


def test_every_good_fix_published_once_and_bad_sentences_counted(router, tmp_path):
    session, endpoint = router
    rng = _rng("gnss fixes")
    uere_m = 0.7
    n_good = 12
    fixes = []
    for i in range(n_good):
        fixes.append({
            "lat_deg": float(-20.59 + rng.normal(0, 0.01)),
            "lon_deg": float(117.18 + rng.normal(0, 0.01)),
            "quality": int(rng.choice([1, 2, 4, 5])),
            "satellites": int(rng.integers(4, 13)),
            "hdop": float(rng.uniform(0.6, 3.0)),
            "altitude_m": float(rng.uniform(5, 40)),
            "geoid_sep_m": float(rng.uniform(-5, 5)) if i % 2 else 0.0,
        })
    # a valid RMC (not GGA), a GGA with a valid checksum but a bad latitude, line noise
    rmc = _sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W")
    bad_field = _sentence("GPGGA,123519,99x7.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
    noise = b"\x00\xffnoise on the line\r\n"

    sink = EventSink(session, SITE, "location_fix", G.DEFAULT_SOURCE, TIMEOUT_S)
    log = tmp_path / "gnss.log"
    sent: list[int] = []  # time of each good fix, UTC ns
    with PtyDevice(write_timeout_s=TIMEOUT_S) as dev:
        process = _start_gnss(dev, endpoint, log, "--uere-m", str(uere_m))
        try:
            wait_liveliness(session, LIVE_KEY, TIMEOUT_S)
            for i, fix in enumerate(fixes):
                t_ns = time.time_ns()
                good = N.format_gga(t_ns, **fix)
                data = good.encode("ascii")
                if i in (2, 7):
                    data = _bad_checksum(good) + data
                if i in (3, 9):
                    data += N.format_gga(t_ns, math.nan, math.nan, 0, 3, 99.9, math.nan).encode()
                if i == 5:
                    data = rmc + noise + bad_field + data
                dev.write(data)
                sent.append(t_ns)
            got = sink.wait_for(n_good, process)
            rc = stop(process)
        finally:
            _kill(process)
        assert dev.dropped_bytes == 0
    sink.close()

    assert rc == 0
    assert len(got) == n_good
    assert [e.seq for e in got] == list(range(n_good))
    for event, fix, t_ns in zip(got, fixes, sent):
        assert event.type == "location_fix" and event.source == "bwr1.gnss"
        msg = check_event(event)  # the ledger would accept it
        # GGA carries the time of day to the centisecond; the date is today's
        assert timestamp_ns(msg.timestamp) == t_ns // NS_PER_CS * NS_PER_CS
        assert msg.frame_id == "bwr1/gnss"
        assert abs(msg.latitude - fix["lat_deg"]) <= ANGLE_TOLERANCE_DEG
        assert abs(msg.longitude - fix["lon_deg"]) <= ANGLE_TOLERANCE_DEG
        # ellipsoidal height = altitude above MSL + geoid separation (3 decimals each)
        assert msg.altitude == pytest.approx(round(fix["altitude_m"], 3)
                                             + round(fix["geoid_sep_m"], 3), abs=1e-9)
        # differential/RTK fixes use --uere-m, autonomous ones the default autonomous UERE
        uere = uere_m if fix["quality"] in (2, 4, 5) else G.DEFAULT_AUTONOMOUS_UERE_M
        h = round(fix["hdop"], 1) * uere
        assert list(msg.position_covariance) == pytest.approx(
            [h * h, 0, 0, 0, h * h, 0, 0, 0, (2 * h) ** 2], rel=1e-12, abs=1e-15)
        assert msg.position_covariance_type == msg.PositionCovarianceType.DIAGONAL_KNOWN

    lines = log_lines(log)
    assert "Traceback" not in log.read_text()
    published = _one(lines, "published")
    assert published["source"] == "bwr1.gnss" and int(published["count"]) == len(got)
    stopped = _one(lines, "stopped")
    assert stopped["reason"] == "SIGTERM"
    assert int(stopped["published"]) == n_good
    assert int(stopped["checksum_errors"]) == 2
    assert int(stopped["no_fix"]) == 2
    assert int(stopped["non_gga"]) == 1
    assert int(stopped["unparseable"]) == 1
    assert int(stopped["sentences"]) == n_good + 2 + 1 + 1
    assert int(stopped["garbage_bytes"]) == len(noise)
    assert "waiting_for_clock" not in stopped


def test_site_clock_dates_fixes_across_midnight(router, tmp_path):
    """``--clock site``: fixes wait for the clock; then the date follows the site clock,
    and a fix from just after midnight gets the next day's date."""
    session, endpoint = router
    log = tmp_path / "gnss.log"
    site_ns = parse_time("2030-03-31T23:59:59Z")  # the site clock, far from the wall clock
    sink = EventSink(session, SITE, "location_fix", G.DEFAULT_SOURCE, TIMEOUT_S)
    dev = PtyDevice(write_timeout_s=TIMEOUT_S)
    process = _start_gnss(dev, endpoint, log, "--clock", "site")

    def fix(time_of_day: str) -> bytes:
        t_ns = parse_time(f"2001-01-01T{time_of_day}Z")  # only the time of day is sent
        return N.format_gga(t_ns, -20.6, 117.2, 2, 9, 0.9, 12.0).encode("ascii")

    try:
        wait_liveliness(session, LIVE_KEY, TIMEOUT_S)
        dev.write(fix("23:59:58.00"))  # before any clock event: the date is unknown
        wait_until(lambda: any(line.get("waiting_for_clock") == "1" for line in log_lines(log)),
                   TIMEOUT_S, "the fix counted as waiting_for_clock")
        with SiteClock(session, SITE, site_ns):
            wait_until(lambda: any(line.get("msg") == "site clock ready"
                                   for line in log_lines(log)),
                       TIMEOUT_S, "the service to follow the site clock")
            dev.write(fix("23:59:58.00") + fix("00:00:00.50"))
            got = sink.wait_for(2, process)
        rc = stop(process)
    finally:
        dev.close()
        _kill(process)
        sink.close()
    assert rc == 0
    assert [timestamp_ns(check_event(e).timestamp) for e in got] == [
        parse_time("2030-03-31T23:59:58Z"), parse_time("2030-04-01T00:00:00.5Z")]
    stopped = _one(log_lines(log), "stopped")
    assert int(stopped["waiting_for_clock"]) == 1 and int(stopped["published"]) == 2


def test_a_device_that_cannot_be_opened_is_one_error_line_and_exit_2(tmp_path):
    missing = tmp_path / "no-such-tty"
    run = subprocess.run([sys.executable, "-m", "stockpile.cli", "service", "gnss",
                          "--device", str(missing), "--mode", "client", "--connect",
                          "tcp/127.0.0.1:9"], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    line = parse_logfmt(lines[0])
    assert line["level"] == "error" and line["msg"] == "cannot open device"


# -------------------------------------------------------------------------- pure parts


@pytest.mark.parametrize("now, time_of_day, expected", [
    # same day
    ("2026-11-01T12:00:00Z", "11:59:59.5", "2026-11-01T11:59:59.5Z"),
    # a fix from just before midnight read just after it keeps yesterday's date
    ("2026-11-02T00:00:00.2Z", "23:59:59.9", "2026-11-01T23:59:59.9Z"),
    # a fix from just after midnight while the local clock is still just before it
    ("2026-11-01T23:59:59.8Z", "00:00:00.1", "2026-11-02T00:00:00.1Z"),
    # across a month and a year end
    ("2027-01-01T00:00:01Z", "23:59:58", "2026-12-31T23:59:58Z"),
    # exactly 12 h either way: the earlier one
    ("2026-11-01T12:00:00Z", "00:00:00", "2026-11-01T00:00:00Z"),
    # a leap second (23:59:60.5) belongs to the day it ends
    ("2026-12-31T23:59:59.9Z", "23:59:60.5", "2027-01-01T00:00:00.5Z"),
])
def test_gga_time_joins_the_closest_date(now, time_of_day, expected):
    h, m, s = time_of_day.split(":")
    tod_s = int(h) * 3600 + int(m) * 60 + float(s)
    assert G.gga_time_ns(tod_s, parse_time(now)) == parse_time(expected)


def test_gga_time_of_a_parsed_sentence_is_exact_to_the_nanosecond():
    t_ns = parse_time("2026-11-01T07:08:09.37Z")
    gga = N.parse_gga(N.format_gga(t_ns, -20.6, 117.2, 1, 8, 1.2, 10.0))
    assert G.gga_time_ns(gga.time_of_day_s, t_ns + 3_000_000_000) == t_ns
    with pytest.raises(ValueError):
        G.gga_time_ns(math.nan, t_ns)


def test_fix_message_height_covariance_and_ledger_checks():
    sentence = N.format_gga(parse_time("2026-11-01T00:00:01Z"), -20.6, 117.2, 2, 9, 1.5, 12.25,
                            geoid_sep_m=-3.5)
    gga = N.parse_gga(sentence)
    msg = G.fix_message(gga, 1_793_491_201_000_000_000, "bwr1/gnss", 0.5)
    event = make_event(msg, source="bwr1.gnss", epoch=1, seq=0)
    checked = check_event(event)
    assert checked.altitude == pytest.approx(8.75)
    assert list(checked.position_covariance) == pytest.approx(
        [0.5625, 0, 0, 0, 0.5625, 0, 0, 0, 2.25])
    # no geoid separation in the sentence: the altitude is the height
    body = "GPGGA,000001.00,2036.0000000,S,11712.0000000,E,1,08,1.0,12.250,M,,M,,"
    assert G.ellipsoidal_height_m(N.parse_gga(_sentence(body).decode())) == 12.25


def test_config_refusals():
    assert G.Config(device="/dev/null").frame_id == "bwr1/gnss"
    for bad in ({"baud": -1}, {"source": ""}, {"clock": "gps"}, {"uere_m": -0.1}, {"uere_m": 0.0},
                {"autonomous_uere_m": math.nan},
                {"uere_m": math.inf}):
        with pytest.raises(ValueError):
            G.Config(device="/dev/null", **bad)
