"""``stockpile service plc``: the machines' PLC tags over OPC UA in, the yard's events out.

The service reads a tag map (``--map plc.toml``, :mod:`devices.opcua_tags`), connects to
the PLC's OPC UA server (``--endpoint opc.tcp://HOST:PORT/...``) with asyncua, and
subscribes to every mapped node: one subscription, monitored items with sampling
interval 0, the data-change trigger status-value-timestamp (every new sample, also an
unchanged value) and a queue of ``--queue-size`` samples per item, so nothing is dropped
between two publish cycles at the simulator's rates.  It never polls a value.

Samples are buffered and handed to one :class:`devices.opcua_tags.MachineTracker` per
machine in ``SourceTimestamp`` order (the PLC's time of the sample, in UTC; OPC UA
carries it to the microsecond); an instant is handled once a later sample arrives or
``--settle-ms`` after its last sample.  What the trackers return is published through
:class:`~services.service.EventPublisher`: ``joint_reading`` under ``<machine>.encoders``,
``stack_started`` / ``stack_ended`` / ``reclaim_cut`` under ``<machine>.plc`` (the
simulator's sources), signed with ``--signing-key`` when given.  ``--source NAME`` (one of
those sources) makes the service publish that source alone and subscribe to its machine's
tags alone: where each source has its own certificate (the router lets a certificate
publish under its own name only), one service runs per source.

Reconnection: a lost connection (a server restart, a network cut; found by a read of the
server's state every ``PROBE_PERIOD_S``) is logged (``connection lost``), the pending
instants are handled, and the service reconnects with a growing delay and subscribes
again.  The trackers and publishers live on, so a pass or cut that spans the outage is
published once, and the sequences stay dense; the initial values a new subscription
brings that are not newer than what was handled are counted as ``stale_samples``.  A
restart of the service is a new epoch.

Security: by default the server must offer ``Basic256Sha256`` with ``SignAndEncrypt``; the
service presents ``--cert`` / ``--key`` (an application-instance certificate, see
:mod:`security.opcua_certs`) and refuses a server whose certificate is not the one
``--server-cert`` names.  ``--opcua-insecure`` connects without security (anonymous,
SecurityPolicy None); the shared ``--insecure`` is Zenoh's (plain TCP beyond loopback).

Status counters (the periodic ``status`` line and the final ``stopped`` line):

=========================  =============================================================
``published``              events published (all sources)
``samples``                samples handed to the trackers
``readings``               joint readings published
``started`` / ``ended``    passes and cuts opened / closed
``bad_samples``            samples with bad or uncertain status: counted, not used (error)
``withheld_readings``      encoder samples not published while a joint was bad
``stale_samples``          samples not newer than the last handled instant (repeats)
``no_data``                notifications without a SourceTimestamp or with status
                           BadWaitingForInitialData (a tag never written): not samples
``unmapped_states``        state values the map does not name (error)
``missing_ids``            instants in the working state with an empty pass or cut id (error)
``totaliser_wrapped``      totaliser rollovers; ``totaliser_reset``: resets to 0
``connections``            subscriptions made; ``connection_lost``: connections lost
=========================  =============================================================

Exit: 0 on SIGINT/SIGTERM, 2 with one ``cannot start`` line for a bad map, key or
certificate, or when the server's security, certificate or nodes do not fit the map.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.crypto.uacrypto import CertProperties
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from common.options import add_signing_key
from devices.opcua_tags import MapError, MachineTracker, Note, PlcMap, load_map
from security.event_keys import SigningKey, load_signing_key
from security.opcua_certs import application_uri_of, file_format
from services.service import (
    DEFAULT_SITE, DEFAULT_STATUS_PERIOD_S, ServiceRuntime, Stopper, ZenohOptions, log)

__all__ = ["SERVICE", "ERROR_KEYS", "DEFAULT_QUEUE_SIZE", "Config", "add_arguments",
           "config_from_args", "main", "only_source", "source_time_ns"]

SERVICE = "plc"
#: samples each monitored item queues on the server between two publish cycles
DEFAULT_QUEUE_SIZE = 10_000
#: requested publishing interval, ms
PUBLISHING_INTERVAL_MS = 50.0
#: an instant is handled this long after its last sample when no later one arrives, ms
DEFAULT_SETTLE_MS = 250.0
#: how often buffered samples go to the trackers, s
TICK_S = 0.02
#: how often the connection is probed (a read of the server's state), s
PROBE_PERIOD_S = 0.5
#: longest wait of one request (connect, read), s
REQUEST_TIMEOUT_S = 4.0
#: waits between reconnection attempts, s (the last one repeats)
RECONNECT_DELAYS_S = (0.2, 0.5, 1.0, 2.0, 5.0)
#: how long the server keeps a session whose client went silent, ms
SESSION_TIMEOUT_MS = 30_000
#: the adapter's application URI when it presents no certificate (--opcua-insecure)
DEFAULT_APPLICATION_URI = "urn:stockpile:plc-adapter"
ERROR_KEYS = ("bad_samples", "unmapped_states", "missing_ids")
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


class _Fatal(Exception):
    """A problem retrying cannot fix (security, certificate, nodes): exit 2."""


@dataclass(frozen=True)
class Config:
    """Options of one PLC adapter.

    Attributes
    ----------
    endpoint : str
        The PLC's OPC UA endpoint, ``opc.tcp://HOST:PORT[/path]``.
    map_path : str
        The tag map (``plc.toml``).
    site, zenoh, status_period_s
        The shared service options.
    insecure : bool
        Connect without security (anonymous, SecurityPolicy None).
    cert, key, server_cert : str or None
        The adapter's application certificate and key, and the server's certificate it
        pins (all three unless ``insecure``).
    signing_key : str or None
        An Ed25519 key (``security.event_keys``) that signs every published event.
    queue_size : int
        Queue of each monitored item on the server, samples.
    settle_ms : float
        How long an instant waits for more samples of its time, ms.
    source : str or None
        Publish only this source (``<machine>.plc`` or ``<machine>.encoders``) and subscribe
        only to its machine's tags; None: every source of every machine in the map.
    """

    endpoint: str
    map_path: str
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    insecure: bool = False
    cert: str | None = None
    key: str | None = None
    server_cert: str | None = None
    signing_key: str | None = None
    queue_size: int = DEFAULT_QUEUE_SIZE
    settle_ms: float = DEFAULT_SETTLE_MS
    source: str | None = None

    def __post_init__(self) -> None:
        if not self.endpoint.startswith("opc.tcp://"):
            raise ValueError(f"the endpoint is opc.tcp://HOST:PORT[/path], got {self.endpoint!r}")
        missing = [flag for flag, value in (("--cert", self.cert), ("--key", self.key),
                                            ("--server-cert", self.server_cert)) if not value]
        if not self.insecure and missing:
            raise ValueError(f"Basic256Sha256 SignAndEncrypt needs {', '.join(missing)} "
                             "(--opcua-insecure connects without security)")
        if not isinstance(self.queue_size, int) or self.queue_size < 1:
            raise ValueError(f"queue size must be a positive integer, got {self.queue_size!r}")
        if not self.settle_ms > 0:
            raise ValueError(f"settle must be > 0 ms, got {self.settle_ms}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the PLC adapter's own options (the shared ones come from ``service_cli``)."""
    parser.add_argument("--endpoint", required=True, metavar="URL",
                        help="the PLC's OPC UA endpoint, opc.tcp://HOST:PORT[/path]")
    parser.add_argument("--map", required=True, dest="map_path", metavar="FILE",
                        help="the tag map (plc.toml, see docs/integration.md)")
    parser.add_argument("--cert", metavar="FILE",
                        help="this adapter's application certificate (DER or PEM)")
    parser.add_argument("--key", metavar="FILE", help="its private key (PEM)")
    parser.add_argument("--server-cert", metavar="FILE",
                        help="the server's certificate: connect only to the server holding it")
    parser.add_argument("--opcua-insecure", action="store_true",
                        help="connect without security (anonymous, SecurityPolicy None)")
    add_signing_key(parser, what="event")
    parser.add_argument("--queue-size", type=int, default=DEFAULT_QUEUE_SIZE, metavar="N",
                        help=f"server-side queue per monitored item (default {DEFAULT_QUEUE_SIZE})")
    parser.add_argument("--settle-ms", type=float, default=DEFAULT_SETTLE_MS, metavar="MS",
                        help="wait for more samples of one time this long, ms (default "
                        f"{DEFAULT_SETTLE_MS:g})")
    parser.add_argument("--source", metavar="NAME",
                        help="publish only this source, MACHINE.plc or MACHINE.encoders, and "
                        "subscribe only to that machine's tags (default: every source)")


def config_from_args(args: argparse.Namespace) -> Config:
    """A :class:`Config` from parsed arguments (raises ValueError on bad values)."""
    return Config(endpoint=args.endpoint, map_path=args.map_path, site=args.site,
                  zenoh=ZenohOptions.from_args(args), status_period_s=args.status_period,
                  insecure=args.opcua_insecure, cert=args.cert, key=args.key,
                  server_cert=args.server_cert, signing_key=args.signing_key,
                  queue_size=args.queue_size, settle_ms=args.settle_ms, source=args.source)


def source_time_ns(stamp: datetime) -> int:
    """UTC ns of an OPC UA timestamp (a naive datetime is UTC)."""
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    delta = stamp - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


def _der(path: str) -> bytes:
    """A certificate file (DER or PEM) as DER bytes."""
    data = Path(path).read_bytes()
    try:
        if data.lstrip().startswith(b"-----"):
            return x509.load_pem_x509_certificate(data).public_bytes(serialization.Encoding.DER)
        x509.load_der_x509_certificate(data)
    except ValueError:
        raise ValueError(f"{path}: not a DER or PEM certificate") from None
    return data


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


# -- the adapter -----------------------------------------------------------------------------


class _Adapter:
    """Connections, the subscription, the trackers and the publishers of one run."""

    def __init__(self, config: Config, plc_map: PlcMap, runtime: ServiceRuntime,
                 signing_key: SigningKey | None, application_uri: str,
                 server_der: bytes | None) -> None:
        self.config, self.map, self.runtime = config, plc_map, runtime
        self.status = runtime.status
        self.application_uri, self.server_der = application_uri, server_der
        self.trackers = {mid: MachineTracker(m) for mid, m in plc_map.machines.items()}
        self.publishers = {}
        for mid, m in plc_map.machines.items():
            if config.source in (None, f"{mid}.plc"):
                plc = runtime.publisher(f"{mid}.plc", signing_key=signing_key)
                plc.declare(*(("stack_started", "stack_ended") if m.kind == "stacker"
                              else ("reclaim_cut",)))
                self.publishers[(mid, "plc")] = plc
            if m.encoders and config.source in (None, f"{mid}.encoders"):
                encoders = runtime.publisher(f"{mid}.encoders", signing_key=signing_key)
                encoders.declare("joint_reading")
                self.publishers[(mid, "encoders")] = encoders
        self.tags = list(plc_map.nodes().items())   # (node, (machine, tag)); handle = index + 1
        self._inbox: list[tuple[int, str, str, Any, bool]] = []
        self._last_arrival = {mid: 0.0 for mid in plc_map.machines}
        self._seen: dict[str, int] = {}
        self._bad_tags: set[tuple[str, str]] = set()

    # the subscription handler (called on the event loop, one call per sample)
    def datachange_notification(self, node, value, data) -> None:
        item = data.monitored_item
        machine, tag = self.tags[item.ClientHandle - 1][1]
        dv = item.Value
        if (dv is None or dv.SourceTimestamp is None or (
                dv.StatusCode is not None
                and dv.StatusCode.value == ua.StatusCodes.BadWaitingForInitialData)):
            self.status.add("no_data")     # a tag never written: not a sample
            return
        good = dv.StatusCode is None or dv.StatusCode.is_good()
        if not good and (machine, tag) not in self._bad_tags:
            self._bad_tags.add((machine, tag))
            self.runtime.log("bad status", level="warning", machine=machine, tag=tag,
                             status=dv.StatusCode.name)
        elif good:
            self._bad_tags.discard((machine, tag))
        raw = dv.Value.Value if dv.Value is not None else None
        self._inbox.append((source_time_ns(dv.SourceTimestamp), machine, tag, raw, good))
        self._last_arrival[machine] = time.monotonic()

    def status_change_notification(self, status) -> None:
        code = getattr(status, "Status", None)
        self.runtime.log("subscription status", level="warning",
                         status=getattr(code, "name", None) or str(status))

    def _emit(self, outputs: list, machine: str) -> None:
        for out in outputs:
            if isinstance(out, Note):
                self.runtime.log(out.msg, level=out.level, **out.fields)
                continue
            publisher = self.publishers.get((machine, out.stream))
            if publisher is not None:   # None: a source this service does not publish
                publisher.publish(out.message)
                self.status.add("published")

    def _sync_counters(self) -> None:
        totals: dict[str, int] = {}
        for tracker in self.trackers.values():
            for name, value in tracker.counters.items():
                totals[name] = totals.get(name, 0) + value
        for name, value in totals.items():
            grown = value - self._seen.get(name, 0)
            if grown:
                self.status.add(name, grown)
                self._seen[name] = value

    def drain(self, *, settle: bool = True) -> None:
        """Hand the buffered samples to the trackers in source-time order; handle the
        instants that waited ``settle_ms`` (all of them with ``settle=False``)."""
        batch, self._inbox = self._inbox, []
        batch.sort(key=lambda s: s[0])   # stable: one tag's samples keep their order
        for t_ns, machine, tag, raw, good in batch:
            self._emit(self.trackers[machine].feed(t_ns, tag, raw, good), machine)
        now = time.monotonic()
        for machine, tracker in self.trackers.items():
            quiet_s = now - self._last_arrival[machine]
            if tracker.pending_ns is not None and (not settle
                                                   or quiet_s * 1000 >= self.config.settle_ms):
                self._emit(tracker.flush(), machine)
        self._sync_counters()

    # -- connecting ---------------------------------------------------------------------------

    async def _connect(self) -> Client:
        config = self.config
        client = Client(config.endpoint, timeout=REQUEST_TIMEOUT_S)
        client.application_uri = self.application_uri
        client.name = client.description = "stockpile PLC adapter"
        # a session left behind by a cut connection is dropped by the server soon after
        client.session_timeout = SESSION_TIMEOUT_MS
        if not config.insecure:
            endpoints = await asyncio.wait_for(client.connect_and_get_server_endpoints(),
                                               REQUEST_TIMEOUT_S)
            secure = [e for e in endpoints
                      if e.SecurityPolicyUri == SecurityPolicyBasic256Sha256.URI
                      and e.SecurityMode == ua.MessageSecurityMode.SignAndEncrypt]
            if not secure:
                raise _Fatal("the server does not offer Basic256Sha256 SignAndEncrypt "
                             "(--opcua-insecure connects without security)")
            if not bytes(secure[0].ServerCertificate or b"").startswith(self.server_der):
                raise _Fatal(f"the server's certificate is not the one {config.server_cert} holds")
            files = {name: CertProperties(path, extension=file_format(path)) for name, path in (
                ("certificate", config.cert), ("private_key", config.key),
                ("server_certificate", config.server_cert))}
            await client.set_security(SecurityPolicyBasic256Sha256,
                                      mode=ua.MessageSecurityMode.SignAndEncrypt, **files)
        await asyncio.wait_for(client.connect(), REQUEST_TIMEOUT_S)
        return client

    async def _node_ids(self, client: Client) -> list[ua.NodeId]:
        namespaces = await client.get_namespace_array()
        ids = []
        for ref, (machine, tag) in self.tags:
            index = ref.namespace_index
            if ref.namespace_uri is not None:
                if ref.namespace_uri not in namespaces:
                    raise _Fatal(f"machines.{machine}.{tag}: the server has no namespace "
                                 f"{ref.namespace_uri}")
                index = namespaces.index(ref.namespace_uri)
            ident: Any = int(ref.identifier) if ref.kind == "i" else ref.identifier
            if ref.kind in ("g", "b"):
                ident = ua.NodeId.from_string(f"ns={index};{ref.kind}={ref.identifier}").Identifier
            ids.append(ua.NodeId(ident, index))
        return ids

    async def _subscribe(self, client: Client) -> None:
        params = ua.CreateSubscriptionParameters()
        params.RequestedPublishingInterval = PUBLISHING_INTERVAL_MS
        params.RequestedLifetimeCount = 10_000
        params.RequestedMaxKeepAliveCount = 20
        params.MaxNotificationsPerPublish = 0          # no limit
        params.PublishingEnabled = True
        params.Priority = 0
        subscription = await client.create_subscription(params, self)
        requests = []
        for handle, nid in enumerate(await self._node_ids(client), 1):
            item = ua.ReadValueId()
            item.NodeId, item.AttributeId = nid, ua.AttributeIds.Value
            monitoring = ua.MonitoringParameters()
            monitoring.ClientHandle = handle
            monitoring.SamplingInterval = 0.0
            monitoring.QueueSize = self.config.queue_size
            monitoring.DiscardOldest = True
            trigger = ua.DataChangeFilter()
            trigger.Trigger = ua.DataChangeTrigger.StatusValueTimestamp
            monitoring.Filter = trigger
            request = ua.MonitoredItemCreateRequest()
            request.ItemToMonitor, request.MonitoringMode = item, ua.MonitoringMode.Reporting
            request.RequestedParameters = monitoring
            requests.append(request)
        results = await subscription.create_monitored_items(requests)
        for (ref, (machine, tag)), result in zip(self.tags, results):
            if isinstance(result, ua.StatusCode):
                raise _Fatal(f"machines.{machine}.{tag}: cannot monitor {ref}: {result.name}")

    async def _follow(self, client: Client) -> None:
        """Feed the trackers until a stop (returns) or a lost connection (raises)."""
        stopper, next_probe = self.runtime.stopper, time.monotonic() + PROBE_PERIOD_S
        while not stopper.is_set():
            await asyncio.sleep(TICK_S)
            self.drain()
            if time.monotonic() >= next_probe:
                await asyncio.wait_for(client.nodes.server_state.read_value(), REQUEST_TIMEOUT_S)
                next_probe = time.monotonic() + PROBE_PERIOD_S

    async def run(self) -> int:
        """Connect, subscribe and follow until a stop, reconnecting after every loss."""
        stopper, attempt, connection = self.runtime.stopper, 0, 0
        while not stopper.is_set():
            client = None
            try:
                client = await self._connect()
                await self._subscribe(client)
                connection, attempt = connection + 1, 0
                self.status.add("connections")
                self.runtime.log("subscribed", endpoint=self.config.endpoint,
                                 connection=connection, items=len(self.tags),
                                 security="none" if self.config.insecure
                                 else "Basic256Sha256-SignAndEncrypt")
                self.runtime.announce()
                await self._follow(client)
            except _Fatal as exc:
                self.runtime.log("cannot start", level="error", error=str(exc))
                return 2
            except Exception as exc:  # noqa: BLE001 - whatever broke the link, retry
                what = "connection lost" if client is not None and connection else "cannot connect"
                if client is not None and connection:
                    self.status.add("connection_lost")
                if attempt == 0 or what == "connection lost":
                    self.runtime.log(what, level="warning", endpoint=self.config.endpoint,
                                     error=f"{type(exc).__name__}: {_first_line(exc)}")
                await self._wait(RECONNECT_DELAYS_S[min(attempt, len(RECONNECT_DELAYS_S) - 1)])
                attempt += 1
            finally:
                self.drain(settle=False)   # what arrived is handled before anything new
                if client is not None:
                    await _disconnect(client)
        self.drain(settle=False)
        return 0

    async def _wait(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while not self.runtime.stopper.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(min(TICK_S * 5, max(0.0, deadline - time.monotonic())))


async def _disconnect(client: Client) -> None:
    try:
        await asyncio.wait_for(client.disconnect(), REQUEST_TIMEOUT_S)
    except Exception:  # noqa: BLE001 - the connection may be gone already
        pass


def only_source(plc_map: PlcMap, source: str | None) -> PlcMap:
    """The map reduced to the machine of ``source`` (``<machine>.plc`` or
    ``<machine>.encoders``; None: the whole map); ValueError when the map has no such
    source."""
    if source is None:
        return plc_map
    machine, _, stream = source.rpartition(".")
    m = plc_map.machines.get(machine)
    if m is None or stream not in ("plc", "encoders") or (stream == "encoders"
                                                          and not m.encoders):
        raise ValueError(f"--source {source}: the map has no such source (MACHINE.plc, or "
                         "MACHINE.encoders of a machine with encoders)")
    return replace(plc_map, machines={machine: m})


def _prepare(config: Config) -> tuple[PlcMap, SigningKey | None, str, bytes | None]:
    """The map, the signing key, this adapter's application URI and the pinned server
    certificate (DER); MapError / ValueError / OSError with one line when one is bad."""
    plc_map = only_source(load_map(config.map_path), config.source)
    signing_key = load_signing_key(config.signing_key) if config.signing_key else None
    if config.insecure:
        return plc_map, signing_key, DEFAULT_APPLICATION_URI, None
    _der(config.cert)
    if not Path(config.key).is_file():
        raise ValueError(f"{config.key}: no such key file")
    return plc_map, signing_key, application_uri_of(config.cert), _der(config.server_cert)


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the PLC adapter until SIGINT/SIGTERM (exit 0); 2 when it cannot start."""
    stopper = stopper or Stopper()   # first: a SIGTERM during start-up stops cleanly
    # asyncua logs tracebacks for every dropped connection: the service reports them itself
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    try:
        plc_map, signing_key, uri, server_der = _prepare(config)
    except (MapError, ValueError, OSError) as exc:
        log(SERVICE, "cannot start", level="error", error=_first_line(exc))
        return 2
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.source or SERVICE,
                             status_period_s=config.status_period_s, stopper=stopper)
    try:
        runtime.open(error_keys=ERROR_KEYS, announce=False)
    except OSError as exc:
        log(SERVICE, "cannot open zenoh session", level="error", error=_first_line(exc))
        return 2
    with runtime:
        adapter = _Adapter(config, plc_map, runtime, signing_key, uri, server_der)
        runtime.log("connecting", endpoint=config.endpoint, map=config.map_path,
                    machines=",".join(plc_map.machines), signed=signing_key is not None)
        return asyncio.run(adapter.run())
