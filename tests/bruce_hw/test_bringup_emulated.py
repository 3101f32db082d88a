"""The bring-up suite for the real robot (tests/bruce_hw/test_bringup.py, marker `hardware`) as CI runs it: the same
tests, pointed at `bruce-emulate`'s ports (`--bruce-emulate`), in a pytest of their own, with the emulator tests'
wall-clock slack (`WALL_CLOCK_SLACK`: the emulator shares this machine's two cores, so its packets and the host are
sometimes tens of milliseconds late)."""

import subprocess
import sys

from support.emulated_robot import WALL_CLOCK_SLACK
from support.paths import REPO


def bringup(*options: str) -> subprocess.CompletedProcess:
    slack = [word for item in WALL_CLOCK_SLACK for word in ("--bruce-set", item)]
    return subprocess.run([sys.executable, "-m", "pytest", "-m", "hardware", "tests/bruce_hw/test_bringup.py",
                           "--bruce-emulate", "-q", "-p", "no:cacheprovider", *slack, *options], cwd=REPO,
                          capture_output=True, text=True, timeout=600)


def test_the_bringup_suite_passes_against_the_emulators():
    run = bringup()
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "8 passed" in run.stdout.splitlines()[-1], run.stdout[-2000:]


def test_a_failed_step_skips_every_step_after_it():
    """A leg bus that cannot be opened: the first step fails, and no later step enables a motor."""
    run = bringup("--bruce-set", "buses.bear.port=/dev/null/bear", "-rs")
    assert run.returncode == 1
    summary = run.stdout.splitlines()[-1]
    assert "1 failed" in summary and "7 skipped" in summary, run.stdout[-3000:]
    assert run.stdout.count("an earlier step failed (test_01_every_device_answers_and_reports_its_identity)") == 7
