"""Fault injection (issue: reliability): every case ends by checking the ledger against
what the producers published, exactly once or an exact gap record.

Cases marked ``long_fault`` run only under ``make faults`` (``pytest --long-faults``);
the rest are part of ``make test``.
"""

import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "/faults/" in str(item.fspath):
            item.add_marker(pytest.mark.faults)
