"""Missed control deadlines on the mock: what a late tick does to Eq. 8 walking and to the PINN / Eq. 9 reference.

On a robot a late tick holds the last torque for (1 + k) ms and the next tick reads the state k ms later than due;
the loop (runtime/loop/run.py) then runs that tick at once, skips the missed deadlines (no burst), schedules the policy
on the backend's clock and steps the PINN once from the measured state, so its LSTM sees a (1 + k)-ms step as a
1-ms one. `SkippingMock` emulates that: with probability p per tick (seeded), read() steps the physics k extra
1-ms steps with the torque held (command, bus delay line, motor lag and sensor delay line all advance per
physics step, as in time), so the backend clock jumps (1 + k) dt. The controller is the ONNX policy at
--cmd 0.4,0,0 (`run_session` with a `CommandSchedule`), on the nominal mock (gap `none`) and the `default`
reality gap; the number of ticks is scaled by 1 / (1 + p k) so each walk covers about --seconds of sim time.

Transfers: `direct` (Eq. 8), `pinn` (Eq. 9, the runtime's one PINN step per executed tick), and `pinn+k1`: the
alternative, only in this bench (a monkeypatch of OnnxPinn.step, runtime code untouched): on a tick after k
skipped deadlines the PINN first rolls its LSTM through the k missed 1-ms steps from its own last prediction with
the torque that was held (the previous tick's tau*), then takes the measured step: k + 1 steps per late tick.

Per tick t the PINN's prediction q_hat_t (made from q_t, tau*_t for t + 1 ms) is scored against the next measured
q_{t+1}; the first 200 ticks are left out. Tick classes (by e_t, the extra steps before tick t's reading):
  N      clean: no skip in the step to t+1 nor in the 10 steps into t-9..t
  A1     late tick: the step into t was skipped (the LSTM just saw (1+k) ms as 1 ms), the step to t+1 is normal
  A2-10  2..10 ticks after a skipped step, next step normal (how long the LSTM disturbance lasts)
  S      the step to t+1 is skipped: q_{t+1} is (1+k) ms after q_t, the prediction 1 ms (S@1ms: scored against
         the state measured 1 ms after tick t, inside the skipped read: the model error without the horizon)
|fb| is the Eq. 9 position feedback |Kp' (q_hat_t - q_t)| (N m, mean over joints and ticks). In every `pinn` run,
shadow PINNs (not in the loop, fed the same measured q, qd, tau*) give a paired comparison on the same ticks:
`1 step` (the runtime's rule; equals the loop's PINN), `k+1 held` (catch-up with the held tau*_{t-1}) and
`k+1 same` (catch-up with this tick's tau*_t for the extra steps), and `no memory` (LSTM state zeroed before
every step: how much the history matters at all). `S end` is |Kp' (q_hat_t - q_{t+1})|, the Eq. 9 position term
at the end of a held (1 + k) ms, when the robot has moved past the 1-ms reference.

    python bench/bench_missed_ticks.py [--seconds 12] [--seeds 2]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import time
from collections import defaultdict
from dataclasses import replace

import numpy as np

from bruce_hw.backend import LifecycleState
from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import load_gap
from runtime.control.commands import CommandSchedule
from runtime.control.inference import OnnxPinn
from runtime.loop.observers import EachTick
from runtime.loop.run import run_session

CASES = ((0.0, 1), (0.02, 1), (0.10, 1), (0.02, 4))  # (skip share p, extra steps k)
GAPS = ("none", "default")
COMMAND = (0.4, 0.0, 0.0)
SETTLE_TICKS = 200            # predictions of the first ticks (soft start, LSTM from zero) are left out
AFTER = 10                    # a tick up to this many ticks after a skipped step is not "clean"
SHADOWS = ("1 step", "k+1 held", "k+1 same", "no memory")
CLASSES = ("N", "A1", "A2-10", "S", "S@1ms")
ORIGINAL_STEP = OnnxPinn.step


class SkippingMock(MujocoBackend):
    """The mock with missed deadlines: while active, each read() first steps the physics `k` extra dt with the
    last torque held, with probability `p` (its own seeded generator). Per active read it logs the extra steps,
    and the noise-free q the reading stands for (the true q `sensor latency` physics steps before; with no gap
    exactly the q read), also 1 ms after the previous tick inside a skipped read."""

    def __init__(self, config, gap, p: float, k: int, seed: int):
        super().__init__(config, gap=gap)
        self.p, self.k = p, k
        self.rng = np.random.default_rng([seed, 1729])
        self.extras: list[int] = []               # per active read: extra physics steps before its reading
        self.q_1ms: list[np.ndarray | None] = []  # ... the q read 1 ms after the previous tick (skipped reads)
        self.clean: list[np.ndarray] = []         # ... the noise-free q its reading stands for
        self.clean_1ms: list[np.ndarray | None] = []

    def _on_configure(self) -> None:
        super()._on_configure()
        self._latency = self._sensor_gap.latency if self._sensor_gap is not None else 0
        self._true = [self.data.qpos[self._qpos].copy()] * (self._latency + 1)  # true q after each physics step

    def _physics_step(self):
        state = super()._read()
        self._true.append(self.data.qpos[self._qpos].copy())
        del self._true[0]
        return state, self._true[0]  # the reading, and the noise-free q it stands for (latency steps back)

    def _read(self):
        if self._state is not LifecycleState.ACTIVE:
            return self._physics_step()[0]
        extra = self.k if self.rng.random() < self.p else 0
        self.extras.append(extra)
        if extra:  # every sub-step: motor torque of the held command (bus delay, lag), mj_step, sensor path
            first, clean = self._physics_step()
            self.q_1ms.append(first.joints.q.copy())
            self.clean_1ms.append(clean)
            for _ in range(extra - 1):
                self._physics_step()
        else:
            self.q_1ms.append(None)
            self.clean_1ms.append(None)
        state, clean = self._physics_step()
        self.clean.append(clean)
        return state


class Probe:
    """Records one run: the loop's PINN predictions (a monkeypatch of OnnxPinn.step), q per tick (an observer),
    the shadow PINNs' predictions; with `catch_up`, the loop's PINN itself rolls through missed steps."""

    def __init__(self, backend: SkippingMock, pinn_path, n_joints: int, catch_up: bool, shadows: bool):
        self.backend, self.catch_up = backend, catch_up
        self.q: list[np.ndarray] = []
        self.q_hat: list[np.ndarray] = []
        self.last = None  # the loop PINN's last (q_hat, qd_hat, tau*)
        self.shadows = {name: OnnxPinn(pinn_path, n_joints) for name in SHADOWS} if shadows else {}
        self.shadow_q_hat = {name: [] for name in self.shadows}
        self.shadow_last = {name: None for name in self.shadows}

    def step(self, pinn: OnnxPinn, q, qd, tau):
        if self.backend.state is not LifecycleState.ACTIVE:  # check_models' warm-up step
            return ORIGINAL_STEP(pinn, q, qd, tau)
        extra = self.backend.extras[-1]
        if self.catch_up and extra and self.last is not None:
            q_hat, qd_hat, tau_held = self.last
            for _ in range(extra):
                q_hat, qd_hat = ORIGINAL_STEP(pinn, q_hat, qd_hat, tau_held)
        q_hat, qd_hat = ORIGINAL_STEP(pinn, q, qd, tau)
        self.last = (q_hat, qd_hat, tau.copy())
        self.q_hat.append(q_hat)
        for name, shadow in self.shadows.items():
            last = self.shadow_last[name]
            if name == "no memory":
                shadow.reset()  # every step from a zero LSTM state: how much the history matters at all
            elif name != "1 step" and extra and last is not None:
                sq, sqd, tau_held = last
                for _ in range(extra):
                    sq, sqd = ORIGINAL_STEP(shadow, sq, sqd, tau_held if name == "k+1 held" else tau)
            sq, sqd = ORIGINAL_STEP(shadow, q, qd, tau)
            self.shadow_last[name] = (sq, sqd, tau.copy())
            self.shadow_q_hat[name].append(sq)
        return q_hat, qd_hat

    def record(self, view):
        self.q.append(view.q.copy())


class Acc:
    """Pooled sums over seeds: squared prediction error and |feedback| per tick class."""

    def __init__(self):
        self.sq = defaultdict(float)
        self.n = defaultdict(int)
        self.fb = defaultdict(float)
        self.fb_n = defaultdict(int)

    def add(self, cls: str, err: np.ndarray, fb: np.ndarray | None = None) -> None:
        self.sq[cls] += float(np.sum(err * err))
        self.n[cls] += err.size
        if fb is not None:
            self.fb[cls] += float(np.sum(np.abs(fb)))
            self.fb_n[cls] += fb.size

    def rmse_urad(self, cls: str) -> float | None:
        return 1e6 * np.sqrt(self.sq[cls] / self.n[cls]) if self.n[cls] else None

    def fb_mean(self, cls: str) -> float | None:
        return self.fb[cls] / self.fb_n[cls] if self.fb_n[cls] else None

    def ticks(self, cls: str, n_joints: int) -> int:
        return self.n[cls] // n_joints


def score(meas: Acc, clean: Acc, q_hat: list, probe: Probe, extras: np.ndarray, kp: np.ndarray) -> None:
    """Add one run's predictions by tick class: to `meas` the error against the next measured q (and |fb|), to
    `clean` the error of the predicted increment q_hat_t - q_t against the noise-free one (sensor noise cancels)."""
    q = np.array(probe.q)
    m = min(len(q) - 1, len(q_hat))  # predictions with a next reading
    if m <= SETTLE_TICKS:
        return
    q_hat = np.array(q_hat[:m])
    c = probe.backend.clean
    c_1ms, q_1ms = probe.backend.clean_1ms, probe.backend.q_1ms
    e = extras[:m + 1] > 0
    recent = np.convolve(e.astype(int), np.ones(AFTER, int))[:m + 1] > 0  # a skip into one of ticks t-9..t
    for t in range(SETTLE_TICKS, m):
        step = q_hat[t] - q[t]
        err, incr_err = q_hat[t] - q[t + 1], step - (c[t + 1] - c[t])
        cls = "S" if e[t + 1] else "A1" if e[t] else "A2-10" if recent[t] else "N"
        meas.add(cls, err, kp * step)
        clean.add(cls, incr_err)
        if e[t + 1]:
            meas.add("S@1ms", q_hat[t] - q_1ms[t + 1])
            meas.add("S end", err[:0], kp * err)  # the Eq. 9 position term at the end of the held (1 + k) ms
            clean.add("S@1ms", step - (c_1ms[t + 1] - c[t]))


def walk(config, gap_name: str, p: float, k: int, transfer: str, seed: int, seconds: float) -> dict:
    gap = load_gap(gap_name, config.joints)
    gap = replace(gap, seed=seed)
    backend = SkippingMock(config, gap, p, k, seed)
    pinn_mode = transfer != "direct"
    probe = Probe(backend, config.models.pinn, config.n_joints, catch_up=transfer == "pinn+k1",
                  shadows=transfer == "pinn" and p > 0)
    OnnxPinn.step = lambda pinn, q, qd, tau: probe.step(pinn, q, qd, tau)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            summary = run_session(backend, config, duration=seconds / (1.0 + p * k), realtime=False,
                                  transfer="pinn" if pinn_mode else "direct",
                                  commands=CommandSchedule.constant(*COMMAND),
                                  observers=[EachTick(probe.record)])
    finally:
        OnnxPinn.step = ORIGINAL_STEP
    truth = summary.truth
    extras = np.array(backend.extras)
    out = {"fell": truth.fell, "tracking": truth.tracking_error, "sim": truth.sim_time,
           "skips": int(np.count_nonzero(extras[:summary.ticks])), "stop": summary.stop_cause}
    if pinn_mode:
        kp = config.eq9.kp
        out["acc"] = (Acc(), Acc())
        score(*out["acc"], probe.q_hat, probe, extras, kp)
        out["shadow"] = {}
        for name in probe.shadows:
            out["shadow"][name] = (Acc(), Acc())
            score(*out["shadow"][name], probe.shadow_q_hat[name], probe, extras, kp)
        if "1 step" in probe.shadows:  # the shadow with the runtime's rule must replay the loop's PINN exactly
            same = np.array_equal(np.array(probe.q_hat), np.array(probe.shadow_q_hat["1 step"]))
            out["replay_ok"] = same
    return out


def fmt(value, spec: str, width: int) -> str:
    return f"{'-':>{width}s}" if value is None else f"{value:{width}{spec}}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=12.0, help="simulated seconds per walk (default 12)")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per row: skip pattern and gap noise (default 2)")
    args = parser.parse_args()
    for name in ("runtime", "bruce_hw"):
        logging.getLogger(name).setLevel(logging.ERROR)  # the soft-start lines; trips show in the stop column
    config = load_config()
    n = config.n_joints
    start = time.perf_counter()
    rows = []
    for gap_name in GAPS:
        for p, k in CASES:
            for transfer in ("direct", "pinn", "pinn+k1"):
                if transfer == "pinn+k1" and p == 0:
                    continue  # identical to pinn without skips
                runs = [walk(config, gap_name, p, k, transfer, seed, args.seconds) for seed in range(args.seeds)]
                rows.append((gap_name, p, k, transfer, runs))
    wall = time.perf_counter() - start

    print(f"missed ticks: ONNX policy, cmd {COMMAND}, ~{args.seconds:g} s sim per walk, seeds 0..{args.seeds - 1} "
          f"(pooled), PINN {config.models.pinn.name}, {wall:.0f} s wall")
    print("\n1) outcome (ground truth; tracking |mean(v) - mean(cmd)| after 2 s, mean over seeds)")
    print(f"{'gap':8s} {'skip':>9s} {'transfer':8s} {'fell':>5s} {'vx err':>7s} {'vy err':>7s} {'wz err':>7s} "
          f"{'sim s':>6s} {'skips':>6s}  end")
    for gap_name, p, k, transfer, runs in rows:
        fell = sum(r["fell"] for r in runs)
        track = [r["tracking"] for r in runs if r["tracking"]]
        mean = {a: (np.mean([t[a] for t in track]) if track else None) for a in ("vx", "vy", "wz")}
        ends = sorted({r["stop"] for r in runs})
        print(f"{gap_name:8s} {f'{100 * p:g}% k={k}':>9s} {transfer:8s} {f'{fell}/{len(runs)}':>5s} "
              f"{fmt(mean['vx'], '.3f', 7)} {fmt(mean['vy'], '.3f', 7)} {fmt(mean['wz'], '.3f', 7)} "
              f"{np.mean([r['sim'] for r in runs]):6.2f} {sum(r['skips'] for r in runs):6d}  {'; '.join(ends)}")

    def pooled(runs, key=None, which=0) -> Acc:
        """Pooled over seeds: which 0, the error against the measured q; 1, the noise-free increment error."""
        total = Acc()
        for r in runs:
            acc = (r["acc"] if key is None else r["shadow"][key])[which]
            for d_from, d_to in ((acc.sq, total.sq), (acc.n, total.n), (acc.fb, total.fb), (acc.fb_n, total.fb_n)):
                for cls, v in d_from.items():
                    d_to[cls] += v
        return total

    pinn_rows = [row for row in rows if row[3] != "direct"]
    label = "{:8s} {:>9s} {:8s} ".format
    for which, title in ((0, "2a) the loop's PINN: RMSE(q_hat_t - q_{t+1}) against the measured next q, µrad; Eq. 9 "
                             "|Kp'(q_hat_t - q_t)|,\n"
                             "    N m (Send: |Kp'(q_hat_t - q_{t+1})|, after the hold); ticks per class"),
                         (1, "2b) the same predictions, noise-free increment error RMSE((q_hat_t - q_t) - (c_{t+1} - "
                             "c_t)), µrad (c: the q a reading stands for without sensor noise; = 2a with gap none)")):
        print(f"\n{title}")
        print(label("gap", "skip", "transfer") + " ".join(f"{c:>7s}" for c in CLASSES)
              + ("" if which else " | " + " ".join(f"{'fb ' + c:>8s}" for c in (*CLASSES[:4], "Send")) + " | "
                 + " ".join(f"{'n ' + c:>7s}" for c in CLASSES[:4])))
        for gap_name, p, k, transfer, runs in pinn_rows:
            acc = pooled(runs, which=which)
            print(label(gap_name, f"{100 * p:g}% k={k}", transfer)
                  + " ".join(fmt(acc.rmse_urad(c), '.1f', 7) for c in CLASSES)
                  + ("" if which else " | " + " ".join(fmt(acc.fb_mean(c), '.4f', 8) for c in (*CLASSES[:4], "S end"))
                     + " | "
                     + " ".join(f"{acc.ticks(c, n):7d}" for c in CLASSES[:4])))

    print("\n3) paired on the same `pinn` walks: shadow PINNs fed the loop's q, qd, tau* (replay: `1 step` equals the "
          "loop's PINN). Noise-free increment error RMSE µrad by tick class; |fb| on A1, N m")
    groups = (("A1", SHADOWS), ("A2-10", SHADOWS[:3]), ("N", (SHADOWS[0], SHADOWS[3])))
    short = {"1 step": "1 step", "k+1 held": "k+1 held", "k+1 same": "k+1 same", "no memory": "no mem"}
    head = " | ".join(f"{cls:^{10 * len(names) - 1}s}" for cls, names in groups) + f" | {'fb A1':^19s}"
    print(f"{'':8s} {'':>9s} " + head + " | replay")
    print(f"{'gap':8s} {'skip':>9s} " + " | ".join(" ".join(f"{short[s]:>9s}" for s in names) for _, names in groups)
          + " | " + " ".join(f"{short[s]:>9s}" for s in SHADOWS[:2]) + " |")
    for gap_name, p, k, transfer, runs in rows:
        if transfer != "pinn" or p == 0:
            continue
        clean = {s: pooled(runs, s, 1) for s in SHADOWS}
        meas = {s: pooled(runs, s, 0) for s in SHADOWS[:2]}
        print(f"{gap_name:8s} {f'{100 * p:g}% k={k}':>9s} "
              + " | ".join(" ".join(fmt(clean[s].rmse_urad(cls), '.1f', 9) for s in names) for cls, names in groups)
              + " | " + " ".join(fmt(meas[s].fb_mean("A1"), '.4f', 9) for s in SHADOWS[:2]) + " | "
              + ("exact" if all(r.get("replay_ok") for r in runs) else "DIFFERS"))

if __name__ == "__main__":
    main()
