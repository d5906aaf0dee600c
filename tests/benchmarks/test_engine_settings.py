"""``benchmarks/engine_settings.py``: variants of the search budget on the same cases."""

from __future__ import annotations

import argparse
import json

import pytest

pytest.importorskip("pybullet_data")

from benchmarks import engine_settings  # noqa: E402


def test_a_variant_names_engine_settings_with_json_values():
    name, changes = engine_settings.parse_variant("quick=screened:4,excellent:0.8")
    assert (name, changes) == ("quick", {"screened": 4, "excellent": 0.8})
    for bad in ("quick", "quick=nonsense:3", "quick=screened:[", "quick=screened:0"):
        with pytest.raises((argparse.ArgumentTypeError, ValueError)):
            engine_settings.parse_variant(bad)


@pytest.mark.slow
def test_every_variant_answers_the_same_cases(tmp_path):
    out = tmp_path / "settings.json"
    report = engine_settings.main(
        ["--objects", "25", "--families", "so3,junk", "--variant", "lean=screened:2",
         "--registered", "cloud", "--json", str(out)]
    )  # fmt: skip
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    assert list(report["variants"]) == ["default", "lean"]
    assert report["settings"]["lean"] == {"screened": 2}
    assert report["registered"] == "cloud"  # the unseen parts registered as their points
    for families in report["variants"].values():
        assert families["so3"]["cases"] == families["so3"]["cases"] > 0
        assert families["so3"]["success"] >= 0.5  # full clouds of registered parts
        assert families["junk"]["false_accepts"] == 0 and families["junk"]["success"] == 0
        assert {"map", "total"} <= set(families["so3"]["steps_ms"])
        # every 25th object: seen and unseen ones, each also apart
        seen, unseen = families["so3/seen"], families["so3/unseen"]
        assert seen["cases"] + unseen["cases"] == families["so3"]["cases"]


def test_the_unseen_parts_are_registered_as_meshes_or_as_clouds():
    assert engine_settings.parse_args([]).registered == "mesh"
    assert not engine_settings.parse_args([]).no_viewpoint
    assert engine_settings.parse_args(["--no-viewpoint"]).no_viewpoint
    assert engine_settings.parse_args(["--registered", "cloud"]).registered == "cloud"
    with pytest.raises(SystemExit):
        engine_settings.parse_args(["--registered", "scan"])
