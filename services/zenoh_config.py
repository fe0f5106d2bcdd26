"""Zenoh options every service shares: ``--connect``, ``--listen``, ``--mode``, ``--config``.

Defaults suit one machine: peer mode, multicast scouting off, so processes find each
other only through the endpoints they are given (``--listen`` on one side,
``--connect`` on the other).  :func:`add_zenoh_arguments` adds the options to a parser,
:class:`ZenohOptions` holds them (typed, frozen; also as command-line arguments for a
child process), and :func:`zenoh_config` / :func:`config_from_args` make the
``zenoh.Config``.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from typing import Sequence

import zenoh

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, listen_default: str | None = None) -> None:
    """Add the shared Zenoh options to a command's parser."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=("peer", "client", "router"), default="peer",
                       help="zenoh session mode (default peer)")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                       help="endpoint to listen on (repeatable)"
                       + (f"; default {listen_default}" if listen_default else ""))
    group.add_argument("--config", dest="zenoh_config", metavar="FILE",
                       help="a zenoh JSON5 configuration file (the options above override it)")
    group.add_argument("--scouting", action="store_true",
                       help="enable multicast scouting (off by default)")
    parser.set_defaults(_listen_default=listen_default)


@dataclass(frozen=True)
class ZenohOptions:
    """The shared Zenoh options.  Defaults: peer mode, multicast scouting off."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    scouting: bool = False

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ZenohOptions:
        return cls(mode=args.mode, connect=tuple(args.connect or ()),
                   listen=tuple(args.listen or ()), config_file=args.zenoh_config,
                   scouting=bool(args.scouting))

    def to_config(self) -> zenoh.Config:
        """A ``zenoh.Config`` from these options."""
        return zenoh_config(mode=self.mode, connect=self.connect, listen=self.listen,
                            config_file=self.config_file, scouting=self.scouting)

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
        return argv


def zenoh_config(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: str | None = None, scouting: bool = False) -> zenoh.Config:
    """A zenoh.Config from the shared options."""
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen and mode != "client":  # a client does not listen
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(scouting)))
    return config


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """A zenoh.Config from parsed shared options."""
    listen = args.listen
    if listen is None:
        default = getattr(args, "_listen_default", None)
        listen = [default] if default else []
    return zenoh_config(mode=args.mode, connect=args.connect, listen=listen,
                        config_file=args.zenoh_config, scouting=args.scouting)


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
        locator = endpoint.split("#", 1)[0]
        proto, _, address = locator.partition("/")
        host, _, port = address.rpartition(":")
        if not port or port == "0":
            continue
        out.append(f"{proto}/{_LOOPBACK_FOR.get(host, host)}:{port}")
    out.extend(e for e in endpoints("connect/endpoints") if e not in out)
    return tuple(out)
