"""The soak: at least 30 minutes at four times the demo yard's event rate, a random service
SIGKILLed every few minutes, memory of every process sampled; nothing lost, chain verifies.

Rate: the process demo (``make demo``, seed 3 scenario ``demo``, 40x) ledgers 312,841 events
in 171 s of wall time, 1,830 events/s on average (its ``summary.json``: ``per_type`` and
``wall_s``).  Four times that is 7,320 events/s: four producers (PLC certificates,
``services.loadgen`` joint readings) at 1,830 events/s each.

Yard: ``stockpile run`` with the ledger, the localizer and the recorder (hourly parts),
a router process, all over mutual TLS.  Every ``KILL_PERIOD_S`` (+-30 %, at most a quarter
of the run) a service is SIGKILLed, each round of kills taking every service once in an
order drawn from the run's seed (``seeding.rng``, printed with the schedule); ``stockpile run`` restarts it.
``STOCKPILE_SOAK_KILL=localizer,recorder`` spares the ledger, so that one ledger process
runs the whole soak and its memory slope covers the run (a killed service's instances
live a few minutes each, too short to resolve the bound).

Memory: every ``RSS_PERIOD_S`` the resident set of every process (router, ``stockpile
run``, each service instance, each producer) is read from ``/proc``.  Per process instance
the least-squares slope of RSS over time after a warm-up (``WARMUP_S``, at most a quarter
of the run: the producers' caches fill in 50,000 / 1,830 = 27 s, DuckDB and Zenoh reach
their working sets) is reported in MB/h, and asserted below ``MAX_SLOPE_MB_PER_H`` for
every instance observed for at least ``MIN_SPAN_S`` after its warm-up.  The bound, 50
MB/h: at 7,320 events/s an hour is 26 million events, so anything that keeps as little
as 2 bytes per event (a set of seen keys, a log list, an unbounded queue) exceeds it,
while a process whose working set is flat stays far below it.  Over a window too short
to resolve 50 MB/h (``STOCKPILE_SOAK_MINUTES=3``) the bound is ``NOISE_FLOOR_MB`` over the
window instead: 20 MB of allocator and page jitter.
"""

from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import psutil
import pytest

import seeding
from harness import Yard, results_path
from zenoh_helpers import wait_until

#: the soak's length, minutes ($STOCKPILE_SOAK_MINUTES; at least 30 for the issue's soak)
SOAK_MINUTES = float(os.environ.get("STOCKPILE_SOAK_MINUTES") or 30)
#: the demo yard's mean event rate, events/s (see the module doc)
DEMO_RATE_HZ = 1_830.0
PRODUCERS = 4
#: each producer's rate: together four times the demo's, events/s
PRODUCER_RATE_HZ = 4 * DEMO_RATE_HZ / PRODUCERS
SERVICES = ("ledger", "localizer", "recorder")
#: the services the kills take ($STOCKPILE_SOAK_KILL, comma-separated; default all): a
#: service left out runs the whole soak as one process, so its slope covers the run
KILLED = tuple(s for s in (os.environ.get("STOCKPILE_SOAK_KILL") or ",".join(SERVICES)).split(",")
               if s)
#: mean period of the kills, s (+-30 %; at most a quarter of the run)
KILL_PERIOD_S = 180.0
#: period of the RSS samples, s
RSS_PERIOD_S = 5.0
#: warm-up ignored by the slopes, s (at most a quarter of the run)
WARMUP_S = 300.0
#: bound on each process's RSS slope after the warm-up, MB/h (see the module doc)
MAX_SLOPE_MB_PER_H = 50.0
#: growth any process may show over a window, whatever its length (allocator and page
#: jitter), MB: what makes a 3-minute try's bound 20 MB / 2.25 min = 530 MB/h
NOISE_FLOOR_MB = 20.0


class RssSampler:
    """Samples the RSS of a set of process trees every ``RSS_PERIOD_S``: per process
    instance ``(name, pid) -> [(monotonic s, MB)]``."""

    def __init__(self, roots: dict[str, int]) -> None:
        self.roots = roots
        self.samples: dict[tuple[str, int], list[tuple[float, float]]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss", daemon=True)

    @staticmethod
    def _name(proc: psutil.Process, root_name: str) -> str:
        cmd = proc.cmdline()
        if "service" in cmd:
            return cmd[cmd.index("service") + 1]
        return root_name

    def _run(self) -> None:
        while not self._stop.is_set():
            t = time.monotonic()
            for root_name, pid in self.roots.items():
                try:
                    root = psutil.Process(pid)
                    procs = [root] + root.children(recursive=True)
                except psutil.NoSuchProcess:
                    continue
                for proc in procs:
                    try:
                        key = (self._name(proc, root_name), proc.pid)
                        rss_mb = proc.memory_info().rss / 1e6
                    except psutil.Error:
                        continue
                    self.samples.setdefault(key, []).append((t, rss_mb))
            self._stop.wait(RSS_PERIOD_S)   # the sampling period

    def start(self) -> "RssSampler":
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(30)


def allowed_slope_mb_per_h(span_h: float) -> float:
    """The slope bound for a window of ``span_h`` hours: ``MAX_SLOPE_MB_PER_H``, or
    ``NOISE_FLOOR_MB`` over the window when that is more (a short try of the soak)."""
    return max(MAX_SLOPE_MB_PER_H, NOISE_FLOOR_MB / span_h)


def slope_mb_per_h(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (s, MB) points, MB/h."""
    t = np.array([p[0] for p in points])
    y = np.array([p[1] for p in points])
    return float(np.polyfit(t - t[0], y, 1)[0] * 3600.0)


@pytest.mark.long_fault
def test_soak_four_times_the_demo_rate_with_random_kills(tmp_path, seed):
    duration_s = SOAK_MINUTES * 60.0
    warmup_s = min(WARMUP_S, duration_s / 4)
    min_span_s = max(60.0, (duration_s - warmup_s) / 3)
    period_s = min(KILL_PERIOD_S, duration_s / 4)
    unknown = set(KILLED) - set(SERVICES)
    assert KILLED and not unknown, f"STOCKPILE_SOAK_KILL: not services of the soak: {unknown}"
    rng = seeding.rng(6)
    schedule, t, order = [], 0.0, []
    while True:
        t += period_s * rng.uniform(0.7, 1.3)
        if t > duration_s - period_s / 2:
            break
        if not order:   # each round kills every service once, in a seeded random order
            order = [KILLED[i] for i in rng.permutation(len(KILLED))]
        schedule.append((round(t, 1), order.pop()))
    print(f"soak: {SOAK_MINUTES:g} min at {PRODUCERS} x {PRODUCER_RATE_HZ:g} events/s; "
          f"seed {seed}; kills (s after start, service): {schedule}")
    with Yard(tmp_path, services=SERVICES, producers=PRODUCERS, poll_period_s=1.0) as yard:
        yard.start()
        producers = yard.start_loadgens(rate_hz=PRODUCER_RATE_HZ, duration_s=duration_s,
                                        cache=50_000)
        sampler = RssSampler({"router": yard.router.process.pid, "run": yard.run.pid,
                              **{p.name: p.process.pid for p in producers}}).start()
        try:
            wait_until(lambda: yard.poller.samples and all(
                yard.poller.samples[-1][1].get(p, 0) > 0 for p in yard.producer_names),
                90, "the first events of every producer in the ledger")
            t0 = time.monotonic()
            kills = []
            for at_s, service in schedule:
                wait_until(lambda: time.monotonic() >= t0 + at_s, at_s + 5, f"kill at {at_s} s")
                kills.append(yard.kill_service(service)[0])
            wait_until(lambda: all(p.report_path.exists() for p in producers),
                       duration_s + 300, "the producers to finish")
        finally:
            sampler.close()
        slopes, checked = {}, {}
        for (name, pid), points in sorted(sampler.samples.items()):
            after = [p for p in points if p[0] >= points[0][0] + warmup_s]
            if len(after) < 5:
                continue
            key = f"{name}:{pid}"
            slopes[key] = round(slope_mb_per_h(after), 1)
            span_h = (after[-1][0] - after[0][0]) / 3600.0
            if span_h * 3600.0 >= min_span_s:
                checked[key] = (slopes[key], allowed_slope_mb_per_h(span_h))
        print(f"RSS slopes (MB/h) after {warmup_s:g} s of warm-up: {slopes}; checked "
              f"(slope, bound): {checked}")
        dump = results_path().with_name("soak_rss.json")   # every sample, for a post-mortem
        dump.parent.mkdir(parents=True, exist_ok=True)
        dump.write_text(json.dumps({f"{n}:{p}": pts for (n, p), pts in
                                    sorted(sampler.samples.items())}))
        extra = {"rate_hz": 4 * DEMO_RATE_HZ, "rss_slope_mb_per_h": slopes,
                 "rss_peak_mb": {f"{n}:{p}": round(max(v for _t, v in pts), 1)
                                 for (n, p), pts in sampler.samples.items()}}
        row = yard.finish(f"soak {SOAK_MINUTES:g} min, 4x demo rate, {len(kills)} random "
                          f"SIGKILLs", kills, extra=extra)
    assert row["ledgered"] + row["gap_events"] == row["published"]
    # the caches hold 50,000 events per producer, 27 s of its events, and a service is
    # back in a few seconds: nothing may be lost
    assert row["gap_events"] == 0, f"events lost (in exact gaps): {row}"
    assert len(checked) >= len(SERVICES) + PRODUCERS - 1, (checked, slopes)
    growing = {k: v for k, v in checked.items() if v[0] > v[1]}
    assert not growing, f"memory grows (MB/h, bound): {growing}"
