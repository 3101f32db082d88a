"""`bruce-eval transfer --schemes`: transfer schemes and their perfect-model controls side by side."""

import json

import pytest

from training.evaluate import main as eval_main
from training.transfer_eval import mode_label, recommended, scheme_of


def test_modes_name_a_scheme_and_optionally_the_perfect_model():
    assert scheme_of("direct") == ("direct", None)
    assert scheme_of("pinn") == ("pinn", None) and scheme_of("pinn_ahead") == ("pinn", None)
    assert scheme_of("shadow@nominal") == ("shadow", "nominal")
    assert mode_label("observer@nominal") == "observer, perfect model" and mode_label("pinn") == "PINN (Eq. 9)"


def _entry(rmse=None, deviation=None, falls=0):
    out = {"falls": falls, "seeds": 3, "fell": falls > 0}
    if rmse is not None:
        out["joint_rmse"] = rmse
    if deviation is not None:
        out["mean_radial_deviation"] = deviation
    return out


def _report(shadow_rmse, shadow_deviation, shadow_falls=0, control_rmse=0.01):
    tracking = {"nominal": _entry(0.0), "direct": _entry(0.10), "pinn": _entry(0.01),
                "shadow": _entry(shadow_rmse, falls=shadow_falls), "shadow@nominal": _entry(control_rmse),
                "shadow_over_direct": {"joint_rmse": shadow_rmse / 0.10}}  # ratios sit beside the modes
    circle = {"nominal": _entry(0.0, 0.1), "direct": _entry(0.1, 0.10), "pinn": _entry(0.01, 0.01),
              "shadow": _entry(0.05, shadow_deviation), "shadow@nominal": _entry(0.01, 0.01),
              "shadow_over_direct": {"mean_radial_deviation": shadow_deviation / 0.10}}
    return {"tracking": tracking, "circle": circle}


MODES = ("direct", "pinn", "shadow", "shadow@nominal")


@pytest.mark.parametrize("rmse, deviation, falls, expected", [
    (0.05, 0.06, 0, "shadow"),   # on both bars
    (0.051, 0.06, 0, None),      # tracking above half of direct's
    (0.05, 0.061, 0, None),      # circle above 0.6 x direct's
    (0.01, 0.01, 1, None),       # a fall direct does not have
])
def test_the_recommendation_is_a_scheme_that_clears_every_bar(rmse, deviation, falls, expected):
    # Eq. 9 (the paper's row) and perfect-model controls are never recommended, however good
    assert recommended(_report(rmse, deviation, falls), MODES) == expected


def test_every_scheme_and_its_perfect_model_control_run_side_by_side(tmp_path):
    out = tmp_path / "transfer"
    code = eval_main(["transfer", "--gap", "none", "--out", str(out), "--seconds", "2.6", "--seeds", "0",
                      "--experiments", "tracking,circle", "--latencies-ms", "", "--gain-scales", "",
                      "--schemes", "shadow,observer@nominal", "--jobs", "1"])
    assert code == 0
    report = json.loads((out / "transfer.json").read_text())
    assert report["meta"]["modes"] == ["direct", "shadow", "observer@nominal"] and "recommended" in report
    for mode in ("direct", "shadow", "observer@nominal"):
        for name in ("tracking", "circle"):
            assert report[name][mode]["seeds"] == 1 and report[name][mode]["falls"] == 0
    # the null test: on a robot that is the simulator, a scheme whose model is the simulator changes nothing
    assert report["tracking"]["direct"]["joint_rmse"] == 0.0
    assert report["tracking"]["observer@nominal"]["joint_rmse"] < 2e-3
    assert "| tracking | joint RMSE (rad) |" in (out / "transfer.md").read_text()


def test_an_unknown_scheme_is_named(tmp_path, capsys):
    assert eval_main(["transfer", "--out", str(tmp_path / "x"), "--schemes", "shadow,eq10"]) == 1
    assert "--schemes: 'eq10'" in capsys.readouterr().err
    assert eval_main(["transfer", "--out", str(tmp_path / "x"), "--schemes", "shadow@twin"]) == 1
    assert "--schemes: 'shadow@twin'" in capsys.readouterr().err
