"""Speed of the unpaced mock as a multiple of real time, on one core.

Measures, in one run: MuJoCo physics alone (mj_step with the model's 1 ms step) and the unpaced
`bruce-run --backend mock` session (backend read incl. physics + standing controller at 100 Hz + Eq. 8 +
backend write + ground-truth log, start-up included). Goal (issue #2): the session >= 20x real time.

    python bench/bench_mock_speed.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import time

import mujoco
import numpy as np

from bruce_hw import load_config, make_backend
from runtime.loop.run import run_session

GOAL = 20.0


def physics_only(config, seconds: float) -> float:
    mock = make_backend("mock", config)
    mock.configure()
    model, data = mock.model, mock.data
    steps = round(seconds * config.loop_hz)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return seconds / (time.perf_counter() - start)


def standing_run(config, seconds: float) -> tuple[float, float]:
    """The `bruce-run --backend mock` session itself; its wall time includes start-up (model loads)."""
    with contextlib.redirect_stdout(io.StringIO()):
        summary = run_session(make_backend("mock", config), config, duration=seconds, realtime=False)
    return summary.truth.sim_time / summary.wall_time, summary.truth.base_height_min


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per measurement")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    config = load_config()
    physics_only(config, 1.0)  # warm caches
    physics = np.median([physics_only(config, args.seconds) for _ in range(3)])
    runs = [standing_run(config, args.seconds) for _ in range(3)]
    loop = float(np.median([r[0] for r in runs]))
    print(f"mock speed on one core, {args.seconds:.0f} s simulated, median of 3:")
    print(f"  physics alone (mj_step)             {physics:7.1f}x real time  ({1e6 / (physics * 1000):.1f} us/tick)")
    print(f"  bruce-run mock session               {loop:7.1f}x real time  ({1e6 / (loop * 1000):.1f} us/tick)")
    print(f"  ratio session / physics alone        {loop / physics:7.2f}")
    print(f"  lowest base height                   {runs[-1][1]:.3f} m")
    print(f"  goal >= {GOAL:.0f}x real time: {'met' if loop >= GOAL else 'NOT met'}")


if __name__ == "__main__":
    main()
