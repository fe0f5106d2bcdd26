"""Where the dashboard's stream goes: the Rerun recording and its sinks (an .rrd file
and/or a gRPC server on loopback, :func:`make_recording`, :func:`close_recording`) and
the web viewer for operators' browsers (:class:`WebViewer`, the ``rerun`` binary that
rerun-sdk ships), with the loopback port checks they need.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Iterable
from urllib.parse import quote

from services.dashboard.config import APP_ID, Config
from services.dashboard.recorder import rr
from services.dashboard.style import recording_blueprint

LOOPBACK = "127.0.0.1"
#: seconds for the gRPC server / the web viewer to accept connections
GRPC_START_S = 10.0
VIEWER_START_S = 20.0


def make_recording(config: Config, analytes: Iterable[str] = ("Fe", "SiO2", "Al2O3", "P", "LOI"),
                   *, recording_id: str | None = None, pile=None, boxes=None):
    """A RecordingStream with our sinks (file and/or loopback gRPC server) and blueprint
    (:func:`~services.dashboard.style.recording_blueprint`: ``pile``, the one pile's
    footprint; ``boxes``, several piles' footprints by id).

    Returns ``(rec, grpc_uri or None)``.  The log time and log tick timelines are disabled:
    the timelines come from the data.
    """
    rerun = rr()
    rec = rerun.RecordingStream(APP_ID, recording_id=recording_id)
    rerun.set_log_time_enabled(False, recording=rec)
    rerun.set_log_tick_enabled(False, recording=rec)
    bp = recording_blueprint(config, analytes, pile=pile, boxes=boxes)
    sinks = []
    uri = None
    if config.serve:
        for name, port in (("--grpc-port", config.grpc_port), ("--web-port", config.web_port)):
            if not port_free(int(port)):
                raise OSError(f"{name} {port}: the port is in use on {LOOPBACK}")
        server = rerun.GrpcServerSink(bind_ip=LOOPBACK, port=int(config.grpc_port))
        uri = server.uri
        sinks.append(server)
    if config.rrd:
        Path(config.rrd).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rerun.FileSink(str(config.rrd)))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=bp)
    else:
        rec.set_sinks(rerun.FileSink("/dev/null"), default_blueprint=bp)
    if config.serve and not wait_listening(int(config.grpc_port), GRPC_START_S, None):
        rec.disconnect()
        raise OSError(f"the gRPC server did not start on {LOOPBACK}:{config.grpc_port}")
    return rec, uri


def close_recording(rec) -> None:
    """Flush and disconnect; a sink that died (a server thread) becomes one OSError."""
    try:
        rec.flush(timeout_sec=60.0)
    except RuntimeError as exc:
        raise OSError(f"Rerun: {exc}") from None
    finally:
        rec.disconnect()


class WebViewer:
    """The Rerun web viewer for operators' browsers, connected to our gRPC server.

    It is the ``rerun`` viewer binary shipped with rerun-sdk, run as a child process with
    ``--web-viewer --bind 127.0.0.1`` so it listens on loopback only (the Python API's
    ``serve_web_viewer`` binds every interface, so it is never used: without the binary
    the web viewer is refused).  :meth:`close` stops the child.
    """

    def __init__(self, config: Config, uri: str) -> None:
        self.process = None
        self.url = f"http://{LOOPBACK}:{config.web_port}/?url={quote(uri, safe='')}"
        command = rerun_binary() or shutil.which("rerun")
        if command:
            self.process = subprocess.Popen(
                [command, "--web-viewer", "--bind", LOOPBACK, "--web-viewer-port",
                 str(int(config.web_port)), uri],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            if not wait_listening(int(config.web_port), VIEWER_START_S, self.process):
                self.close()
                raise OSError(f"the Rerun web viewer did not start on port {config.web_port}")
        else:   # pragma: no cover - rerun-sdk ships the command
            # the Python API's serve_web_viewer would listen on every interface
            raise OSError("no Rerun viewer binary (rerun_cli/rerun or rerun on the PATH): "
                          "the web viewer is served only by it, bound to 127.0.0.1")

    def close(self) -> None:
        """Stop the viewer (terminate, then kill after 10 s)."""
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except Exception:  # noqa: BLE001 - it must not outlive us
                self.process.kill()
                self.process.wait()
        self.process = None


def rerun_binary() -> str | None:
    """The viewer binary rerun-sdk ships (``rerun_cli/rerun``): run directly, not through its
    Python wrapper, so that terminating it stops the viewer."""
    try:
        import rerun_cli   # deferred: optional, only to find the binary
    except ImportError:   # pragma: no cover
        return None
    exe = Path(rerun_cli.__file__).with_name("rerun")
    return str(exe) if exe.exists() else None


def port_free(port: int) -> bool:
    """Whether a TCP port can be bound on loopback."""
    with socket.socket() as sock:
        try:
            sock.bind((LOOPBACK, port))
        except OSError:
            return False
    return True


def wait_listening(port: int, timeout_s: float, process) -> bool:
    """Until something accepts TCP connections on 127.0.0.1:port (or ``process`` exits)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            return False
        with socket.socket() as sock:
            sock.settimeout(0.2)
            if sock.connect_ex((LOOPBACK, port)) == 0:
                return True
        time.sleep(0.1)
    return False
