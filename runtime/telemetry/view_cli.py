"""bruce-view: a saved telemetry recording (`bruce-run --rerun save=RUN.rrd`, its continuation parts RUN.001.rrd, ...
included) in rerun's viewer on this machine, or with --web in a browser anywhere on the network: a gRPC server holds
the recording and rerun's web viewer is served over HTTP beside it (docs/telemetry.md#live-view-in-a-browser).

    bruce-view runs/walk.rrd                 # rerun's native viewer (needs a display)
    bruce-view runs/walk.rrd --web           # prints the link to open in a browser; Ctrl-C ends
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import threading
import warnings
from pathlib import Path

from runtime.telemetry.sink import (
    DEFAULT_BUFFER_MB,
    DEFAULT_GRPC_PORT,
    DEFAULT_WEB_PORT,
    HOST_NAME,
    TelemetryError,
    check_port_free,
    recording_parts,
    viewer_host,
    web_origins,
    web_viewer_link,
)

PROG = "bruce-view"
STOP_POLL_S = 0.2
MEMORY_FACTOR = 2.0  # the gRPC server drops the oldest data past its limit: room for the whole recording, twice


class ViewError(ValueError):
    """The recording or an option cannot be served; the message is the one line to print."""


def port(text: str) -> int:
    if not (text.isdigit() and 0 < int(text) < 65536):
        raise argparse.ArgumentTypeError(f"expected a port in 1..65535, got {text!r}")
    return int(text)


def host(text: str) -> str:
    if not HOST_NAME.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected a host name or an IP address (IPv6 in brackets), got {text!r}")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("recording", type=Path, metavar="RUN.rrd",
                   help="a recording of bruce-run --rerun save=RUN.rrd; its parts RUN.001.rrd, ... come along")
    p.add_argument("--web", action="store_true",
                   help="serve it to a browser instead of opening rerun's native viewer")
    p.add_argument("--web-port", type=port, default=DEFAULT_WEB_PORT, metavar="PORT",
                   help="--web: the web viewer's HTTP port (default: %(default)s)")
    p.add_argument("--grpc-port", type=port, default=DEFAULT_GRPC_PORT, metavar="PORT",
                   help="--web: the port of the gRPC server that holds the recording (default: %(default)s)")
    p.add_argument("--host", type=host, default=None, metavar="NAME",
                   help="--web: the host in the printed link (default: this machine's address; both servers listen "
                        "on all interfaces)")
    return p


def checked_parts(path: Path) -> list[Path]:
    """The recording's files, each one checked to be a readable rerun recording; ViewError otherwise."""
    from rerun.chunk import RrdReader

    parts = recording_parts(path)
    if not parts:
        raise ViewError(f"{path}: recording file not found")
    for part in parts:
        try:
            with warnings.catch_warnings():  # a file without footer (a run that was killed) is still readable
                warnings.simplefilter("ignore")
                stores = RrdReader(part).recordings()
        except (OSError, RuntimeError, ValueError) as exc:
            raise ViewError(f"{part}: not a readable rerun recording ({exc})") from exc
        if not stores:
            raise ViewError(f"{part}: the file holds no recording (only a blueprint?)")
    return parts


def serve_web(parts: list[Path], web_port: int, grpc_port: int, link_host: str) -> int:
    """Serve the recording and the web viewer until Ctrl-C (or SIGTERM)."""
    import rerun as rr
    from rerun.chunk import RrdReader

    if web_port == grpc_port:
        raise ViewError(f"--web-port and --grpc-port need different ports (both {web_port})")
    for number, role in ((grpc_port, "the gRPC server"), (web_port, "the web viewer")):
        check_port_free(number, role)
    store = RrdReader(parts[0]).recordings()[0]
    # The file's application and recording id: its data, blueprint included, lands in this one recording, and the
    # viewer lists no second, empty one.
    recording = rr.RecordingStream(store.application_id, recording_id=store.recording_id)
    size_mb = sum(part.stat().st_size for part in parts) / 1e6
    limit_mb = max(DEFAULT_BUFFER_MB, math.ceil(MEMORY_FACTOR * size_mb))
    local = recording.serve_grpc(grpc_port=grpc_port, server_memory_limit=f"{limit_mb}MB",
                                 cors_allow_origin=web_origins(web_port))
    try:
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=local)
        for part in parts:
            recording.log_file_from_path(part)
        recording.flush()
        names = parts[0].name + (f" .. {parts[-1].name} ({len(parts)} files)" if len(parts) > 1 else "")
        print(f"{PROG}: serving {names}, {size_mb:.1f} MB, web viewer on port {web_port}, gRPC on port {grpc_port} "
              f"(all interfaces); open in a browser: {web_viewer_link(link_host, web_port, grpc_port)}  (Ctrl-C "
              "ends)", flush=True)
        wait_for_stop()
    finally:
        recording.disconnect()
    return 0


def wait_for_stop() -> None:
    """Block until SIGINT or SIGTERM. A short wait in a loop: the signal may land on one of rerun's threads, and
    Python runs its handler only when the main thread next runs."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop.wait(STOP_POLL_S):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def open_native(parts: list[Path]) -> int:
    """rerun's native viewer on the parts (one recording id: it shows them as one recording)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewError("no display (DISPLAY and WAYLAND_DISPLAY unset) for rerun's viewer; on a headless machine "
                        "use --web and open the printed link in a browser")
    viewer = subprocess.Popen([sys.executable, "-m", "rerun", *map(str, parts)])
    try:
        return viewer.wait()
    except KeyboardInterrupt:  # Ctrl-C reached the viewer too (one process group): let it close
        return viewer.wait()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        parts = checked_parts(args.recording)
        if args.web:
            return serve_web(parts, args.web_port, args.grpc_port, args.host or viewer_host())
        return open_native(parts)
    except (ViewError, TelemetryError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
