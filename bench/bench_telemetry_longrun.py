"""Telemetry that can run all day: memory of every process and recording size over a long paced mock walk.

Runs `bruce-run --backend mock --realtime --cmd 0.4,0,0.3 --transfer pinn --rerun save=DIR/walk.rrd[,OPTIONS]`
as a subprocess for `--duration` seconds and samples, every `--every` seconds, the resident memory (VmRSS from
/proc) of the control process and of each of its child processes (the telemetry process), and the size of the
recording (all `walk*.rrd` files in DIR, so rotated parts count too). Reported at the end:

- per process: RSS at 1 min and at the end, its growth in MB/min after the first minute (least-squares slope
  over the samples from 60 s on; the first minute holds start-up, imports and the allocators' warm-up) and its
  CPU use;
- recording: total size, MB per minute of run, the files;
- from the run's --stats JSON: late share, skipped ticks, worst overrun, tick work p99, the loop's telemetry
  section, how the run ended; and the hypervisor's CPU steal during the run (/proc/stat).

`--off` runs the same walk with `--rerun off`: the reference for the loop figures on the same machine.

Goals (issue #19): every process grows <= 5 MB/min after the first minute; <= 0.5 GB of recording for 10 minutes
with the default settings; the late share stays at the telemetry-off level.

    python bench/bench_telemetry_longrun.py [--duration 120] [--every 5] [--sink-options max_mb=200,keep=3]
        [--off] [--set KEY=VALUE ...] [--dir /tmp/bruce-longrun] [--keep]

Recordings go to --dir (default: a temporary directory, removed unless --keep); nothing is written in the repo.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

GROWTH_GOAL_MB_MIN = 5.0
SIZE_GOAL_MB_10MIN = 500.0
WARMUP_S = 60.0
REPO = Path(__file__).resolve().parent.parent


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process so far."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            pass
    return sorted(set(found))


def cpu_steal() -> dict[str, tuple[int, int]]:
    """Per CPU line of /proc/stat: (steal, total) jiffies; steal is time the hypervisor ran something else."""
    found = {}
    for line in Path("/proc/stat").read_text().splitlines():
        if line.startswith("cpu"):
            name, *values = line.split()
            values = [int(v) for v in values]
            found[name] = (values[7] if len(values) > 7 else 0, sum(values[:8]))
    return found


def growth(samples: list[tuple[float, float]], since: float) -> float | None:
    """Least-squares slope in MB/min of the samples at t >= since."""
    late = [(t, v) for t, v in samples if t >= since]
    if len(late) < 3 or late[-1][0] - late[0][0] < 10:
        return None
    t, v = np.array(late).T
    return float(np.polyfit(t / 60.0, v, 1)[0])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=120.0, help="seconds of paced walking (default 120)")
    parser.add_argument("--every", type=float, default=5.0, help="sampling period in seconds (default 5)")
    parser.add_argument("--sink-options", default="", help="appended to save=PATH, e.g. max_mb=200")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="passed to bruce-run --set (repeatable)")
    parser.add_argument("--transfer", choices=("pinn", "direct"), default="pinn")
    parser.add_argument("--off", action="store_true", help="the same run with --rerun off: the reference late share")
    parser.add_argument("--dir", type=Path, default=None, help="where the recording goes (default: a temp dir)")
    parser.add_argument("--keep", action="store_true", help="keep the recording")
    args = parser.parse_args()

    work = args.dir or Path(tempfile.mkdtemp(prefix="bruce-longrun-"))
    work.mkdir(parents=True, exist_ok=True)
    for old in work.glob("walk*.rrd"):
        old.unlink()
    stats_path = work / "stats.json"
    sink = "off" if args.off else f"save={work / 'walk.rrd'}" + (f",{args.sink_options}" if args.sink_options else "")
    command = [sys.executable, "-m", "runtime.cli", "--backend", "mock", "--realtime", "--duration",
               f"{args.duration:g}", "--cmd", "0.4,0,0.3", "--transfer", args.transfer, "--rerun", sink,
               "--stats", str(stats_path)]
    for override in args.overrides:
        command += ["--set", override]
    print("running:", " ".join(command), flush=True)
    steal0 = cpu_steal()
    log = open(work / "run.log", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    series: dict[str, list[tuple[float, float]]] = {"control": []}
    cpu: dict[str, float] = {}  # CPU seconds at the last sample
    sizes: list[tuple[float, float]] = []
    started = None  # when the telemetry process appeared: the run's clock starts about then
    while proc.poll() is None:
        now = time.monotonic() - t0
        kids = children(proc.pid)
        if started is None and (kids or (args.off and now > 1.0)):
            started = now  # the telemetry process appears just before the loop starts
        t = now - (started or now)
        if started is not None:
            for name, pid in [("control", proc.pid)] + [(f"telemetry{'' if k == 0 else k}", kid)
                                                        for k, kid in enumerate(kids)]:
                value, used = rss_mb(pid), cpu_s(pid)
                if value is not None:
                    series.setdefault(name, []).append((t, value))
                if used is not None:
                    cpu[name] = used
            sizes.append((t, sum(p.stat().st_size for p in work.glob("walk*.rrd")) / 1e6))
        time.sleep(args.every if started is not None else 0.2)
    log.close()
    code = proc.returncode
    steal1 = cpu_steal()
    files = sorted(work.glob("walk*.rrd"))
    total_mb = sum(p.stat().st_size for p in files) / 1e6
    print(f"exit code {code}; {len(sizes)} samples every {args.every:g} s over {args.duration:g} s")
    worst = 0.0
    for name, samples in series.items():
        samples = [(t, v) for t, v in samples if t <= args.duration] or samples  # not the shutdown
        if not samples:
            continue
        at_1min = next((v for t, v in samples if t >= WARMUP_S), samples[-1][1])
        slope = growth(samples, WARMUP_S)
        slope_text = "n/a (run shorter than ~70 s)" if slope is None else f"{slope:+.2f} MB/min"
        worst = max(worst, slope or 0.0)
        print(f"  {name:10s} RSS start {samples[0][1]:6.0f} MB, at 1 min {at_1min:6.0f} MB, end {samples[-1][1]:6.0f}"
              f" MB, peak {max(v for _, v in samples):6.0f} MB; growth after 1 min {slope_text}; CPU "
              f"{100 * cpu.get(name, 0.0) / max(samples[-1][0], 1e-9):.0f} % of one core")
    per_min = total_mb / (args.duration / 60.0)
    if not args.off:
        print(f"  recording {total_mb:.1f} MB in {len(files)} file(s) = {per_min:.1f} MB/min ({per_min * 10:.0f} MB "
              f"per 10 min): {', '.join(f'{p.name} {p.stat().st_size / 1e6:.1f}' for p in files)}")
        slope = growth(sizes, min(WARMUP_S, sizes[-1][0] / 2)) if len(sizes) > 2 else None
        if slope is not None:
            print(f"  recording growth while running: {slope:.1f} MB/min")
    steal = {cpu_name: 100 * (steal1[cpu_name][0] - steal_start) / max(1, steal1[cpu_name][1] - total_start)
             for cpu_name, (steal_start, total_start) in steal0.items() if cpu_name in steal1}
    print("  CPU steal (hypervisor) during the run: " + ", ".join(f"{k} {v:.2f} %" for k, v in steal.items()))
    stats = json.loads(stats_path.read_text()) if stats_path.exists() else {}
    if stats.get("ticks"):
        worst_overrun_ms = max(stats["worst_overruns_us"] or [0]) / 1e3
        print(f"  late share {100 * stats['late_share']:.3f} % ({stats['late_ticks']} of {stats['ticks']} ticks), "
              f"skipped {stats['skipped_ticks']}, worst overrun {worst_overrun_ms:.1f} ms, tick work p99 "
              f"{stats['work_us']['p99']:.0f} µs, telemetry section p99 "
              f"{stats['sections_us'].get('telemetry', {}).get('p99', float('nan')):.1f} µs, stop: "
              f"{stats['stop_cause']}, fell {stats.get('fell')}")
        dropped = [line for line in (work / "run.log").read_text().splitlines() if "dropped" in line or "fault" in line
                   or "damping" in line]
        for line in dropped[:5]:
            print("  log:", line)
    else:
        print("  the run did not start its loop:", (work / "run.log").read_text().strip()[-2000:])
    if not stats.get("ticks") or not series["control"]:
        return code or 1
    print(f"goals: growth <= {GROWTH_GOAL_MB_MIN:g} MB/min: {'met' if worst <= GROWTH_GOAL_MB_MIN else 'MISSED'} "
          f"(worst {worst:+.2f})" + ("" if args.off else f"; <= {SIZE_GOAL_MB_10MIN:g} MB per 10 min: "
                                     f"{'met' if per_min * 10 <= SIZE_GOAL_MB_10MIN else 'MISSED'} "
                                     f"({per_min * 10:.0f} MB)"))
    if args.keep or args.dir is not None:
        print(f"  kept in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if code == 0 else code


if __name__ == "__main__":
    sys.exit(main())
