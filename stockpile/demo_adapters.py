"""The process demo through the real adapters (``stockpile demo --adapters real``).

The simulator (``stockpile sim --adapters real``) serves its machines' PLCs over OPC UA,
writes the lab's results as LIMS files into a drop folder and sends its scans to an
emulated LMS511 on TCP (:mod:`sim.adapters`); the demo runs the product's adapters on
them instead of taking those events from the simulator:

* ``stockpile service plc --source S``, one process per source ``S`` (the router lets a
  certificate publish under its own name only): the reclaimer's joint readings
  (``<machine>.encoders``), its cuts (``<machine>.plc``) and the stacker's passes
  (``<stacker>.plc``), over ``Basic256Sha256`` ``SignAndEncrypt`` with throw-away
  application certificates in ``<out>/opcua``;
* ``stockpile service lab --watch <sim>/lims-drop`` (source ``lab1``);
* ``stockpile service scanner --tcp 127.0.0.1:PORT --protocol cola-b`` (source
  ``<machine>.scanner``), in place of the serial scanner.

The money events (cuts, passes, assays) are signed with the keys the demo declared for
their sources (:mod:`stockpile.demo_signing`).  Once the scenario ends the demo waits until
the ledger holds what the devices handed out (the simulator's ``devices:`` line), then
stops the adapters; each one's published count comes from its ``published`` log line.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Callable

from security.opcua_certs import make_application_certificate
from services.ledger_client import LedgerClient
from sim.opcua_server import APPLICATION_URI

__all__ = ["LAB_SOURCE", "adapter_members", "opcua_certificates", "sim_options",
           "start_adapters", "expected_counts", "wait_delivered"]

#: the lab adapter's source (the LIMS map's lab id, and the simulator's)
LAB_SOURCE = "lab1"
#: the PLC adapter's OPC UA application URI (its certificate carries it)
ADAPTER_URI = "urn:stockpile:plc-adapter"


def plc_sources(machine: str, stacker: str) -> tuple[str, ...]:
    """The PLC adapter's sources: one ``service plc`` process each."""
    return (f"{machine}.encoders", f"{machine}.plc", f"{stacker}.plc")


def adapter_members(machine: str, stacker: str) -> dict[str, str]:
    """The adapters' certificate names (= their sources) -> role."""
    return {**{source: "plc" for source in plc_sources(machine, stacker)}, LAB_SOURCE: "lab"}


def opcua_certificates(out_dir: Path) -> tuple[list[str], list[str]]:
    """Make the simulated PLC's and the adapter's application certificates afresh in
    ``out_dir/opcua``; return the simulator's options and the adapter's."""
    folder = Path(out_dir) / "opcua"
    server_cert, server_key = make_application_certificate(folder, "sim-plc", APPLICATION_URI,
                                                           force=True)
    cert, key = make_application_certificate(folder, "plc-adapter", ADAPTER_URI, force=True)
    return (["--opcua-cert", str(server_cert), "--opcua-key", str(server_key)],
            ["--cert", str(cert), "--key", str(key), "--server-cert", str(server_cert)])


def sim_options(site: str, machine: str, stacker: str, opcua: list[str]) -> list[str]:
    """``stockpile sim`` options of the real devices: start once every PLC adapter and the
    lab adapter are live and the scanner streams."""
    live = f"stockpile/{site}/@live"
    waits = [f"{live}/plc/{source}" for source in plc_sources(machine, stacker)]
    waits.append(f"{live}/lab/{LAB_SOURCE}")
    return ["--adapters", "real", *opcua, "--wait-lms511", "60",
            *(arg for key in waits for arg in ("--wait-live", key))]


def start_adapters(yard, sim, *, machine: str, stacker: str, keys: Path,
                   opcua: list[str], common: Callable[[str], list[str]]) -> list[str]:
    """Start the PLC adapters, the lab adapter and the scanner on the simulator's devices
    (read from its stdout); return the children's names.  ``keys``: the folder of the
    sources' signing keys; ``common(name)``: the options of a child with certificate
    ``name``."""
    said = {p: sim.wait_stdout(lambda l, p=p: l.startswith(p), 60)[len(p):]
            for p in ("OPC UA server on ", "LIMS drop folder ", "LMS511 on tcp ")}
    (endpoint, plc_map), (drop, lims_map) = (
        (said[p].split()[0], re.search(r"map (.+)\)$", said[p].strip()).group(1))
        for p in ("OPC UA server on ", "LIMS drop folder "))
    lms = said["LMS511 on tcp "].split()[0]
    names = []
    for source in plc_sources(machine, stacker):
        key = keys / f"{source}.sign.key"
        signing = ["--signing-key", str(key)] if key.exists() else []
        name = f"plc-{source}"
        yard.start(name, ["service", "plc", "--endpoint", endpoint, "--map", plc_map,
                          "--source", source, *opcua, *signing, *common(source)])
        names.append(name)
    yard.start("lab", ["service", "lab", "--watch", drop, "--map", lims_map,
                       "--source", LAB_SOURCE, "--settle", "0",
                       "--signing-key", str(keys / f"{LAB_SOURCE}.sign.key"),
                       *common(LAB_SOURCE)])
    yard.start("scanner", ["service", "scanner", "--tcp", lms, "--protocol", "cola-b",
                           "--clock", "events", "--source", f"{machine}.scanner",
                           *common(f"{machine}.scanner")])
    print(f"   adapters: PLC on {endpoint} ({len(names)} sources), LIMS drop folder {drop}, "
          f"LMS511 on tcp {lms}", flush=True)
    return [*names, "lab", "scanner"]


def expected_counts(sim, machine: str, stacker: str) -> dict[str, int]:
    """Events per source the adapters should publish, from the simulator's ``devices:``
    line: a joint reading per encoder sample, two events per pass, one per cut, assay
    and scan sent."""
    line = sim.wait_stdout(lambda l: l.strip().startswith("devices:"), 60)
    number = {label: int(value.replace(",", "")) for value, label in re.findall(
        r"([0-9,]+) (encoder samples|passes|cuts|assays|LMS511 telegrams)", line)}
    return {f"{machine}.encoders": number["encoder samples"], f"{stacker}.plc": 2 * number["passes"],
            f"{machine}.plc": number["cuts"], LAB_SOURCE: number["assays"],
            f"{machine}.scanner": number["LMS511 telegrams"]}


def wait_delivered(client: LedgerClient, expected: dict[str, int],
                   timeout_s: float) -> dict[str, int]:
    """Block until the ledger holds ``expected`` events of every source, at most
    ``timeout_s``; return what is still short per source (empty: everything arrived)."""
    deadline = time.monotonic() + timeout_s
    while True:
        per_source = client.stats()["per_source"]
        short = {s: n - per_source.get(s, 0) for s, n in expected.items()
                 if per_source.get(s, 0) < n}
        if not short or time.monotonic() > deadline:
            return short
        time.sleep(0.2)
