"""The OLNN baseline (training/dynamics/olnn.py): structure of M, physics of the step, analytic vs autograd
derivatives, RK4, ONNX export parity, and that it trains."""

import json
import math
from types import SimpleNamespace

import numpy as np
import onnxruntime as ort
import pytest
import torch

from training.dynamics.olnn import (
    OlnnConfig,
    OlnnStep,
    export_olnn_onnx,
    make_random_olnn,
    rk4_step,
    unit_lower_inverse_factors,
)
from training.onnx_export import sidecar_path

N = 10
SMALL = OlnnConfig(mass_widths=(16, 16), potential_widths=(8, 8), force_widths=(24, 24))


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Small batches: one thread is faster, and on a shared 2-core machine a second spinning thread is much slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def randomise(model: OlnnStep, seed: int) -> OlnnStep:
    """Random normalisation and non-zero potential/force output layers, so every term of the dynamics is active."""
    rng = np.random.default_rng(seed)
    n = model.n_joints
    model.set_normalisation(q_mean=rng.normal(0, 0.3, n), q_std=rng.uniform(0.2, 0.8, n),
                            qd_mean=rng.normal(0, 0.5, n), qd_std=rng.uniform(1, 3, n),
                            tau_mean=rng.normal(0, 0.5, n), tau_std=rng.uniform(1, 4, n),
                            m_scale=rng.uniform(0.01, 0.1, n), f_scale=rng.uniform(0.5, 2, n), v_scale=1.5)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for net in (model.potential_net, model.force_net):
            for tensor in (net.layers[-1].weight, net.layers[-1].bias):
                tensor.copy_(0.3 * torch.randn(tensor.shape, generator=generator))
    return model


def random_inputs(batch: int, seed: int, dtype=torch.float32, n: int = N):
    generator = torch.Generator().manual_seed(seed)
    return [torch.randn(batch, n, generator=generator, dtype=dtype) * s for s in (0.5, 2.0, 3.0)]


def test_config_checks_and_default_size_is_the_pinns_range():
    with pytest.raises(ValueError, match="mass_widths"):
        OlnnConfig(mass_widths=())
    with pytest.raises(ValueError, match="activation"):
        OlnnConfig(activation="relu")
    with pytest.raises(ValueError, match="diag_eps"):
        OlnnConfig(diag_eps=0.0)
    with pytest.raises(ValueError, match="derivatives"):
        OlnnStep(SMALL, derivatives="finite-differences")
    n_params = sum(p.numel() for p in make_random_olnn().parameters())
    assert 80_000 <= n_params <= 130_000  # the PINN has 123,055


def test_interface_shapes_and_stateless():
    model = make_random_olnn(SMALL)
    q, qd, tau = random_inputs(5, seed=0)
    assert model.initial_state(5) == ()
    q_next, qd_next = model(q, qd, tau, *model.initial_state(5))
    assert q_next.shape == qd_next.shape == (5, N) and q_next.dtype == qd_next.dtype == torch.float32
    assert model.mass_matrix(q).shape == (5, N, N) and model.potential(q).shape == (5,)
    assert (model.n_joints, model.dt) == (N, 1e-3)


def test_mass_matrix_is_symmetric_positive_definite_and_depends_on_q():
    model = randomise(make_random_olnn(seed=3).double(), seed=3)
    q = random_inputs(128, seed=1, dtype=torch.float64)[0] * 6
    mass = model.mass_matrix(q)
    torch.testing.assert_close(mass, mass.transpose(1, 2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(mass).min() > 0
    assert (mass[1:] - mass[:1]).abs().amax() > 1e-3


@pytest.mark.parametrize("n", [1, 2, 3, 10, 16, 17])
def test_triangular_inverse_is_exact(n):
    model = make_random_olnn(OlnnConfig(n_joints=n, mass_widths=(8,), potential_widths=(4,), force_widths=(4,)),
                             seed=n).double()
    factor = model._factor(random_inputs(16, seed=n, dtype=torch.float64, n=n)[0] * 3)[0]
    eye = torch.eye(n, dtype=torch.float64)
    torch.testing.assert_close(model._lower_inverse(factor) @ factor, eye.expand(16, n, n), rtol=0, atol=1e-10)
    assert 2 ** unit_lower_inverse_factors(n) >= n


def test_analytic_derivatives_match_autograd_float64():
    model = randomise(make_random_olnn(seed=5).double(), seed=5)
    q, qd, tau = random_inputs(32, seed=2, dtype=torch.float64)
    analytic = model.accel(q, qd, tau, derivatives="analytic")
    reference = model.accel(q, qd, tau, derivatives="autograd")
    assert reference.abs().amax() > 1.0  # a non-trivial acceleration
    torch.testing.assert_close(analytic, reference, rtol=1e-10, atol=1e-10)
    for a, b in zip(model.step(q, qd, tau, "analytic"), model.step(q, qd, tau, "autograd"), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_analytic_derivatives_match_autograd_float32_within_1e5():
    model = randomise(make_random_olnn(seed=6), seed=6)
    q, qd, tau = random_inputs(64, seed=3)
    for a, b in zip(model.step(q, qd, tau, "analytic"), model.step(q, qd, tau, "autograd"), strict=True):
        assert (a - b).abs().amax() <= 1e-5


def test_parameter_gradients_agree_between_the_two_paths():
    """The analytic path trains the same model the reference defines: d(loss)/d(theta) agree."""
    model = randomise(make_random_olnn(SMALL, seed=7).double(), seed=7)
    q, qd, tau = random_inputs(8, seed=4, dtype=torch.float64)
    grads = []
    for derivatives in ("analytic", "autograd"):
        model.zero_grad()
        q_next, qd_next = model.step(q, qd, tau, derivatives)
        (q_next.pow(2).sum() + qd_next.pow(2).sum()).backward()
        # V's offset (the potential MLP's last bias) exerts no force: its gradient is None on both paths.
        grads.append(torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1)
                                for p in model.parameters()]))
    assert grads[1].abs().amax() > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-8, atol=1e-10)


def test_autograd_path_runs_under_no_grad_and_inference_mode():
    model = randomise(make_random_olnn(SMALL, seed=8), seed=8)
    inputs = random_inputs(4, seed=5)
    with torch.no_grad():
        expected = model.step(*inputs, "analytic")
        q_next, qd_next = model.step(*inputs, "autograd")
    assert not q_next.requires_grad and not qd_next.requires_grad
    with torch.inference_mode():
        inference_inputs = [t.clone() for t in inputs]  # inference tensors, as an evaluator would make them
        for got, want in zip(model.step(*inference_inputs, "autograd"), expected, strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=1e-5)


def test_unforced_motion_conserves_energy_while_exchanging_it():
    """tau + F = 0: RK4 keeps 1/2 qd^T M qd + V constant (a wrong Coriolis term or gravity sign would not), while
    kinetic and potential energy trade places."""
    model = randomise(make_random_olnn(seed=9).double(), seed=9)
    with torch.no_grad():
        model.force_net.layers[-1].weight.zero_()
        model.force_net.layers[-1].bias.zero_()
        q, qd, _ = random_inputs(4, seed=6, dtype=torch.float64)
        tau = torch.zeros_like(q)
        energy0 = model.energy(q, qd)
        potential0 = model.potential(q)
        for _ in range(300):
            q, qd = model(q, qd, tau)
        drift = (model.energy(q, qd) - energy0).abs() / energy0.abs()
        exchanged = (model.potential(q) - potential0).abs() / energy0.abs()
    assert drift.max() < 1e-9
    assert exchanged.min() > 1e-3


def test_constant_networks_give_the_hand_computed_rk4_step():
    """Constant M, V and F: qdd = M^-1 (tau + F) is constant and RK4 is exact: q' = q + qd dt + a dt^2 / 2."""
    model = make_random_olnn(SMALL, seed=10).double()
    model.set_normalisation(m_scale=np.linspace(0.5, 2.0, N), f_scale=np.full(N, 3.0))
    with torch.no_grad():
        for net in (model.mass_net, model.potential_net, model.force_net):
            for layer in net.layers:
                layer.weight.zero_()
        model.mass_net.layers[-1].bias.normal_(0, 0.2, generator=torch.Generator().manual_seed(0))
        model.force_net.layers[-1].bias.copy_(torch.linspace(-1, 1, N, dtype=torch.float64))
        model.potential_net.layers[-1].bias.fill_(7.0)  # a constant V exerts no force
    q, qd, tau = random_inputs(3, seed=7, dtype=torch.float64)
    mass = model.mass_matrix(q)
    torch.testing.assert_close(mass[0], mass[2])
    accel = torch.linalg.solve(mass, (tau + 3.0 * torch.linspace(-1, 1, N, dtype=torch.float64)).unsqueeze(2))
    accel = accel.squeeze(2)
    dt = model.dt
    q_next, qd_next = model(q, qd, tau)
    torch.testing.assert_close(q_next, q + qd * dt + 0.5 * accel * dt**2, rtol=1e-12, atol=0)
    torch.testing.assert_close(qd_next, qd + accel * dt, rtol=1e-12, atol=0)


def test_rk4_is_fourth_order_taylor_on_a_linear_oscillator():
    """For y' = A y every 4-stage 4th-order Runge-Kutta step is y' = (I + hA + (hA)^2/2 + (hA)^3/6 + (hA)^4/24) y;
    a large step (h omega = 0.6) makes a wrong stage visible."""
    omega, dt = 3.0, 0.2
    q, qd = torch.tensor([[0.7]], dtype=torch.float64), torch.tensor([[-0.4]], dtype=torch.float64)
    q_next, qd_next = rk4_step(lambda q_, qd_: -omega**2 * q_, q, qd, dt)
    ha = dt * torch.tensor([[0.0, 1.0], [-omega**2, 0.0]], dtype=torch.float64)
    taylor = sum(torch.linalg.matrix_power(ha, k) / math.factorial(k) for k in range(5))
    expected = taylor @ torch.tensor([0.7, -0.4], dtype=torch.float64)
    torch.testing.assert_close(torch.cat([q_next[0], qd_next[0]]), expected, rtol=0, atol=1e-14)
    exact = torch.linalg.matrix_exp(ha) @ torch.tensor([0.7, -0.4], dtype=torch.float64)
    assert (expected - exact).abs().max() > 1e-5  # the check distinguishes RK4 from the exact flow


def test_fit_normalisation_sets_scales_from_the_training_statistics():
    rng = np.random.default_rng(11)
    fields = ("q_mean", "q_std", "qd_mean", "qd_std", "tau_mean", "tau_std", "q_inc_std", "qd_inc_std")
    stats = SimpleNamespace(**{name: rng.uniform(0.1, 2.0, N) for name in fields})
    model = make_random_olnn(SMALL)
    model.fit_normalisation(stats)
    for name in fields[:6]:
        np.testing.assert_allclose(getattr(model, name).numpy(), getattr(stats, name), rtol=1e-6)
    np.testing.assert_allclose(model.m_scale.numpy(), stats.tau_std * 1e-3 / stats.qd_inc_std, rtol=1e-6)
    np.testing.assert_allclose(model.f_scale.numpy(), stats.tau_std, rtol=1e-6)
    np.testing.assert_allclose(model.v_scale.item(), np.mean(stats.tau_std * stats.q_std), rtol=1e-6)
    assert "m_scale" in model.state_dict()


def test_set_normalisation_rejects_bad_values_and_changes_nothing():
    model = make_random_olnn(SMALL)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(ValueError, match="m_scale must be > 0"):
        model.set_normalisation(q_mean=np.ones(N), m_scale=np.zeros(N))
    with pytest.raises(ValueError, match=r"q_std must have shape \(10,\)"):
        model.set_normalisation(q_std=np.ones(9))
    with pytest.raises(ValueError, match="v_scale has non-finite"):
        model.set_normalisation(v_scale=float("nan"))
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def pendulum_data(batch: int, seed: int) -> tuple[torch.Tensor, ...]:
    """One RK4 step of independent damped pendulums, m qdd = tau - k sin q - c qd: structure the OLNN can express."""
    generator = torch.Generator().manual_seed(seed)
    q, qd, tau = (torch.randn(batch, N, generator=generator) * s for s in (0.8, 2.0, 1.0))
    mass, stiffness, damping = torch.linspace(0.05, 0.2, N), torch.linspace(1.0, 3.0, N), 0.1
    q_next, qd_next = rk4_step(lambda q_, qd_: (tau - stiffness * torch.sin(q_) - damping * qd_) / mass, q, qd, 1e-3)
    return q, qd, tau, q_next, qd_next


def test_a_few_optimisation_steps_lower_the_loss():
    q, qd, tau, q_next, qd_next = pendulum_data(512, seed=12)
    q_inc = q_next - q - qd * 1e-3
    qd_inc = qd_next - qd
    stats = SimpleNamespace(q_mean=q.mean(0).numpy(), q_std=q.std(0).numpy(), qd_mean=qd.mean(0).numpy(),
                            qd_std=qd.std(0).numpy(), tau_mean=tau.mean(0).numpy(), tau_std=tau.std(0).numpy(),
                            q_inc_std=q_inc.std(0).numpy(), qd_inc_std=qd_inc.std(0).numpy())
    model = make_random_olnn(SMALL, seed=13)
    model.fit_normalisation(stats)
    q_scale, qd_scale = torch.as_tensor(stats.q_inc_std), torch.as_tensor(stats.qd_inc_std)

    def loss() -> torch.Tensor:
        q_pred, qd_pred = model(q, qd, tau)
        return (((q_pred - q_next) / q_scale).pow(2).mean() + ((qd_pred - qd_next) / qd_scale).pow(2).mean())

    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=1e-2)
    with torch.no_grad():
        initial = loss().item()
    for _ in range(40):
        optimiser.zero_grad()
        value = loss()
        value.backward()
        optimiser.step()
    with torch.no_grad():
        final = loss().item()
    assert np.isfinite(final) and final < 0.5 * initial


@pytest.fixture(scope="module")
def exported_olnn(tmp_path_factory):
    model = randomise(make_random_olnn(seed=14, derivatives="autograd"), seed=14)
    path = export_olnn_onnx(model, tmp_path_factory.mktemp("olnn") / "olnn.onnx")
    assert model.derivatives == "autograd"  # export switched to the analytic path and back
    return model, path


def ort_session(path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def test_onnx_io_and_sidecar(exported_olnn):
    _, path = exported_olnn
    session = ort_session(path)
    assert [(t.name, t.shape) for t in session.get_inputs()] == [("q", [1, N]), ("qd", [1, N]), ("tau", [1, N])]
    assert [(t.name, t.shape) for t in session.get_outputs()] == [("q_next", [1, N]), ("qd_next", [1, N])]
    sidecar = json.loads(sidecar_path(path).read_text())
    assert sidecar["kind"] == "olnn_step" and sidecar["integrator"] == "rk4_3/8"


def test_onnx_matches_the_autograd_reference_per_step_and_over_a_rollout(exported_olnn):
    model, path = exported_olnn
    session = ort_session(path)
    q, qd, tau = random_inputs(20, seed=15)
    with torch.no_grad():
        reference = model.step(q, qd, tau, "autograd")
    for i in range(20):
        feeds = {"q": q[i:i + 1].numpy(), "qd": qd[i:i + 1].numpy(), "tau": tau[i:i + 1].numpy()}
        q_ort, qd_ort = session.run(["q_next", "qd_next"], feeds)
        assert np.abs(q_ort - reference[0][i:i + 1].numpy()).max() <= 1e-5
        assert np.abs(qd_ort - reference[1][i:i + 1].numpy()).max() <= 1e-5

    # Closed loop, each side on its own predictions, under a torque sequence.
    q_torch, qd_torch = q[:1], qd[:1] * 0.2
    q_ort, qd_ort = q_torch.numpy(), qd_torch.numpy()
    taus = random_inputs(200, seed=16)[2] * 0.3
    worst = 0.0
    with torch.no_grad():
        for t in range(200):
            q_torch, qd_torch = model.step(q_torch, qd_torch, taus[t:t + 1], "analytic")
            q_ort, qd_ort = session.run(["q_next", "qd_next"], {"q": q_ort, "qd": qd_ort, "tau": taus[t:t + 1].numpy()})
            worst = max(worst, np.abs(q_ort - q_torch.numpy()).max(), np.abs(qd_ort - qd_torch.numpy()).max())
    assert np.isfinite(qd_ort).all() and np.abs(qd_ort - qd[:1].numpy() * 0.2).max() > 1e-3  # it moved
    assert worst <= 1e-5
