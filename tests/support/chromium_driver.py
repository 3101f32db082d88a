"""Headless Chromium driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`: NUL-terminated JSON on
fds 3 and 4, so no websocket client is needed), for the browser tests (tests/runtime/telemetry/test_web_viewer.py) and
the web viewer benchmark (bench/bench_web_viewer.py). Needs Debian's `chromium` (`apt-get install chromium`)."""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import subprocess
import threading
from pathlib import Path

import numpy as np

CHROMIUM = shutil.which("chromium")
WINDOW = (1280, 800)
# WebGL2 without a GPU: ANGLE on SwiftShader. --no-sandbox: CI runs as root.
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--no-first-run", "--disable-extensions", f"--window-size={WINDOW[0]},{WINDOW[1]}")
# The viewer also fetches fonts, release notes and analytics from the internet; the page stays on this network.
OUTSIDE = ["*://*.rerun.io/*", "*://api.github.com/*", "*://fonts.googleapis.com/*", "*://fonts.gstatic.com/*"]
STREAM_PATH = "MessageProxyService/ReadMessages"  # the viewer's gRPC-web call that reads the stream


class HeadlessChromium:
    """One headless Chromium with one page, driven over the DevTools protocol on a pipe. It runs in its own
    process group, so freeze() and kill() reach all of its processes (the network service included)."""

    def __init__(self, profile: Path):
        to_browser, from_browser = os.pipe(), os.pipe()
        ours = (to_browser[1], from_browser[0])
        theirs = (to_browser[0], from_browser[1])

        def onto_fds_3_and_4():
            commands, replies = os.dup(theirs[0]), os.dup(theirs[1])
            os.dup2(commands, 3)
            os.dup2(replies, 4)

        self.proc = subprocess.Popen(
            [CHROMIUM, *CHROMIUM_FLAGS, "--remote-debugging-pipe", f"--user-data-dir={profile}", "about:blank"],
            pass_fds=(3, 4), preexec_fn=onto_fds_3_and_4, start_new_session=True, stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for fd in theirs:
            os.close(fd)
        self._write, self._read = ours
        self._next_id = 0
        self._replies: dict[int, dict] = {}
        self._replied = threading.Condition()
        self.events: list[dict] = []
        self._reader = threading.Thread(target=self._receive, daemon=True)
        self._reader.start()
        self.session: str | None = None

    def _receive(self) -> None:
        buffer = b""
        while True:
            try:
                chunk = os.read(self._read, 1 << 20)
            except OSError:
                chunk = b""
            if not chunk:
                with self._replied:
                    self._replied.notify_all()
                return
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for raw in messages:
                message = json.loads(raw)
                with self._replied:
                    if "id" in message:
                        self._replies[message["id"]] = message
                        self._replied.notify_all()
                    else:
                        self.events.append(message)

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        with self._replied:
            self._next_id += 1
            ident = self._next_id
        message = {"id": ident, "method": method, "params": params}
        if self.session is not None and not method.startswith(("Target.", "Browser.")):
            message["sessionId"] = self.session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        with self._replied:
            if not self._replied.wait_for(lambda: ident in self._replies or not self._reader.is_alive(), timeout):
                raise TimeoutError(f"chromium did not answer {method} within {timeout:.0f} s")
            reply = self._replies.pop(ident, None)
        if reply is None or "error" in reply:
            raise RuntimeError(f"chromium: {method} failed: {reply}")
        return reply["result"]

    def open(self, url: str) -> None:
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride", width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1,
                  mobile=False)
        self.call("Network.enable")
        self.call("Network.setBlockedURLs", urls=OUTSIDE)
        self.call("Page.enable")
        self.call("Page.navigate", url=url)

    def _events(self, method: str) -> list[dict]:
        with self._replied:
            return [event["params"] for event in self.events if event.get("method") == method]

    def document_status(self) -> int | None:
        """The HTTP status of the page itself."""
        statuses = [event["response"]["status"] for event in self._events("Network.responseReceived")
                    if event.get("type") == "Document"]
        return statuses[0] if statuses else None

    def stream_bytes(self) -> int:
        """Bytes the viewer has read from the gRPC stream (the body of its ReadMessages calls)."""
        ids = {event["requestId"] for event in self._events("Network.requestWillBeSent")
               if STREAM_PATH in event["request"]["url"]}
        return sum(event["dataLength"] for event in self._events("Network.dataReceived") if event["requestId"] in ids)

    def stream_failures(self) -> list[str]:
        ids = {event["requestId"] for event in self._events("Network.requestWillBeSent")
               if STREAM_PATH in event["request"]["url"]}
        return [f"{event.get('errorText')} {event.get('corsErrorStatus', '')}"
                for event in self._events("Network.loadingFailed") if event["requestId"] in ids]

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def freeze(self) -> None:
        """A tab that stops reading (a sleeping laptop, a dead link): every process stops, the sockets stay open."""
        os.killpg(self.proc.pid, signal.SIGSTOP)

    def viewer_state(self) -> bytes:
        """The viewer's own account of what it shows (the encoded GetStateResponse of rerun's Viewer Control API:
        the active recording, its timelines and time cursor, the blueprint's views); empty before the viewer runs."""
        reply = self.call("Runtime.evaluate", returnByValue=True,
                          expression="window._handle ? Array.from(window._handle.viewer_state()) : null")
        return bytes(reply["result"].get("value") or [])

    def viewer_time_s(self) -> float | None:
        """Where the viewer's time cursor stands on the `time` timeline (it follows the newest data it has taken
        in); None where that cannot be read (before the viewer runs, or a rerun whose state is laid out
        otherwise: read for rerun 0.41's GetStateResponse, field 3.3.3.1 in ns). For measurements only."""
        try:
            found = [v for path, v in protobuf_fields(self.viewer_state()) if path == (3, 3, 3, 1)]
        except (RuntimeError, TimeoutError, ValueError, IndexError):
            return None
        return found[0] / 1e9 if found else None

    def cpu_s(self) -> float:
        """CPU seconds used so far by all of the browser's processes (its process group)."""
        total = 0
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == self.proc.pid:
                total += int(fields[11]) + int(fields[12])
        return total / os.sysconf("SC_CLK_TCK")

    def kill(self) -> None:
        """A closed tab, as abrupt as it gets."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(30)
        for fd in (self._write, self._read):
            try:
                os.close(fd)
            except OSError:
                pass


def server_sockets(port: int) -> list[tuple[str, int]]:
    """(state, bytes waiting in the send queue) of each TCP socket whose local port is `port`, from /proc/net;
    state "01" is ESTABLISHED."""
    sockets = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if int(fields[1].rsplit(":", 1)[1], 16) == port:
                sockets.append((fields[3], int(fields[4].split(":")[0], 16)))
    return sockets


def established_connections(port: int) -> int:
    """Clients connected to the server listening on `port`."""
    return sum(state == "01" for state, _ in server_sockets(port))


def drawn(png: bytes) -> tuple[int, float]:
    """Distinct colours and the pixels' standard deviation of a screenshot."""
    from PIL import Image  # rerun-sdk depends on pillow

    image = Image.open(io.BytesIO(png)).convert("RGB")
    return len(image.getcolors(maxcolors=1 << 24)), float(np.asarray(image).std())


def changed_share(png: bytes, other: bytes, rows: slice = slice(None)) -> float:
    """The share of pixels that differ between two screenshots of the same size (in `rows` of pixels)."""
    from PIL import Image

    a, b = (np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))[rows] for data in (png, other))
    return float(np.any(a != b, axis=2).mean())


def protobuf_fields(data: bytes, path: tuple[int, ...] = ()):
    """(field path, value) of every varint in a protobuf message, nested messages walked where they parse."""
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        field, wire = path + (key >> 3,), key & 7
        if wire == 0:
            value, i = _varint(data, i)
            yield field, value
        elif wire in (1, 5):
            i += 8 if wire == 1 else 4
        elif wire == 2:
            size, i = _varint(data, i)
            inner = data[i:i + size]
            i += size
            try:
                yield from list(protobuf_fields(inner, field))
            except (ValueError, IndexError):
                pass  # a string or bytes, not a message
        else:
            raise ValueError(f"wire type {wire}")
    if i != len(data):
        raise ValueError("truncated")


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, i
