"""A producer's wall clock steps back by 10 s (an NTP step) in the middle of a run.

Nothing on the machine changes: the producer (``tests/faults/wall_producer.py``, which
dates its ``clock`` and ``joint_reading`` events by ``time.time_ns()``) runs with a
``sitecustomize`` the test writes, which on SIGUSR2 steps its ``time.time``,
``time.time_ns`` and ``datetime`` back by 10 s (the monotonic clock, like the kernel's,
is untouched).  The ledger runs on the site clock (``--clock events``), so the producer's
``clock`` events are its recorded time: after the step they say 10 s earlier.  Then the
producer restarts with its clock still 10 s behind: its new epoch (the wall clock at
start) is lower than the old one.

The ledger must keep everything (no quarantine: an earlier valid time and a lower epoch
are not errors), recorded time along the global sequence must never go backwards, and
the closing check must find every event of both epochs exactly once.
"""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

from harness import PYTHON, SITE, Producer, Yard
from ledger import open_ledger
from zenoh_helpers import wait_until

RATE_HZ = 200.0
#: how far the producer's wall clock steps back, ns
STEP_NS = 10 * 1_000_000_000
FIRST_S, SECOND_S = 6.0, 3.0
WALL_PRODUCER = Path(__file__).with_name("wall_producer.py")

SITECUSTOMIZE = '''"""Steps this process's wall clock back on SIGUSR2 (written by test_fault_clock_step)."""
import datetime as _dt
import os
import signal
import time as _time

_STEP_NS = int(os.environ["FAULT_CLOCK_STEP_NS"])
_offset_ns = [-_STEP_NS if os.environ.get("FAULT_CLOCK_STEPPED") == "1" else 0]
_real_time, _real_time_ns = _time.time, _time.time_ns


def _time_s():
    return _real_time() + _offset_ns[0] / 1e9


def _time_ns():
    return _real_time_ns() + _offset_ns[0]


class _SteppedDatetime(_dt.datetime):
    @classmethod
    def now(cls, tz=None):
        return cls.fromtimestamp(_time_s(), tz)

    @classmethod
    def today(cls):
        return cls.fromtimestamp(_time_s())

    @classmethod
    def utcnow(cls):
        return cls.fromtimestamp(_time_s(), _dt.timezone.utc).replace(tzinfo=None)


def _step(signum, frame):
    _offset_ns[0] -= _STEP_NS
    with open(os.environ["FAULT_CLOCK_STEP_LOG"], "a") as f:
        f.write(f"{_time.monotonic()}\\n")


_time.time, _time.time_ns = _time_s, _time_ns
_dt.datetime = _SteppedDatetime
signal.signal(signal.SIGUSR2, _step)
'''


def _start_producer(yard: Yard, hooks: Path, name: str, duration_s: float,
                    stepped: bool) -> Producer:
    report, log = yard.base / f"{name}.json", yard.base / f"{name}.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(hooks), os.environ.get(
        "PYTHONPATH", "")]), "FAULT_CLOCK_STEP_NS": str(STEP_NS),
        "FAULT_CLOCK_STEP_LOG": str(yard.base / "steps.txt"),
        "FAULT_CLOCK_STEPPED": "1" if stepped else "0", "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(
        [PYTHON, str(WALL_PRODUCER), "--site", SITE, "--source", "load0", "--rate", str(RATE_HZ),
         "--duration", str(duration_s), "--report", str(report), *yard.client_args("load0")],
        stderr=open(log, "w"), stdout=subprocess.DEVNULL, env=env)
    producer = Producer(name, process, report, log)
    yard.producers.append(producer)
    return producer


def test_a_producer_clock_stepping_back_10_s_keeps_recorded_time_monotone(tmp_path):
    hooks = tmp_path / "hooks"
    hooks.mkdir()
    (hooks / "sitecustomize.py").write_text(SITECUSTOMIZE)
    steps = tmp_path / "yard" / "steps.txt"
    with Yard(tmp_path / "yard", services=("ledger",), producers=1,
              ledger_clock="events") as yard:
        yard.start()
        first = _start_producer(yard, hooks, "load0-a", FIRST_S, stepped=False)
        wait_until(lambda: yard.poller.samples
                   and yard.poller.samples[-1][1].get("load0", 0) >= RATE_HZ * 2, 60,
                   "2 s of the producer's events in the ledger")
        first.process.send_signal(signal.SIGUSR2)
        wait_until(steps.exists, 10, "the producer's clock to step back")
        step_at = float(steps.read_text().split()[0])
        wait_until(first.report_path.exists, 60, "the first producer's report")
        # it restarts (a PLC rebooting after the step) with its clock still 10 s behind
        assert first.process.poll() is None
        first.process.send_signal(signal.SIGTERM)
        assert first.process.wait(30) == 0
        second = _start_producer(yard, hooks, "load0-b", SECOND_S, stepped=True)
        row = yard.finish("producer wall clock steps back 10 s, then restarts", [step_at])
    [a], [b] = first.streams(), second.streams()
    assert b.epoch < a.epoch, "the restarted producer's epoch should be the lower one"
    assert row["ledgered"] == row["published"] == a.count + b.count, row
    with open_ledger(yard.ledger_path, read_only=True) as store:
        assert list(store.quarantine()) == [], "the ledger refused events it should keep"
        rows = list(store.read())
    recorded = [r.recorded_time_ns for r in rows]
    assert all(x <= y for x, y in zip(recorded, recorded[1:])), "recorded time went back"
    # the fault happened: the first stream's valid time stepped back by about 10 s
    valid = [r.valid_time_ns for r in sorted((r for r in rows if r.epoch == a.epoch),
                                             key=lambda r: r.seq)]
    biggest_step_back_ns = max(x - y for x, y in zip(valid, valid[1:]))
    assert 9 * 10**9 < biggest_step_back_ns < 11 * 10**9
    # and the ledger held its recorded time through the step instead of following the
    # clock events back: it ends at the latest clock time it was ever told
    assert recorded[-1] >= max(r.valid_time_ns for r in rows if r.type == "clock")
