"""The simulated yard's machine PLCs as an OPC UA server (asyncua), in a thread of its own.

:class:`PlcServer` serves every tag a PLC map (:mod:`devices.opcua_tags`, e.g.
``docs/plc.example.toml``) names, as a real machine PLC would: raw encoder counts (Int64:
the values :meth:`sim.encoders.EncoderModel.read` gives, quantisation and drift included,
as counts of the map's scale and offset), the machine state (Int32, the map's raw state
value), the active pass, cut, bench, lot and pile ids (String), the plan values (Double,
exact: a pass's start and end, a cut's travel, luff and slew range) and the belt-scale
totaliser (UInt32), which accumulates whole counts and wraps at the map's ``rollover``.
Every write carries the site time as its ``SourceTimestamp`` (OPC UA keeps it to the
microsecond); a tag that was never written has status ``BadWaitingForInitialData`` and no timestamp.

The simulator's runner drives it with site times (UTC ns), one call per thing that
happens (each call's writes land together, before the server publishes)::

    server = PlcServer(load_map("docs/plc.example.toml"), port=4840).start()
    server.encoder_sample(t_ns, travel_m, slew_rad, luff_rad)          # the reclaimer
    server.pass_started(t_ns, pass_id="P001", lot_id="L01", pile_id="pile-a",
                        start_y_m=10.0, end_y_m=190.0)                   # the stacker
    server.pass_ended(t_ns, belt_tonnes=1234.5)
    server.cut_started(t_ns, cut_id="B1-C01", bench_id="B1", pile_id="pile-a",
                       travel_m=52.0, luff_rad=-0.1, slew_start_rad=-0.4, slew_end_rad=0.4)
    server.cut_ended(t_ns, belt_tonnes=310.2)
    server.stop()

``machine=`` picks the machine when the map has several of a kind (default: the map's
first reclaimer for encoders and cuts, its first stacker for passes).  :meth:`write`
writes one raw tag with any status (``good``, ``uncertain``, ``bad``), for tests.

Security: given a certificate and key, the server offers only ``Basic256Sha256`` with
``SignAndEncrypt`` (``allow_none=True`` adds the insecure endpoint); without them only
the insecure endpoint, and then only on a loopback address.  It accepts any client
certificate (a simulator; the adapter is the side that pins its peer's).

Standalone (tests run it as a process): ``python -m sim.opcua_server --map FILE --port P
[--cert DER --key PEM]`` prints ``listening <endpoint>``, then reads one JSON object a
line on stdin, ``{"op": "<method>", ...keyword arguments}``, calls that method and prints
``ok <n>`` (or ``error <n> <reason>``); end of input stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import ipaddress
import json
import logging
import sys
import threading
import uuid
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from devices.opcua_tags import MapError, MachineMap, NodeRef, PlcMap, load_map
from security.opcua_certs import file_format

__all__ = ["APPLICATION_URI", "STATUS", "PlcServer", "node_id", "site_datetime", "main"]

#: the simulated PLC's OPC UA application URI (its certificate carries it)
APPLICATION_URI = "urn:stockpile:sim:plc"
#: status names :meth:`PlcServer.write` takes -> OPC UA status codes
STATUS = {"good": ua.StatusCodes.Good, "uncertain": ua.StatusCodes.UncertainLastUsableValue,
          "bad": ua.StatusCodes.BadSensorFailure}
#: longest wait for the server thread to start or answer a call, seconds
CALL_TIMEOUT_S = 30.0
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)
_RUNNER_OPS = ("encoder_sample", "pass_started", "pass_ended", "cut_started", "cut_ended",
               "set_state", "write")


def site_datetime(t_ns: int) -> datetime:
    """A site time (UTC ns) as the UTC datetime OPC UA carries (whole microseconds, floor)."""
    return _EPOCH + timedelta(microseconds=int(t_ns) // 1000)


def node_id(ref: NodeRef, namespaces: dict[str, int]) -> ua.NodeId:
    """The asyncua node id of a map's node (``nsu=`` through ``namespaces``: URI -> index)."""
    index = ref.namespace_index
    if ref.namespace_uri is not None:
        index = namespaces[ref.namespace_uri]
    ident: Any = ref.identifier
    if ref.kind == "i":
        ident = int(ident)
    elif ref.kind == "g":
        ident = uuid.UUID(ident)
    elif ref.kind == "b":
        ident = base64.b64decode(ident)
    return ua.NodeId(ident, index)


def _loopback(host: str) -> bool:
    try:
        return host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _variant_type(machine: MachineMap, tag: str) -> ua.VariantType:
    if tag in machine.ids:
        return ua.VariantType.String
    if tag == "state":
        return ua.VariantType.Int32
    if tag.startswith("plan."):
        return ua.VariantType.Double
    if tag == "totaliser":
        rollover = machine.totaliser.rollover
        return ua.VariantType.UInt32 if 0 < rollover <= 2 ** 32 else ua.VariantType.UInt64
    return ua.VariantType.Int64


class PlcServer:
    """The PLCs of a map's machines, served over OPC UA from a background thread.

    Parameters
    ----------
    plc_map : PlcMap
        The machines and tags to serve.
    host, port : str, int
        Where to listen (``opc.tcp://host:port/stockpile/plc``).
    certificate, private_key : str or Path, optional
        The server's application certificate (DER or PEM, URI :data:`APPLICATION_URI` in
        its subjectAltName) and key: offer ``Basic256Sha256`` ``SignAndEncrypt``.
    allow_none : bool
        Also offer the insecure endpoint when a certificate is given.
    start_ns : int, optional
        Site time (UTC ns) of the PLCs' state at start: every machine ``idle`` with empty
        ids and its totaliser at 0.  Without it every tag waits for its first write.
    """

    def __init__(self, plc_map: PlcMap, *, host: str = "127.0.0.1", port: int = 4840,
                 certificate: str | Path | None = None, private_key: str | Path | None = None,
                 allow_none: bool = False, start_ns: int | None = None) -> None:
        if (certificate is None) != (private_key is None):
            raise ValueError("give both a certificate and its private key, or neither")
        if certificate is None and not _loopback(host):
            raise ValueError(f"without a certificate the server listens on loopback only, "
                             f"not {host}")
        self.map, self.host, self.port = plc_map, host, int(port)
        self.certificate, self.private_key, self.allow_none = certificate, private_key, allow_none
        self.start_ns = start_ns
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        self._server: Server | None = None
        self._nodes: dict[tuple[str, str], tuple[ua.NodeId, ua.VariantType]] = {}
        self._totals: dict[str, int] = {m: 0 for m in plc_map.machines}

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}/stockpile/plc"

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> PlcServer:
        """Start serving; returns once the server listens (raises what stopped it)."""
        # asyncua logs a line per request at INFO: only its warnings concern the simulator
        logging.getLogger("asyncua").setLevel(max(logging.WARNING,
                                                  logging.getLogger("asyncua").level))
        self._thread = threading.Thread(target=self._run, name="opcua-plc-server", daemon=True)
        self._thread.start()
        if not self._ready.wait(CALL_TIMEOUT_S):
            raise TimeoutError(f"the OPC UA server did not start in {CALL_TIMEOUT_S:g} s")
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        """Stop serving and join the thread."""
        if (self._thread is not None and self._thread.is_alive() and self._loop is not None
                and self._stop is not None):
            self._loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(CALL_TIMEOUT_S)

    def __enter__(self) -> PlcServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._loop.run_until_complete(self._serve())
        except BaseException as exc:  # noqa: BLE001 - handed to start()
            self._error = exc
        finally:
            self._ready.set()
            self._loop.close()

    async def _serve(self) -> None:
        self._stop = asyncio.Event()
        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("stockpile simulated machine PLCs")
        await server.set_application_uri(APPLICATION_URI)
        policies = []
        if self.certificate is not None:
            await server.load_certificate(str(self.certificate),
                                          format=file_format(self.certificate))
            await server.load_private_key(str(self.private_key),
                                          format=file_format(self.private_key))
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
        if self.certificate is None or self.allow_none:
            policies.append(ua.SecurityPolicyType.NoSecurity)
        server.set_security_policy(policies)
        await self._add_nodes(server)
        self._server = server
        if self.start_ns is not None:
            await self._write_now(self._datavalues(self.start_ns, self._initial_values()))
        async with server:
            self._ready.set()
            await self._stop.wait()

    async def _add_nodes(self, server: Server) -> None:
        uris = {ref.namespace_uri for ref in self.map.nodes() if ref.namespace_uri is not None}
        namespaces = {uri: await server.register_namespace(uri) for uri in sorted(uris)}
        default_ns = (next(iter(namespaces.values())) if namespaces
                      else await server.register_namespace("urn:stockpile:sim"))
        for machine in self.map.machines.values():
            folder = await server.nodes.objects.add_object(default_ns, machine.machine_id)
            for tag, ref in machine.tags().items():
                nid, vtype = node_id(ref, namespaces), _variant_type(machine, tag)
                initial = "" if vtype == ua.VariantType.String else 0
                await folder.add_variable(nid, f"{machine.machine_id}.{tag}", initial,
                                          varianttype=vtype)
                await server.write_attribute_value(nid, ua.DataValue(
                    Value=ua.Variant(None, ua.VariantType.Null),
                    StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
                self._nodes[(machine.machine_id, tag)] = (nid, vtype)

    # -- writing ---------------------------------------------------------------------------

    def _initial_values(self) -> list[tuple[str, str, Any, str]]:
        """``(machine, tag, raw, status)`` of every machine at start: idle, no ids, 0 t."""
        values = []
        for m in self.map.machines.values():
            values += [(m.machine_id, tag, "", "good") for tag in m.ids]
            if "idle" in m.state_values.values():
                values.append((m.machine_id, "state", int(m.state_raw("idle")), "good"))
            if m.totaliser is not None:
                values.append((m.machine_id, "totaliser", 0, "good"))
        return values

    def _datavalues(self, t_ns: int, values: list[tuple[str, str, Any, str]]) -> list:
        """``(node id, DataValue)`` of ``(machine, tag, raw, status)`` at site time ``t_ns``."""
        writes = []
        stamp = site_datetime(t_ns)
        for machine, tag, raw, status in values:
            try:
                nid, vtype = self._nodes[(machine, tag)]
            except KeyError:
                raise ValueError(f"the map has no tag {tag!r} on machine {machine!r}") from None
            if status not in STATUS:
                raise ValueError(f"status must be one of {', '.join(STATUS)}, got {status!r}")
            value = (ua.Variant(raw, vtype) if status != "bad"
                     else ua.Variant(None, ua.VariantType.Null))
            writes.append((nid, ua.DataValue(Value=value, StatusCode=ua.StatusCode(STATUS[status]),
                                             SourceTimestamp=stamp,
                                             ServerTimestamp=datetime.now(timezone.utc))))
        return writes

    def _write_all(self, t_ns: int, machine: str, values: list[tuple[str, Any, str]]) -> None:
        """Write ``(tag, raw value, status)`` of ``machine`` at ``t_ns``, all before the
        server publishes again."""
        if self._loop is None or self._server is None:
            raise RuntimeError("the OPC UA server is not running (start() it)")
        writes = self._datavalues(t_ns, [(machine, *value) for value in values])
        future = asyncio.run_coroutine_threadsafe(self._write_now(writes), self._loop)
        future.result(CALL_TIMEOUT_S)

    async def _write_now(self, writes: list) -> None:
        for nid, datavalue in writes:
            await self._server.write_attribute_value(nid, datavalue)

    def _machine(self, machine: str | None, kind: str) -> MachineMap:
        if machine is not None:
            try:
                return self.map.machines[machine]
            except KeyError:
                raise ValueError(f"the map has no machine {machine!r}") from None
        for m in self.map.machines.values():
            if m.kind == kind:
                return m
        raise ValueError(f"the map has no {kind}")

    def write(self, t_ns: int, machine: str, tag: str, raw: Any = None,
              status: str = "good") -> None:
        """Write one raw tag value (``status`` ``good``, ``uncertain`` or ``bad``; a bad
        value is served as null, as OPC UA requires)."""
        self._write_all(t_ns, machine, [(tag, raw, status)])

    def encoder_sample(self, t_ns: int, travel_m: float, slew_rad: float, luff_rad: float, *,
                       machine: str | None = None) -> None:
        """One reading of the joint encoders (m, rad, rad), as raw counts."""
        m = self._machine(machine, "reclaimer")
        values = [(tag, m.encoders[tag].raw(v), "good")
                  for tag, v in (("travel", travel_m), ("slew", slew_rad), ("luff", luff_rad))]
        self._write_all(t_ns, m.machine_id, values)

    def set_state(self, t_ns: int, state: str, *, machine: str) -> None:
        """Set a machine's state (``idle``, ``travelling``, ``fault`` ...)."""
        m = self._machine(machine, "")
        self._write_all(t_ns, m.machine_id, [("state", int(m.state_raw(state)), "good")])

    def _add_tonnes(self, m: MachineMap, belt_tonnes: float) -> tuple[str, int, str]:
        t = m.totaliser
        counts = self._totals[m.machine_id] + round(float(belt_tonnes) / t.tonnes_per_count)
        self._totals[m.machine_id] = counts % t.rollover if t.rollover else counts
        return ("totaliser", self._totals[m.machine_id], "good")

    def _plan(self, m: MachineMap, values: dict[str, float]) -> list[tuple[str, Any, str]]:
        return [(f"plan.{name}", m.plan[name].raw(v, whole=False), "good")
                for name, v in values.items() if name in m.plan]

    def pass_started(self, t_ns: int, *, pass_id: str, lot_id: str, pile_id: str,
                     start_y_m: float, end_y_m: float, machine: str | None = None) -> None:
        """A stacking pass starts: its ids and ends, then the state ``stacking``."""
        m = self._machine(machine, "stacker")
        values = [("pass_id", pass_id, "good"), ("lot_id", lot_id, "good"),
                  ("pile_id", pile_id, "good")]
        values += self._plan(m, {"start_y": start_y_m, "end_y": end_y_m})
        values.append(("state", int(m.state_raw("stacking")), "good"))
        self._write_all(t_ns, m.machine_id, values)

    def pass_ended(self, t_ns: int, belt_tonnes: float, *, state: str = "idle",
                   machine: str | None = None) -> None:
        """A stacking pass ends: the totaliser counts ``belt_tonnes`` more, then the state
        becomes ``state``."""
        self._activity_ended(t_ns, belt_tonnes, state, self._machine(machine, "stacker"))

    def cut_started(self, t_ns: int, *, cut_id: str, bench_id: str, pile_id: str,
                    travel_m: float = 0.0, luff_rad: float = 0.0, slew_start_rad: float = 0.0,
                    slew_end_rad: float = 0.0, machine: str | None = None) -> None:
        """A reclaim cut starts: its ids and plan (when the map has one), then ``reclaiming``."""
        m = self._machine(machine, "reclaimer")
        values = [("cut_id", cut_id, "good"), ("bench_id", bench_id, "good"),
                  ("pile_id", pile_id, "good")]
        values += self._plan(m, {"travel": travel_m, "luff": luff_rad,
                                 "slew_start": slew_start_rad, "slew_end": slew_end_rad})
        values.append(("state", int(m.state_raw("reclaiming")), "good"))
        self._write_all(t_ns, m.machine_id, values)

    def cut_ended(self, t_ns: int, belt_tonnes: float, *, state: str = "idle",
                  machine: str | None = None) -> None:
        """A reclaim cut ends: the totaliser counts ``belt_tonnes`` more, then ``state``."""
        self._activity_ended(t_ns, belt_tonnes, state, self._machine(machine, "reclaimer"))

    def _activity_ended(self, t_ns: int, belt_tonnes: float, state: str, m: MachineMap) -> None:
        values = [self._add_tonnes(m, belt_tonnes)] if m.totaliser is not None else []
        values.append(("state", int(m.state_raw(state)), "good"))
        self._write_all(t_ns, m.machine_id, values)

    def totaliser_counts(self, machine: str) -> int:
        """The totaliser's raw value as served now."""
        return self._totals[machine]


# -- standalone ------------------------------------------------------------------------------


def _serve_stdin(server: PlcServer, lines, out) -> None:
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            command = json.loads(line)
            op = command.pop("op")
            if op not in _RUNNER_OPS:
                raise ValueError(f"unknown op {op!r}")
            getattr(server, op)(**command)
        except Exception as exc:  # noqa: BLE001 - one bad command is reported, not fatal
            out.write(f"error {n} {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}\n")
        else:
            out.write(f"ok {n}\n")
        out.flush()


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.opcua_server``: serve a map's machines, driven by JSON lines on stdin."""
    p = argparse.ArgumentParser(prog="python -m sim.opcua_server",
                                description=__doc__.splitlines()[0])
    p.add_argument("--map", required=True, help="the PLC map (plc.toml)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default loopback)")
    p.add_argument("--port", type=int, default=4840, help="TCP port (default 4840)")
    p.add_argument("--cert", default=None, help="server application certificate (DER or PEM)")
    p.add_argument("--key", default=None, help="its private key (PEM)")
    p.add_argument("--allow-none", action="store_true",
                   help="with --cert, also offer the insecure endpoint")
    p.add_argument("--start-ns", type=int, default=None, metavar="NS",
                   help="site time (UTC ns) of the start: machines idle, totalisers at 0")
    args = p.parse_args(argv)
    try:
        server = PlcServer(load_map(args.map), host=args.host, port=args.port,
                           certificate=args.cert, private_key=args.key,
                           allow_none=args.allow_none, start_ns=args.start_ns).start()
    except (MapError, ValueError, OSError, TimeoutError) as exc:
        print(f"error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return 2
    print(f"listening {server.endpoint}", flush=True)
    try:
        _serve_stdin(server, sys.stdin, sys.stdout)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
