"""Every command a user runs answers a wrong file, a wrong value and a missing argument with one line that names
the problem (after argparse's usage lines for a malformed command line), a non-zero exit code and no traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from bruce_hw.hw_check import main as hw_check
from runtime.cli import main as bruce_run
from runtime.emulate_cli import main as bruce_emulate
from training.collect import main as bruce_collect
from training.dynamics.export import main as bruce_export
from training.dynamics.train import main as bruce_train
from training.evaluation.cli import main as bruce_eval
from training.import_cli import main as bruce_import_data
from training.rl.train_cli import main as bruce_train_policy

EMPTY_FILE = Path(__file__).resolve().parents[1] / "configs" / "gaps" / "__init__.py"  # a file with nothing in it
CASES = [
    # (command, argv, what the last line must say)
    (bruce_run, ["--config", "nope.yaml"], "nope.yaml: robot config file not found"),
    # an output that cannot be written is refused before anything moves (it was a traceback after the run)
    (bruce_run, ["--duration", "0.01", "--rerun", "off", "--stats", "/proc/x.json"],
     "--stats /proc/x.json: cannot be written"),
    (bruce_run, ["--duration", "0.01", "--rerun", "off", "--gap", str(EMPTY_FILE)], f"{EMPTY_FILE}: empty"),
    (bruce_run, ["--gap", "nope", "--rerun", "off"], "unknown reality-gap profile 'nope'"),
    (bruce_run, ["--duration", "-1"], "argument --duration: expected a duration > 0 s, got -1"),
    (bruce_run, ["--duration", "inf"], "argument --duration: expected a duration > 0 s, got inf"),
    (bruce_run, ["--set", "rates.loop_hz=7"], "rates.loop_hz"),
    (bruce_run, ["--cmd"], "argument --cmd: expected one argument"),
    # within what the controllers support, outside what the committed policy was trained on (its sidecar)
    (bruce_run, ["--duration", "0.01", "--rerun", "off", "--cmd", "0.95,0.25,0"],
     "--cmd: vx = 0.95 m/s is outside [-0.5, 0.8] m/s, the range the policy"),
    (bruce_emulate, ["--config", "nope.yaml"], "nope.yaml: robot config file not found"),
    (bruce_emulate, ["--bear-delay", "-1"], "--bear-delay: -1 s is not a delay in [0, 0.1] s"),
    (hw_check, ["--config", "nope.yaml"], "nope.yaml: robot config file not found"),
    (hw_check, ["--rtt-cycles", "x"], "--rtt-cycles: 'x' is not a count in 0..100000"),
    (bruce_collect, ["--seconds", "1", "--out", "x.npz", "--config", "nope.yaml"],
     "nope.yaml: robot config file not found"),
    (bruce_collect, ["--seconds", "-1", "--out", "x.npz"], "argument --seconds: expected a duration > 0 s"),
    (bruce_collect, ["--seconds", "inf", "--out", "x.npz"], "argument --seconds: expected a duration > 0 s, got inf"),
    (bruce_collect, [], "the following arguments are required: --out"),
    (bruce_train, ["--data", "nope.npz", "--model", "pinn", "--out", "x.pt"], "nope.npz: dataset file not found"),
    (bruce_train, ["--data", "x.npz", "--model", "nope", "--out", "x.pt"], "argument --model: invalid choice: 'nope'"),
    (bruce_train, ["--data", "x.npz"], "the following arguments are required: --model, --out"),
    (bruce_export, ["--checkpoint", "nope.pt", "--out", "x.onnx"], "checkpoint nope.pt: file not found"),
    (bruce_export, ["--checkpoint", "x.pt"], "the following arguments are required: --out"),
    (bruce_eval, ["transfer", "--gap", "nope", "--out", "out"], "unknown reality-gap profile 'nope'"),
    (bruce_eval, ["transfer", "--out", "out", "--seeds", "a"], "--seeds: expected comma-separated numbers"),
    (bruce_eval, ["transfer"], "the following arguments are required: --out"),
    (bruce_eval, ["transfer", "--out", "out", "--set", "policy.model=nope.onnx"],
     "nope.onnx: policy file not found"),
    (bruce_eval, ["transfer", "--out", "out", "--set", "policy.spec=nope.yaml"], "nope.yaml"),
    (bruce_eval, ["dynamics", "--data", "nope.npz", "--model", "pinn=x.pt", "--out", "out"],
     "nope.npz: dataset file not found"),
    (bruce_train_policy, ["--out", "run", "--config", "nope.yaml"], "nope.yaml: training config file not found"),
    (bruce_train_policy, ["--out", "run", "--set", "train.action_scale=5"], "train.action_scale: expected"),
    (bruce_train_policy, ["--out", "run", "--set", "env.randomisation.latency_ticks=[0, 20]"],
     "env.randomisation.latency_ticks[1]: expected"),
    (bruce_train_policy, ["--out", "run", "--warm-start", "nope.onnx"],
     "nope.onnx: --warm-start policy file not found"),
    (bruce_train_policy, ["--out", "run", "--resume"], "--resume: no checkpoint to continue from"),
    (bruce_train_policy, [], "the following arguments are required: --out"),
    (bruce_import_data, ["nope.csv", "--out", "x.npz"], "nope.csv"),
    (bruce_import_data, ["nope.csv"], "the following arguments are required: --out"),
    (bruce_train, ["--data", "nope.csv", "--model", "pinn", "--out", "x.pt"], "nope.csv"),
]


@pytest.mark.parametrize("command, argv, says", CASES, ids=[f"{c.__module__}:{' '.join(a)}" for c, a, _ in CASES])
def test_a_bad_command_line_is_one_clear_line(command, argv, says, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    try:
        code = command(argv)
    except SystemExit as exc:  # argparse: usage lines, then one error line
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code not in (0, None), err
    assert err and says in err[-1], err
    assert not any("Traceback" in line for line in err)
    usage = [line for line in err[:-1] if not line.startswith(("usage:", " "))]
    assert not usage, f"more than one line besides argparse's usage: {err}"
