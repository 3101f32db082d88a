"""rerun's web viewer in a real browser: headless Chromium (software rendering, tests/support/chromium_driver.py) opens
the link that `bruce-run --rerun web` and `bruce-view --web` print, and the tests check what a lab would see: the page
loads, the viewer reads the gRPC stream, the screenshots show something that moves, and a frozen or closed tab
never holds up the run. Needs Debian's `chromium` (`apt-get install chromium`); skipped without it.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from support.chromium_driver import (
    CHROMIUM,
    HeadlessChromium,
    changed_share,
    drawn,
    established_connections,
    server_sockets,
)
from support.paths import REPO

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium on PATH (apt-get install chromium)")]

START_TIMEOUT_S = 90.0    # bruce-run's or bruce-view's link, on a loaded machine
CONNECT_TIMEOUT_S = 90.0  # page, wasm and the first bytes of the stream, software-rendered
DRAW_TIMEOUT_S = 60.0
MIN_COLOURS = 1000        # a loading screen has ~300 distinct colours (anti-aliased text), the viewer thousands
MIN_PIXEL_STD = 10.0
MIN_CHANGED = 0.002       # of the pixels between two screenshots 2 s apart: the plots scroll
VIEW_ROWS = slice(100, 700)  # the views of a 1280 x 800 page, below the top bar and its notices
BLUEPRINT_MARKS = (b"loop timing", b"/joints/r_knee", b"safety events", b"/world")
RUN_S = 60                # the live run: long enough for the browser to connect, be frozen and be closed
ROW_HZ = 1000             # every tick (~0.7 MB/s): a frozen tab fills the socket's buffers in seconds
STUCK_BYTES = 1_000_000   # unsent to the frozen tab: its TCP window is closed, the server cannot write
LATE_SHARE_BOUND = 0.05   # generous: a shared CI machine; a stalled loop would be far past it
MAX_PERIOD_BOUND_US = 500_000
TELEMETRY_SECTION_P99_BOUND_US = 1000  # the section hands a row to the telemetry process: tens of µs


def wait_for(condition, timeout: float, what: str, every: float = 0.5):
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout:.0f} s")
        time.sleep(every)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("0.0.0.0", 0))
        return probe.getsockname()[1]


class Command:
    """A CLI in a child process whose output is collected line by line (the pipe never fills)."""

    def __init__(self, argv: list[str]):
        self.proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        threading.Thread(target=self._collect, daemon=True).start()

    def _collect(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def link(self) -> str:
        def found():
            for line in self.lines:
                if match := re.search(r"open in a browser: (\S+)", line):
                    return match[1]
            if self.proc.poll() is not None:
                raise AssertionError(f"{self.proc.args[:4]} ended without a link: {self.lines}")
            return None

        return wait_for(found, START_TIMEOUT_S, "the link to open")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)


def connect_browser(link: str, profile: Path) -> HeadlessChromium:
    browser = HeadlessChromium(profile)
    try:
        browser.open(link)
        wait_for(lambda: browser.stream_bytes() > 0 or browser.stream_failures(), CONNECT_TIMEOUT_S,
                 "the viewer reading the gRPC stream")
        assert not browser.stream_failures(), f"the viewer could not read the stream: {browser.stream_failures()}"
    except BaseException:
        browser.kill()
        raise
    return browser


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """bruce-run on the paced mock with --rerun web, and a browser on the link it printed."""
    folder = tmp_path_factory.mktemp("web_live")
    grpc_port = free_port()
    # --realtime, as on the robot: the loop at SCHED_FIFO on a CPU of its own, so that the headless browser's software
    # rendering on the same two cores does not decide its late share (5.2 % without it on a slower VM, 2026-11-28);
    # a stream that held the loop up would still make it late, whatever its priority. Standing, not walking: the same
    # row per tick goes out either way, and on that VM the walk's policy ticks alone made 4 % of the ticks late with
    # no browser at all (tick CPU p99 1.25 ms), which would have decided the late share instead of the stream.
    run = Command([sys.executable, "-m", "runtime.cli", "--backend", "mock", "--realtime", "--duration", str(RUN_S),
                   "--controller", "standing", "--rerun", f"web={free_port()},grpc_port={grpc_port},row_hz={ROW_HZ}",
                   "--stats", str(folder / "stats.json")])
    browser = None
    try:
        link = run.link()
        browser = connect_browser(link, folder / "profile")
        yield {"run": run, "browser": browser, "link": link, "grpc_port": grpc_port, "folder": folder}
    finally:
        if browser is not None:
            browser.kill()
        run.stop()


def test_a_browser_shows_the_live_run(live_run):
    browser, grpc_port = live_run["browser"], live_run["grpc_port"]
    assert browser.document_status() == 200
    assert f"%3A{grpc_port}%2Fproxy" in live_run["link"]
    assert established_connections(grpc_port) >= 1, "the gRPC server has no client"
    first = browser.stream_bytes()
    wait_for(lambda: browser.stream_bytes() > first, CONNECT_TIMEOUT_S, "more of the live stream")
    # The viewer shows the run's recording with the default blueprint (its views, by name and entity).
    wait_for(lambda: all(name in browser.viewer_state() for name in BLUEPRINT_MARKS), DRAW_TIMEOUT_S,
             f"the viewer's state naming the blueprint's views {BLUEPRINT_MARKS}")
    shot = live_run["folder"] / "web_viewer.png"

    def looks_drawn():
        shot.write_bytes(browser.screenshot())
        colours, std = drawn(shot.read_bytes())
        return colours > MIN_COLOURS and std > MIN_PIXEL_STD

    wait_for(looks_drawn, DRAW_TIMEOUT_S, f"a screenshot that is not blank ({shot})", every=2.0)
    # Live: the views move (the plots scroll); below the top bar, where notices come and go.
    wait_for(lambda: changed_share(shot.read_bytes(), browser.screenshot(), VIEW_ROWS) > MIN_CHANGED,
             DRAW_TIMEOUT_S, "a screenshot whose views differ from the last one", every=2.0)
    assert live_run["run"].proc.poll() is None, "the run ended while the browser was on it"


def test_a_frozen_then_closed_tab_never_holds_up_the_run(live_run):
    run, browser, grpc_port = live_run["run"], live_run["browser"], live_run["grpc_port"]
    assert run.proc.poll() is None, "the run ended before the browser could be frozen"
    browser.freeze()  # its sockets stay open, unread, while the stream goes on
    wait_for(lambda: max((queued for _, queued in server_sockets(grpc_port)), default=0) > STUCK_BYTES,
             RUN_S, f"more than {STUCK_BYTES} bytes stuck in the server's send queue to the frozen tab")
    assert run.proc.poll() is None, "the run ended before the frozen tab held up the stream"
    browser.kill()
    code = run.proc.wait(RUN_S + START_TIMEOUT_S)
    stats = json.loads((live_run["folder"] / "stats.json").read_text())
    assert code == 0 and stats["stop_cause"] == "duration reached", run.lines[-5:]
    assert stats["realtime"] and stats["ticks"] == RUN_S * 1000
    assert stats["telemetry_dropped"] == 0, "the telemetry process fell behind"
    late = {key: stats[key] for key in stats if key.startswith("late_") or key == "period_us"}
    assert stats["late_share"] < LATE_SHARE_BOUND, late
    assert stats["period_us"]["max"] < MAX_PERIOD_BOUND_US
    # the telemetry section itself, tick by tick: a send held by the tab would hold the tick, and the freeze lasts
    # seconds of the run, far more than the 1 % of its ticks that p99 leaves out
    assert stats["sections_us"]["telemetry"]["p99"] < TELEMETRY_SECTION_P99_BOUND_US, stats["sections_us"]


def test_bruce_view_serves_a_saved_recording_with_its_parts(tmp_path):
    path = tmp_path / "walk.rrd"
    saved = subprocess.run([sys.executable, "-m", "runtime.cli", "--backend", "mock", "--realtime", "--duration", "5",
                            "--rerun", f"save={path},max_mb=1"], cwd=REPO, capture_output=True, text=True,
                           timeout=START_TIMEOUT_S + 5)
    assert saved.returncode == 0, saved.stderr
    parts = sorted(tmp_path.glob("walk*.rrd"))
    assert len(parts) >= 2, "the recording should have been rotated into parts"
    size = sum(part.stat().st_size for part in parts)
    grpc_port = free_port()
    view = Command([sys.executable, "-m", "runtime.telemetry.view_cli", str(path), "--web",
                    "--web-port", str(free_port()), "--grpc-port", str(grpc_port)])
    browser = None
    try:
        link = view.link()
        assert f"({len(parts)} files)" in "\n".join(view.lines)
        browser = connect_browser(link, tmp_path / "profile")
        assert browser.document_status() == 200
        assert established_connections(grpc_port) >= 1
        # Every part reaches the viewer, not only the first (the stream carries about the files' size).
        wait_for(lambda: browser.stream_bytes() > 0.8 * size, CONNECT_TIMEOUT_S,
                 f"the viewer reading all {len(parts)} parts ({size / 1e6:.1f} MB)")
        view.proc.send_signal(signal.SIGINT)
        assert view.proc.wait(30) == 0
    finally:
        if browser is not None:
            browser.kill()
        view.stop()
