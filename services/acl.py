"""The router's access control, generated from the site's roles.

Zenoh's ACL (``access_control`` in a router's config) decides per message and per
direct link: its subject is the common name of the connected client's certificate, and
a rule matches a message only when one of the rule's key expressions *contains* the
message's key.  ``**`` never matches a chunk that starts with ``@``, so every rule here
names ``@v1``, ``@ledger``, ``@live`` and ``@adv`` explicitly.  Everything not allowed
is denied.

:func:`access_control` builds the block from ``{certificate name: role}``; what each
role may do is :data:`ROLE_GRANTS`, drawn as key templates (``{site}``: the site,
``{name}``: the certificate's common name, which is also the source name of the events
that certificate publishes).

Message kinds (zenoh 1.x): ``put``, ``delete``, ``declare_subscriber``, ``query``,
``reply``, ``declare_queryable``, ``liveliness_token``, ``liveliness_query``,
``declare_liveliness_subscriber``.  Flows: ``ingress`` is from the client to the
router, ``egress`` from the router to the client.

A head office links the sites' routers to its own (``docs/security.md``).  At the
head-office router, a site router's link (an ``uplink`` certificate named
``<site>.router``) may announce and answer that site's ledger queries and put its head
(:data:`UPLINK_GRANTS`), and the head-office service (role ``hq``) may query every
site's ledger and follow its head.  At a site router, the head-office router's link
(:func:`access_control`'s ``head_office``) may do the mirror image: query the ledger and
follow its head, nothing that writes to the site (:data:`HEAD_OFFICE_GRANTS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping

from security.pki import ROLES


#: event types each publishing role may put, under its own name as the source
PUBLISHES: dict[str, tuple[str, ...]] = {
    "scanner": ("scan",),
    "gnss": ("location_fix",),
    "plc": ("joint_reading", "stack_started", "stack_ended", "reclaim_cut", "clock"),
    "localizer": ("joint_estimate", "frame_transform"),
    "lab": ("assay", "lot_declared"),
}

#: event types each subscribing role reads live
SUBSCRIBES: dict[str, tuple[str, ...]] = {
    "localizer": ("joint_reading", "location_fix", "clock", "site_declared", "machine_declared"),
}


@dataclass(frozen=True)
class Grant:
    """Messages a role may exchange on some keys, in some directions."""

    messages: tuple[str, ...]
    flows: tuple[str, ...]
    keys: tuple[str, ...]  # templates with {site}, {name}, {type}


EVENT = "stockpile/{site}/@v1/{type}/{name}"
EVENT_ADV = "stockpile/{site}/@v1/{type}/{name}/@adv/**"
ALL_EVENTS = "stockpile/{site}/@v1/**"
#: every AdvancedPublisher's and AdvancedSubscriber's cache, liveliness and history keys
ALL_ADV = "stockpile/{site}/@v1/**/@adv/**"
LEDGER_Q = "stockpile/{site}/@ledger/q/*"
LEDGER_HEAD = "stockpile/{site}/@ledger/head"
LEDGER_CHECKPOINT = "stockpile/{site}/@ledger/checkpoint"
LEDGER_STATUS = "stockpile/{site}/@ledger/status"
LIVE_OF = "stockpile/{site}/@live/{service}/**"
LIVE_ANY = "stockpile/{site}/@live/**"

#: the service name in a role's liveliness token (``stockpile/<site>/@live/<service>/...``)
ROLE_SERVICE = {"scanner": "scanner", "gnss": "gnss", "plc": "plc", "localizer": "localizer",
                "lab": "lab", "ledger": "ledger", "projector": "projector",
                "recorder": "recorder", "dashboard": "dashboard", "hq": "hq"}


def _publisher(types: tuple[str, ...]) -> list[Grant]:
    """An AdvancedPublisher of ``types`` under its own name: puts, its cache queryable and
    liveliness token under ``@adv``, answers to history queries, and the sight of the
    subscribers that want its events (without which a publisher's puts go nowhere)."""
    own = tuple(EVENT.replace("{type}", t) for t in types)
    own_adv = tuple(EVENT_ADV.replace("{type}", t) for t in types)
    return [
        Grant(("put",), ("ingress",), own),
        Grant(("declare_queryable", "liveliness_token"), ("ingress",), own_adv),
        # a cache answers a history query with the samples' own keys
        Grant(("reply",), ("ingress",), own + own_adv),
        Grant(("query", "liveliness_token"), ("egress",), (ALL_ADV,)),
        Grant(("liveliness_query", "declare_liveliness_subscriber"), ("ingress",), (ALL_ADV,)),
        Grant(("declare_subscriber",), ("egress",), (ALL_EVENTS,)),
    ]


def _event_reader(keys: tuple[str, ...], adv: tuple[str, ...]) -> list[Grant]:
    """An AdvancedSubscriber with history on ``keys``: the events, and the publishers'
    caches and liveliness under ``@adv``."""
    return [
        Grant(("declare_subscriber",), ("ingress",), keys),
        Grant(("put",), ("egress",), keys),
        Grant(("query", "liveliness_query", "declare_liveliness_subscriber", "liveliness_token"),
              ("ingress",), adv),
        Grant(("liveliness_token",), ("egress",), adv),
        Grant(("reply",), ("egress",), keys + adv),
    ]


def _ledger_reader() -> list[Grant]:
    """Queries of the ledger service, its head and its status (alarms)."""
    return [
        Grant(("query",), ("ingress",), (LEDGER_Q,)),
        Grant(("reply",), ("egress",), (LEDGER_Q,)),
        Grant(("declare_subscriber",), ("ingress",), (LEDGER_HEAD, LEDGER_CHECKPOINT,
                                                      LEDGER_STATUS)),
        Grant(("put",), ("egress",), (LEDGER_HEAD, LEDGER_CHECKPOINT, LEDGER_STATUS)),
    ]


def _republisher() -> list[Grant]:
    """Publishes any event type under any source (a replay of a recording, the
    simulator), and sees which services are live (it waits for them)."""
    grants = [Grant(g.messages, g.flows, tuple(k.replace("{name}", "*") for k in g.keys))
              for g in _publisher(("*",))]
    return grants + [
        Grant(("declare_liveliness_subscriber", "liveliness_query"), ("ingress",), (LIVE_ANY,)),
        Grant(("liveliness_token",), ("egress",), (LIVE_ANY,)),
    ]


#: which services are live (their liveliness tokens): operators' and auditors' view
LIVE_READ = Grant(("declare_liveliness_subscriber", "liveliness_query"), ("ingress",),
                  (LIVE_ANY,))
LIVE_SEEN = Grant(("liveliness_token",), ("egress",), (LIVE_ANY,))

#: the site clock's events: a service on the simulated yard's clock (``--clock events``)
#: dates what it publishes by them
CLOCK_READ = [Grant(("declare_subscriber",), ("ingress",), ("stockpile/{site}/@v1/clock/**",)),
              Grant(("put",), ("egress",), ("stockpile/{site}/@v1/clock/**",))]

#: the ledger's read queries (``q/backup`` is not one: it makes the site write a backup)
LEDGER_READS = ("events", "as_of", "stats", "head", "gaps", "quarantine", "streams")
READ_QUERIES = tuple(f"stockpile/{{site}}/@ledger/q/{what}" for what in LEDGER_READS)
#: at the head-office router, a site router's link ({site}: the site its name names)
UPLINK_GRANTS = [
    Grant(("declare_queryable",), ("ingress",), READ_QUERIES),
    Grant(("query",), ("egress",), READ_QUERIES),
    Grant(("reply",), ("ingress",), READ_QUERIES),
    Grant(("declare_subscriber",), ("egress",), (LEDGER_HEAD,)),
    Grant(("put",), ("ingress",), (LEDGER_HEAD,)),
]
#: at a site router, the head-office router's link: reads of the ledger, nothing else
#: (the uplink's grants seen from the other end of the same link: every flow reversed)
_REVERSED = {"ingress": "egress", "egress": "ingress"}
HEAD_OFFICE_GRANTS = [Grant(g.messages, tuple(_REVERSED[f] for f in g.flows), g.keys)
                      for g in UPLINK_GRANTS]
ANY_SITE_READS = tuple(q.replace("{site}", "*") for q in READ_QUERIES)
ANY_SITE_HEAD = "stockpile/*/@ledger/head"
HQ_STATUS = "stockpile/{site}/@hq/status"
#: where an uplink certificate's name says which site it links (``<site>.router``)
UPLINK_SUFFIX = ".router"

ROLE_GRANTS: dict[str, list[Grant]] = {
    **{role: _publisher(types) + CLOCK_READ for role, types in PUBLISHES.items()},
    "replay": _republisher(),
    "ledger": _event_reader((ALL_EVENTS,), (ALL_ADV,)) + [
        Grant(("declare_queryable",), ("ingress",), (LEDGER_Q,)),
        Grant(("query",), ("egress",), (LEDGER_Q,)),
        Grant(("reply",), ("ingress",), (LEDGER_Q,)),
        Grant(("put",), ("ingress",), (LEDGER_HEAD, LEDGER_CHECKPOINT, LEDGER_STATUS)),
        Grant(("declare_subscriber",), ("egress",), (LEDGER_HEAD, LEDGER_CHECKPOINT,
                                                     LEDGER_STATUS)),
    ],
    "recorder": _event_reader((ALL_EVENTS,), (ALL_ADV,)) + [
        Grant(("declare_subscriber",), ("ingress",), (LEDGER_CHECKPOINT,)),
        Grant(("put",), ("egress",), (LEDGER_CHECKPOINT,))],
    "auditor": _ledger_reader() + [LIVE_READ, LIVE_SEEN],
    "dashboard": _ledger_reader() + [LIVE_READ, LIVE_SEEN],
    "projector": _ledger_reader(),
    "hq": [Grant(("query",), ("ingress",), ANY_SITE_READS),
           Grant(("reply",), ("egress",), ANY_SITE_READS),
           Grant(("declare_subscriber",), ("ingress",), (ANY_SITE_HEAD, HQ_STATUS)),
           Grant(("put",), ("egress",), (ANY_SITE_HEAD, HQ_STATUS)),
           Grant(("put",), ("ingress",), (HQ_STATUS,))],
    "uplink": UPLINK_GRANTS,
}
ROLE_GRANTS["localizer"] = ROLE_GRANTS["localizer"] + _event_reader(
    tuple(f"stockpile/{{site}}/@v1/{t}/**" for t in SUBSCRIBES["localizer"]),
    tuple(f"stockpile/{{site}}/@v1/{t}/**/@adv/**" for t in SUBSCRIBES["localizer"]))
#: a localizer started after its declarations' publishers left reads them from the ledger
LEDGER_EVENTS_Q = "stockpile/{site}/@ledger/q/events"
ROLE_GRANTS["localizer"] += [Grant(("query",), ("ingress",), (LEDGER_EVENTS_Q,)),
                             Grant(("reply",), ("egress",), (LEDGER_EVENTS_Q,))]
for _role, _service in ROLE_SERVICE.items():
    ROLE_GRANTS[_role] = ROLE_GRANTS.get(_role, []) + [
        Grant(("liveliness_token",), ("ingress",), (LIVE_OF.replace("{service}", _service),))]


def _fill(template: str, site: str, name: str) -> str:
    return template.replace("{site}", site).replace("{name}", name)


def uplink_site(name: str) -> str:
    """The site an uplink certificate's name links (``<site>.router``), else ValueError."""
    site = name[:-len(UPLINK_SUFFIX)] if name.endswith(UPLINK_SUFFIX) else ""
    if not site or "/" in site or "*" in site or site.startswith("@"):
        raise ValueError(f"{name}: an uplink certificate is named <site>{UPLINK_SUFFIX}")
    return site


def access_control(site: str, members: Mapping[str, str], *,
                   head_office: str | None = None) -> dict:
    """The router's ``access_control`` block for ``{certificate name: role}``.

    Deny by default; each certificate name is a subject with its role's grants (an
    ``uplink`` name's for the site it names).  ``head_office`` is the common name of the
    head-office router's certificate, granted :data:`HEAD_OFFICE_GRANTS` on this site's
    ledger (the link this router opens to it).  Raises ValueError for an unknown role, a
    badly named uplink, or a head office named like a member.
    """
    entries = []
    for name, role in sorted(members.items()):
        if role not in ROLES:
            raise ValueError(f"{name}: unknown role {role!r} (known: {', '.join(ROLES)})")
        where = uplink_site(name) if role == "uplink" else site
        entries.append((name, role, where, ROLE_GRANTS.get(role, [])))
    if head_office:
        if head_office in members:
            raise ValueError(f"the head office's router {head_office!r} is also a certificate "
                             "of this site: give its own name")
        entries.append((head_office, "head-office", site, HEAD_OFFICE_GRANTS))
    rules, subjects, policies = [], [], []
    for name, role, where, grants in entries:
        if not grants:
            continue
        subject = f"cert:{name}"
        subjects.append({"id": subject, "cert_common_names": [name]})
        ids = []
        for i, grant in enumerate(grants):
            rule_id = f"{name}:{role}:{i}"
            rules.append({"id": rule_id, "permission": "allow", "flows": list(grant.flows),
                          "messages": list(grant.messages),
                          "key_exprs": sorted({_fill(k, where, name) for k in grant.keys})})
            ids.append(rule_id)
        policies.append({"id": f"policy:{name}", "rules": ids, "subjects": [subject]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def members_from_index(entries: Iterable[Mapping]) -> dict[str, str]:
    """``{name: role}`` of the certificate names in a PKI index.

    The ACL matches a certificate's common name, not its serial, and Zenoh checks no
    revocation list.  So a name with a certificate revoked for any reason but
    ``superseded`` (a rotation: the old key was replaced, not lost) gets no rights at all;
    its replacement is issued under a new name.
    """
    entries = list(entries)
    denied = {str(e["name"]) for e in entries
              if e.get("revoked") and e.get("revocation_reason") != "superseded"}
    return {str(e["name"]): str(e["role"]) for e in entries if str(e["name"]) not in denied}
