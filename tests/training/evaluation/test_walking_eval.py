"""bruce-eval walking: the grid's verdicts come from the runs (a standing controller walks nowhere and fails the
walking points), and a bad policy path is one line."""

from __future__ import annotations

import json

from training.evaluation.cli import main as bruce_eval
from training.evaluation.walking_eval import GRID, walk_point


def test_a_point_passes_only_when_it_tracks(config):
    standing = walk_point(str(config.path), [], "standing", (0.4, 0.0, 0.0), 3.0)
    assert not standing["fell"] and not standing["passes"]
    assert standing["tracking_error"]["vx"] > 0.3  # stood still under a 0.4 m/s command
    still = walk_point(str(config.path), [], "standing", (0.0, 0.0, 0.0), 3.0)
    assert still["passes"]


def test_the_grid_is_the_walking_acceptance():
    assert len(GRID) == 17 and len(set(GRID)) == 17
    assert {c[0] for c in GRID} == {-0.5, -0.3, 0.0, 0.4, 0.8} and {c[1] for c in GRID} == {-0.2, 0.0, 0.2}


def test_a_missing_policy_is_one_line(tmp_path, capsys):
    assert bruce_eval(["walking", "--out", str(tmp_path), "--policy", "nope.onnx"]) == 2
    assert capsys.readouterr().err.strip() == "bruce-eval: nope.onnx: policy file not found"
    assert not (tmp_path / "walking.json").exists()


def test_policy_table_counts_falls_and_averages_the_worst_axis(tmp_path, capsys):
    def report(fell, errors):
        runs = [{"fell": f, "velocity_error": e} for f, e in zip(fell, errors, strict=True)]
        return {"profiles": {"harsh": {"reverse": {"direct": {"per_seed": runs}}}}}

    for name, fell, errors in (("a", [False, True, False], [[0.1, 0.0, 0.3], [0.2, 0.2, 0.2], [0.0, 0.1, 0.0]]),
                               ("b", [False, False, False], [[0.05, 0.0, 0.0]] * 3)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "transfer.json").write_text(json.dumps(report(fell, errors)))
    assert bruce_eval(["policies", "--run", f"a={tmp_path / 'a'}", "--run", f"b={tmp_path / 'b'}"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| harsh")]
    assert rows == ["| harsh | reverse | 1/3 | 0.200 | 0/3 | 0.050 |"]
    assert bruce_eval(["policies", "--run", f"c={tmp_path / 'c'}"]) == 2
