"""PostgreSQL for the tests (a pytest plugin, loaded from conftest.py).

``pg_server``: one throw-away :class:`~ledger.pg_local.LocalPostgres` per session,
started by the first test that asks for it (as ``nobody`` when the tests run as root),
stopped at the end; the tests that use it are skipped, with the reason, only when no
PostgreSQL server binaries can be found at all.  ``pg_schemas`` makes fresh ledger
URLs (a schema each) on it and drops them after the test; ``pg_url`` is one of them.
"""

from __future__ import annotations

import itertools

import psycopg
import pytest

from ledger.pg_local import LocalPostgres, PostgresNotFound, find_bindir
from ledger.postgres_sql import quoted

_NAMES = itertools.count()
#: how long dropping a test's schema may wait for a lock, ms
_DROP_LOCK_TIMEOUT_MS = 5_000


@pytest.fixture(scope="session")
def pg_server():
    """The session's local PostgreSQL server (not durable: fsync off)."""
    try:
        bindir = find_bindir()
    except PostgresNotFound as exc:
        pytest.skip(str(exc))
    server = LocalPostgres(bindir=bindir, durable=False)
    try:
        yield server
    finally:
        server.stop()


class PgSchemas:
    """Fresh ledger schemas on the session's server, each named once, all dropped by
    :meth:`drop_all`."""

    def __init__(self, server: LocalPostgres) -> None:
        self.server = server
        self.names: list[str] = []

    @property
    def admin_url(self) -> str:
        """The superuser's URL (no schema parameter)."""
        return self.server.url()

    def new_schema(self, prefix: str = "t") -> str:
        name = f"{prefix}_{next(_NAMES)}"
        self.names.append(name)
        return name

    def url_of(self, schema: str, user: str | None = None, password: str | None = None) -> str:
        base = self.server.url() if user is None else self.server.url(user, password=password)
        return f"{base}?schema={schema}"

    def new_url(self, prefix: str = "t") -> str:
        """The superuser's URL of a schema no test has used (installed on first open)."""
        return self.url_of(self.new_schema(prefix))

    def drop_all(self) -> None:
        with psycopg.connect(self.admin_url, autocommit=True) as con:
            con.execute(f"SET lock_timeout = {_DROP_LOCK_TIMEOUT_MS}")
            for name in self.names:
                try:
                    con.execute(f"DROP SCHEMA IF EXISTS {quoted(name)} CASCADE")
                except psycopg.errors.LockNotAvailable:
                    # a store the test left open: end its sessions, then drop
                    con.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                                "WHERE pid <> pg_backend_pid() AND backend_type = "
                                "'client backend'")
                    con.execute(f"DROP SCHEMA IF EXISTS {quoted(name)} CASCADE")
        self.names.clear()


@pytest.fixture
def pg_schemas(pg_server):
    """Fresh schema URLs on the session's server, dropped after the test."""
    schemas = PgSchemas(pg_server)
    try:
        yield schemas
    finally:
        schemas.drop_all()


@pytest.fixture
def pg_url(pg_schemas) -> str:
    """A superuser URL of a fresh ledger schema (installed when first opened)."""
    return pg_schemas.new_url()
