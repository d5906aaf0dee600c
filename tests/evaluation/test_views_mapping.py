"""The single-view study of the mapping (issue 11) runs end to end on one object of each set."""

from __future__ import annotations

import json

import pytest

from evaluation.views_mapping import main, table


@pytest.mark.slow
def test_the_study_measures_every_model_on_the_same_cases(tmp_path):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    pytest.importorskip("pybullet_data")
    out, records = tmp_path / "study.json", tmp_path / "records.json"
    argv = ["--objects", "1", "--cases", "1", "--json", str(out), "--records", str(records)]
    report = main([*argv, "--model", "a=models/dpc_mn.onnx", "--model", "b=models/dpc_mn.onnx"])
    assert set(report["models"]) == {"a", "b"}
    groups = report["models"]["a"]
    families = ("sensor", "so3", "view-pairs")
    splits = ("seen", "unseen")
    assert set(groups) == {f"{family}/{split}" for family in families for split in splits}
    assert report["models"]["a"] == report["models"]["b"]  # one model, the same draws: alike
    for summary in groups.values():
        assert summary["cases"] == 1 and 0.0 <= summary["quality"] <= 1.0
    assert json.loads(out.read_text())["models"] == json.loads(json.dumps(report["models"]))
    assert len(json.loads(records.read_text())["a"]) == 6
    assert table(report).count("\n") == 2 + 2 * 6 - 1
    assert "engine_success_with_mapped" not in groups["so3/seen"]  # only with --engine
