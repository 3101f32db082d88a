"""`bruce-eval dynamics` (training/evaluation/dynamics_eval.py, dynamics_cli.py): NMSE definitions against
hand-computed values, start points and transitions that never cross a run, the oracle, checkpoints, and the CLI end
to end on a tiny synthetic file."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from training.dataset import Dataset, config_hash, save_dataset, split_by_time
from training.dynamics import checkpoint
from training.dynamics.pinn import PinnConfig, make_random_pinn
from training.episodes import episode_runs, run_indices
from training.evaluation import dynamics_eval as evaluate
from training.evaluation import report as eval_report
from training.evaluation.cli import main as eval_main
from training.evaluation.dynamics_eval import (
    EvalError,
    Protocol,
    bounded_check,
    evaluate_model,
    load_eval_data,
    nmse_per_joint,
    select_start_points,
)
from training.evaluation.report import json_safe

N = 10
DT = 1e-3
SMALL_PINN = PinnConfig(resnet_widths=(16, 55), lstm_hidden=8, lstm_layers=1)


# -- stand-in models with the shared interface -------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class EulerConfig:
    n_joints: int = N
    dt: float = DT
    gain: float = 0.5


class EulerModel(nn.Module):
    """Stateless: q' = q + qd dt, qd' = qd + gain tau dt."""

    def __init__(self, config: EulerConfig | None = None):
        super().__init__()
        self.config = config = config or EulerConfig()
        self.n_joints, self.dt, self.gain = config.n_joints, config.dt, config.gain

    def initial_state(self, batch: int = 1) -> tuple:
        return ()

    def forward(self, q, qd, tau):
        return q + qd * self.dt, qd + self.gain * tau * self.dt


class ExtrapolatingModel(nn.Module):
    """Recurrent: remembers the previous (q, qd) and extrapolates linearly, x' = 2 x - x_prev. Zero state -> x' = 2x,
    so only a correct warm-up gives the hand-computed values."""

    def __init__(self, n_joints: int = N, dt: float = DT):
        super().__init__()
        self.n_joints, self.dt = n_joints, dt

    def initial_state(self, batch: int = 1) -> tuple:
        return torch.zeros(batch, self.n_joints), torch.zeros(batch, self.n_joints)

    def forward(self, q, qd, tau, q_prev, qd_prev):
        return 2 * q - q_prev, 2 * qd - qd_prev, q, qd


class OracleModel(nn.Module):
    """Looks the (q, qd, tau) row up in the recording and returns the recorded next state."""

    def __init__(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray):
        super().__init__()
        self.n_joints, self.dt = q.shape[1], DT
        self.q, self.qd = torch.from_numpy(q.astype(np.float32)), torch.from_numpy(qd.astype(np.float32))
        rows = np.concatenate([q, qd, tau], axis=1).astype(np.float32)
        self.index = {row.tobytes(): t for t, row in enumerate(rows)}

    def initial_state(self, batch: int = 1) -> tuple:
        return ()

    def forward(self, q, qd, tau):
        rows = torch.cat([q, qd, tau], dim=1).numpy()
        t = torch.tensor([self.index[row.tobytes()] + 1 for row in rows])
        return self.q[t], self.qd[t]


# -- synthetic data --------------------------------------------------------------------------------------------
def synthetic_arrays(samples: int = 1500, episode_cut: int = 1300, seed: int = 0) -> dict[str, np.ndarray]:
    """Smooth joint motion with noise, float32 values (stored exactly), two episodes."""
    rng = np.random.default_rng(seed)
    t = np.arange(samples)[:, None] * DT
    freq, phase = rng.uniform(1.0, 3.0, N), rng.uniform(0, 2 * np.pi, N)
    q = 0.3 * np.sin(2 * np.pi * freq * t + phase) + 1e-4 * rng.standard_normal((samples, N))
    qd = 0.6 * np.pi * freq * np.cos(2 * np.pi * freq * t + phase) + 1e-2 * rng.standard_normal((samples, N))
    tau = rng.uniform(-2.0, 2.0, (samples, N))
    episode = (np.arange(samples) >= episode_cut).astype(np.int64)
    return {"q": q.astype(np.float32), "qd": qd.astype(np.float32), "tau": tau.astype(np.float32),
            "episode": episode, "dt": np.float64(DT)}


def write_dataset(path: Path, config, arrays: dict) -> Path:
    """The documented dataset format, with the metadata the loader checks against the robot config."""
    metadata = {"joint_names": list(config.joints), "config_hash": config_hash(config), "seed": 7}
    return save_dataset(path, Dataset(arrays["q"], arrays["qd"], arrays["tau"], arrays["episode"],
                                      float(arrays["dt"]), metadata))


@pytest.fixture
def data(tmp_path, config):
    return load_eval_data(write_dataset(tmp_path / "data.npz", config, synthetic_arrays()), config)


def make_protocol(data, ks=(5, 20, 50), warmup=10, count=12, chunk=64) -> Protocol:
    starts = select_start_points(data.runs, warmup, max(ks), count)
    return Protocol(tuple(ks), warmup, starts, run_indices(data.runs, before=warmup), chunk)


# -- NMSE, hand-computed ---------------------------------------------------------------------------------------
def test_nmse_per_joint_is_mse_over_variance_per_joint():
    pred = np.array([[1.0, 2.0], [3.0, 4.0]])
    true = np.array([[0.0, 2.0], [1.0, 1.0]])
    # joint 0: errors 1, 2 -> MSE 2.5, / 2 = 1.25; joint 1: errors 0, 3 -> MSE 4.5, / 3 = 1.5
    np.testing.assert_allclose(nmse_per_joint(pred, true, np.array([2.0, 3.0])), [1.25, 1.5])


def test_one_step_and_k_step_nmse_of_a_stateless_model_match_a_hand_computation(data):
    model = EulerModel()
    protocol = make_protocol(data)
    result, _ = evaluate_model(model, data, protocol)

    q, qd, tau = (getattr(data, k).astype(np.float64) for k in ("q", "qd", "tau"))
    test = np.arange(data.test_start, len(q))
    valid = np.array([t for t in test[:-1] if data.episode[t] == data.episode[t + 1]])
    scored = np.array([t for t in valid if data.episode[t - 10] == data.episode[t] and t - 10 >= data.test_start])
    dq_true, dqd_true = q[valid + 1] - q[valid], qd[valid + 1] - qd[valid]
    q_inc_var, qd_inc_var = dq_true.var(axis=0), dqd_true.var(axis=0)
    # predicted increments: qd dt and gain tau dt; true ones: recorded differences
    q_err = qd[scored] * DT - (q[scored + 1] - q[scored])
    qd_err = 0.5 * tau[scored] * DT - (qd[scored + 1] - qd[scored])
    expected_q = np.mean(np.mean(q_err ** 2, axis=0) / q_inc_var)
    expected_qd = np.mean(np.mean(qd_err ** 2, axis=0) / qd_inc_var)
    assert result["one_step"]["q"] == pytest.approx(expected_q, rel=1e-4)
    assert result["one_step"]["qd"] == pytest.approx(expected_qd, rel=1e-4)

    q_var, qd_var = q[test].var(axis=0), qd[test].var(axis=0)
    for k in protocol.ks:
        sq_q, sq_qd = np.zeros(N), np.zeros(N)
        for s in protocol.starts:
            q_hat, qd_hat = q[s].copy(), qd[s].copy()
            for step in range(k):
                q_hat, qd_hat = q_hat + qd_hat * DT, qd_hat + 0.5 * tau[s + step] * DT
                sq_q += (q_hat - q[s + step + 1]) ** 2
                sq_qd += (qd_hat - qd[s + step + 1]) ** 2
        count = k * len(protocol.starts)
        assert result["k_step"][str(k)]["q"] == pytest.approx(np.mean(sq_q / count / q_var), rel=1e-4)
        assert result["k_step"][str(k)]["qd"] == pytest.approx(np.mean(sq_qd / count / qd_var), rel=1e-4)
        np.testing.assert_allclose(result["k_step"][str(k)]["q_per_joint"], sq_q / count / q_var, rtol=1e-4)


def test_a_recurrent_model_is_warmed_up_on_the_recorded_steps_before_each_start(data):
    model = ExtrapolatingModel()
    protocol = make_protocol(data, ks=(3, 8), warmup=4, chunk=50)
    result, traces = evaluate_model(model, data, protocol)

    q = data.q.astype(np.float64)
    t = protocol.transitions
    inc_var = np.var(np.concatenate([np.diff(q[a:b], axis=0) for a, b in data.runs]), axis=0)
    q_err = (2 * q[t] - q[t - 1]) - q[t + 1]  # warm-up and chunking leave x_prev = the recorded previous sample
    assert result["one_step"]["q"] == pytest.approx(np.mean(np.mean(q_err ** 2, axis=0) / inc_var), rel=1e-4)

    sq = np.zeros(N)
    first_trace = None
    for s in protocol.starts:
        prev, cur, trace = q[s - 1], q[s], []
        for step in range(8):
            prev, cur = cur, 2 * cur - prev
            sq += (cur - q[s + step + 1]) ** 2
            trace.append(cur)
        first_trace = np.array(trace) if first_trace is None else first_trace
    expected = np.mean(sq / (8 * len(protocol.starts)) / q[data.test_start:].var(axis=0))
    assert result["k_step"]["8"]["q"] == pytest.approx(expected, rel=1e-4)
    np.testing.assert_allclose(traces["q"], first_trace, rtol=1e-5, atol=1e-6)  # Fig. 4 shows the first start


def test_the_oracle_that_returns_the_recorded_next_state_scores_zero(data):
    oracle = OracleModel(data.q, data.qd, data.tau)
    result, _ = evaluate_model(oracle, data, make_protocol(data))
    assert result["one_step"]["q"] == 0.0 and result["one_step"]["qd"] == 0.0
    for entry in result["k_step"].values():
        assert entry["q"] == 0.0 and entry["qd"] == 0.0
    assert result["bounded"]["within_bound"]
    worse, _ = evaluate_model(EulerModel(), data, make_protocol(data))
    assert worse["k_step"]["50"]["qd"] > 1e-3  # the metric can tell a model from the oracle


# -- start points and transitions --------------------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(lengths=st.lists(st.integers(1, 60), min_size=1, max_size=8), test_start=st.integers(0, 120),
       warmup=st.integers(0, 15), horizon=st.integers(1, 30), count=st.integers(1, 40),
       seed=st.none() | st.integers(0, 100))
def test_start_points_and_scored_transitions_never_cross_an_episode_or_the_split(lengths, test_start, warmup,
                                                                                  horizon, count, seed):
    episode = np.repeat(np.arange(len(lengths)), lengths)
    test_start = min(test_start, episode.size)
    runs = episode_runs(episode, test_start, episode.size)
    eligible = run_indices(runs, before=warmup, after=horizon)
    for s in eligible:
        window = np.arange(s - warmup, s + horizon + 1)
        assert window[0] >= test_start and window[-1] < episode.size
        assert np.all(episode[window] == episode[s])
    brute = [s for s in range(test_start + warmup, episode.size - horizon)
             if np.all(episode[s - warmup:s + horizon + 1] == episode[s])]
    assert eligible.tolist() == brute  # and none is missed
    for t in run_indices(runs, before=warmup):
        assert t - warmup >= test_start and episode[t - warmup] == episode[t] == episode[t + 1]
    if eligible.size == 0:
        with pytest.raises(EvalError, match="no start point"):
            select_start_points(runs, warmup, horizon, count, seed)
        return
    starts = select_start_points(runs, warmup, horizon, count, seed)
    assert len(starts) == min(count, eligible.size) and len(set(starts.tolist())) == len(starts)
    assert set(starts.tolist()) <= set(eligible.tolist()) and np.all(np.diff(starts) > 0)
    np.testing.assert_array_equal(starts, select_start_points(runs, warmup, horizon, count, seed))


def test_evenly_spaced_start_points_span_the_eligible_range():
    runs = ((100, 400),)
    starts = select_start_points(runs, warmup=10, horizon=50, count=5)
    np.testing.assert_array_equal(starts, [110, 170, 230, 289, 349])  # linspace over 110 .. 349, rounded


# -- checks on outputs -----------------------------------------------------------------------------------------
def test_bounded_check_flags_divergent_and_non_finite_rollouts(data):
    q_pred = np.broadcast_to(data.q[data.test_start], (5, 2, N)).copy()
    qd_pred = np.broadcast_to(data.qd[data.test_start], (5, 2, N)).copy()
    assert bounded_check(q_pred, qd_pred, data)["within_bound"]
    qd_pred[-1, 0, 3] = data.qd[data.test_start:, 3].max() + 20 * np.ptp(data.qd[data.test_start:, 3])
    check = bounded_check(q_pred, qd_pred, data)
    assert check["finite"] and not check["within_bound"] and check["max_range_ratio"] > 10
    qd_pred[-1, 0, 3] = np.nan
    assert not bounded_check(q_pred, qd_pred, data)["finite"]
    assert json_safe({"a": [float("inf"), np.float32(1.5)], "b": float("nan")}) == {"a": [None, 1.5], "b": None}


class DivergingModel(EulerModel):
    """qd grows x1000 per step: float32 overflows within the rollout."""

    def forward(self, q, qd, tau):
        return q + qd * self.dt, qd * 1e3


def test_a_diverging_model_is_reported_as_such_not_averaged_away(data):
    protocol = make_protocol(data)
    result, _ = evaluate_model(DivergingModel(), data, protocol)
    assert not result["bounded"]["finite"] and not result["bounded"]["within_bound"]
    assert not np.isfinite(result["k_step"]["50"]["qd"]) and np.isfinite(result["k_step"]["5"]["qd"])
    fine, _ = evaluate_model(EulerModel(), data, protocol)
    summary = evaluate.summarise([fine, result])
    assert summary["k50_qd"]["non_finite"] == 1 and not np.isfinite(summary["k50_qd"]["mean"])
    assert summary["k5_qd"]["non_finite"] == 0 and np.isfinite(summary["k5_qd"]["std"])
    assert eval_report._fmt(json_safe(summary["k50_qd"])) == "diverged (1/2)"


# -- data and checkpoints ----------------------------------------------------------------------------------------
def test_the_test_split_is_the_dataset_layers_and_runs_stop_at_episode_boundaries(tmp_path, config):
    arrays = synthetic_arrays(samples=503, episode_cut=450)
    path = write_dataset(tmp_path / "d.npz", config, arrays)
    loaded = load_eval_data(path, config, train_fraction=0.8)
    _, test = split_by_time(evaluate.load_dataset(path, config), 0.8)
    assert loaded.test_start == test.span[0] == round(0.8 * 503)
    assert loaded.runs == ((402, 450), (450, 503))
    assert loaded.metadata["seed"] == 7


def save_pinn_checkpoint(path: Path, seed: int, config: PinnConfig = SMALL_PINN) -> Path:
    model = make_random_pinn(config, seed=seed)
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 100)
        model.head.weight.normal_(std=1e-3)  # a live head, so the LSTM state matters
    return checkpoint.save_checkpoint(path, model)


# -- the CLI ---------------------------------------------------------------------------------------------------
def test_the_cli_writes_json_markdown_and_figures(tmp_path, monkeypatch, capsys, config):
    monkeypatch.setitem(checkpoint.MODEL_KINDS, "euler",
                        checkpoint.ModelKind(f"{__name__}:EulerModel", f"{__name__}:EulerConfig"))
    data_path = write_dataset(tmp_path / "walk.npz", config, synthetic_arrays())
    seeds = [save_pinn_checkpoint(tmp_path / f"pinn_{s}.pt", seed=s) for s in (0, 1)]
    checkpoint.save_checkpoint(tmp_path / "euler.pt", EulerModel(), data={"sha256": evaluate.file_sha256(data_path)})
    out = tmp_path / "eval"
    code = eval_main(["dynamics", "--data", str(data_path), "--model", f"pinn={seeds[0]},{seeds[1]}",
                          "--model", f"euler={tmp_path / 'euler.pt'}", "--out", str(out), "--k", "5,20,50",
                          "--starts", "12", "--warmup", "10", "--chunk", "64", "--timing-calls", "40"])
    assert code == 0, capsys.readouterr().err
    report = json.loads((out / "dynamics_eval.json").read_text())

    assert report["data"]["sha256"] == evaluate.file_sha256(data_path)
    assert report["data"]["metadata"]["config_hash"] == config_hash(config)
    assert report["data"]["test_split"] == {"train_fraction": 0.8, "start": 1200, "stop": 1500,
                                            "runs": [[1200, 1300], [1300, 1500]]}
    assert report["protocol"]["k"] == [5, 20, 50] and report["protocol"]["warmup"] == 10
    assert report["protocol"]["starts"] == 12 == len(report["protocol"]["start_points"])
    pinn, euler = report["models"]["pinn"], report["models"]["euler"]
    assert len(pinn["per_checkpoint"]) == 2 and pinn["summary"]["k20_q"]["n"] == 2
    per_seed = [r["k_step"]["20"]["q"] for r in pinn["per_checkpoint"]]
    assert pinn["summary"]["k20_q"]["mean"] == pytest.approx(np.mean(per_seed))
    assert pinn["summary"]["k20_q"]["std"] == pytest.approx(np.std(per_seed, ddof=1))
    assert per_seed[0] != per_seed[1]
    assert euler["summary"]["k50_qd"]["std"] is None
    assert euler["per_checkpoint"][0]["trained_on_this_file"] is True
    assert pinn["per_checkpoint"][0]["trained_on_this_file"] is None  # no provenance in that checkpoint

    # the CLI's numbers are the library's on the same protocol
    data = load_eval_data(data_path, config)
    protocol = Protocol((5, 20, 50), 10, np.array(report["protocol"]["start_points"]),
                        run_indices(data.runs, before=10), 64)
    direct, _ = evaluate_model(EulerModel(), data, protocol)
    assert euler["per_checkpoint"][0]["k_step"]["50"]["qd"] == pytest.approx(direct["k_step"]["50"]["qd"])
    assert euler["per_checkpoint"][0]["one_step"]["q"] == pytest.approx(direct["one_step"]["q"])

    compute = report["compute"]
    assert compute["pinn"]["torch"]["p50_us"] > 0 and compute["pinn"]["torch"]["mode"] == "inference_mode"
    assert compute["pinn"]["ort"]["call"] == "runtime.control.inference.OnnxPinn.step"
    assert compute["pinn"]["ort"]["parity_max_abs"] <= 1e-5
    assert "ort" not in compute["euler"]  # no exporter for this kind
    assert list(report["models"]) == ["pinn", "euler"]

    table = (out / "dynamics_eval.md").read_text()
    assert "| pinn | 2 |" in table and "| euler | 1 |" in table and "K=50 q̇" in table
    for name in ("fig4_joint0_rollout.png", "fig5_nmse_runtime.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_cli_rejects_a_model_or_a_file_that_does_not_fit(tmp_path, capsys, config):
    data_path = write_dataset(tmp_path / "walk.npz", config, synthetic_arrays())
    ckpt = save_pinn_checkpoint(tmp_path / "pinn.pt", seed=0, config=dataclasses.replace(SMALL_PINN, dt=2e-3))
    args = ["--k", "5", "--warmup", "2", "--timing-calls", "0", "--out", str(tmp_path / "out")]
    assert eval_main(["dynamics", "--data", str(data_path), "--model", f"pinn={ckpt}", *args]) == 1
    assert f"pinn.pt: model dt=0.002 s, data file {data_path} has dt=0.001 s" in capsys.readouterr().err

    other = synthetic_arrays()
    np.savez(tmp_path / "bare.npz", **other)  # no metadata: not tied to a robot config
    ckpt = save_pinn_checkpoint(tmp_path / "pinn_ok.pt", seed=0)
    assert eval_main(["dynamics", "--data", str(tmp_path / "bare.npz"), "--model", f"pinn={ckpt}", *args]) == 1
    assert "bare.npz: missing array 'metadata'" in capsys.readouterr().err

    torch.save({"kind": "pinn", "config": {}}, tmp_path / "broken.pt")
    assert eval_main(["dynamics", "--data", str(data_path), "--model", f"pinn={tmp_path / 'broken.pt'}",
                          *args]) == 1
    assert "broken.pt: missing key(s) ['state_dict']" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
