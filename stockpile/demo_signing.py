"""The process demo's signed events: a throw-away site admin key, a signing key per
producer of the events that move money, their declarations in a fresh ledger, and the
options that make the ledger require signatures and the simulator sign."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from ledger import open_ledger
from ledger.clock import ManualClock
from ledger.signing import ADMIN_EPOCH, ADMIN_SOURCE, key_declaration
from schemas.times import NS_PER_S
from security.event_keys import load_signing_key, new_signing_key

#: validity of the demo's keys: from the epoch to 2100 (simulated yards run in any year)
_VALID_UNTIL_NS = 4_102_444_800 * 10**9


@dataclass(frozen=True)
class DemoSigning:
    """What the demo passes on: the ledger's and the simulator's options, and the admin's
    declarations (``source -> (epoch, count)``, for the exactly-once check)."""

    ledger_args: list[str]
    sim_args: list[str]
    published: dict[str, tuple[int, int]]


def money_sources(machine: str, stacker: str) -> dict[str, str]:
    """The simulated yard's producers of signed types -> the role of their key."""
    return {"yard.config": "admin", f"{machine}.plc": "plc", f"{stacker}.plc": "plc",
            "lims": "lab", "lab1": "lab"}


def prepare_signing(out_dir: Path, ledger_path: Path, sources: dict[str, str],
                    start_ns: int) -> DemoSigning:
    """Make the keys in ``out_dir/keys`` (afresh) and declare them in ``ledger_path``, valid
    and recorded one second before the simulated yard starts (``start_ns``, UTC ns)."""
    keys = Path(out_dir) / "keys"
    if keys.exists():
        shutil.rmtree(keys)
    new_signing_key(keys / "admin", "admin")
    admin = load_signing_key(keys / "admin" / "admin.sign.key")
    subjects = [("site admin", "admin", admin)]
    for source, role in sources.items():
        new_signing_key(keys / "sources", source)
        subjects.append((source, role, load_signing_key(keys / "sources" / f"{source}.sign.key")))
    now = start_ns - NS_PER_S
    events = [key_declaration(admin, key.public_raw, role, name, seq, now, 0, _VALID_UNTIL_NS)
              for seq, (name, role, key) in enumerate(subjects)]
    with open_ledger(ledger_path, ManualClock(now)) as store:
        result = store.append(events)
    refused = [o.reason for o in result.outcomes if o.status != "appended"]
    if refused:
        raise ValueError(f"the demo's key declarations were refused: {refused[0]}")
    return DemoSigning(["--admin-key", str(keys / "admin" / "admin.sign.pub")],
                       ["--signing-keys", str(keys / "sources")],
                       {ADMIN_SOURCE: (ADMIN_EPOCH, len(events))})
