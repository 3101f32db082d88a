"""Training the dynamics models: Eq. 7 as stated, the loss falls, TBPTT burn-in, resume = uninterrupted."""

import dataclasses

import numpy as np
import pytest
import torch

from bruce_hw.config import load_config
from training.collect import CollectSettings, collect
from training.dataset import DatasetStats, save_dataset
from training.dynamics import train as train_dynamics
from training.dynamics.checkpoint import CheckpointError, load_model_checkpoint, read_checkpoint
from training.dynamics.pinn import joint_stop_range
from training.dynamics.train import MODEL_PRESETS, TRAIN_PRESETS, Eq7Loss, TrainConfig, main, train

N = 10


@pytest.fixture(scope="module")
def walk_data(tmp_path_factory):
    """8 s of the committed policy walking the mock (the real collection path, short)."""
    config = load_config()
    data = collect(config, CollectSettings(seconds=8.0, seed=1, segment_s=2.0))
    return save_dataset(tmp_path_factory.mktemp("data") / "walk.npz", data), config


def small(**changes) -> TrainConfig:
    return TrainConfig(**{**TRAIN_PRESETS["small"], **changes})


def test_eq7_terms_are_normalised_by_the_increment_spreads():
    rng = np.random.default_rng(0)
    ones = np.ones(N)
    stats = DatasetStats(q_mean=0 * ones, q_std=ones, qd_mean=0 * ones, qd_std=ones, tau_mean=0 * ones,
                         tau_std=ones, q_inc_std=rng.uniform(1e-5, 1e-4, N), qd_inc_std=rng.uniform(0.01, 0.1, N))
    q_err, qd_err = rng.normal(size=(3, N)), rng.normal(size=(3, N))
    loss = Eq7Loss(stats, lambda_q=2.0, lambda_qd=0.5).per_sample(
        torch.tensor(q_err, dtype=torch.float32), torch.tensor(qd_err, dtype=torch.float32),
        torch.zeros(3, N), torch.zeros(3, N))
    expected = (2.0 * (q_err / stats.q_inc_std) ** 2 + 0.5 * (qd_err / stats.qd_inc_std) ** 2).mean(axis=1)
    np.testing.assert_allclose(loss.numpy(), expected, rtol=1e-5)


@pytest.mark.parametrize("kind", ["pinn", "lstm"])
def test_a_short_training_run_lowers_the_loss_and_writes_a_loadable_checkpoint(walk_data, tmp_path, kind):
    path, config = walk_data
    out = tmp_path / f"{kind}.pt"
    result = train(path, kind, out, model_config=MODEL_PRESETS["small"][kind], train_config=small(epochs=6),
                   robot_config=config, progress=False)
    losses = [h["loss"] for h in result["train"]["history"]]
    assert len(losses) == 6 and all(np.isfinite(losses))
    assert losses[-1] < 0.75 * losses[0], losses
    model, payload = load_model_checkpoint(out)
    assert payload["kind"] == kind and "resume" not in payload  # a finished run keeps no optimizer state
    assert payload["data"]["config_hash"] and payload["data"]["train_samples"] == 6400
    np.testing.assert_allclose(model.q_mean.numpy() if kind == "pinn" else model.input_mean[:N].numpy(),
                               payload["stats"]["q_mean"], rtol=1e-6)
    if kind == "pinn":  # the PINN carries the joint-range stop, and the simulator's data never reaches it
        q = np.load(path)["q"]
        lower, upper = joint_stop_range(config, q[:6400])  # the training part
        np.testing.assert_allclose(model.q_stop_lower.numpy(), lower, rtol=1e-6)
        np.testing.assert_allclose(model.q_stop_upper.numpy(), upper, rtol=1e-6)
        assert (q[:6400] > lower).all() and (q[:6400] < upper).all()
        assert (lower <= config.q_lower - 0.1).all() and (upper >= config.q_upper + 0.1).all()


def test_resume_after_an_interruption_gives_the_uninterrupted_result(walk_data, tmp_path, monkeypatch):
    path, config = walk_data
    settings = dict(model_config=MODEL_PRESETS["small"]["pinn"], train_config=small(epochs=4, checkpoint_every=2),
                    robot_config=config, progress=False)
    whole = train(path, "pinn", tmp_path / "whole.pt", **settings)

    real_epoch, calls = train_dynamics.run_epoch, []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_epoch(*args, **kwargs)

    monkeypatch.setattr(train_dynamics, "run_epoch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(path, "pinn", tmp_path / "cut.pt", **settings)
    assert read_checkpoint(tmp_path / "cut.pt")["train"]["epoch"] == 2
    monkeypatch.setattr(train_dynamics, "run_epoch", real_epoch)
    resumed = train(path, "pinn", tmp_path / "cut.pt", resume=True, **settings)
    assert [h["loss"] for h in resumed["train"]["history"]] == [h["loss"] for h in whole["train"]["history"]]
    a, _ = load_model_checkpoint(tmp_path / "whole.pt")
    b, _ = load_model_checkpoint(tmp_path / "cut.pt")
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y), name
    again = train(path, "pinn", tmp_path / "cut.pt", resume=True, **settings)  # finished: returned as it is
    assert again["train"]["history"] == resumed["train"]["history"]
    with pytest.raises(ValueError, match="other settings"):
        train(path, "pinn", tmp_path / "whole.pt", resume=True,
              **{**settings, "train_config": small(epochs=5, checkpoint_every=2)})


def test_burn_in_steps_after_a_fresh_state_are_not_counted(walk_data, monkeypatch):
    """With burn-in = window - 1 only the last step of each window after a fresh start counts: the loss equals
    the loss computed over exactly those transitions."""
    path, config = walk_data
    from training.dataset import compute_stats, load_dataset, split_by_time, windows

    train_part, _ = split_by_time(load_dataset(path, config))
    stats = compute_stats(train_part)
    model = train_dynamics.build_model("lstm", MODEL_PRESETS["small"]["lstm"])
    model.fit_normalisation(stats)
    cfg = small(window=10, burn_in=9, streams=4)
    loss_fn = Eq7Loss(stats, 1.0, 1.0)
    got = train_dynamics.run_epoch(model, train_part, loss_fn, cfg, np.random.default_rng(5), None)

    cut = windows(train_part, 10, offset=int(np.random.default_rng(5).integers(10)))
    index, fresh = cut.streams(4)
    state, counted = model.initial_state(4), []
    with torch.no_grad():
        for step in range(index.shape[0]):
            batch = {k: torch.from_numpy(v).transpose(0, 1) for k, v in cut.gather(train_part, index[step],
                                                                                     np.float32).items()}
            state = tuple(torch.where(torch.from_numpy(fresh[step])[None, :, None], 0.0, s) for s in state)
            q_hat, qd_hat, *state = model(batch["q"][:-1], batch["qd"][:-1], batch["tau"][:-1], *state)
            per = loss_fn.per_sample(q_hat, qd_hat, batch["q"][1:], batch["qd"][1:])
            for b in range(4):
                counted.extend(per[9:, b].tolist() if fresh[step, b] else per[:, b].tolist())
    assert got == pytest.approx(np.mean(counted), rel=1e-5)
    assert fresh[0].all()


def test_settings_and_checkpoints_are_checked(tmp_path):
    with pytest.raises(ValueError, match="burn_in"):
        TrainConfig(window=10, burn_in=10)
    with pytest.raises(CheckpointError, match="file not found"):
        load_model_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a torch checkpoint that loads with weights_only=True"):
        load_model_checkpoint(tmp_path / "junk.pt")
    assert dataclasses.asdict(TrainConfig())["lr"] == 1e-2  # the paper's optimiser is the default


def test_cli_trains_and_reports(walk_data, tmp_path, capsys):
    path, _ = walk_data
    out = tmp_path / "cli.pt"
    assert main(["--data", str(path), "--model", "lstm", "--preset", "small", "--epochs", "2", "--out", str(out),
                 "--no-progress"]) == 0
    assert "2 epochs" in capsys.readouterr().out and out.is_file()


def test_the_analytic_baseline_is_identified_not_trained(walk_data, tmp_path):
    path, config = walk_data
    result = train(path, "analytic", tmp_path / "analytic.pt", robot_config=config, progress=False)
    assert result["train"]["history"] == [] and result["identification"]["n_params"] == 130
    model, payload = load_model_checkpoint(tmp_path / "analytic.pt")
    assert payload["kind"] == "analytic" and payload["data"]["train_samples"] == 6400
    q = torch.zeros(1, N)
    q_next, qd_next = model(q, q, torch.zeros(1, N))
    assert torch.isfinite(qd_next).all() and not torch.equal(qd_next, q)  # gravity moves a resting leg


def test_export_cli_writes_onnx_with_parity_and_the_commands_that_regenerate_it(walk_data, tmp_path):
    import json

    from training.dynamics.export import main as export_main

    path, _ = walk_data
    checkpoint = tmp_path / "p.pt"
    main(["--data", str(path), "--model", "pinn", "--preset", "small", "--epochs", "2", "--out", str(checkpoint),
          "--no-progress"])
    onnx_path = tmp_path / "p.onnx"
    assert export_main(["--checkpoint", str(checkpoint), "--out", str(onnx_path)]) == 0
    sidecar = json.loads(onnx_path.with_name("p.onnx.json").read_text())
    assert sidecar["parity_1000_steps"] <= 1e-5 and sidecar["seed"] == 0 and sidecar["epochs"] == 2
    assert "bruce-train --data" in sidecar["command"] and "bruce-export --checkpoint" in sidecar["command"]
    assert sidecar["data"]["sha256"] and sidecar["kind"] == "pinn_step"


@pytest.mark.parametrize("argv, says", [
    (["bruce-train", "--data", "nope.npz", "--model", "pinn", "--out", "x.pt"], "nope.npz: dataset file not found"),
    (["bruce-export", "--checkpoint", "nope.pt", "--out", "x.onnx"], "checkpoint nope.pt: file not found"),
    (["bruce-export", "--checkpoint", "NOT_A_CHECKPOINT", "--out", "x.onnx"], "not a torch checkpoint"),
])
def test_training_clis_answer_a_bad_file_in_one_line(argv, says, tmp_path, monkeypatch, capsys):
    from training.dynamics.export import main as export_main
    from training.dynamics.train import main as train_main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "NOT_A_CHECKPOINT").write_text("robot\n")
    code = (train_main if argv[0] == "bruce-train" else export_main)(argv[1:])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and says in err[0] and "Traceback" not in err[0]
