"""The evaluation: an oracle scores perfectly, and the quick run writes its whole report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from evaluation.cases import make_cases, object_scale
from evaluation.metrics import diameter, summarize
from evaluation.records import Answer, Truth, case_record
from evaluation.report import PLOTS
from service.engine.sampling import sample_surface
from tests.meshes import pybullet_mesh


def test_an_oracle_scores_perfectly():
    """Answers at the true pose with the true label: every metric at its best, the alignment
    error at its floor."""
    meshes = {"duck": pybullet_mesh("duck.obj"), "mug": pybullet_mesh("objects/mug.obj")}
    references = {name: sample_surface(mesh, 2048, 0) for name, mesh in meshes.items()}
    truths = {
        name: Truth(points.astype(np.float64), object_scale(points), diameter(points), "seen")
        for name, points in references.items()
    }
    scales = {name: truth.scale for name, truth in truths.items()}
    records = []
    for family in ("paper-poses", "so3", "partial"):
        for case in make_cases(family, meshes, scales, 512, seed=5, poses_per_object=2):
            answer = Answer(case.object_name, case.rotation, case.translation)
            record = case_record(case, truths, answer, 1.0)
            assert record["align_err"] == pytest.approx(record["align_err_floor"], abs=1e-9)
            records.append(record)
    summary = summarize(records)
    assert summary["accuracy"] == summary["success"] == summary["precise"] == 1.0
    assert summary["median_rot_err_deg"] < 1e-3
    assert summary["median_add_s"] < 1e-6
    other = "mug" if case.object_name == "duck" else "duck"
    wrong = case_record(case, truths, Answer(other, case.rotation, case.translation), 1.0)
    assert not wrong["label_ok"]
    assert summarize([wrong])["success"] == 0.0


def test_answer_cases_cover_every_family_with_millimetres_of_metric_parts_only():
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    from evaluation.evaluate import QUICK, answer_cases

    meshes = {
        "mug": pybullet_mesh("objects/mug.obj"),  # metres
        "diff-shaft": pybullet_mesh("differential/diff_leftshaft.stl"),  # millimetres
    }
    foreign = {"duck": pybullet_mesh("duck.obj")}
    truths = {}
    for name, mesh in (meshes | foreign).items():
        points = sample_surface(mesh, 2048, 0).astype(np.float64)
        truths[name] = Truth(points, object_scale(points), diameter(points), "unseen")
    symmetric = {"diff-shaft": meshes["diff-shaft"]}
    cases = answer_cases(QUICK, meshes, foreign, symmetric, truths, seed=0)
    families = {case.family for case in cases}
    assert families == {"sensor", "units", "table", "foreign", "junk", "symmetric"}
    assert {c.object_name for c in cases if c.family == "units"} == {"mug"}
    assert {c.object_name for c in cases if c.family == "foreign"} == {"duck"}
    junk_sizes = {c.params["size"] for c in cases if c.family == "junk"}
    assert junk_sizes <= {truths["mug"].scale, truths["diff-shaft"].scale}  # not the duck's


@pytest.mark.slow
def test_a_small_run_writes_the_whole_report(tmp_path: Path, capsys, monkeypatch):
    """Every study, system and family of ``--quick`` on fewer objects and cases: one seen and
    one unseen object in the full gallery, one paper pose, one keep share, one symmetric part
    (the baselines' cases, the noise levels and the targets are the quick run's)."""
    pytest.importorskip("cv2")
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    pytest.importorskip("pybullet_data")
    from evaluation import evaluate

    small = dataclasses.replace(
        evaluate.QUICK,
        seen=1,
        unseen=1,
        paper_poses=1,
        keep_shares=(0.5,),
        http_cases=2,
        symmetric_objects=1,
        baseline_sparse_poses=0,  # the baselines' slowest cases (PPF: 2 s each)
        baseline_random_cases=0,
        frames=dataclasses.replace(  # a scene and an empty table: the study end to end (the
            evaluate.QUICK.frames,  # real frame: tests/api/test_detect_real_frame.py)
            bin_seen=0,
            seen_objects=1,
            unseen_objects=2,
            shipped_real=False,
        ),
    )
    monkeypatch.setattr(evaluate, "QUICK", small)  # the command line, on the smaller plan
    result = evaluate.main(["--quick", "--out", str(tmp_path)])
    assert result["plan"] == dataclasses.asdict(small)
    assert "report written to" in capsys.readouterr().out
    readme = (tmp_path / "README.md").read_text()
    for heading in (
        "## Machine and run",
        "## Targets",
        "## Tables: side-by-side",
        "## Tables: sensor-side-by-side",
        "## Knowing when not to answer",
        "## Latency",
        "## Whole frames",
    ):
        assert heading in readme
    results = json.loads((tmp_path / "results.json").read_text())
    records = results["records"]
    systems = {r["system"] for r in records}
    assert {"engine", "engine-no-refine", "engine-paper", "ppf", "fpfh"} <= systems
    assert results["http"]["cases"] > 0
    assert len(results["targets"]) == 8
    full = [r for r in records if r["study"] == "full-gallery" and r["system"] == "engine"]
    assert {"sensor", "foreign", "junk", "units", "table", "symmetric"} <= {
        r["family"] for r in full
    }
    assert {"seen", "unseen"} <= {r["set"] for r in full if r["family"] == "sensor"}
    assert all(r["verdict"] in ("match", "uncertain", "no_match") for r in full)
    blind = [r for r in records if r["system"] == "engine-no-viewpoint"]
    assert blind and not any(r["viewpoint_given"] for r in blind)
    assert all(r["viewpoint_given"] for r in full if r["family"] == "sensor")
    side = [r for r in records if r["study"] == "sensor-side-by-side"]
    assert {(r["system"], r["family"]) for r in side} == {
        (system, "sensor") for system in ("engine", "engine-no-viewpoint", "ppf", "fpfh")
    }
    answers = results["answers"]
    assert answers["verdicts"] and answers["symmetric"] and answers["targets"]
    assert {row["issue"] for row in answers["targets"]} == {11, 12, 16}
    for name in PLOTS.values():
        assert (tmp_path / name).stat().st_size > 1000, name
    frames = json.loads((tmp_path / "frames.json").read_text())
    assert {r["family"] for r in frames["records"]} == {"scene", "empty"}
    assert {r["body"] for r in frames["records"]} == {"pcd", "depth-png"}
    assert frames["real"] == [] and "baseline" in frames
    from evaluation.report_frames import PLOTS as FRAME_PLOTS

    for name in FRAME_PLOTS.values():
        assert (tmp_path / name).stat().st_size > 1000, name
