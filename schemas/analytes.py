"""Analyte names: the site's declared list and one canonical spelling per analyte.

An analyte is named by its declared spelling (``Fe``, ``SiO2``); any other spelling of
it counts as that analyte: case is ignored and surrounding white space stripped, so
``FE``, ``fe`` and ``Fe `` are ``Fe``.  A name on no declared list is *unknown*; the site
chooses whether the ledger quarantines an event that names one (``quarantine``) or keeps
it and shows the name to auditors without making it a column (``flag``).

An unknown name still gets a canonical spelling, so that two spellings of it count as
one: a name written in one case (``ZN``, ``zn``) is read as a chemical formula and
written in element case (``Zn``); a name in mixed case is kept as written.

Everything here is pure: no I/O, no ledger state.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterable, Mapping

#: The usual iron-ore assay suite (mass %), the list a site gets unless it declares one.
DEFAULT_ANALYTES: tuple[str, ...] = (
    "Fe", "SiO2", "Al2O3", "P", "S", "Mn", "TiO2", "CaO", "MgO", "K2O", "Na2O", "LOI",
)

#: What the ledger does with an event naming an analyte that is on no declared list.
UNKNOWN_POLICIES: tuple[str, ...] = ("quarantine", "flag")
DEFAULT_UNKNOWN_POLICY = "flag"

#: Longest analyte name, characters.
MAX_NAME_CHARS = 32

_ELEMENTS = frozenset("""
H He Li Be B C N O F Ne Na Mg Al Si P S Cl Ar K Ca Sc Ti V Cr Mn Fe Co Ni Cu Zn Ga Ge As
Se Br Kr Rb Sr Y Zr Nb Mo Tc Ru Rh Pd Ag Cd In Sn Sb Te I Xe Cs Ba La Ce Pr Nd Pm Sm Eu Gd
Tb Dy Ho Er Tm Yb Lu Hf Ta W Re Os Ir Pt Au Hg Tl Pb Bi Po At Rn Fr Ra Ac Th Pa U Np Pu
""".split())
_TOKEN_RE = re.compile(r"[A-Za-z]+|[0-9]+")


def key(name: str) -> str:
    """The comparison key of a spelling: stripped of surrounding white space, case-folded."""
    return name.strip().casefold()


def _element_case(letters: str) -> str | None:
    """Lower-case ``letters`` split into element symbols (two-letter symbols first), in
    element case; None when they do not split."""
    if not letters:
        return ""
    for width in (2, 1):
        head = letters[:width].capitalize()
        if len(head) == width and head in _ELEMENTS:
            rest = _element_case(letters[width:])
            if rest is not None:
                return head + rest
    return None


@lru_cache(maxsize=4096)
def formula_case(name: str) -> str:
    """``name`` stripped, and when written in one case and it reads as a chemical formula,
    in element case (``ZN`` -> ``Zn``, ``sio2`` -> ``SiO2``); otherwise as written."""
    text = name.strip()
    letters = "".join(c for c in text if c.isalpha())
    if not letters or (letters != letters.upper() and letters != letters.lower()):
        return text
    if not re.fullmatch(r"[A-Za-z0-9]+", text):
        return text
    parts = []
    for token in _TOKEN_RE.findall(text.lower()):
        if token.isdigit():
            parts.append(token)
            continue
        cased = _element_case(token)
        if cased is None:
            return text
        parts.append(cased)
    return "".join(parts)


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name an analyte (empty, too long, control characters), or None."""
    text = name.strip()
    if not text:
        return "an analyte name is empty or white space"
    if len(text) > MAX_NAME_CHARS:
        return f"analyte name {text[:MAX_NAME_CHARS]!r}... is longer than {MAX_NAME_CHARS} characters"
    if any(not c.isprintable() for c in text):
        return f"analyte name {text!r} has a control character"
    return None


def declared_list(names: Iterable[str]) -> tuple[str, ...]:
    """A declared list made canonical: each name stripped, spelled as in
    :data:`DEFAULT_ANALYTES` when it is one of those (else :func:`formula_case`), and
    later spellings of a name already listed dropped.  Raises ValueError naming a bad name.
    """
    defaults = {key(a): a for a in DEFAULT_ANALYTES}
    out: dict[str, str] = {}
    for name in names:
        problem = name_problem(name)
        if problem:
            raise ValueError(problem)
        k = key(name)
        out.setdefault(k, defaults.get(k) or formula_case(name))
    if not out:
        raise ValueError("the declared analyte list is empty")
    return tuple(out.values())


def parse_list(text: str) -> tuple[str, ...]:
    """A comma-separated declared list (``"Fe,SiO2,P"``), made canonical by
    :func:`declared_list`; raises ValueError with a one-line reason."""
    return declared_list(part for part in text.split(",") if part.strip()) if text.strip() \
        else declared_list(())


@dataclass(frozen=True)
class AnalytePolicy:
    """A site's declared analytes and what to do with an unknown one.

    Attributes
    ----------
    declared : tuple of str
        Canonical names, in the site's order (:func:`declared_list`).
    unknown : str
        ``"quarantine"`` or ``"flag"`` (:data:`UNKNOWN_POLICIES`).
    """

    declared: tuple[str, ...] = DEFAULT_ANALYTES
    unknown: str = DEFAULT_UNKNOWN_POLICY

    def __post_init__(self) -> None:
        if self.unknown not in UNKNOWN_POLICIES:
            raise ValueError(f"unknown-analyte policy must be one of {', '.join(UNKNOWN_POLICIES)}, "
                             f"not {self.unknown!r}")
        object.__setattr__(self, "declared", declared_list(self.declared))
        object.__setattr__(self, "_by_key", {key(a): a for a in self.declared})

    def canonical(self, name: str) -> str | None:
        """The declared name ``name`` spells, or None when it is unknown."""
        return self._by_key.get(key(name))  # type: ignore[attr-defined]

    def resolve(self, recorded: "AnalytePolicy | None") -> "AnalytePolicy":
        """As :meth:`AnalyteOptions.resolve` with this list and policy given."""
        return AnalyteOptions(self.declared, self.unknown).resolve(recorded)


def canonical_name(name: str, declared: Iterable[str] = DEFAULT_ANALYTES) -> str:
    """The canonical spelling of ``name``: the declared name it spells (case-insensitive,
    white space stripped), else :func:`formula_case`."""
    k = key(name)
    for d in declared:
        if key(d) == k:
            return d
    return formula_case(name)


def canonical_grades(grades: Mapping[str, float],
                     declared: Iterable[str] = DEFAULT_ANALYTES) -> dict[str, float]:
    """A grade (analyte -> mass %) keyed by canonical names, in name order.  When two
    spellings of one analyte appear, the value under the canonical spelling wins, else the
    first spelling in sorted order."""
    declared = tuple(declared)
    out: dict[str, float] = {}
    exact: set[str] = set()
    for name in sorted(grades):
        canon = canonical_name(name, declared)
        if canon not in out or (name == canon and canon not in exact):
            out[canon] = float(grades[name])
            if name == canon:
                exact.add(canon)
    return {name: out[name] for name in sorted(out)}


def spellings(grades: Iterable[str], policy: AnalytePolicy) -> tuple[list[str], list[str]]:
    """(unknown names, problems) of the analyte names of one event under ``policy``.

    A problem is a name that cannot be an analyte (:func:`name_problem`) or a second
    spelling of an analyte the event already names (``Fe`` and ``FE``)."""
    unknown: list[str] = []
    problems: list[str] = []
    seen: dict[str, str] = {}
    for name in sorted(grades):
        problem = name_problem(name)
        if problem:
            problems.append(problem)
            continue
        k = key(name)
        if k in seen:
            problems.append(f"{seen[k]!r} and {name!r} name one analyte")
            continue
        seen[k] = name
        if policy.canonical(name) is None:
            unknown.append(name)
    return unknown, problems


@dataclass(frozen=True)
class AnalyteOptions:
    """What a writer was told about analytes; None where it was told nothing (then the
    list and policy the ledger recorded hold)."""

    declared: tuple[str, ...] | None = None
    unknown: str | None = None

    def resolve(self, recorded: AnalytePolicy | None) -> AnalytePolicy:
        """The policy to write with: the ``recorded`` list followed by the declared names it
        lacks (a list only grows), the given unknown-analyte policy else the recorded one;
        for a ledger that recorded none, the given list else :data:`DEFAULT_ANALYTES`."""
        if recorded is None:
            return AnalytePolicy(self.declared or DEFAULT_ANALYTES,
                                 self.unknown or DEFAULT_UNKNOWN_POLICY)
        return AnalytePolicy(recorded.declared + (self.declared or ()),
                             self.unknown or recorded.unknown)


def policy_from_args(args) -> AnalyteOptions | None:
    """The options of ``common.options.add_analytes``' arguments (None when neither is
    given); raises ValueError with a one-line reason for a bad list."""
    names, unknown = getattr(args, "analytes", None), getattr(args, "unknown_analyte", None)
    if names is None and unknown is None:
        return None
    if unknown is not None and unknown not in UNKNOWN_POLICIES:
        raise ValueError(f"--unknown-analyte must be one of {', '.join(UNKNOWN_POLICIES)}, "
                         f"not {unknown!r}")
    return AnalyteOptions(parse_list(names) if names is not None else None, unknown)
