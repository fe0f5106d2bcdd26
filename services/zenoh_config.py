"""Zenoh options every service shares: ``--connect``, ``--listen``, ``--mode``, ``--config``,
``--tls-dir``/``--tls-name`` and ``--insecure``.

Defaults suit one machine: peer mode, multicast scouting off, and no listening unless
``--listen`` says so, so processes find each other only through the endpoints they are
given (``--listen`` on one side, ``--connect`` on the other).

Links are mutual TLS when ``--tls-dir DIR --tls-name NAME`` name a site PKI directory
(``stockpile pki``): ``DIR/ca.pem`` is the only trusted root, and ``DIR/NAME.pem`` /
``DIR/NAME.key`` are this process's certificate (whose common name the router's access
control sees) for the links it opens and the ones it accepts.  Endpoints are then
``tls/HOST:PORT``.  Plain TCP beyond loopback is refused (:class:`InsecureEndpoint`)
unless ``--insecure`` is given.

:func:`add_zenoh_arguments` adds the options to a parser, :class:`ZenohOptions` holds
them (typed, frozen; also as command-line arguments for a child process), and
:func:`zenoh_config` / :func:`config_from_args` make the ``zenoh.Config``.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import zenoh

from common.options import add_duration

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
#: how long before its certificate expires a process starts warning, seconds (30 days)
DEFAULT_CERT_WARN_S = 30 * 86_400.0
#: how long a message under congestion control BLOCK may wait for room in a link's queue
#: before Zenoh closes the link, microseconds (Zenoh's own default: 5 s); set unless a
#: ``--config`` file is given.  docs/operations.md "Backpressure" says why 60 s.
BLOCK_WAIT_BEFORE_CLOSE_US = 60_000_000
BLOCK_WAIT_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
#: link protocols that carry data in the clear
PLAIN_PROTOCOLS = frozenset({"tcp", "udp", "ws", "unixsock-stream", "unixpipe"})


class InsecureEndpoint(ValueError):
    """A plain (unencrypted) endpoint beyond loopback without ``--insecure``, or TLS
    material that is missing."""


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, listen_default: str | None = None) -> None:
    """Add the shared Zenoh options to a command's parser."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=("peer", "client", "router"), default="peer",
                       help="zenoh session mode (default peer)")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tls/127.0.0.1:7447 (repeatable)")
    group.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                       help="endpoint to listen on (repeatable)"
                       + (f"; default {listen_default}" if listen_default else ""))
    group.add_argument("--config", dest="zenoh_config", metavar="FILE",
                       help="a zenoh JSON5 configuration file (the options above override it)")
    group.add_argument("--scouting", action="store_true",
                       help="enable multicast scouting (off by default)")
    group.add_argument("--tls-dir", metavar="DIR", default=os.environ.get("STOCKPILE_TLS_DIR"),
                       help="site PKI directory (stockpile pki): mutual TLS with DIR/ca.pem as "
                       "the only root and DIR/NAME.pem, DIR/NAME.key as this process's "
                       "certificate (default $STOCKPILE_TLS_DIR)")
    group.add_argument("--tls-name", metavar="NAME", default=os.environ.get("STOCKPILE_TLS_NAME"),
                       help="the certificate name in --tls-dir (default $STOCKPILE_TLS_NAME)")
    add_duration(group, "--cert-warn", default=DEFAULT_CERT_WARN_S,
                 help="log a warning this long before this process's certificate expires, "
                 "with a unit, wall time (default 30d)")
    group.add_argument("--insecure", action="store_true",
                       help="allow plain TCP endpoints beyond loopback (no encryption, no "
                       "authentication)")
    parser.set_defaults(_listen_default=listen_default)


@dataclass(frozen=True)
class ZenohOptions:
    """The shared Zenoh options.  Defaults: peer mode, multicast scouting off, no TLS."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    scouting: bool = False
    tls_dir: str | None = None
    tls_name: str | None = None
    insecure: bool = False
    cert_warn_s: float = DEFAULT_CERT_WARN_S

    @property
    def certificate(self) -> Path | None:
        """This process's certificate file (with TLS), else None."""
        if self.tls_dir and self.tls_name:
            return Path(self.tls_dir) / f"{self.tls_name}.pem"
        return None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ZenohOptions:
        return cls(mode=args.mode, connect=tuple(args.connect or ()),
                   listen=tuple(args.listen or ()), config_file=args.zenoh_config,
                   scouting=bool(args.scouting), tls_dir=getattr(args, "tls_dir", None),
                   tls_name=getattr(args, "tls_name", None),
                   insecure=bool(getattr(args, "insecure", False)),
                   cert_warn_s=float(getattr(args, "cert_warn", None) or DEFAULT_CERT_WARN_S))

    def to_config(self) -> zenoh.Config:
        """A ``zenoh.Config`` from these options; :class:`InsecureEndpoint` when they
        would expose plain TCP or name missing TLS files."""
        return zenoh_config(mode=self.mode, connect=self.connect, listen=self.listen,
                            config_file=self.config_file, scouting=self.scouting,
                            tls_dir=self.tls_dir, tls_name=self.tls_name, insecure=self.insecure)

    def to_argv(self) -> list[str]:
        """The same options as command-line arguments (to start a child process)."""
        argv = ["--mode", self.mode]
        for endpoint in self.connect:
            argv += ["--connect", endpoint]
        for endpoint in self.listen:
            argv += ["--listen", endpoint]
        if self.config_file:
            argv += ["--config", self.config_file]
        if self.scouting:
            argv.append("--scouting")
        if self.tls_dir:
            argv += ["--tls-dir", self.tls_dir]
        if self.tls_name:
            argv += ["--tls-name", self.tls_name]
        if self.insecure:
            argv.append("--insecure")
        if self.cert_warn_s != DEFAULT_CERT_WARN_S:
            argv += ["--cert-warn", f"{self.cert_warn_s:g}s"]
        return argv


def split_endpoint(endpoint: str) -> tuple[str, str, str]:
    """``"tls/127.0.0.1:7447#iface=lo"`` -> ``("tls", "127.0.0.1", "7447")``."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    proto, _, address = locator.partition("/")
    host, _, port = address.rpartition(":")
    return proto, host, port


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` (an IP, ``[v6]`` or ``localhost``) is this machine only."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_endpoints(listen: Sequence[str], connect: Sequence[str], *, insecure: bool) -> None:
    """Refuse plain endpoints beyond loopback unless ``insecure`` (:class:`InsecureEndpoint`)."""
    if insecure:
        return
    for flag, endpoints in (("--listen", listen), ("--connect", connect)):
        for endpoint in endpoints:
            proto, host, _port = split_endpoint(endpoint)
            if proto in PLAIN_PROTOCOLS and not is_loopback_host(host):
                raise InsecureEndpoint(
                    f"{flag} {endpoint} is plain {proto} beyond loopback: use tls/{host}:... "
                    "with --tls-dir and --tls-name, or say --insecure")


def tls_files(tls_dir: str, tls_name: str) -> tuple[Path, Path, Path]:
    """``(ca.pem, NAME.pem, NAME.key)`` in a PKI directory; :class:`InsecureEndpoint`
    naming the first that is missing."""
    root = Path(tls_dir)
    files = (root / "ca.pem", root / f"{tls_name}.pem", root / f"{tls_name}.key")
    for path in files:
        if not path.is_file():
            raise InsecureEndpoint(f"TLS: no {path.name} in {root} (make it with stockpile pki)")
    return files


def zenoh_config(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: str | None = None, scouting: bool = False,
                 tls_dir: str | None = None, tls_name: str | None = None,
                 insecure: bool = False) -> zenoh.Config:
    """A zenoh.Config from the shared options (see the module docstring)."""
    check_endpoints(listen if mode != "client" else (), connect, insecure=insecure)
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if mode != "client" and (listen or not config_file):
        # explicit, even when empty: zenoh's own default has a peer listen on every
        # interface (tcp/[::]:0)
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting)))
    if not config_file:
        config.insert_json5(BLOCK_WAIT_KEY, json.dumps(BLOCK_WAIT_BEFORE_CLOSE_US))
    if tls_dir or tls_name:
        if not (tls_dir and tls_name):
            raise InsecureEndpoint("TLS needs both --tls-dir and --tls-name")
        ca, cert, key = tls_files(tls_dir, tls_name)
        tls = {"root_ca_certificate": str(ca), "enable_mtls": True,
               "connect_certificate": str(cert), "connect_private_key": str(key),
               "listen_certificate": str(cert), "listen_private_key": str(key),
               "verify_name_on_connect": True, "close_link_on_expiration": True}
        for name, value in tls.items():
            config.insert_json5(f"transport/link/tls/{name}", json.dumps(value))
    return config


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """A zenoh.Config from parsed shared options."""
    listen = args.listen
    if listen is None:
        default = getattr(args, "_listen_default", None)
        listen = [default] if default else []
    return zenoh_config(mode=args.mode, connect=args.connect, listen=listen,
                        config_file=args.zenoh_config, scouting=args.scouting,
                        tls_dir=getattr(args, "tls_dir", None),
                        tls_name=getattr(args, "tls_name", None),
                        insecure=bool(getattr(args, "insecure", False)))


_LOOPBACK_FOR = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}


def reader_endpoints(config: zenoh.Config) -> tuple[str, ...]:
    """Endpoints through which another process on this machine reaches a session of ``config``.

    Its listen endpoints with a fixed port (an unspecified address becomes loopback),
    then the endpoints it connects to (a router there forwards queries to it).
    """
    mode = json.loads(config.get_json("mode")) or "peer"

    def endpoints(key: str) -> list[str]:
        value = json.loads(config.get_json(key))
        if isinstance(value, dict):
            value = value.get(mode, [])
        return [str(e) for e in value or ()]

    out: list[str] = []
    for endpoint in endpoints("listen/endpoints") if mode != "client" else ():
        proto, host, port = split_endpoint(endpoint)
        if not port or port == "0":
            continue
        out.append(f"{proto}/{_LOOPBACK_FOR.get(host, host)}:{port}")
    out.extend(e for e in endpoints("connect/endpoints") if e not in out)
    return tuple(out)
