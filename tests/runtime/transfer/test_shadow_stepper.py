"""The shadow's step beside the loop (runtime/transfer/shadow_stepper.py): the same shadow as on the tick, its step
on another thread; an answer not back in time is a resync, a step still running is not asked again, an error in
it ends the run at the tick it was due."""

import json
import threading

import numpy as np
import pytest

from bruce_hw.config import PdGains
from bruce_hw.mock import MujocoBackend
from runtime.control.inference import ModelError, OnnxPinn
from runtime.control.mixing import eq8_torque
from runtime.loop.run import run_session
from runtime.robot_config import load_config
from runtime.transfer.reference_models import PinnReference
from runtime.transfer.schemes import build_scheme
from runtime.transfer.shadow import ShadowScheme
from runtime.transfer.shadow_stepper import InlineShadowStepper, ThreadShadowStepper

GAINS = PdGains(kp=np.full(10, 8.0), kd=np.full(10, 0.3))


@pytest.fixture(scope="module")
def config():
    return load_config()


def pinn_reference(config):
    pinn = OnnxPinn(config.models.pinn, config.n_joints)
    pinn.warmup()
    return PinnReference(pinn)


def drive(scheme, ticks, seed=0):
    """Ticks of a walk-like input; per tick what the loop reads of the scheme: (one_step before predict, q_hat,
    qd_hat, torque)."""
    rng = np.random.default_rng(seed)
    out = []
    scheme.reset()
    q, qd = np.zeros(10), np.zeros(10)
    for _ in range(ticks):
        q = q + 0.01 * rng.normal(size=10)
        qd = rng.normal(size=10)
        a = 0.1 * rng.normal(size=10)
        tau_star = eq8_torque(a, q, qd, GAINS)
        one_step = scheme.one_step
        scheme.predict(a, q, qd, tau_star)
        out.append((None if one_step is None else np.concatenate(one_step), scheme.q_hat.copy(),
                    scheme.qd_hat.copy(), scheme.torque(tau_star, q, qd)))
    scheme.close()
    return out


def test_the_shadow_stepped_beside_the_loop_is_the_shadow_stepped_on_the_tick(config):
    """The PINN's LSTM carried on another thread: every one-step prediction, shadow state and torque of 60 ticks the
    same bit for bit as on the tick, and each step ran on the stepper's thread."""
    inline = drive(ShadowScheme(pinn_reference(config), GAINS, config.eq8, 5), 60)
    reference = pinn_reference(config)
    threads = set()
    step = reference.step

    def recorded(q, qd, tau):
        threads.add(threading.current_thread().name)
        return step(q, qd, tau)

    reference.step = recorded
    stepper = ThreadShadowStepper(reference, wait=True)
    beside = drive(ShadowScheme(reference, GAINS, config.eq8, 5, stepper), 60)
    assert threads == {"shadow-step"}
    assert stepper.late == stepper.skipped == 0
    predictions = 0
    for (one_i, *rest_i), (one_b, *rest_b) in zip(inline, beside, strict=True):
        assert (one_i is None) == (one_b is None)
        if one_i is not None:
            predictions += 1
            np.testing.assert_array_equal(one_i, one_b)
        for x, y in zip(rest_i, rest_b, strict=True):
            np.testing.assert_array_equal(x, y)
    assert predictions == 12  # a resync every 5 ticks, its prediction read at the next


class HeldModel:
    """A self-contained reference whose step waits until released (a thread beside the loop that is not run)."""

    name = "held"
    pinn = None
    self_contained = True

    def __init__(self):
        self.release = threading.Event()
        self.steps = []

    def reset(self):
        pass

    def step(self, q, qd, tau):
        self.steps.append(q.copy())
        self.release.wait(5.0)
        return q + 1.0, qd + 1.0


def test_an_answer_not_back_in_time_is_a_resync_and_a_running_step_is_not_asked_again():
    model = HeldModel()
    stepper = ThreadShadowStepper(model)
    scheme = ShadowScheme(model, GAINS, GAINS, resync_ticks=100, stepper=stepper)
    scheme.reset()
    q = [np.full(10, float(k)) for k in range(4)]
    zero = np.zeros(10)
    tau_star = np.full(10, 0.5)
    scheme.predict(zero, q[0], zero, tau_star)  # tick 0 asks; its step is held
    scheme.predict(zero, q[1], zero, tau_star)  # tick 1: not back, resync from the measured state; not asked
    assert stepper.late == 1 and stepper.skipped == 1
    np.testing.assert_array_equal(scheme.q_hat, q[1])
    np.testing.assert_array_equal(scheme.torque(tau_star, q[1], zero), tau_star)  # direct transfer this tick
    model.release.set()
    with stepper._done:  # the held step comes back (late): the stepper is free again
        assert stepper._done.wait_for(lambda: stepper._answer is not None, timeout=5.0)
    scheme.predict(zero, q[2], zero, tau_star)  # tick 2: nothing asked at tick 1, resync; asks again
    np.testing.assert_array_equal(scheme.q_hat, q[2])
    stepper.wait = True
    scheme.predict(zero, q[3], zero, tau_star)  # tick 3: tick 2's step, from q[2]
    np.testing.assert_array_equal(scheme.q_hat, q[2] + 1.0)
    assert stepper.late == 1 and stepper.skipped == 1
    assert scheme.report() == {"shadow": {"steps_on": "a thread beside the loop", "late": 1, "skipped": 1}}
    scheme.close()  # the thread takes the step asked at tick 3, then ends
    assert stepper._worker.thread is None
    assert [s[0] for s in model.steps] == [0.0, 2.0, 3.0]  # from q[0], q[2] and tick 3's shadow (q[2] + 1)


class FailingModel:
    name = "failing"
    pinn = None
    self_contained = True

    def __init__(self, error):
        self.error = error

    def reset(self):
        pass

    def step(self, q, qd, tau):
        raise self.error


@pytest.mark.parametrize("error, match", [
    (ModelError("PINN model x.onnx: returned non-finite q_next/qd_next"), r"^PINN model x\.onnx: returned non-finite"),
    (MemoryError("out of memory"), r"^shadow's reference model: MemoryError: out of memory$"),
])
def test_an_error_in_the_step_beside_the_loop_is_raised_by_the_tick_it_was_due_for(error, match):
    """The loop reads `one_step` before `predict`: it gives None there, and `predict` raises (where the loop ends the
    run in damping)."""
    stepper = ThreadShadowStepper(FailingModel(error), wait=True)
    scheme = ShadowScheme(stepper.reference, GAINS, GAINS, resync_ticks=10, stepper=stepper)
    scheme.reset()
    zero = np.zeros(10)
    scheme.predict(zero, zero, zero, zero)  # asks; the step fails on its thread
    assert scheme.one_step is None
    with pytest.raises(ModelError, match=match):
        scheme.predict(zero, zero, zero, zero)
    scheme.close()


def test_a_paced_run_steps_the_pinn_beside_the_loop_and_the_nominal_model_on_the_tick(config):
    """The nominal model reads the robot's base estimate as it steps: it stays on the control thread. The twin's
    inner shadow is paced as the run is."""
    nominal = load_config(overrides=["transfer.reference_model=nominal"])
    base = lambda: None  # noqa: E731 -- the nominal model's base state (never read here)
    assert type(build_scheme(config, "shadow", paced=True).stepper) is ThreadShadowStepper
    assert type(build_scheme(config, "shadow", paced=False).stepper) is InlineShadowStepper
    assert type(build_scheme(nominal, "shadow", base_state=base, paced=True).stepper) is InlineShadowStepper
    twin = build_scheme(config, "shadow_twin", base_state=base, paced=True)
    assert type(twin.inner.stepper) is ThreadShadowStepper
    twin.close()


def test_a_paced_run_reports_where_the_shadow_stepped_and_its_late_answers(config, tmp_path):
    """A paced mock run with the shadow: its PINN stepped beside the loop, in the stats and the summary's lines."""
    stats = tmp_path / "run.json"
    summary = run_session(MujocoBackend(config), config, duration=0.3, realtime=True, transfer="shadow",
                          stats_path=stats)
    report = json.loads(stats.read_text())["shadow"]
    assert report["steps_on"] == "a thread beside the loop"
    assert 0 <= report["late"] + report["skipped"] < summary.ticks
    assert f"shadow: its model steps on a thread beside the loop; {report['late']} answers not back" in summary.text()
    unpaced = run_session(MujocoBackend(config), config, duration=0.05, realtime=False, transfer="shadow")
    assert unpaced.scheme_report["shadow"]["steps_on"] == "the control thread"
    assert "shadow: its model steps" not in unpaced.text()
