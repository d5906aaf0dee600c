"""The single-view study of the mapping (issue 11) runs end to end on one object of each set."""

from __future__ import annotations

import json

import pytest

from evaluation.views_mapping import main, table


@pytest.mark.slow
def test_the_study_measures_every_model_on_the_same_cases(tmp_path):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    pytest.importorskip("pybullet_data")
    out = tmp_path / "study.json"
    argv = ["--objects", "1", "--cases", "1", "--json", str(out)]
    report = main([*argv, "--model", "a=models/dpc_mn.onnx", "--model", "b=models/dpc_mn.onnx"])
    assert set(report["models"]) == {"a", "b"}
    groups = report["models"]["a"]
    assert set(groups) == {"sensor/seen", "sensor/unseen", "so3/seen", "so3/unseen"}
    assert report["models"]["a"] == report["models"]["b"]  # one model, the same draws: alike
    for summary in groups.values():
        assert summary["cases"] == 1 and 0.0 <= summary["quality"] <= 1.0
    written = json.loads(out.read_text())
    assert len(written["records"]["a"]) == 4
    assert table(report).count("\n") == 2 + 2 * 4 - 1
    assert "engine_success_with_mapped" not in groups["so3/seen"]  # only with --engine
