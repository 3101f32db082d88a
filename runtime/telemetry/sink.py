"""Where telemetry goes (`--rerun SINK`): parsing and checking the sink, the file parts of a rotated recording.

Sinks: spawn | connect[=ADDR] | serve[=PORT][,buffer_mb=MB] |
web[=PORT][,grpc_port=P][,buffer_mb=MB][,host=NAME][,row_hz=HZ] | save=PATH[,max_mb=MB][,keep=N] | off; a trailing
`,key=value` is an option (a comma otherwise stays in the path), max_mb=0 writes one file. ADDR is host:port or a
full rerun+http(s)://host:port/proxy URL (default rerun+http://127.0.0.1:9876/proxy). `web` serves rerun's web
viewer over HTTP beside the gRPC stream; NAME is the host put in the link it prints (default: this machine's
address, see `viewer_host`).
"""

from __future__ import annotations

import math
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, urlsplit

DEFAULT_MAX_MB = 1000.0     # save=: a new part starts when the current file reaches this size
DEFAULT_BUFFER_MB = 256     # serve: history the gRPC server keeps for viewers that connect late
WEB_BUFFER_MB = 64          # web: less, a browser that opens the link late replays all of it first (~4 min)
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090     # rerun's own default for its web viewer
WEB_ROW_HZ = 100.0          # web: joint rows per second a browser's viewer is sent (docs/telemetry.md)
SINK_HELP = ("where telemetry goes: spawn (a local viewer), connect[=HOST:PORT|URL] (a running viewer), "
             "serve[=PORT][,buffer_mb=MB] (a gRPC server a laptop viewer attaches to; keeps the newest MB for late "
             f"viewers, default {DEFAULT_BUFFER_MB}), web[=PORT][,grpc_port=P][,buffer_mb=MB][,host=NAME]"
             f"[,row_hz=HZ] (the gRPC server plus rerun's web viewer over HTTP on PORT, default {DEFAULT_WEB_PORT}, "
             f"gRPC on P, default {DEFAULT_GRPC_PORT}; prints the link to open in a browser, with NAME as its host, "
             f"default this machine's address; rows at HZ, default {WEB_ROW_HZ:g}, loop timing as each interval's "
             f"maximum; history MB, default {WEB_BUFFER_MB}), save=PATH[,max_mb=MB][,keep=N] (an .rrd file; "
             f"continues in PATH-stem.001.rrd, .002, ... each time the file reaches MB, default {DEFAULT_MAX_MB:g}, "
             "0: one file; keep=N: only the newest N files stay on disk), off")
SINK_KINDS = ("spawn", "connect", "serve", "web", "save", "off")
ACCEPTED = ("expected one of spawn, connect, connect=HOST:PORT|URL, serve[=PORT][,buffer_mb=MB], "
            "web[=PORT][,grpc_port=P][,buffer_mb=MB][,host=NAME][,row_hz=HZ], save=PATH[,max_mb=MB][,keep=N], off")
SINK_OPTIONS = {"save": ("max_mb", "keep"), "serve": ("buffer_mb",),
                "web": ("grpc_port", "buffer_mb", "host", "row_hz")}
OPTION_ITEM = re.compile(r"[A-Za-z_]\w*=")  # a trailing ",key=value" is an option, not part of a path
HOST_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\]")  # a name, IPv4, [IPv6]
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"  # where rerun connects without ADDR
VIEWER_PROBE_TIMEOUT_S = 2.0
class TelemetryError(RuntimeError):
    """Telemetry could not be started; the message names the sink."""


@dataclass(frozen=True)
class RerunSink:
    kind: str
    target: str | None = None  # connect: ADDR (None: rerun's default); serve: PORT (None: 9876); web: the web
    #                            viewer's PORT (None: 9090); save: PATH
    max_mb: float | None = None   # save: rotation size (None: DEFAULT_MAX_MB; 0: one file)
    keep: int | None = None       # save: parts kept on disk (None: all)
    buffer_mb: int | None = None  # serve, web: the server's history (None: DEFAULT_BUFFER_MB, WEB_BUFFER_MB)
    grpc_port: int | None = None  # web: the gRPC server's port (None: DEFAULT_GRPC_PORT)
    host: str | None = None       # web: the host in the printed link (None: viewer_host())
    row_hz: float | None = None   # web: joint rows per second sent (None: WEB_ROW_HZ)

    def __str__(self) -> str:
        text = self.kind if self.target is None else f"{self.kind}={self.target}"
        for key in ("max_mb", "keep", "buffer_mb", "grpc_port", "host", "row_hz"):
            value = getattr(self, key)
            if value is not None:
                text += f",{key}={value}" if isinstance(value, str) else f",{key}={value:g}"
        return text

    @property
    def web_port(self) -> int:
        """web: the port of the web viewer's HTTP server."""
        return int(self.target) if self.target else DEFAULT_WEB_PORT

    @property
    def server_port(self) -> int:
        """serve, web: the port of the gRPC server."""
        if self.kind == "web":
            return self.grpc_port or DEFAULT_GRPC_PORT
        return int(self.target) if self.target else DEFAULT_GRPC_PORT


def parse_sink(text: str) -> RerunSink:
    """`spawn`, `connect`, `connect=ADDR`, `serve[=PORT][,buffer_mb=MB]`, `save=PATH[,max_mb=MB][,keep=N]` or
    `web[=PORT][,grpc_port=P][,buffer_mb=MB][,host=NAME][,row_hz=HZ]` or `off`; ValueError (one line naming the
    value or option) otherwise."""
    parts = text.strip().split(",")
    n = len(parts)
    while n > 1 and OPTION_ITEM.match(parts[n - 1]):
        n -= 1
    kind, sep, target = ",".join(parts[:n]).partition("=")
    if kind not in SINK_KINDS:
        raise ValueError(f"unknown rerun sink {text!r}: {ACCEPTED}")
    if kind in ("spawn", "off") and sep:
        raise ValueError(f"rerun sink {text!r} takes no value: {ACCEPTED}")
    if sep and not target:
        raise ValueError(f"rerun sink {text!r} has nothing after '=': {ACCEPTED}")
    if kind == "save" and not sep:
        raise ValueError(f"rerun sink {text!r} needs a file, save=PATH: {ACCEPTED}")
    if kind in ("serve", "web") and sep and not (target.isdigit() and 0 < int(target) < 65536):
        raise ValueError(f"rerun sink {text!r}: the port must be an integer in 1..65535: {ACCEPTED}")
    options: dict[str, float | int | str] = {}
    for item in parts[n:]:
        key, _, value = item.partition("=")
        allowed = SINK_OPTIONS.get(kind, ())
        if key not in allowed:
            takes = f"{kind} takes " + (", ".join(f"{k}=" for k in allowed) if allowed else "no options")
            raise ValueError(f"rerun sink {text!r}: unknown option {key!r} ({takes}): {ACCEPTED}")
        if key in options:
            raise ValueError(f"rerun sink {text!r}: option {key} given twice")
        options[key] = _sink_option(text, key, value)
    if options.get("keep") is not None and options.get("max_mb") == 0:
        raise ValueError(f"rerun sink {text!r}: keep= needs rotation, but max_mb=0 writes one file")
    sink = RerunSink(kind, target if sep else None, **options)
    if kind == "web" and sink.web_port == sink.server_port:
        raise ValueError(f"rerun sink {text!r}: the web viewer (port {sink.web_port}) and the gRPC server "
                         f"(grpc_port={sink.server_port}) need different ports")
    return sink


def _sink_option(text: str, key: str, value: str) -> float | int | str:
    """One option's value, checked; ValueError naming the option otherwise."""
    if key == "host":
        if not HOST_NAME.fullmatch(value):
            raise ValueError(f"rerun sink {text!r}: host must be a host name or an IP address (an IPv6 one in "
                             f"brackets), got {value!r}")
        return value
    if key == "grpc_port":
        if not (value.isdigit() and 0 < int(value) < 65536):
            raise ValueError(f"rerun sink {text!r}: grpc_port must be an integer in 1..65535, got {value!r}")
        return int(value)
    if key == "row_hz":
        try:
            rate = float(value)
        except ValueError:
            rate = math.nan
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rerun sink {text!r}: row_hz must be a rate in Hz > 0, got {value!r}")
        return rate
    wants = {"max_mb": "a number of megabytes >= 0 (0: one file, never rotated)",
             "keep": "an integer >= 1 (how many of the newest parts stay on disk)",
             "buffer_mb": "an integer number of megabytes >= 1"}[key]
    try:
        number = float(value) if key == "max_mb" else int(value)
    except ValueError:
        number = None
    if number is None or not math.isfinite(number) or number < (0 if key == "max_mb" else 1):
        raise ValueError(f"rerun sink {text!r}: {key} must be {wants}, got {value!r}")
    return number


def part_path(path: str | Path, part: int) -> Path:
    """The file of part `part` of a rotated save=PATH recording: PATH itself, then PATH-stem.001.rrd, ..."""
    path = Path(path)
    return path if part == 0 else path.with_name(f"{path.stem}.{part:03d}{path.suffix}")


def recording_parts(path: str | Path) -> list[Path]:
    """The files of a save=PATH recording on disk, oldest first: PATH and its continuation parts (with keep=N the
    oldest ones, PATH itself included, may be gone)."""
    path = Path(path)
    pattern = re.compile(re.escape(path.stem) + r"\.(\d{3,})" + re.escape(path.suffix))
    try:
        names = [entry.name for entry in path.parent.iterdir()]
    except OSError:
        names = []
    numbered = sorted((int(match[1]), path.with_name(name)) for name in names if (match := pattern.fullmatch(name)))
    return ([path] if path.is_file() else []) + [part for _, part in numbered if part.is_file()]


def grpc_url(addr: str | None) -> str | None:
    """A connect ADDR as rerun wants it: host:port -> rerun+http://host:port/proxy; URLs pass unchanged."""
    if addr is None or "://" in addr:
        return addr
    return f"rerun+http://{addr}/proxy"


def probe_viewer(sink: RerunSink, url: str) -> None:
    """Fail fast, naming the address, when nothing listens where a viewer should be."""
    parts = urlsplit(url)
    if parts.hostname is None or parts.port is None:
        return  # let rerun judge URLs it may complete itself
    try:
        socket.create_connection((parts.hostname, parts.port), timeout=VIEWER_PROBE_TIMEOUT_S).close()
    except OSError as exc:
        raise TelemetryError(f"rerun sink {sink}: no viewer reachable at {parts.hostname}:{parts.port} ({exc}); "
                             "start one there with `rerun`, or use --rerun serve / --rerun save=PATH") from exc


def check_port_free(port: int, what: str, owner: str | None = None) -> None:
    """TelemetryError "[`owner`: ]cannot listen on port ..." when nothing could listen on `port` on all interfaces
    (rerun's gRPC server only logs a failed bind)."""
    with socket.socket() as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError as exc:
            text = f"cannot listen on port {port} for {what}: {exc}"
            raise TelemetryError(f"{owner}: {text}" if owner else text) from exc


def viewer_host() -> str:
    """The address a browser on another machine most likely reaches this one by: the source address of the
    default route (a UDP socket's connect sends nothing), else the host name."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: only the routing table is consulted
            address = probe.getsockname()[0]
        except OSError:
            address = ""
    return address if address and not address.startswith("127.") else socket.gethostname()


def web_viewer_link(host: str, web_port: int, grpc_port: int) -> str:
    """The page to open: rerun's web viewer on `web_port`, told by its `url` parameter where the gRPC stream is."""
    stream = f"rerun+http://{host}:{grpc_port}/proxy"
    return f"http://{host}:{web_port}/?url={quote(stream, safe='')}"


def web_origins(web_port: int) -> list[str]:
    """The origins whose pages may read the gRPC stream (rerun allows localhost and rerun.io only): the web
    viewer served on `web_port`, whatever name or address the browser reached it by."""
    return [f"http://*:{web_port}", f"https://*:{web_port}"]
