"""The shared service runtime: what every ``stockpile service NAME`` imports.

A service is one small process on the yard network.  Each one has:

- a typed ``main(config, ...)`` taking a frozen config dataclass (built from the
  command line by the module's ``config_from_args``), so tests and ``stockpile run``
  can start it without argparse;
- the shared Zenoh options (:func:`add_service_arguments`: ``--connect``,
  ``--listen``, ``--mode``, ``--config FILE``, ``--site``; :class:`ZenohOptions`) and a
  session opened from them (:meth:`ServiceRuntime.open`);
- a liveliness token ``stockpile/<site>/@live/<service>/<name>`` while it runs;
- clean shutdown on SIGINT/SIGTERM (:class:`Stopper`);
- an :class:`Inbox` between Zenoh's callbacks and the thread that handles what they
  bring (a wait with a timeout that a signal cannot turn into one without);
- structured log lines on stderr in logfmt (:func:`log`, read back by
  :func:`parse_logfmt`), and a one-line status every few seconds
  (:class:`StatusReporter`: rate, backlog, errors);
- ledger-bound publishing through :class:`EventPublisher`: one source with its epoch
  and dense sequence, Zenoh ``AdvancedPublisher`` per key with a sample cache
  (:func:`declare_ledger_publisher`), sample-miss detection (heartbeat) and publisher
  detection, congestion control BLOCK, so a ledger that restarts can recover what it
  missed from the cache;
- site time (:class:`SiteTime`): the wall clock, or the simulated yard's clock events.

This module defines :class:`ServiceRuntime` (session, token, status, publishers,
stopper of one running service), :func:`add_service_arguments` and
:data:`DEFAULT_SITE`, and re-exports the rest of the service-author API from the
modules that hold it, each one concern: :mod:`services.zenoh_config`
(:class:`ZenohOptions`), :mod:`services.logfmt` (:func:`log`, :func:`parse_logfmt`),
:mod:`services.stopping` (:class:`Stopper`), :mod:`services.inbox` (:class:`Inbox`),
:mod:`services.status` (:class:`StatusReporter`, :data:`DEFAULT_STATUS_PERIOD_S`),
:mod:`services.publishing` (:class:`EventPublisher`, :func:`declare_ledger_publisher`)
and :mod:`services.site_time` (:class:`SiteTime`).  ``__all__`` lists the names.

When it stops, a service logs one ``published`` line per source it published::

    ts=2026-11-22T10:00:00.000Z level=info service=scanner msg=published source=bwr1.scanner epoch=1795... count=1200

which the demo and the end-to-end tests compare with the ledger.
"""

from __future__ import annotations

import argparse
import os
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import zenoh

from security.certificates import expiry_warning
from services.inbox import Inbox
from services.logfmt import log, parse_logfmt
from services.publishing import EventPublisher, declare_ledger_publisher
from services.site_time import SiteTime
from services.status import DEFAULT_STATUS_PERIOD_S, StatusReporter
from services.stopping import Stopper
from services.zenoh_config import ZenohOptions, add_zenoh_arguments

__all__ = [
    "DEFAULT_SITE", "DEFAULT_STATUS_PERIOD_S", "DEFAULT_SMOOTH_LAG_S", "LIVE_REORDER_S", "EventPublisher", "Inbox", "ServiceRuntime",
    "SiteTime", "StatusReporter", "Stopper", "ZenohOptions", "add_service_arguments",
    "declare_ledger_publisher", "log", "parse_logfmt",
]

#: how often a running service re-checks its certificate's expiry, seconds (12 h)
CERT_CHECK_PERIOD_S = 12 * 3600.0

#: the site id when ``--site`` is not given
DEFAULT_SITE = "demo"

#: site seconds the localizer holds each estimate to smooth it (its ``--smooth-lag``)
DEFAULT_SMOOTH_LAG_S = 60.0
#: site seconds a live fold waits for late geometry (the projector's and the dashboard's
#: ``--reorder-s``): an estimate trails its reading by up to 1.5 smoothing lags (the lag
#: and a block of half a lag, ``FixedLagSmoother``'s default), and 30 s more for transport
LIVE_REORDER_S = 1.5 * DEFAULT_SMOOTH_LAG_S + 30.0


def add_service_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options every service shares: Zenoh, ``--site``, ``--status-period``."""
    parser.add_argument("--site", default=DEFAULT_SITE,
                        help=f"site id: keys are stockpile/<site>/@v1/... (default {DEFAULT_SITE})")
    parser.add_argument("--status-period", type=float, default=DEFAULT_STATUS_PERIOD_S,
                        metavar="S", help="seconds between status lines on stderr (default 5)")
    add_zenoh_arguments(parser)


def open_session(options: ZenohOptions, config: zenoh.Config | None = None) -> zenoh.Session:
    """A Zenoh session for these options (or for ``config``, made from them); :class:`OSError`
    with zenoh's one-line reason when it cannot be opened (an endpoint that refuses, a bad
    config file)."""
    try:
        return zenoh.open(config if config is not None else options.to_config())
    except zenoh.ZError as exc:
        reason = str(exc).split("  at ")[0].strip()
        raise OSError(f"cannot open the Zenoh session: {reason}") from None


@dataclass
class ServiceRuntime:
    """What a running service holds: its session, liveliness token, status and stopper.

    Use as a context manager; on exit the publishers log their ``published`` lines,
    the token is dropped and the session closed.
    """

    service: str
    site: str
    zenoh_options: ZenohOptions
    name: str = ""
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    stopper: Stopper | None = None
    session: Any = None
    status: StatusReporter | None = None
    publishers: list[EventPublisher] = field(default_factory=list)
    _token: Any = None

    def open(self, *, rate_of: str = "published", backlog: Callable[[], int] | None = None,
             error_keys: Sequence[str] = ("errors",), announce: bool = True,
             zenoh_config: zenoh.Config | None = None) -> ServiceRuntime:
        """Open the session and start the status line.

        With ``announce`` (default) the liveliness token is declared at once; a
        service that must set up subscribers or queryables first passes
        ``announce=False`` and calls :meth:`announce` when it is ready, so that
        "token present" means "serving".  ``zenoh_config`` replaces the config made
        from the options (the router adds its access control to it).
        """
        self.stopper = self.stopper or Stopper()
        self.session = open_session(self.zenoh_options, zenoh_config)
        self.status = StatusReporter(self.service, period_s=self.status_period_s,
                                     rate_of=rate_of, backlog=backlog, error_keys=error_keys)
        self.log("started", site=self.site, pid=os.getpid(), zid=str(self.session.zid()))
        self.status.start()
        if self.zenoh_options.certificate is not None:
            threading.Thread(target=self._watch_certificate, name="certificate-expiry",
                             daemon=True).start()
        if announce:
            self.announce()
        return self

    def _watch_certificate(self) -> None:
        """Warn when this process's certificate is within ``--cert-warn`` of expiring:
        at start, then twice a day."""
        path = self.zenoh_options.certificate
        assert path is not None and self.stopper is not None
        while True:
            try:
                warning = expiry_warning(path, self.zenoh_options.cert_warn_s)
            except (OSError, ValueError) as exc:
                warning = f"cannot read the certificate {path}: {exc}"
            if warning:
                self.log("certificate", level="warning", problem=warning)
            if self.stopper.event.wait(CERT_CHECK_PERIOD_S):
                return

    @property
    def token_key(self) -> str:
        """``stockpile/<site>/@live/<service>/<name>``."""
        return f"stockpile/{self.site}/@live/{self.service}/{self.name or self.service}"

    def announce(self) -> None:
        """Declare the liveliness token (once)."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.token_key)
            self.log("ready", liveliness=self.token_key)

    def publisher(self, source: str, **kwargs: Any) -> EventPublisher:
        pub = EventPublisher(self.session, self.site, source, **kwargs)
        self.publishers.append(pub)
        return pub

    def log(self, msg: str, *, level: str = "info", **fields: Any) -> None:
        log(self.service, msg, level=level, **fields)

    def close(self) -> None:
        if self.status is not None:
            self.status.stop()
        for pub in self.publishers:
            self.log("published", source=pub.source, epoch=pub.epoch, count=pub.count)
            pub.close()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:  # noqa: BLE001
                pass
            self._token = None
        if self.session is not None:
            self.session.close()
            self.session = None
        fields = dict(self.status.snapshot()) if self.status else {}
        reason = self.stopper.signal_name if self.stopper and self.stopper.signal_name else "done"
        self.log("stopped", reason=reason, **fields)

    def __enter__(self) -> ServiceRuntime:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
