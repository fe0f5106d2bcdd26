"""``stockpile record``, ``stockpile replay`` and ``stockpile export-mcap``.

Exit codes, as for every ``stockpile`` command: 0 ok; 1 the input file was damaged
or held messages that are not stockpile events (what could be used was used, and
what was lost or skipped is counted on stderr); 2 bad usage or an error (one line).
"""

from __future__ import annotations

import argparse
import sys
import threading
from typing import Callable
from pathlib import Path

import zenoh

from common.progress import enabled_from_args, progress
from common.options import (add_accept_loss, add_batch_size, add_clock, add_deprecated_positional_out,
                            add_ledger, add_out, add_progress, add_types, describe_ledger,
                            out_path)
from ledger import open_ledger
from ledger.clock import clock_by_name
from ledger.signing import add_signing_options, policy_from_args
from replay import record
from replay.export import export_ledger
from replay.recover import recover
from replay.replay import iter_events, replay_publish, replay_to_ledger
from schemas.events import EVENT_TYPES, key_expr
from schemas.times import MAX_TIME_NS, NS_PER_S
from services.service import DEFAULT_SITE, Stopper, add_service_arguments
from services.zenoh_config import add_zenoh_arguments, config_from_args

EXIT_OK, EXIT_DAMAGED, EXIT_USAGE = 0, 1, 2


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _report_input(report, *, what: str) -> int:
    """Print what was lost or skipped reading an input file; return the exit code."""
    code = EXIT_OK
    if report.damaged:
        _say(f"stockpile: warning: {report.path} is damaged: {report.loss_text()}")
        code = EXIT_DAMAGED
    if report.unknown:
        _say(f"stockpile: warning: {report.unknown_messages:,} messages of {report.path} are not "
             f"stockpile events and were not {what}: {report.unknown_text()}")
        code = EXIT_DAMAGED
    return code


# -- record -----------------------------------------------------------------------------------


def cmd_record(args: argparse.Namespace) -> int:
    args.out = out_path(args)
    if args.recover:
        if args.out:
            raise ValueError("give --out OUT.mcap or --recover BROKEN FIXED, not both")
        return _recover(*args.recover)
    if not args.out:
        raise ValueError("give --out OUT.mcap (or --recover BROKEN FIXED)")
    return int(record.main(record.config_from_args(args)) or 0)


def _recover(broken: str, fixed: str) -> int:
    result = recover(broken, fixed)
    report = result.report
    lost = report.lost + result.orphaned
    print(f"recovered {result.messages:,} messages from {broken} into {fixed}"
          + (f" ({report.salvaged:,} salvaged from a chunk cut short)" if report.salvaged else ""))
    if not report.damaged and not result.orphaned:
        print(f"{broken} was intact: nothing lost")
        return EXIT_OK
    more = " and an unknown number after the end of the readable data" if report.lost_unknown else ""
    print(f"lost: {lost:,} messages{more}")
    for problem in report.problems:
        print(f"  {problem}")
    if result.orphaned:
        print(f"  {result.orphaned:,} messages whose channel definition was lost")
    return EXIT_DAMAGED


# -- replay -------------------------------------------------------------------------------------


def cmd_replay(args: argparse.Namespace) -> int:
    if not Path(args.input).is_file():
        raise FileNotFoundError(f"no such file: {args.input}")
    if bool(args.publish) == bool(args.ledger):
        raise ValueError("give exactly one of --publish or --ledger PATH")
    for name in ("start_offset", "until"):
        value = getattr(args, name)
        if value is not None and not 0 <= value <= MAX_TIME_NS / NS_PER_S:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 0 s and within the "
                             f"representable time range, got {value:g}")
    topics = topic_matcher(args.topics)
    if args.ledger:
        return _replay_ledger(args, topics)
    return _replay_publish(args, topics)


def _replay_ledger(args: argparse.Namespace, topics) -> int:
    if args.rate is not None or args.max or args.loop:
        raise ValueError("--rate, --max and --loop are for --publish")
    signing = policy_from_args(args)
    with open_ledger(args.ledger, clock_by_name(args.clock), signing=signing,
                     accept_loss=args.accept_loss) as store, \
            progress(desc="replay", enabled=enabled_from_args(args)) as bar:
        result = replay_to_ledger(args.input, store,
                                  preserve_recorded_time=args.preserve_recorded_time,
                                  topics=topics, start_offset_s=args.start_offset,
                                  until_s=args.until, batch_size=args.batch_size,
                                  progress=bar)
    c = result.counts
    print(f"replayed {args.input} into {describe_ledger(args.ledger)}: {result.events:,} events -> "
          f"{c['appended']:,} appended, {c['duplicate']:,} duplicate, {c['conflict']:,} conflict, "
          f"{c['rejected']:,} rejected; head global_seq {result.head_global_seq}")
    if result.malformed:
        print(f"  {result.malformed:,} recorded malformed samples went to the quarantine")
    if result.signed:
        print(f"  {result.signed:,} signed events kept their signatures"
              + ("" if signing is None else " (checked against the site's signing policy)"))
    recorded = "the file's log times" if args.preserve_recorded_time else f"the {args.clock} clock"
    print(f"  {result.site_span_s / 3600:.2f} site h in {result.wall_s:.2f} s "
          f"({result.speed_up:,.0f}x real time; recorded time = {recorded})")
    assert result.scan is not None
    code = _report_input(result.scan, what="imported")
    if result.events == 0 and code:
        raise ValueError(f"no stockpile events could be read from {args.input}")
    return code


def _replay_publish(args: argparse.Namespace, topics) -> int:
    if args.admin_key is not None or args.signed_types is not None:
        raise ValueError("--admin-key and --signed-types are for --ledger")
    if args.rate is not None and args.max:
        raise ValueError("give --rate R or --max, not both")
    rate = None if args.max else (1.0 if args.rate is None else args.rate)
    if rate is not None and not rate > 0:
        raise ValueError(f"--rate must be > 0, got {rate:g}")
    stopper = Stopper()
    session = zenoh.open(config_from_args(args))
    try:
        if args.wait_subscriber:
            _wait_subscriber(session, args, stopper)
        with progress(desc="replay", enabled=enabled_from_args(args)) as bar:
            result = replay_publish(args.input, session, rate=rate, loop=args.loop,
                                    topics=topics, start_offset_s=args.start_offset,
                                    until_s=args.until, site=args.site, stop=stopper,
                                    progress=bar)
        if args.linger > 0 and not stopper.is_set():
            stopper.wait(args.linger)  # the caches stay up for late joiners
    finally:
        session.close()
    pace = "as fast as possible" if rate is None else f"at {rate:g}x"
    print(f"published {result.published:,} events from {args.input} ({result.passes} "
          f"pass{'es' if result.passes != 1 else ''}, {pace}) in {result.wall_s:.2f} s = "
          f"{result.rate_per_s:,.0f} msgs/s" + ("; stopped early" if result.stopped else ""))
    assert result.scan is not None
    code = _report_input(result.scan, what="published")
    if result.published == 0 and code:
        raise ValueError(f"no stockpile events could be read from {args.input}")
    return code


def _wait_subscriber(session, args: argparse.Namespace, stopper) -> None:
    """Block until a subscriber matches the first topic of the file (or time runs out)."""
    first = next(iter(iter_events(args.input)), None)
    if first is None:
        return
    key = first.topic if args.site is None else key_expr(args.site, first.type, first.source)
    probe = session.declare_publisher(key)
    matched = threading.Event()
    listener = probe.declare_matching_listener(lambda s: s.matching and matched.set())
    try:
        if not probe.matching_status.matching and not matched.wait(args.wait_subscriber):
            raise OSError(f"no subscriber matched {key} within {args.wait_subscriber:g} s")
    finally:
        listener.undeclare()
        probe.undeclare()


# -- export-mcap ---------------------------------------------------------------------------------


def cmd_export_mcap(args: argparse.Namespace) -> int:
    for name in args.types or ():
        if name not in EVENT_TYPES:
            raise ValueError(f"unknown event type {name!r}; known: {', '.join(EVENT_TYPES)}")
    output = out_path(args)
    if not output:
        raise ValueError("give --out OUT.mcap")
    with open_ledger(args.ledger, read_only=True) as store, \
            progress(desc="export", enabled=enabled_from_args(args)) as bar:
        result = export_ledger(store, output, site=args.site, types=args.types,
                               progress=bar)
    print(f"exported {result.events:,} events of {describe_ledger(args.ledger)} (head global_seq "
          f"{result.head_global_seq}) to {result.path} in {result.wall_s:.2f} s")
    return EXIT_OK


# -- registration -------------------------------------------------------------------------------


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``record``, ``replay`` and ``export-mcap`` to the ``stockpile`` parser."""
    p = subparsers.add_parser(
        "record", help="record the site's events to MCAP (or --recover a damaged recording)",
        description="Subscribe to the site's events and write them to an MCAP file (zstd "
        "chunks with CRCs; topic = key expression, protobuf schemas, publish_time = valid "
        "time, log_time = receive time in site time) until SIGINT/SIGTERM or --duration. "
        "--recover BROKEN FIXED salvages a file a crash left behind.")
    add_out(p, metavar="OUT.mcap", help="the file to write (must not exist)")
    add_deprecated_positional_out(p)
    p.add_argument("--recover", nargs=2, metavar=("BROKEN", "FIXED"),
                   help="write every readable message of BROKEN to a complete file FIXED and "
                   "report what was lost (exit 1 if anything was)")
    record.add_recording_arguments(p)
    add_service_arguments(p)
    p.set_defaults(func=cmd_record)

    p = subparsers.add_parser(
        "replay", help="replay an MCAP file onto Zenoh (--publish) or into a ledger (--ledger)",
        description="Replay a recording. --publish republishes byte-identical payloads with "
        "their original identities, paced by valid time; --ledger appends straight into a "
        "ledger as fast as it goes, keeping the file's log times as recorded times. Signed "
        "events keep their signer and signature either way; with --admin-key the ledger "
        "quarantines what is not properly signed, as it would live.")
    p.add_argument("input", metavar="IN.mcap", help="the MCAP file")
    target = p.add_argument_group("target (one of)")
    target.add_argument("--publish", action="store_true", help="publish on Zenoh")
    add_ledger(target, required=False, help="appended to; created if missing")
    sel = p.add_argument_group("selection")
    sel.add_argument("--topics", nargs="+", metavar="EXPR",
                     help="only topics under these key expressions (e.g. 'stockpile/*/@v1/assay/**')")
    sel.add_argument("--start-offset", type=float, metavar="S",
                     help="skip messages logged less than S seconds after the first one")
    sel.add_argument("--until", type=float, metavar="S",
                     help="stop at messages logged more than S seconds after the first one")
    pub = p.add_argument_group("--publish")
    pub.add_argument("--rate", type=float, metavar="R",
                     help="site seconds per wall second (default 1 = real time)")
    pub.add_argument("--max", action="store_true", help="publish as fast as possible")
    pub.add_argument("--loop", action="store_true", help="start again at the end, until stopped")
    pub.add_argument("--site", help="republish under this site's keys (default: as recorded)")
    pub.add_argument("--wait-subscriber", type=float, default=0.0, metavar="S",
                     help="first wait up to S seconds for a subscriber (default 0: do not wait)")
    pub.add_argument("--linger", type=float, default=1.0, metavar="S",
                     help="keep the publishers' caches up S seconds after the last message, for "
                     "late joiners (default 1)")
    add_zenoh_arguments(p)
    led = p.add_argument_group("--ledger")
    led.add_argument("--preserve-recorded-time", action=argparse.BooleanOptionalAction,
                     default=True, help="recorded time = the message's log_time (default on)")
    add_clock(led, help="with --no-preserve-recorded-time: recorded time from the wall clock "
              "or the file's clock events")
    add_batch_size(led)
    add_signing_options(led)
    add_accept_loss(led)
    add_progress(p)
    p.set_defaults(func=cmd_replay)

    p = subparsers.add_parser(
        "export-mcap", help="write a ledger's events as an MCAP file",
        description="Write a ledger's events in global order as MCAP (log_time = recorded "
        "time, publish_time = valid time), readable by the mcap tools, Foxglove and Rerun.")
    add_ledger(p, help="opened read-only")
    add_out(p, metavar="OUT.mcap", help="the file to write (replaced if it exists; required)")
    add_deprecated_positional_out(p)
    p.add_argument("--site", default=DEFAULT_SITE,
                   help=f"site id for the topics stockpile/<site>/@v1/... (default {DEFAULT_SITE})")
    add_types(p)
    add_progress(p)
    p.set_defaults(func=cmd_export_mcap)


def topic_matcher(expressions: list[str] | tuple[str, ...] | None) -> Callable[[str], bool] | None:
    """A predicate: does a topic fall under any of these Zenoh key expressions?"""
    if not expressions:
        return None

    try:
        exprs = [zenoh.KeyExpr(e) for e in expressions]
    except Exception as exc:  # noqa: BLE001 - zenoh raises its own error type
        raise ValueError(f"bad key expression in --topics: {exc}") from None

    def matches(topic: str) -> bool:
        try:
            key = zenoh.KeyExpr(topic)
        except Exception:  # noqa: BLE001 - a topic that is not a key expression
            return False
        return any(e.includes(key) for e in exprs)

    return matches
