"""The whole-frame study's scoring (evaluation.detect, evaluation.report_frames) on a real frame
of evaluation.frames, and the FPFH baseline's several instances, without a server."""

from __future__ import annotations

import numpy as np
import pytest

from service.engine.sampling import sample_surface

pytest.importorskip("pybullet")
pytest.importorskip("open3d")
frames = pytest.importorskip("evaluation.frames")
detect = pytest.importorskip("evaluation.detect")
report_frames = pytest.importorskip("evaluation.report_frames")


@pytest.fixture(scope="module")
def truths(parts):
    """Every part's, and a registered part that no frame holds (a box)."""
    import trimesh

    box = frames.FramePart("box", trimesh.creation.box((0.1, 0.06, 0.04)), 1.0, True)
    return {p.name: detect.PartTruth.of(p) for p in [*parts[0], *parts[1], box]}


def _detection(label, rotation, translation, verdict="match", confidence=0.9, indices=()):
    return {
        "label": label,
        "verdict": verdict,
        "confidence": confidence,
        "rotation": np.asarray(rotation).tolist(),
        "translation": np.asarray(translation).tolist(),
        "indices": list(indices),
        "num_points": len(indices),
    }


def test_detections_are_scored_against_the_ground_truth(scene, truths):
    registered = [k for k, i in enumerate(scene.instances) if i.registered]
    first, second = (scene.instances[k] for k in registered[:2])
    absent = "box"
    shift = np.array([truths[second.name].diameter, 0.0, 0.0])
    support = np.flatnonzero(scene.labels.ravel() == frames.SUPPORT)[:50]
    detections = [
        _detection(first.name, first.rotation, first.translation, confidence=0.95),
        _detection(first.name, first.rotation, first.translation, confidence=0.9),  # again
        _detection(second.name, second.rotation, second.translation + shift, confidence=0.8),
        _detection(
            absent,
            np.eye(3),
            second.translation,
            confidence=0.7,
            indices=scene.instance_pixels(registered[1]),
        ),  # fmt: skip
        _detection(absent, np.eye(3), [0, 0, 1], confidence=0.6, indices=support),
        _detection(second.name, second.rotation, second.translation, "uncertain", 0.5),
    ]
    records, instances = detect.match_detections(scene, detections, truths)
    outcomes = [r["outcome"] for r in records]
    assert outcomes == ["right", "duplicate", "wrong pose", "wrong label", "nothing", None]
    assert records[0]["add_s"] == pytest.approx(0.0, abs=0.01)
    assert instances[registered[0]]["found"] and instances[registered[0]]["found_as"] == "match"
    assert not instances[registered[1]]["found"]
    assert instances[registered[1]]["found_as"] == "uncertain"  # posed right, not acted on

    record = {
        "family": "scene", "set": "unseen", "size": "640x480", "body": "pcd", "stem": "s",
        "latency_ms": 100.0, "detections": records, "instances": instances,
    }  # fmt: skip
    figures = report_frames.summarize_frames([record])
    assert figures["matches"] == 5 and figures["right_matches"] == 1
    assert figures["precision"] == pytest.approx(0.2)
    assert figures["wrong_matches"] == {
        "duplicate": 1, "wrong pose": 1, "wrong label": 1, "not registered": 0, "nothing": 1,
    }  # fmt: skip
    found = sum(i["found"] for i in instances if i["registered"])
    bands = figures["bands"].values()
    assert sum(b["found"] for b in bands) == found == 1
    assert sum(b["instances"] for b in bands) == len(registered)


def test_a_match_in_a_frame_without_registered_parts_is_counted(parts):
    foreign = frames.make_frame("foreign", 0, 0, *parts)
    truths = {p.name: detect.PartTruth.of(p) for p in parts[1]}
    instance = foreign.instances[0]
    pixels = foreign.instance_pixels(0)
    records, instances = detect.match_detections(
        foreign,
        [_detection("mug", instance.rotation, instance.translation, indices=pixels)],
        truths | {"mug": detect.PartTruth.of(parts[0][0])},
    )
    assert records[0]["outcome"] == "not registered"
    record = {
        "family": "foreign", "set": "none", "size": "640x480", "body": "pcd", "stem": "f",
        "latency_ms": 50.0, "detections": records, "instances": instances,
    }  # fmt: skip
    empty = {**record, "family": "empty", "stem": "e", "detections": [], "instances": []}
    figures = report_frames.summarize_frames([record, empty])
    assert figures["frames_without_registered"] == 2
    assert figures["frames_without_registered_with_match"] == 1
    result = {"records": [record, empty], "references": 54, "plan": {}, "seed": 0}
    targets = {t["target"]: t for t in report_frames.frames_report(result)["targets"]}
    no_match = next(t for name, t in targets.items() if name.startswith("frames with no"))
    assert not no_match["met"] and no_match["figure"].startswith("50.0 %")


def test_the_frame_bodies_are_what_a_driver_writes(scene):
    files, data = detect.frame_body(scene, as_depth=False)
    assert files["file"][0].endswith(".pcd") and data == {}
    assert frames.read_pcd(files["file"][1]).shape == (480, 640, 3)
    files, data = detect.frame_body(scene, as_depth=True)
    assert files["file"][0].endswith(".png")
    assert data == {"fx": "525.0", "fy": "525.0", "cx": "319.5", "cy": "239.5"}


def test_fpfh_finds_two_instances_of_a_part_beside_a_plane(parts):
    from scipy.spatial.transform import Rotation

    from evaluation.baselines.fpfh import locate_instances

    duck = next(p for p in parts[0] if p.name == "duck")
    truth = detect.PartTruth.of(duck)
    rng = np.random.default_rng(0)
    poses = [
        (Rotation.random(random_state=1).as_matrix(), np.array([-0.2, 0.0, 1.0])),
        (Rotation.random(random_state=2).as_matrix(), np.array([0.2, 0.05, 1.0])),
    ]
    model = sample_surface(duck.mesh, 6000, 3).astype(np.float64)
    clouds = [model @ r.T + t for r, t in poses]
    plane = np.column_stack(
        [rng.uniform(-0.6, 0.6, 30000), rng.uniform(-0.4, 0.4, 30000), np.full(30000, 1.2)]
    )
    found = locate_instances(np.vstack([*clouds, plane]), sample_surface(duck.mesh, 2048, 0), 2)
    assert len(found) == 2
    for rotation, translation in poses:
        errors = [truth.add_s(r, t, rotation, translation) for r, t in found]
        assert min(errors) < 0.1


def test_frames_told_their_parts_are_reported_beside_the_same_frames_untold(scene, truths):
    # a cell that knows what it loaded passes the registered parts a frame holds
    told = detect.told_parts(scene, "unseen")
    assert told == sorted({i.name for i in scene.instances if i.registered})
    assert detect.told_parts(scene, "seen") is None  # only the unseen frames are posted again
    first = next(i for i in scene.instances if i.registered)
    right = [_detection(first.name, first.rotation, first.translation)]
    records = {}
    for name, detections in (("untold", []), ("told", right)):
        scored, instances = detect.match_detections(scene, detections, truths)
        records[name] = {
            "family": "scene", "set": "unseen", "size": "640x480", "body": "pcd",
            "stem": scene.stem, "latency_ms": 100.0, "detections": scored,
            "instances": instances,
        }  # fmt: skip
    result = {
        "records": [records["untold"]], "told": [records["told"]], "references": 54,
        "plan": {"baseline_frames": 0}, "seed": 0,
    }  # fmt: skip
    report = report_frames.frames_report(result)
    pair = report["told"]["scene"]
    assert pair["untold"]["right_matches"] == 0 and pair["told"]["right_matches"] == 1
    assert "bin" not in report["told"]  # no bin frame was told
    lines = report_frames.told_lines(report["told"])
    assert any("| scene, unseen | candidates | 1 |" in line for line in lines)
    assert any("| scene, unseen | nothing | 1 |" in line for line in lines)
