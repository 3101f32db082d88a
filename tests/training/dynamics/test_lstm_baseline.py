"""The pure-LSTM baseline: increments, normalisation, window = ticks, export parity through the runtime's runner."""

import numpy as np
import pytest
import torch

from runtime.control.inference import OnnxPinn
from training.dataset import DatasetStats
from training.dynamics.export import export_pinn_onnx
from training.dynamics.lstm_baseline import LstmConfig, LstmStep

N = 10


def random_stats(seed: int) -> DatasetStats:
    rng = np.random.default_rng(seed)
    return DatasetStats(q_mean=rng.normal(0, 0.3, N), q_std=rng.uniform(0.2, 0.8, N), qd_mean=rng.normal(0, 0.5, N),
                        qd_std=rng.uniform(1, 3, N), tau_mean=rng.normal(0, 0.5, N), tau_std=rng.uniform(1, 4, N),
                        q_inc_std=rng.uniform(1e-5, 1e-4, N), qd_inc_std=rng.uniform(0.01, 0.1, N))


def trained_looking(seed: int) -> LstmStep:
    model = LstmStep()
    model.fit_normalisation(random_stats(seed))
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.head.weight.copy_(0.3 * torch.randn(model.head.weight.shape, generator=generator))
    return model


def test_untrained_model_predicts_no_change_and_size_matches_the_pinn_lstm():
    model = LstmStep()
    q, qd, tau = torch.randn(4, N), torch.randn(4, N), torch.randn(4, N)
    q_next, qd_next, h, c = model(q, qd, tau, *model.initial_state(4))
    assert torch.equal(q_next, q) and torch.equal(qd_next, qd) and h.shape == c.shape == (3, 4, 72)
    assert sum(p.numel() for p in model.parameters()) == 115_508
    with pytest.raises(ValueError, match="lstm_hidden"):
        LstmConfig(lstm_hidden=0)


def test_increments_are_scaled_by_the_training_spread():
    stats = random_stats(1)
    model = LstmStep()
    model.fit_normalisation(stats)
    with torch.no_grad():
        model.head.bias.fill_(1.0)  # a unit normalised increment on every output
    q, qd, tau = torch.zeros(1, N), torch.zeros(1, N), torch.zeros(1, N)
    q_next, qd_next, _, _ = model(q, qd, tau, *model.initial_state(1))
    torch.testing.assert_close(q_next[0].double(), torch.tensor(stats.qd_std * model.dt))
    torch.testing.assert_close(qd_next[0].double(), torch.tensor(stats.qd_inc_std))


def test_window_equals_ticks_and_folded_equals_model():
    model = trained_looking(2).double()
    generator = torch.Generator().manual_seed(2)
    q, qd, tau = (torch.randn(6, 2, N, generator=generator, dtype=torch.float64) for _ in range(3))
    with torch.no_grad():
        q_w, qd_w, *state_w = model(q, qd, tau, *model.initial_state(2))
        state = model.initial_state(2)
        folded = model.folded()
        folded_state = folded.initial_state(2)
        for t in range(6):
            q_t, qd_t, *state = model(q[t], qd[t], tau[t], *state)
            q_f, qd_f, *folded_state = folded(q[t], qd[t], tau[t], *folded_state)
            torch.testing.assert_close((q_w[t], qd_w[t]), (q_t, qd_t), rtol=1e-12, atol=1e-12)
            torch.testing.assert_close((q_f - q[t], qd_f - qd[t]), (q_t - q[t], qd_t - qd[t]), rtol=1e-9, atol=1e-14)
    torch.testing.assert_close(tuple(state_w), tuple(state), rtol=1e-12, atol=1e-12)
    assert (qd_w - qd).abs().amax() > 1e-3


def test_export_runs_in_the_runtime_pinn_runner_with_parity(tmp_path):
    model = trained_looking(3)
    path = export_pinn_onnx(model, tmp_path / "lstm.onnx")
    runner = OnnxPinn(path, N)
    rng = np.random.default_rng(3)
    state = model.initial_state(1)
    worst = 0.0
    with torch.no_grad():
        for _ in range(200):
            q, qd, tau = rng.normal(0, 0.3, N), rng.normal(0, 1, N), rng.normal(0, 1, N)
            q_ort, qd_ort = runner.step(q, qd, tau)
            as_t = [torch.as_tensor(v, dtype=torch.float32)[None] for v in (q, qd, tau)]
            q_t, qd_t, *state = model(*as_t, *state)
            worst = max(worst, np.abs(q_ort - q_t[0].numpy()).max(), np.abs(qd_ort - qd_t[0].numpy()).max())
    assert worst <= 1e-5
