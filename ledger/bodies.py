"""The JSON bodies the SQL views read, checked against the payloads they were made from.

A ledger keeps, beside the payload of each domain event (``ledger.store.BODY_TYPES``), its
protobuf JSON body for the auditors' views.  :func:`body_problem` tells whether a stored
body is still that JSON: a body edited behind the writer's back changes what the views
say without touching the chained payload.
"""

from __future__ import annotations

import json
from typing import Collection

from schemas.events import decode_payload
from schemas.jsonl import body_json


def same_json(a: object, b: object) -> bool:
    """JSON values equal, numbers compared as doubles (a database's JSON type may keep
    ``1.0`` as ``1`` or a decimal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_json(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_json(x, y) for x, y in zip(a, b))
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) \
            and not isinstance(b, bool):
        return float(a) == float(b)
    return a == b


def body_problem(type_name: str, payload: bytes, body: object,
                 body_types: Collection[str]) -> str | None:
    """What is wrong with a stored ``body`` (JSON text, or the value a database decoded)
    of an event of ``type_name`` with ``payload``; None when it is the payload's JSON, or
    when a type outside ``body_types`` has none."""
    if type_name not in body_types:
        return None if body is None else "a body stored for a type that has none"
    if body is None:
        return "the body is missing"
    try:
        expected = json.loads(body_json(decode_payload(type_name, payload)))
    except Exception:  # noqa: BLE001 - a stored payload always decoded; say so if not
        return "payload does not decode"
    stored = json.loads(body) if isinstance(body, (str, bytes)) else body
    if not same_json(stored, expected):
        return "stored body does not match the payload (what the SQL views read was edited)"
    return None
