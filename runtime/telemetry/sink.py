"""Where telemetry goes (`--rerun SINK`): parsing and checking the sink, the file parts of a rotated recording.

Sinks: spawn | connect[=ADDR] | serve[=PORT][,buffer_mb=MB] | save=PATH[,max_mb=MB][,keep=N] | off; a trailing
`,key=value` is an option (a comma otherwise stays in the path), max_mb=0 writes one file. ADDR is host:port or a
full rerun+http(s)://host:port/proxy URL (default rerun+http://127.0.0.1:9876/proxy).
"""

from __future__ import annotations

import math
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

DEFAULT_MAX_MB = 1000.0     # save=: a new part starts when the current file reaches this size
DEFAULT_BUFFER_MB = 256     # serve: history the gRPC server keeps for viewers that connect late
SINK_HELP = ("where telemetry goes: spawn (a local viewer), connect[=HOST:PORT|URL] (a running viewer), "
             "serve[=PORT][,buffer_mb=MB] (a gRPC server a laptop viewer attaches to; keeps the newest MB for late "
             f"viewers, default {DEFAULT_BUFFER_MB}), save=PATH[,max_mb=MB][,keep=N] (an .rrd file; continues in "
             f"PATH-stem.001.rrd, .002, ... each time the file reaches MB, default {DEFAULT_MAX_MB:g}, 0: one file; "
             "keep=N: only the newest N files stay on disk), off")
SINK_KINDS = ("spawn", "connect", "serve", "save", "off")
ACCEPTED = ("expected one of spawn, connect, connect=HOST:PORT|URL, serve[=PORT][,buffer_mb=MB], "
            "save=PATH[,max_mb=MB][,keep=N], off")
SINK_OPTIONS = {"save": ("max_mb", "keep"), "serve": ("buffer_mb",)}
OPTION_ITEM = re.compile(r"[A-Za-z_]\w*=")  # a trailing ",key=value" is an option, not part of a path
DEFAULT_GRPC_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"  # where rerun connects without ADDR
VIEWER_PROBE_TIMEOUT_S = 2.0
class TelemetryError(RuntimeError):
    """Telemetry could not be started; the message names the sink."""


@dataclass(frozen=True)
class RerunSink:
    kind: str
    target: str | None = None  # connect: ADDR (None: rerun's default); serve: PORT (None: 9876); save: PATH
    max_mb: float | None = None   # save: rotation size (None: DEFAULT_MAX_MB; 0: one file)
    keep: int | None = None       # save: parts kept on disk (None: all)
    buffer_mb: int | None = None  # serve: the server's history (None: DEFAULT_BUFFER_MB)

    def __str__(self) -> str:
        text = self.kind if self.target is None else f"{self.kind}={self.target}"
        for key in ("max_mb", "keep", "buffer_mb"):
            value = getattr(self, key)
            if value is not None:
                text += f",{key}={value:g}"
        return text


def parse_sink(text: str) -> RerunSink:
    """`spawn`, `connect`, `connect=ADDR`, `serve[=PORT][,buffer_mb=MB]`, `save=PATH[,max_mb=MB][,keep=N]` or
    `off`; ValueError (one line naming the value or option) otherwise."""
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
    if kind == "serve" and sep and not (target.isdigit() and 0 < int(target) < 65536):
        raise ValueError(f"rerun sink {text!r}: the port must be an integer in 1..65535: {ACCEPTED}")
    options: dict[str, float | int] = {}
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
    return RerunSink(kind, target if sep else None, **options)


def _sink_option(text: str, key: str, value: str) -> float | int:
    """One option's value, checked; ValueError naming the option otherwise."""
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


