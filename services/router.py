"""``stockpile service router``: the site's Zenoh router, mutual TLS only, access by role.

Every other service connects to it as a client (an ACL sees only its own direct links,
so nothing may go peer to peer around it).  It listens on TLS endpoints only (plain TCP
needs ``--insecure``, and then there is no access control to speak of), requires a
client certificate from the site CA (``enable_mtls``), and denies by default: what each
certificate may publish, subscribe, query and answer comes from its role
(:mod:`services.acl`), and the certificates and roles come from the site PKI's index
(``--pki DIR``, default ``--tls-dir``: ``index.json`` as ``stockpile pki`` writes it;
revoked certificates get no rights).

A site router links to its head office's router with ``--uplink tls/HOST:PORT`` (Zenoh
routers do not link up on their own): that one link is made with the head office's
credentials from ``--uplink-tls DIR`` (the head-office CA as its only root, this site's
``uplink`` certificate ``<site>.router``), given in the endpoint's own TLS settings, so
the site's own links keep trusting the site CA alone; the head-office router's
certificate name (``--head-office-name``) is granted reads of this site's ledger and
nothing else (:func:`services.acl.access_control`, ``docs/security.md``).

Refused messages are logged, one ``refused`` line per (subject, message, key) with a
count: the router reads zenoh's access-control trace on its own standard output.

The router's own session runs in this process (the Python bindings run a router: no
external binary).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from services.acl import access_control, members_from_index
from services.service import ServiceRuntime, Stopper, ZenohOptions, log
from services.zenoh_config import InsecureEndpoint, split_endpoint, tls_files

SERVICE = "router"
DEFAULT_LISTEN = "tls/127.0.0.1:7447"
#: the Rust log filter that makes zenoh write its access-control decisions
ACL_TRACE = "zenoh::net::routing::interceptor::access_control=trace"

_DECISION = re.compile(r"CertCommonName\((?P<cn>[^)]*)\).* is unauthorized to (?P<what>.+?) "
                       r"\((?P<flow>ingress|egress)\) on (?P<key>\S+)")
_CACHING = re.compile(r"caching permissions for `(?P<key>[^`]*)`")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_ABOUT = re.compile(r" on (\S+)\s*$")
#: a zenoh log line at WARN or ERROR (passed on to the router's log, one line each)
_ZENOH_PROBLEM = re.compile(r"\b(WARN|ERROR)\b")


#: the head-office router's certificate name a site router grants reads when none is given
DEFAULT_HEAD_OFFICE = "hq.router"


@dataclass(frozen=True)
class Uplink:
    """The link a site router opens to its head office's router.

    Attributes
    ----------
    endpoint : str
        The head-office router, ``tls/HOST:PORT``.
    tls_dir : str
        The head office's files for this link: ``ca.pem`` (the head-office CA) and this
        site's uplink certificate ``NAME.pem`` / ``NAME.key``.
    name : str
        The uplink certificate's name, ``<site>.router``.
    head_office : str
        The head-office router's certificate name, granted reads of this site's ledger.
    """

    endpoint: str
    tls_dir: str
    name: str
    head_office: str = DEFAULT_HEAD_OFFICE

    def __post_init__(self) -> None:
        proto, host, port = split_endpoint(self.endpoint)
        if proto != "tls" or not host or not port or "#" in self.endpoint:
            raise ValueError(f"--uplink {self.endpoint}: give the head office's router as "
                             "tls/HOST:PORT")

    def link_endpoint(self) -> str:
        """The endpoint with this link's own TLS settings (zenoh's endpoint config)."""
        files = tls_files(self.tls_dir, self.name)
        if any(c in str(path) for path in files for c in "#;="):
            raise InsecureEndpoint(f"--uplink-tls {self.tls_dir}: a path with '#', ';' or '=' "
                                   "cannot be given in an endpoint")
        ca, cert, key = files
        return (f"{self.endpoint}#root_ca_certificate_file={ca};"
                f"connect_certificate_file={cert};connect_private_key_file={key}")


@dataclass(frozen=True)
class Config:
    """Options of the router.

    Attributes
    ----------
    pki_dir : str or None
        The site PKI directory whose ``index.json`` names the certificates and roles
        (default: the TLS directory).
    acl : bool
        Generate and enforce access control (off only with ``--insecure --no-acl``).
    uplink : Uplink or None
        The link to the head office's router, if this site has one.
    """

    site: str
    zenoh: ZenohOptions
    pki_dir: str | None = None
    acl: bool = True
    status_period_s: float = 5.0
    members: dict[str, str] = field(default_factory=dict)
    uplink: Uplink | None = None

    def __post_init__(self) -> None:
        if self.zenoh.mode != "router":
            raise ValueError("the router runs in router mode")
        if not self.zenoh.listen:
            raise ValueError("the router needs a --listen endpoint")
        if not self.zenoh.tls_dir and not self.zenoh.insecure:
            raise ValueError("the router listens on TLS only: give --tls-dir and --tls-name "
                             "(stockpile pki), or say --insecure")
        if not self.acl and not self.zenoh.insecure:
            raise ValueError("--no-acl needs --insecure")
        if self.uplink is not None and not self.zenoh.tls_dir:
            raise ValueError("--uplink needs this router on TLS (--tls-dir, --tls-name)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pki", metavar="DIR",
                        help="site PKI directory with index.json (default: --tls-dir)")
    parser.add_argument("--no-acl", action="store_true",
                        help="no access control (only with --insecure: a test bench)")
    parser.add_argument("--uplink", metavar="ENDPOINT",
                        help="the head office's router (tls/HOST:PORT): link to it and grant it "
                        "reads of this site's ledger")
    parser.add_argument("--uplink-tls", metavar="DIR",
                        help="the head office's files for the uplink: DIR/ca.pem (its CA, "
                        "trusted on that link only) and this site's uplink certificate")
    parser.add_argument("--uplink-name", metavar="NAME",
                        help="the uplink certificate's name in --uplink-tls (default "
                        "SITE.router)")
    parser.add_argument("--head-office-name", default=DEFAULT_HEAD_OFFICE, metavar="NAME",
                        help="the head-office router's certificate name, granted reads of this "
                        f"site's ledger (default {DEFAULT_HEAD_OFFICE})")
    parser.set_defaults(mode="router")


def uplink_from_args(args: argparse.Namespace) -> Uplink | None:
    """The uplink the options describe (None without ``--uplink``); ValueError when
    ``--uplink`` and ``--uplink-tls`` do not come together."""
    if bool(args.uplink) != bool(args.uplink_tls):
        raise ValueError("--uplink and --uplink-tls go together")
    if not args.uplink:
        return None
    return Uplink(args.uplink, args.uplink_tls, args.uplink_name or f"{args.site}.router",
                  args.head_office_name)


def config_from_args(args: argparse.Namespace) -> Config:
    options = ZenohOptions.from_args(args)
    listen = options.listen or (DEFAULT_LISTEN,)
    options = ZenohOptions(mode="router", connect=options.connect, listen=listen,
                           config_file=options.config_file, scouting=options.scouting,
                           tls_dir=options.tls_dir, tls_name=options.tls_name or "router",
                           insecure=options.insecure)
    pki = args.pki or options.tls_dir
    members = load_members(pki) if pki and not args.no_acl else {}
    return Config(site=args.site, zenoh=options, pki_dir=pki, acl=not args.no_acl,
                  status_period_s=args.status_period, members=members,
                  uplink=uplink_from_args(args))


def load_members(pki_dir: str) -> dict[str, str]:
    """``{certificate name: role}`` from a PKI directory's ``index.json``."""
    path = Path(pki_dir) / "index.json"
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read the PKI index {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON: {exc}") from None
    entries = data.get("certificates", data) if isinstance(data, dict) else data
    if isinstance(entries, dict):
        entries = list(entries.values())
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected a list of certificates")
    return members_from_index(entries)


def router_config(config: Config) -> zenoh.Config:
    """The router's ``zenoh.Config``: the shared options, the uplink, the generated ACL."""
    return site_router_config(config.site, config.zenoh, config.members if config.acl else None,
                              config.uplink)


def site_router_config(site: str, options: ZenohOptions, members: dict[str, str] | None,
                       uplink: Uplink | None = None) -> zenoh.Config:
    """A router's ``zenoh.Config`` from its options, with the link to ``uplink`` (its own
    TLS settings) and the access control for ``members`` (None: no access control)."""
    zconfig = options.to_config()
    if uplink is not None:
        zconfig.insert_json5("connect/endpoints",
                             json.dumps([*options.connect, uplink.link_endpoint()]))
    if members is not None:
        zconfig.insert_json5("access_control", json.dumps(access_control(
            site, members, head_office=uplink.head_office if uplink else None)))
    return zconfig


class RefusalLog:
    """Reads zenoh's access-control trace (a file descriptor) and logs each refused
    (subject, message, flow, key) once, then every 1,000th repeat, with a count."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.counts: dict[tuple[str, str, str, str], int] = {}
        self._caching: dict[str, int] = {}
        self.thread = threading.Thread(target=self._run, name="router-refusals", daemon=True)

    def start(self) -> RefusalLog:
        self.thread.start()
        return self

    def _run(self) -> None:
        with os.fdopen(self.fd, "r", errors="replace") as lines:
            for line in lines:
                self.take(line)

    def take(self, line: str) -> None:
        """One line of zenoh's log.  Every message's decision is a line, so the common
        case (an allowed message outside a permission table) costs one substring test."""
        if "caching permissions" in line:
            match = _CACHING.search(line)
            if match:   # the next decisions on this key are a permission table, not traffic
                self._caching[match["key"]] = self._caching.get(match["key"], 0) + 10
            return
        if self._caching and "authorized" in line:
            about = _ABOUT.search(_ANSI.sub("", line))
            if about and about[1] in self._caching:
                left = self._caching[about[1]] - 1
                if left:
                    self._caching[about[1]] = left
                else:
                    del self._caching[about[1]]
                return
        if " is unauthorized " not in line:
            if _ZENOH_PROBLEM.search(line):
                text = _ANSI.sub("", line).strip()
                log(SERVICE, "zenoh", level="warning", line=text[:500])
            return
        match = _DECISION.search(_ANSI.sub("", line))
        if match is None:
            return
        refusal = (match["cn"], match["what"].lower(), match["flow"], match["key"])
        n = self.counts.get(refusal, 0) + 1
        self.counts[refusal] = n
        if n == 1 or n % 1000 == 0:
            log(SERVICE, "refused", level="warning", subject=refusal[0], message=refusal[1],
                flow=refusal[2], key=refusal[3], count=n)


def _capture_zenoh_log() -> int:
    """Point this process's standard output (where zenoh writes its log) at a pipe;
    return the pipe's read end."""
    read_fd, write_fd = os.pipe()
    os.dup2(write_fd, 1)
    os.close(write_fd)
    return read_fd


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the router until SIGINT/SIGTERM (or ``stopper``); return an exit code."""
    refusals = None
    if config.acl:
        os.environ["RUST_LOG"] = ",".join(filter(None, [os.environ.get("RUST_LOG", "error"),
                                                        ACL_TRACE]))
        refusals = RefusalLog(_capture_zenoh_log()).start()
        zenoh.init_log_from_env_or("error")
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.zenoh.tls_name or "",
                             status_period_s=config.status_period_s, stopper=stopper)
    runtime.open(rate_of="refused", error_keys=(), zenoh_config=router_config(config))
    try:
        roles: dict[str, int] = {}
        for role in config.members.values():
            roles[role] = roles.get(role, 0) + 1
        runtime.log("routing", listen=list(config.zenoh.listen),
                    uplink=config.uplink.endpoint if config.uplink else "-",
                    tls=bool(config.zenoh.tls_dir), acl=config.acl,
                    certificates=len(config.members),
                    roles=",".join(f"{r}:{n}" for r, n in sorted(roles.items())))
        runtime.stopper.wait()
        if refusals is not None:
            runtime.log("refusals", total=sum(refusals.counts.values()),
                        distinct=len(refusals.counts))
    finally:
        runtime.close()
    return 0
