"""The paced control loop with rerun's web viewer connected, next to telemetry off and to a file, in one run.

Three paced mock walks (`bruce-run --backend mock --realtime --cmd 0.4,0,0 --duration S --stats ...`, each in a
process of its own, as a user runs it), one after the other, `--repeat` times:
    off   --rerun off
    save  --rerun save=TMP/walk.rrd
    web   --rerun web=PORT,grpc_port=PORT with headless Chromium (tests/support/chromium_driver.py: software rendering)
          on the link bruce-run prints, from as soon as it is printed to the end of the run
Per walk: the late share (ticks > 250 µs behind), skipped deadlines, the period's p99 and maximum, tick work p99 and
the rows telemetry dropped; for web also when the viewer started reading, the bytes it read, its CPU use and where
its time cursor stood at the end against the run's length (how far behind the live run it was). Then the ratios
web / off and web / save. Goal (issue #24): the late share with the web viewer connected no worse than with save=.

The browser runs on the robot's computer here, a stand-in for a laptop elsewhere: its CPU use competes with the
loop as a remote browser's would not. Needs Debian's `chromium`.

    python bench/bench_web_viewer.py [--seconds 30] [--repeat 1] [--screenshot docs/img/web_viewer.png]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the Chromium driver the browser tests use

from support.chromium_driver import CHROMIUM, HeadlessChromium  # noqa: E402

LINK_TIMEOUT_S = 90.0
KINDS = ("off", "save", "web")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("0.0.0.0", 0))
        return probe.getsockname()[1]


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def walk(kind: str, seconds: float, folder: Path, screenshot: Path | None) -> dict:
    """One paced walk with the sink `kind`; its stats, plus the browser's figures for web."""
    stats_path = folder / f"{kind}.json"
    sink = {"off": "off", "save": f"save={folder / 'walk.rrd'}",
            "web": f"web={free_port()},grpc_port={free_port()}"}[kind]
    argv = [sys.executable, "-m", "runtime.cli", "--backend", "mock", "--realtime", "--duration", f"{seconds:g}",
            "--cmd", "0.4,0,0", "--rerun", sink, "--stats", str(stats_path)]
    proc = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: list[str] = []
    link: list[str] = []
    linked = threading.Event()
    started = time.monotonic()

    def collect():
        for line in proc.stdout:
            lines.append(line)
            if match := re.search(r"open in a browser: (\S+)", line):
                link.append(match[1])
                linked.set()
        linked.set()

    threading.Thread(target=collect, daemon=True).start()
    browser = None
    extra: dict = {}
    try:
        if kind == "web":
            if not linked.wait(LINK_TIMEOUT_S) or not link:
                raise RuntimeError(f"bruce-run printed no link: {''.join(lines)[-2000:]}")
            browser = HeadlessChromium(folder / "profile")
            cpu0 = browser.cpu_s()
            opened = time.monotonic()
            browser.open(link[0])
            while proc.poll() is None and browser.stream_bytes() == 0:
                time.sleep(0.2)
            extra["reading_after_s"] = time.monotonic() - started
            cursor = None
            while proc.poll() is None:  # the last reading before the run ends
                cursor = browser.viewer_time_s() or cursor
                time.sleep(1.0)
                if screenshot is not None and cursor is not None:
                    screenshot.write_bytes(browser.screenshot())
            extra.update(bytes_read=browser.stream_bytes(), cursor_s=cursor,
                         cpu_share=(browser.cpu_s() - cpu0) / max(1e-9, time.monotonic() - opened))
        proc.wait()
    finally:
        if browser is not None:
            browser.kill()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    stats = json.loads(stats_path.read_text())
    if stats["exit_code"] != 0:
        raise RuntimeError(f"{kind}: bruce-run ended with {stats['exit_code']}: {stats.get('error')}")
    return {**stats, **extra}


def line(kind: str, stats: dict) -> str:
    period, work = stats["period_us"], stats["work_us"]
    text = (f"  {kind:4s}: late {stats['late_ticks']:4d} of {stats['ticks']} = {100 * stats['late_share']:.3f} %, "
            f"skipped {stats['skipped_ticks']}, period p99 {period['p99']:.0f} / max {period['max']:.0f} µs, "
            f"work p99 {work['p99']:.0f} µs, rows dropped {stats['telemetry_dropped']}")
    if kind == "web":
        cursor = "n/a" if stats.get("cursor_s") is None else f"{stats['cursor_s']:.1f} s"
        text += (f"\n        browser: reading the stream {stats['reading_after_s']:.1f} s after start, "
                 f"{stats['bytes_read'] / 1e6:.1f} MB read, {100 * stats['cpu_share']:.0f} % of a core; its time "
                 f"cursor at the end: {cursor} of {stats['loop_s']:.1f} s")
    return text


def ratio(a: float, b: float) -> str:
    return "n/a (0 late ticks in the reference)" if b == 0 else f"{a / b:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each paced walk (default 30)")
    parser.add_argument("--repeat", type=int, default=1, help="rounds of off, save, web (default 1)")
    parser.add_argument("--screenshot", type=Path, default=None,
                        help="save the browser's last screenshot of the (last) web walk here")
    args = parser.parse_args()
    if CHROMIUM is None:
        sys.exit("bench_web_viewer: needs Debian's chromium on PATH (apt-get install chromium)")
    print(f"paced mock walks of {args.seconds:g} s, --cmd 0.4,0,0, {args.repeat} round(s) of {', '.join(KINDS)}; "
          f"{os.cpu_count()} CPUs, load average {load()} at the start")
    results: dict[str, list[dict]] = {kind: [] for kind in KINDS}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.repeat):
            for kind in KINDS:
                folder = Path(tmp) / f"{kind}{round_}"
                folder.mkdir()
                stats = walk(kind, args.seconds, folder, args.screenshot if kind == "web" else None)
                results[kind].append(stats)
                print(line(kind, stats), flush=True)
    print(f"load average {load()} at the end")
    late = {kind: sum(s["late_ticks"] for s in runs) / sum(s["ticks"] for s in runs) for kind, runs in results.items()}
    p99 = {kind: max(s["period_us"]["p99"] for s in runs) for kind, runs in results.items()}
    print(f"late share over all rounds: off {100 * late['off']:.3f} %, save {100 * late['save']:.3f} %, "
          f"web {100 * late['web']:.3f} %; web / off {ratio(late['web'], late['off'])}, "
          f"web / save {ratio(late['web'], late['save'])}")
    print(f"period p99 (worst round): off {p99['off']:.0f}, save {p99['save']:.0f}, web {p99['web']:.0f} µs; "
          f"web / off {p99['web'] / p99['off']:.3f}, web / save {p99['web'] / p99['save']:.3f}")
    print(f"goal: late share with the web viewer connected <= with save=: "
          f"{'met' if late['web'] <= late['save'] else 'NOT met'}")


if __name__ == "__main__":
    main()
