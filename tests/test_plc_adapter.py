"""``stockpile service plc``: a real OPC UA server, a real Zenoh router, a real ledger.

The simulator's PLC server (``python -m sim.opcua_server``) runs as a child process the
test drives through its stdin (one JSON command a line); the adapter and the ledger
service run as ``stockpile service ...`` processes on a loopback Zenoh router (scouting
off).  The test waits on conditions (log lines, the ledger's head), never on sleeps.
Ground truth is what the test wrote to the PLC: the encoder values (from a seeded
:class:`sim.encoders.EncoderModel`), the passes and cuts, and the tonnes put on the belts
(rounded to the totaliser's kilogram here, independently of the adapter).
"""

from __future__ import annotations

import json
import queue
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from devices.opcua_tags import load_map
from ledger.testing_signing import key_declared, make_keys
from schemas.events import decode_payload, encode_attachment, key_expr, timestamp_ns
from schemas.times import parse_time_ns
from security.opcua_certs import make_application_certificate
from services.ledger_client import LedgerClient
from services.service import parse_logfmt
from sim.encoders import EncoderModel
from sim.opcua_server import APPLICATION_URI
from seeding import session_seed
from zenoh_helpers import (
    PYTHON, client_args, free_port, log_lines, open_router, stockpile, stop_all,
    wait_liveliness, wait_until)

SEED = session_seed()
pytestmark = pytest.mark.seeded
ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_MAP = ROOT / "docs" / "plc.example.toml"
SITE = "plctest"
TIMEOUT_S = 60.0
T0 = parse_time_ns("2030-01-01T00:00:00Z")
MS = 1_000_000  # ns


class SimPlc:
    """``python -m sim.opcua_server`` as a child process, driven line by line; it keeps
    every command it ran, so that a restarted server can be brought back to the same
    values and timestamps (a PLC keeps its state while its OPC UA server restarts)."""

    def __init__(self, tmp: Path, port: int, map_path: Path, *extra: str) -> None:
        self.args = [PYTHON, "-m", "sim.opcua_server", "--map", str(map_path),
                     "--port", str(port), "--start-ns", str(T0), *extra]
        self.log = tmp / "opcua-server.log"
        self.history: list[dict] = []
        self.endpoint = ""
        self.process: subprocess.Popen | None = None

    def start(self) -> SimPlc:
        self.process = subprocess.Popen(self.args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=open(self.log, "a"), text=True, bufsize=1)
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, args=(self.process.stdout, self._lines),
                         daemon=True).start()
        first = self._answer()
        assert first.startswith("listening "), first + self.log.read_text()[-2000:]
        self.endpoint = first.split()[1]
        return self

    @staticmethod
    def _read(stream, lines: queue.Queue) -> None:
        for line in stream:
            lines.put(line.strip())
        lines.put("")

    def _answer(self) -> str:
        try:
            return self._lines.get(timeout=TIMEOUT_S)
        except queue.Empty:
            raise AssertionError(f"the OPC UA server did not answer in {TIMEOUT_S} s") from None

    def __call__(self, op: str, *, record: bool = True, **kwargs) -> None:
        command = {"op": op, **kwargs}
        self.process.stdin.write(json.dumps(command) + "\n")
        self.process.stdin.flush()
        answer = self._answer()
        assert answer.startswith("ok "), f"{command}: {answer}"
        if record:
            self.history.append(command)

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    def restart(self) -> None:
        """Kill the server, start a new one on the same port, replay what the PLC holds."""
        self.kill()
        self.start()
        for command in self.history:
            self(**dict(command), record=False)


class Yard:
    """A router, a ledger service, a PLC server and the adapter, and their logs."""

    def __init__(self, tmp: Path, map_path: Path, server_args=(), adapter_args=()) -> None:
        self.router, self.zenoh = open_router()
        self.ledger = self.adapter = None
        self.plc = SimPlc(tmp, free_port(), map_path, *server_args)
        self.log = tmp / "plc.log"
        try:
            self.ledger = stockpile("service", "ledger", "--ledger", str(tmp / "ledger.duckdb"),
                                    "--site", SITE, "--status-period", "1",
                                    *client_args(self.zenoh), stderr_path=tmp / "ledger.log")
            wait_liveliness(self.router, f"stockpile/{SITE}/@live/ledger/**", TIMEOUT_S)
            self.client = LedgerClient(self.router, SITE, timeout_s=10)
            self.plc.start()
            self.adapter = stockpile("service", "plc", "--endpoint", self.plc.endpoint,
                                     "--map", str(map_path), "--site", SITE,
                                     "--status-period", "0.5", *adapter_args,
                                     *client_args(self.zenoh), stderr_path=self.log)
            self.wait_log("subscribed", 1)
        except BaseException:
            self.close()
            raise

    def lines(self, msg: str) -> list[dict]:
        return [line for line in log_lines(self.log) if line.get("msg") == msg]

    def wait_log(self, msg: str, n: int) -> None:
        wait_until(lambda: len(self.lines(msg)) >= n or self.adapter.poll() is not None,
                   TIMEOUT_S, f"{n} {msg!r} lines of the adapter")
        assert self.adapter.poll() is None, self.log.read_text()[-3000:]

    def wait_events(self, per_source: dict[str, int]) -> None:
        def arrived() -> bool:
            have = self.client.stats().get("per_source", {})
            return all(have.get(source, 0) >= n for source, n in per_source.items())
        wait_until(arrived, TIMEOUT_S, f"{per_source} in the ledger", interval_s=0.2)

    def close(self) -> list[int]:
        """Stop everything (once, the adapter first); the adapter's and the ledger's exit
        codes."""
        try:
            return stop_all(self.adapter, self.ledger)
        finally:
            self.plc.kill()
            self.adapter = self.ledger = None
            self.router.close()

    def __enter__(self) -> Yard:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.router is not None and (self.adapter or self.ledger):
            self.close()


def _events(yard: Yard) -> dict[str, list]:
    """The ledger's events by source: (record, decoded message)."""
    out: dict[str, list] = {}
    for record in yard.client.read(0):
        out.setdefault(record.source, []).append((record, decode_payload(record.type,
                                                                         record.payload)))
    return out


def _kg(tonnes: float) -> float:
    """What a kilogram totaliser reports for ``tonnes`` put on the belt."""
    return round(round(tonnes * 1000) / 1000, 6)


def _encoders(name: str) -> EncoderModel:
    print(f"{name}: seed {SEED} (--seed {SEED} reproduces it)")
    return EncoderModel(rng=np.random.default_rng(SEED))


def _samples(model: EncoderModel, t_ns: int, n: int, rng: np.random.Generator
             ) -> list[tuple[int, float, float, float]]:
    """``n`` encoder readings 100 ms apart from ``t_ns``, of a boom slewing through a cut."""
    out = []
    for k in range(n):
        t = t_ns + k * 100 * MS
        truth = (52.0 + 0.001 * k, -0.4 + 0.01 * k + rng.normal(0, 1e-3), -0.05)
        out.append((t, *model.read(t, *truth)))
    return out


def _send_samples(plc: SimPlc, samples) -> None:
    for t, travel, slew, luff in samples:
        plc("encoder_sample", t_ns=t, travel_m=travel, slew_rad=slew, luff_rad=luff)


# -------------------------------------------------------------------------- end to end


def test_a_server_restart_mid_pass_loses_and_doubles_nothing_over_sign_and_encrypt(tmp_path):
    """Basic256Sha256 SignAndEncrypt with pinned certificates; the PLC's OPC UA server is
    killed while a pass and a cut are open, and the pass ends while it is down.  Every
    joint reading, pass and cut reaches the ledger once, the sequences stay dense in
    one epoch, and the tonnes are what went on the belts."""
    certs = tmp_path / "certs"
    server_cert, server_key = make_application_certificate(certs, "sim-plc", APPLICATION_URI)
    cert, key = make_application_certificate(certs, "plc-adapter", "urn:stockpile:plc-adapter")
    assert oct(key.stat().st_mode & 0o777) == "0o600"
    rng = np.random.default_rng(SEED)
    model = _encoders("restart")
    with Yard(tmp_path, EXAMPLE_MAP, ("--cert", str(server_cert), "--key", str(server_key)),
              ("--cert", str(cert), "--key", str(key), "--server-cert", str(server_cert))) as yard:
        plc = yard.plc
        (subscribed,) = yard.lines("subscribed")
        assert subscribed["security"] == "Basic256Sha256-SignAndEncrypt"
        t = T0 + 1000 * MS
        before = _samples(model, t, 20, rng)
        _send_samples(plc, before[:10])
        t_p1 = before[9][0] + 50 * MS
        plc("pass_started", t_ns=t_p1, pass_id="L1-P1", lot_id="L1", pile_id="P1",
            start_y_m=10.25, end_y_m=190.5)
        t_c1 = t_p1 + 10 * MS
        plan_c1 = dict(travel_m=52.0, luff_rad=-0.05, slew_start_rad=-0.4, slew_end_rad=0.4)
        plc("cut_started", t_ns=t_c1, cut_id="B1-C01", bench_id="B1", pile_id="P1", **plan_c1)
        _send_samples(plc, before[10:])
        yard.wait_events({"bwr1.encoders": 20, "stk1.plc": 1})

        plc.restart()                                   # mid-pass, mid-cut
        t_p1_end = before[-1][0] + 30 * MS
        plc("pass_ended", t_ns=t_p1_end, belt_tonnes=1234.5678)   # while the adapter is away
        yard.wait_log("connection lost", 1)
        yard.wait_log("subscribed", 2)

        after = _samples(model, before[-1][0] + 100 * MS, 20, rng)
        _send_samples(plc, after[:12])
        t_c1_end = after[11][0] + 20 * MS
        plc("cut_ended", t_ns=t_c1_end, belt_tonnes=321.0004, state="travelling")
        t_c2 = t_c1_end + 30 * MS
        plan_c2 = dict(travel_m=52.75, luff_rad=-0.05, slew_start_rad=0.4, slew_end_rad=-0.4)
        plc("cut_started", t_ns=t_c2, cut_id="B1-C02", bench_id="B1", pile_id="P1", **plan_c2)
        _send_samples(plc, after[12:])
        t_c2_end = after[-1][0] + 40 * MS
        plc("cut_ended", t_ns=t_c2_end, belt_tonnes=99.9)
        t_p2 = t_c2_end + 10 * MS
        plc("pass_started", t_ns=t_p2, pass_id="L1-P2", lot_id="L1", pile_id="P1",
            start_y_m=190.5, end_y_m=10.25)
        plc("pass_ended", t_ns=t_p2 + 500 * MS, belt_tonnes=50.0)
        yard.wait_events({"bwr1.encoders": 40, "stk1.plc": 4, "bwr1.plc": 2})
        events = _events(yard)
        gaps, quarantined = yard.client.gaps(), yard.client.quarantine()
        codes = yard.close()
    assert codes == [0, 0]
    assert gaps == [] and quarantined == []
    assert set(events) == {"bwr1.encoders", "bwr1.plc", "stk1.plc"}
    for source, records in events.items():
        assert [r.seq for r, _ in records] == list(range(len(records))), source
        assert len({r.epoch for r, _ in records}) == 1, source

    readings = events["bwr1.encoders"]
    sent = before + after
    assert [timestamp_ns(m.time) for _, m in readings] == [s[0] for s in sent]
    for (_, msg), (_, travel, slew, luff) in zip(readings, sent):
        assert msg.machine_id == "bwr1"
        assert msg.travel_m == pytest.approx(travel, abs=1e-12)
        assert msg.slew_rad == pytest.approx(slew, abs=1e-12)
        assert msg.luff_rad == pytest.approx(luff, abs=1e-12)

    stack = [(r.type, m) for r, m in events["stk1.plc"]]
    assert [(kind, m.pass_id) for kind, m in stack] == [
        ("stack_started", "L1-P1"), ("stack_ended", "L1-P1"),
        ("stack_started", "L1-P2"), ("stack_ended", "L1-P2")]
    started, ended = stack[0][1], stack[1][1]
    assert timestamp_ns(started.time) == t_p1 and timestamp_ns(ended.time) == t_p1_end
    assert (started.lot_id, started.pile_id, started.machine_id) == ("L1", "P1", "stk1")
    assert (started.start_y_m, started.end_y_m, started.pattern) == (10.25, 190.5, 1)
    assert [m.tonnes for kind, m in stack if kind == "stack_ended"] == [_kg(1234.5678), _kg(50.0)]
    assert all(m.bad_samples == 0 for kind, m in stack if kind == "stack_ended")

    cuts = [m for _, m in events["bwr1.plc"]]
    assert [c.cut_id for c in cuts] == ["B1-C01", "B1-C02"]
    for cut, t_start, t_end, plan, tonnes in ((cuts[0], t_c1, t_c1_end, plan_c1, 321.0004),
                                              (cuts[1], t_c2, t_c2_end, plan_c2, 99.9)):
        assert (timestamp_ns(cut.start_time), timestamp_ns(cut.end_time)) == (t_start, t_end)
        assert (cut.travel_m, cut.luff_rad, cut.slew_start_rad, cut.slew_end_rad) == (
            plan["travel_m"], plan["luff_rad"], plan["slew_start_rad"], plan["slew_end_rad"])
        assert cut.tonnes == _kg(tonnes) and cut.bad_samples == 0
        assert (cut.bench_id, cut.pile_id, cut.machine_id) == ("B1", "P1", "bwr1")

    published = {line["source"]: int(line["count"]) for line in yard.lines("published")}
    assert published == {source: len(records) for source, records in events.items()}
    (stopped,) = yard.lines("stopped")
    assert stopped["reason"] == "SIGTERM" and int(stopped["connections"]) == 2
    assert int(stopped["connection_lost"]) == 1 and int(stopped.get("bad_samples", 0)) == 0
    assert int(stopped["stale_samples"]) > 0     # the new subscription's repeats
    assert "Traceback" not in yard.log.read_text()


def test_bad_status_is_counted_not_published_and_a_totaliser_wrap_gives_the_tonnes(tmp_path):
    """Insecure (``--opcua-insecure``) on loopback, events signed with ``--signing-key``.  Bad
    and uncertain encoder samples during a cut are counted and not published, and flag the
    cut; five passes through a 2,000 t totaliser that wraps twice give each pass the tonnes
    put on the belt."""
    keys = make_keys(tmp_path / "keys", "admin", "plc")
    text = EXAMPLE_MAP.read_text()
    assert text.count("rollover = 1000000000") == 2
    map_path = tmp_path / "plc.toml"
    map_path.write_text(text.replace("rollover = 1000000000", "rollover = 2000000"))
    assert load_map(map_path).machines["stk1"].totaliser.rollover == 2_000_000
    rng = np.random.default_rng(SEED + 1)
    model = _encoders("bad status")
    with Yard(tmp_path, map_path, (), ("--opcua-insecure", "--signing-key",
                                       str(tmp_path / "keys" / "plc.sign.key"))) as yard:
        plc = yard.plc
        (subscribed,) = yard.lines("subscribed")
        assert subscribed["security"] == "none"
        # the site's admin key (self-declared: the trust anchor) declares the adapter's key
        for seq, (subject, role) in enumerate(((keys["admin"], "admin"), (keys["plc"], "plc"))):
            declared = key_declared(keys["admin"], subject, role, role, seq, T0)
            yard.router.put(key_expr(SITE, declared.type, declared.source), declared.payload,
                            attachment=encode_attachment(declared.epoch, declared.seq,
                                                         declared.valid_time_ns, declared.signer,
                                                         declared.signature))
        yard.wait_events({declared.source: 2})
        t = T0 + 1000 * MS
        plc("cut_started", t_ns=t, cut_id="B2-C07", bench_id="B2", pile_id="P1", travel_m=60.0,
            luff_rad=-0.1, slew_start_rad=-0.3, slew_end_rad=0.3)
        samples = _samples(model, t + 100 * MS, 30, rng)
        bad = {7: ("travel", "bad"), 8: ("travel", "bad"), 15: ("luff", "uncertain"),
               22: ("slew", "bad")}
        for k, (ts, travel, slew, luff) in enumerate(samples):
            if k not in bad:
                plc("encoder_sample", t_ns=ts, travel_m=travel, slew_rad=slew, luff_rad=luff)
                continue
            joint, status = bad[k]
            for tag in ("travel", "slew", "luff"):   # one sample, one joint not good
                raw = {"travel": travel / 0.0005, "slew": np.degrees(slew) / 0.001,
                       "luff": np.degrees(luff) / 0.01}[tag]
                plc("write", t_ns=ts, machine="bwr1", tag=tag, raw=int(round(raw)),
                    status=status if tag == joint else "good")
        t_end = samples[-1][0] + 50 * MS
        plc("cut_ended", t_ns=t_end, belt_tonnes=12.5)
        # through a 2,000 t counter: the third and the fifth pass wrap it
        belts = [800.0004, 900.25, 700.5, 950.75, 999.9]
        t_pass = t_end + 1000 * MS
        for k, tonnes in enumerate(belts):
            plc("pass_started", t_ns=t_pass, pass_id=f"L2-P{k + 1}", lot_id="L2",
                pile_id="P1", start_y_m=0.0, end_y_m=200.0)
            plc("pass_ended", t_ns=t_pass + 600_000 * MS, belt_tonnes=tonnes)
            t_pass += 700_000 * MS
        good = len(samples) - len(bad)
        yard.wait_events({"bwr1.encoders": good, "bwr1.plc": 1, "stk1.plc": 2 * len(belts)})
        events = _events(yard)
        quarantined = yard.client.quarantine()
        codes = yard.close()
    assert codes == [0, 0] and quarantined == []
    for source in ("bwr1.encoders", "bwr1.plc", "stk1.plc"):
        assert {r.signer for r, _ in events[source]} == {keys["plc"].key_id}, source
    readings = [m for _, m in events["bwr1.encoders"]]
    expected = [s for k, s in enumerate(samples) if k not in bad]
    assert [timestamp_ns(m.time) for m in readings] == [s[0] for s in expected]
    assert [m.slew_rad for m in readings] == pytest.approx([s[2] for s in expected], abs=1e-12)
    (cut,) = [m for _, m in events["bwr1.plc"]]
    assert cut.cut_id == "B2-C07" and cut.bad_samples == len(bad)
    assert cut.tonnes == _kg(12.5)
    ended = [m for r, m in events["stk1.plc"] if r.type == "stack_ended"]
    assert [m.pass_id for m in ended] == [f"L2-P{k + 1}" for k in range(len(belts))]
    assert [m.tonnes for m in ended] == [_kg(b) for b in belts]
    assert all(m.bad_samples == 0 for m in ended)
    counters = yard.lines("stopped")[0]
    assert int(counters["bad_samples"]) == len(bad) == int(counters["withheld_readings"])
    assert int(counters["totaliser_wrapped"]) == 2
    assert int(counters["readings"]) == good == int(
        [line for line in yard.lines("published") if line["source"] == "bwr1.encoders"][0]["count"])
    warned = {(line["machine"], line["tag"]) for line in yard.lines("bad status")}
    assert warned == {("bwr1", "travel"), ("bwr1", "luff"), ("bwr1", "slew")}
    wraps = yard.lines("totaliser wrapped")
    assert len(wraps) == 2 and all(line["machine"] == "stk1" for line in wraps)


def test_a_server_with_another_certificate_is_refused(tmp_path):
    """The adapter pins the server's certificate: a server holding another one is refused
    with one line and exit 2, before anything is subscribed."""
    certs = tmp_path / "certs"
    server_cert, server_key = make_application_certificate(certs, "sim-plc", APPLICATION_URI)
    other, _ = make_application_certificate(certs, "impostor", APPLICATION_URI)
    cert, key = make_application_certificate(certs, "plc-adapter", "urn:stockpile:plc-adapter")
    router, zenoh = open_router()
    plc = SimPlc(tmp_path, free_port(), EXAMPLE_MAP, "--cert", str(server_cert),
                 "--key", str(server_key)).start()
    try:
        run = subprocess.run([PYTHON, "-m", "stockpile.cli", "service", "plc", "--endpoint",
                              plc.endpoint, "--map", str(EXAMPLE_MAP), "--site", SITE,
                              "--cert", str(cert), "--key", str(key), "--server-cert", str(other),
                              *client_args(zenoh)], capture_output=True, text=True,
                             timeout=TIMEOUT_S)
    finally:
        plc.kill()
        router.close()
    assert run.returncode == 2, run.stderr
    errors = [line for line in log_lines_of(run.stderr) if line["level"] == "error"]
    assert len(errors) == 1 and errors[0]["msg"] == "cannot start", run.stderr
    assert "certificate" in errors[0]["error"] and "Traceback" not in run.stderr


def log_lines_of(text: str) -> list[dict]:
    return [parse_logfmt(line) for line in text.splitlines() if line.startswith("ts=")]
