"""Behaviour before and after a restructuring: the same commands run in a checkout of `--base` and in this one, and
their outputs compared with what depends on the wall clock left out (issue #35's "behaviour unchanged").

Cases (each in both checkouts, as `python -m <module>` with the checkout first on PYTHONPATH):
  walk         bruce-run --backend mock, the ONNX policy at 0.4 m/s: --stats
  shadow_twin  the same with --gap default --transfer shadow_twin: --stats
  collect      bruce-collect, 6 s: every array of the dataset
  transfer     bruce-eval transfer, `default`, tracking, gap seed 0, direct and shadow_twin: transfer.json
  hw_lockstep  bruce-run --backend hw against bruce-emulate --lockstep, a 2-s stand: --stats

The mock runs on its own clock, so its figures are compared exactly. The lockstep hw run steps the physics once per
bulk cycle, but the devices' replies and the host's threads still meet on the wall clock, so two runs of one
checkout differ in their last digits: for it only the outcome is compared (how it ended, ticks, exit code), not the
trajectory, with the hw tests' wall-clock slack.

    python bench/behaviour_diff.py --base 63b0994 [--cases walk,shadow_twin,collect,transfer,hw_lockstep]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]
# stats keys that measure the machine, not the robot
WALL_CLOCK = {"wall_time", "loop_s", "rate_hz", "work_us", "cpu_us", "period_us", "sections_us", "sections_cpu_us",
              "cpu_share_of_period", "worst_overruns_us", "late_ticks", "late_share", "skipped_ticks", "data_age_us",
              "late_ticks_machine", "late_ticks_loop", "late_share_loop", "realtime_grant", "link", "host_stalls",
              "telemetry_dropped"}
# the hw tests' slack (tests/support/emulated_robot.py): on a loaded machine the lockstep devices still answer on
# the wall clock, and these runs are about behaviour, not the machine's timing
WALL_CLOCK_SLACK = ("safety.min_rate_hz=50", "safety.rate_window_s=1.0", "safety.max_sensor_age_s=0.05",
                    "buses.bear.reply_timeout_s=0.02", "buses.bear.watchdog_s=0.1", "safety.host_stall_max_s=0.09")
HW_OUTCOME = ("backend", "transfer", "final_state", "stop_cause", "exit_code", "fault_class", "ticks", "fell")
CASES = ("walk", "shadow_twin", "collect", "transfer", "hw_lockstep")


def run(tree: Path, module: str, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run([sys.executable, "-m", module, *args], cwd=tree, env=env, capture_output=True, text=True,
                          timeout=timeout)
    if done.returncode not in (0,):
        raise RuntimeError(f"{tree.name}: python -m {module} {' '.join(args)} exited {done.returncode}:\n"
                           f"{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return done


def stats_of(path: Path, keep: tuple[str, ...] | None = None) -> dict:
    stats = json.loads(path.read_text())
    if keep is not None:
        return {k: stats.get(k) for k in keep}
    return {k: v for k, v in stats.items() if k not in WALL_CLOCK}


def differences(a, b, where: str = "") -> list[str]:
    """Where two JSON-like values differ (exactly: floats bit for bit)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                out.append(f"{where}{key}: only in {'after' if key in b else 'before'}")
            else:
                out += differences(a[key], b[key], f"{where}{key}.")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where.rstrip('.')}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{where}{i}.")]
    return [] if a == b or (a != a and b != b) else [f"{where.rstrip('.')}: {a!r} vs {b!r}"]


def case(name: str, tree: Path, out: Path):
    """Run one case in `tree`; returns what is compared."""
    out.mkdir(parents=True, exist_ok=True)
    walk = ("--backend", "mock", "--duration", "5", "--cmd", "0.4,0,0", "--rerun", "off")
    if name == "walk":
        run(tree, "runtime.cli", *walk, "--stats", str(out / "stats.json"))
        return stats_of(out / "stats.json")
    if name == "shadow_twin":
        run(tree, "runtime.cli", *walk, "--gap", "default", "--transfer", "shadow_twin", "--stats",
            str(out / "stats.json"))
        return stats_of(out / "stats.json")
    if name == "collect":
        run(tree, "training.collect", "--seconds", "6", "--seed", "0", "--out", str(out / "data.npz"),
            "--no-progress")
        with np.load(out / "data.npz", allow_pickle=False) as data:
            return {key: data[key].tolist() for key in sorted(data.files) if data[key].dtype.kind in "fiub"}
    if name == "transfer":
        run(tree, "training.evaluation.cli", "transfer", "--gap", "default", "--experiments", "tracking", "--seeds",
            "0", "--latencies-ms", "", "--gain-scales", "", "--schemes", "shadow_twin", "--jobs", "1", "--out",
            str(out / "eval"))
        result = json.loads((out / "eval" / "transfer.json").read_text())
        result.pop("meta", None)  # the command line, the commit, the time
        return result
    if name == "hw_lockstep":
        return hw_lockstep(tree, out)
    raise ValueError(name)


def hw_lockstep(tree: Path, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    emulator = subprocess.Popen([sys.executable, "-m", "runtime.emulate_cli", "--lockstep"], cwd=tree, env=env,
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = ""
        for line in emulator.stdout:
            if line.strip().startswith("bruce-run "):
                break
        argv = line.split()[1:]
        slack = [w for item in WALL_CLOCK_SLACK for w in ("--set", item)]
        run(tree, "runtime.cli", *argv, *slack, "--controller", "standing", "--duration", "2", "--rerun", "off",
            "--stats", str(out / "stats.json"), timeout=120)
    finally:
        emulator.terminate()
        emulator.wait(timeout=10)
    return stats_of(out / "stats.json", HW_OUTCOME)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="the commit before the change")
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args()
    names = args.cases.split(",")
    with tempfile.TemporaryDirectory(prefix="behaviour_diff_") as tmp:
        base = Path(tmp) / "base"
        subprocess.run(["git", "-C", str(HERE), "worktree", "add", "--detach", "-f", str(base), args.base],
                       check=True, capture_output=True)
        try:
            head = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"], capture_output=True,
                                  text=True, check=True).stdout.strip()
            print(f"before: {args.base} (a clean checkout); after: {head} with this working tree")
            same = 0
            for name in names:
                before = case(name, base, Path(tmp) / "before" / name)
                after = case(name, HERE, Path(tmp) / "after" / name)
                diff = differences(before, after)
                same += not diff
                count = len(before) if isinstance(before, dict) else 1
                print(f"  {name:12s} {'identical' if not diff else f'{len(diff)} difference(s)'} "
                      f"({count} top-level fields compared)")
                for line in diff[:10]:
                    print(f"      {line}")
            print(f"{same} of {len(names)} cases identical")
        finally:
            subprocess.run(["git", "-C", str(HERE), "worktree", "remove", "--force", str(base)], capture_output=True)


if __name__ == "__main__":
    main()
