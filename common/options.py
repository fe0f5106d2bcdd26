"""The command line's shared vocabulary: one spelling, one default, one unit per concept.

Every ``stockpile`` subcommand and service adds its shared options through these
functions, so that a concept is spelled the same everywhere:

``--valid-time T`` / ``--known-time K``
    the bitemporal coordinates (ISO-8601 or integer UTC ns).  Default valid time: the
    end of the ledger (everything); default known time: everything recorded so far.
``--types T [T ...]``
    event selection by event type (default: all types).
``--clock wall|events``
    where site time comes from: the machine's UTC clock or the site's clock events
    (``site`` is a deprecated alias of ``events``).
``--out PATH``
    where output goes.
``--progress`` / ``--no-progress``
    progress on stderr (default: on when stderr is a terminal).
``--batch-size N``
    events per atomic ledger batch (default :data:`DEFAULT_BATCH_SIZE`).
``--accept-loss``
    open a ledger for writing although its head went backwards (``ledger.head_file``).
``--ledger PATH|URL``
    a ledger file, or a ``postgresql://`` URL of a PostgreSQL ledger (:func:`add_ledger`);
    messages name a ledger with :func:`describe_ledger`, which masks a URL's password.
``--analytes A,...`` / ``--unknown-analyte quarantine|flag``
    the ledger writer's declared analyte list and what it does with an analyte on no
    list (parsed by ``schemas.analytes.policy_from_args``).
durations
    a number with a unit (``90s``, ``15min``, ``1h``, ``2d``); a bare number is refused
    because it used to mean hours, seconds or nanoseconds depending on the command.

Ranges: ``--max-rows N`` is the most rows a command expands a range into (default
:data:`DEFAULT_MAX_ROWS`); a larger range is refused before anything is allocated
(:func:`check_range_rows`).

Old spellings are registered with :func:`add_deprecated` (hidden from ``--help``): they
still work for this release and print one warning line on stderr.

This module imports nothing of the project (``common`` is the bottom layer); commands
parse time values with ``schemas.times.parse_time_ns``.
"""

from __future__ import annotations

import argparse
import re
import sys
from typing import Any, Callable, Sequence

PROG = "stockpile"

#: events per atomic ledger batch, for every command and service that appends
DEFAULT_BATCH_SIZE = 2_000

#: the most rows (times, steps) a command expands a range into unless ``--max-rows`` raises it
DEFAULT_MAX_ROWS = 100_000

#: the clock choices: the machine's UTC clock, or the site's ``clock`` events
CLOCKS = ("wall", "events")

#: seconds per duration unit
DURATION_UNITS_S = {"ms": 1e-3, "s": 1.0, "sec": 1.0, "min": 60.0, "m": 60.0,
                    "h": 3600.0, "d": 86_400.0}

DURATION_EXAMPLE = "e.g. 1h or 90s"

VALID_TIME_HELP = ("valid time V: ISO-8601 or integer UTC ns (default: the end of the ledger, "
                   "everything)")
KNOWN_TIME_HELP = ("known time K: ISO-8601 or integer UTC ns (default: everything recorded "
                   "so far)")

#: URL schemes of a PostgreSQL ledger (``--ledger postgresql://...``)
LEDGER_URL_SCHEMES = ("postgresql", "postgres")

#: how a ledger's password shows in messages
MASKED_PASSWORD = "***"

_QUERY_PASSWORD = re.compile(r"(?i)([?&]password=)[^&#]*")

_DURATION_RE = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*(ms|min|sec|s|m|h|d)")


def warn_deprecated(old: str, new: str) -> None:
    """Print ``stockpile: warning: OLD is deprecated, use NEW`` on stderr."""
    print(f"{PROG}: warning: {old} is deprecated, use {new}", file=sys.stderr)


def parse_duration_s(text: str) -> float:
    """``"90s"``, ``"15min"``, ``"1h"``, ``"2d"``, ``"1h30min"`` -> seconds (a positive float).

    Raises ValueError for a bare number (``"3600"``: which unit?), anything else that is
    not a duration, and durations that are not positive.
    """
    value = str(text).strip().lower().replace(" ", "")
    if re.fullmatch(r"[-+]?(\d+(\.\d*)?|\.\d+)(e[-+]?\d+)?", value):
        raise ValueError(f"needs a unit, {DURATION_EXAMPLE}, got {str(text)!r}")
    parts = _DURATION_RE.findall(value)
    if not parts or "".join(n + u for n, u in parts) != value:
        raise ValueError(f"is not a duration ({DURATION_EXAMPLE}, 15min, 2d), got {str(text)!r}")
    total = sum(float(n) * DURATION_UNITS_S[u] for n, u in parts)
    if not total < float("inf"):   # also NaN
        raise ValueError(f"is too long, got {str(text)!r}")
    if total <= 0:
        raise ValueError(f"must be positive, got {str(text)!r}")
    return total


def format_duration_s(seconds: float) -> str:
    """Seconds as a duration with units, the way a user writes one: 60 -> ``1min``,
    5400 -> ``1h30min``, 90 -> ``1min30s``, 0.25 -> ``0.25s``."""
    out, rest = [], float(seconds)
    for unit, size in (("d", 86_400.0), ("h", 3600.0), ("min", 60.0)):
        whole = int(rest // size)
        if whole:
            out.append(f"{whole}{unit}")
            rest -= whole * size
    if rest > 1e-9 or not out:
        out.append(f"{round(rest, 9):g}s")
    return "".join(out)


class DurationAction(argparse.Action):
    """Store a duration given with a unit as float seconds; a bad value is a usage error
    such as ``--every needs a unit, e.g. 1h or 90s, got '3600'``.

    ``bare_unit`` (deprecated path, one release): a bare number is read in this unit with a
    deprecation warning instead of being refused.
    """

    def __init__(self, option_strings: Sequence[str], dest: str, *,
                 bare_unit: str | None = None, **kwargs: Any) -> None:
        self.bare_unit = bare_unit
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        flag = option_string or self.dest
        try:
            seconds = parse_duration_s(values)
        except ValueError as exc:
            bare = re.fullmatch(r"(\d+(\.\d*)?|\.\d+)(e[-+]?\d+)?", str(values).strip())
            if self.bare_unit is None or not bare or not float(values) > 0:
                parser.error(f"{flag} {exc}")
            warn_deprecated(f"{flag} {values} (a bare number)", f"{flag} {values}{self.bare_unit}")
            seconds = float(values) * DURATION_UNITS_S[self.bare_unit]
        setattr(namespace, self.dest, seconds)


def add_duration(parser: argparse.ArgumentParser | Any, *flags: str, help: str,
                 default: float | None = None, metavar: str = "DURATION",
                 bare_unit: str | None = None, **kwargs: Any) -> argparse.Action:
    """An option taking a duration with a unit, stored as float seconds (``default`` in
    seconds too).  ``help`` must say whether it is site or wall time.  ``bare_unit``: accept
    a bare number in this unit, deprecated (options that took bare numbers before)."""
    return parser.add_argument(*flags, action=DurationAction, default=default,
                               metavar=metavar, help=help, bare_unit=bare_unit, **kwargs)


def positive_float(text: str) -> float:
    """argparse type: a float > 0 (speeds, rates)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


class _DeprecatedAction(argparse.Action):
    """An old spelling: warn once on stderr, then store like the new one."""

    def __init__(self, option_strings: Sequence[str], dest: str, *, new: str,
                 store_const: Any = None, **kwargs: Any) -> None:
        self.new = new
        self.store_const = store_const
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        warn_deprecated(option_string or self.option_strings[0], self.new)
        setattr(namespace, self.dest, self.store_const if self.nargs == 0 else values)


def add_deprecated(parser: argparse.ArgumentParser | Any, old: str, new: str, dest: str, *,
                   nargs: Any = None, type: Callable[[str], Any] | None = None,
                   const: Any = None) -> argparse.Action:
    """Register ``old`` as a hidden, deprecated spelling of the option ``new`` (same dest).

    ``nargs=0`` with ``const`` gives a flag that stores ``const``.  Register it after the
    new option so the new option's default stands.
    """
    kwargs: dict[str, Any] = {"nargs": nargs}
    if nargs == 0:
        kwargs["store_const"] = const
    elif type is not None:
        kwargs["type"] = type
    return parser.add_argument(old, dest=dest, action=_DeprecatedAction, new=new,
                               default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)


def add_bitemporal(parser: argparse.ArgumentParser | Any, *, valid: bool = True,
                   known: bool = True, deprecated: bool = False) -> None:
    """``--valid-time T`` and/or ``--known-time K`` (strings; None = the default stated in
    the help).  ``deprecated`` also accepts ``--as-of-valid`` / ``--as-of-known``."""
    if valid:
        parser.add_argument("--valid-time", metavar="T", help=VALID_TIME_HELP)
        if deprecated:
            add_deprecated(parser, "--as-of-valid", "--valid-time", "valid_time")
    if known:
        parser.add_argument("--known-time", metavar="K", help=KNOWN_TIME_HELP)
        if deprecated:
            add_deprecated(parser, "--as-of-known", "--known-time", "known_time")


def add_types(parser: argparse.ArgumentParser | Any, *, deprecated: Sequence[str] = ()) -> None:
    """``--types T [T ...]``: only these event types (None = all).  ``deprecated``: old
    spellings such as ``--topics`` that meant event types."""
    parser.add_argument("--types", nargs="+", metavar="TYPE",
                        help="only these event types (default: all)")
    for old in deprecated:
        add_deprecated(parser, old, "--types", "types", nargs="+")


class _ClockAction(argparse.Action):
    """``--clock wall|events``; ``site`` is a deprecated alias of ``events``."""

    def __init__(self, option_strings: Sequence[str], dest: str, *, events_as: str = "events",
                 **kwargs: Any) -> None:
        self.events_as = events_as
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        value = str(values)
        if value == "site":
            warn_deprecated(f"{option_string} site", f"{option_string} events")
            value = "events"
        if value not in CLOCKS:
            parser.error(f"{option_string}: choose from {', '.join(CLOCKS)}, got {value!r}")
        setattr(namespace, self.dest, self.events_as if value == "events" else value)


def add_clock(parser: argparse.ArgumentParser | Any, *, help: str,
              events_as: str = "events") -> argparse.Action:
    """``--clock wall|events`` (default wall).  The value stored for ``events`` is
    ``events_as``, for code whose own name for the events clock differs (``"site"``)."""
    return parser.add_argument("--clock", action=_ClockAction, default="wall",
                               metavar="{wall,events}", events_as=events_as,
                               help=f"{help} (default wall)")


def add_out(parser: argparse.ArgumentParser | Any, *, help: str, metavar: str = "PATH",
            deprecated: Sequence[str] = (), **kwargs: Any) -> argparse.Action:
    """``--out PATH``; ``deprecated``: old spellings such as ``-o``/``--output``."""
    action = parser.add_argument("--out", metavar=metavar, help=help, **kwargs)
    for old in deprecated:
        add_deprecated(parser, old, "--out", action.dest)
    return action


def add_progress(parser: argparse.ArgumentParser | Any) -> argparse.Action:
    """``--progress/--no-progress`` -> True, False or None (None: on when stderr is a
    terminal)."""
    return parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=None,
        help="progress on stderr (default: on when stderr is a terminal; --progress "
        "prints plain lines when it is not)")


def add_batch_size(parser: argparse.ArgumentParser | Any) -> argparse.Action:
    """``--batch-size N``: events per atomic ledger batch (default DEFAULT_BATCH_SIZE)."""
    return parser.add_argument("--batch-size", type=positive_int, default=DEFAULT_BATCH_SIZE,
                               metavar="N", help="events per atomic ledger batch "
                               f"(default {DEFAULT_BATCH_SIZE:,})")


def add_accept_loss(parser: argparse.ArgumentParser | Any) -> argparse.Action:
    """``--accept-loss``: open a ledger for writing although its head went backwards."""
    return parser.add_argument(
        "--accept-loss", action="store_true",
        help="open the ledger although its head went backwards (it holds less than its "
        "head sidecar recorded as committed): only after a human has looked; the loss is "
        "logged and the sidecar rewritten (see docs/operations.md)")


def add_signing_key(parser: argparse.ArgumentParser | Any, *,
                    what: str = "event") -> argparse.Action:
    """``--signing-key FILE``: the Ed25519 key (``NAME.sign.key``) a producer signs every
    ``what`` it publishes with (default None: unsigned)."""
    return parser.add_argument(
        "--signing-key", metavar="FILE",
        help=f"sign every published {what} with this Ed25519 key (NAME.sign.key)")


def add_analytes(parser: argparse.ArgumentParser | Any) -> None:
    """``--analytes A,...`` and ``--unknown-analyte quarantine|flag`` (both default None:
    what the ledger recorded, else the built-in list with unknown analytes flagged)."""
    parser.add_argument("--analytes", metavar="A,...",
                        help="the site's declared analytes, comma-separated (default: the "
                        "list the ledger recorded, else Fe,SiO2,Al2O3,P,S,Mn,TiO2,CaO,MgO,"
                        "K2O,Na2O,LOI); other spellings (FE, fe) count as the declared one")
    parser.add_argument("--unknown-analyte", choices=("quarantine", "flag"), default=None,
                        help="an assay or lot naming an undeclared analyte is quarantined, or "
                        "kept with the name listed in assays.unrecognised_analytes (default: "
                        "what the ledger recorded, else flag)")


def epsg_code(text: str) -> int:
    """``--crs``'s value: ``7850`` or ``EPSG:7850`` -> 7850 (an argparse type)."""
    try:
        code = int(text.strip().upper().removeprefix("EPSG:"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an EPSG code: {text!r}") from None
    if code <= 0:
        raise argparse.ArgumentTypeError(f"not an EPSG code: {text!r}")
    return code


def non_negative_float(text: str) -> float:
    """argparse type: a float >= 0 (speeds where 0 means as fast as possible)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return value


def positive_int(text: str, what: str = "an integer") -> int:
    """argparse type: an integer > 0 (counts; ``what`` names the unit in the error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


_ROLE_RE = re.compile(r":(?:mod|func|class|meth|data|attr|obj|ref|doc):`~?([^`]+)`")


def plain_text(text: str) -> str:
    """``text`` without reST markup (roles such as ``:mod:`x``` and double backticks), for
    help and descriptions taken from docstrings."""
    text = _ROLE_RE.sub(r"\1", text)
    return text.replace("``", "")


def refuse_inapplicable(args: argparse.Namespace, mode: str,
                        options: dict[str, str]) -> None:
    """Raise ValueError naming the first of ``options`` (dest -> option spelling) that was
    given (not None) although it does not apply to ``mode``."""
    given = [flag for dest, flag in options.items() if getattr(args, dest, None) is not None]
    if given:
        raise ValueError(f"{', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply "
                         f"to {mode}")


def add_deprecated_positional_out(parser: argparse.ArgumentParser | Any,
                                  dest: str = "out_positional") -> argparse.Action:
    """A hidden optional positional for an output file that is now given with ``--out``;
    read it with :func:`out_path`."""
    return parser.add_argument(dest, nargs="?", default=None, help=argparse.SUPPRESS)


def out_path(args: argparse.Namespace, dest: str = "out_positional") -> str | None:
    """``--out``, or the deprecated positional output file (with a warning); both is an
    error (ValueError)."""
    positional = getattr(args, dest, None)
    if positional is None:
        return args.out
    if args.out is not None:
        raise ValueError(f"give the output file once, with --out (not also as {positional})")
    warn_deprecated(f"the output file as a positional argument ({positional})",
                    f"--out {positional}")
    return positional


def add_max_rows(parser: argparse.ArgumentParser | Any, *, what: str = "rows") -> argparse.Action:
    """``--max-rows N``: the most ``what`` a range may expand into (default DEFAULT_MAX_ROWS)."""
    return parser.add_argument("--max-rows", type=positive_int, default=DEFAULT_MAX_ROWS,
                               metavar="N", help=f"refuse a range of more than N {what} "
                               f"(default {DEFAULT_MAX_ROWS:,})")


def check_range_rows(count: int, limit: int = DEFAULT_MAX_ROWS, *, what: str = "rows",
                     hint: str = "") -> None:
    """Raise ValueError naming ``count`` and ``limit`` when a range expands into more than
    ``limit`` ``what``; call it with the count computed arithmetically, before allocating.
    ``hint`` ends the message (e.g. ``"choose a longer --every or raise --max-rows"``)."""
    if count > limit:
        raise ValueError(f"the range is {count:,} {what}, more than the limit of {limit:,}"
                         + (f": {hint}" if hint else ""))


# -- ledgers: a file or a PostgreSQL URL ----------------------------------------------------


def is_ledger_url(text: str | Any) -> bool:
    """Whether ``--ledger`` names a PostgreSQL ledger (``postgresql://`` or ``postgres://``)
    rather than a file.  Such a value must never become a ``Path`` (that collapses
    ``//``)."""
    scheme, sep, _rest = str(text).partition("://")
    return bool(sep) and scheme.lower() in LEDGER_URL_SCHEMES


def describe_ledger(text: str | Any) -> str:
    """A ledger as messages name it: a file path as given; a URL with its password
    replaced by ``***`` (in the user information and in a ``password=`` parameter).  A
    password is never printed: when the URL is ambiguous (an ``@`` in its query), more is
    masked rather than less."""
    text = str(text)
    if not is_ledger_url(text):
        return text
    scheme, _sep, rest = text.partition("://")
    at = rest.rfind("@")
    if at >= 0 and ":" in rest[:at]:
        rest = rest[:at].split(":", 1)[0] + ":" + MASKED_PASSWORD + rest[at:]
    rest = _QUERY_PASSWORD.sub(r"\1" + MASKED_PASSWORD, rest)
    return f"{scheme}://{rest}"


def add_ledger(parser: argparse.ArgumentParser | Any, *, help: str = "", required: bool = True,
               metavar: str = "PATH|URL") -> argparse.Action:
    """``--ledger PATH|URL``: a ledger file or a ``postgresql://`` URL; ``help`` says what
    the command does with it (e.g. "opened read-only")."""
    text = "ledger file or postgresql:// URL" + (f" ({help})" if help else "")
    return parser.add_argument("--ledger", required=required, metavar=metavar, help=text)
