"""The calibration's corpus and its held-out report (evaluation.calibration_corpus,
evaluation.calibrate): parts the evaluation never uses, sensor profiles that do what they say,
bins with walls, and a held-out group scored by a calibration that never saw it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from evaluation.calibrate import family_of, held_out, matched, transfer_report
from evaluation.camera import PROFILES, SensorProfile, cast, cast_profiled
from evaluation.scenes import PART, TABLE, placed, table_scene
from service.engine.confidence import measures
from service.engine.tuning import BIN_ACCEPT

pytest.importorskip("open3d")
corpus = pytest.importorskip("evaluation.calibration_corpus")


def _box_in_front(distance: float = 0.5) -> list[trimesh.Trimesh]:
    """A 10 cm cube half a metre in front of the camera, a wall a metre behind it."""
    cube = placed(trimesh.creation.box((0.1, 0.1, 0.1)), np.eye(3), [0.0, 0.0, distance])
    wall = placed(trimesh.creation.box((3.0, 3.0, 0.01)), np.eye(3), [0.0, 0.0, distance + 1])
    return [cube, wall]


def test_the_corpus_holds_none_of_the_manifests_parts():
    from training.objects import load_manifest

    parts = corpus.corpus_parts(per_group=3)
    listed = {spec.path.resolve() for spec in load_manifest()}
    assert parts and not {part.path.resolve() for part in parts} & listed
    assert len({part.name for part in parts}) == len(parts)
    groups = {part.group for part in parts}
    assert {"random-0xx", "random-9xx", "laikago"} <= groups


def test_a_loaded_part_has_a_tables_size():
    part = next(p for p in corpus.corpus_parts(per_group=1) if p.group == "random-3xx")
    mesh = corpus.load_part(part, np.random.default_rng(0))
    radius = corpus.mesh_radius(mesh)
    assert corpus.RADIUS_M[0] <= radius <= corpus.RADIUS_M[1]


def test_the_sensor_profile_sees_what_cast_sees():
    meshes = _box_in_front()
    plain = cast(meshes, np.random.default_rng(1))
    profiled = cast_profiled(meshes, np.random.default_rng(1), PROFILES["sensor"])
    assert len(profiled.points) == len(plain.points)
    assert np.abs(profiled.points[:, 2] - plain.points[:, 2]).max() < 0.02


def test_the_camera_profile_quantises_and_drops_pixels_at_depth_jumps():
    meshes = _box_in_front()
    plain = cast_profiled(meshes, np.random.default_rng(2), PROFILES["sensor"])
    camera = cast_profiled(meshes, np.random.default_rng(2), PROFILES["camera"])
    z = camera.points[:, 2]
    assert np.allclose(z / 0.001, np.round(z / 0.001), atol=1e-6)  # 1 mm steps
    lost = len(plain.points) - len(camera.points)
    cube_outline = 4 * 2 * 60  # about the pixels either side of the cube's edge, 60 a side
    assert 0.2 * cube_outline < lost < cube_outline  # about half of them dropped
    assert (camera.mesh_index == 0).sum() < (plain.mesh_index == 0).sum()


def test_the_tof_profile_smears_outline_pixels_back():
    profile = SensorProfile("test", noise_share=0.0, flying=1.0, smear=0.05)
    meshes = _box_in_front()
    seen = cast_profiled(meshes, np.random.default_rng(3), profile)
    on_cube = seen.mesh_index == 0
    behind = seen.points[on_cube, 2] > 0.45 + 1e-3  # the cube's front face is at z = 0.45
    assert 0 < behind.sum() < 0.2 * on_cube.sum()  # its outline, not the whole face


def test_a_bin_adds_walls_around_the_part():
    mesh = trimesh.creation.box((0.06, 0.04, 0.03))
    rng = np.random.default_rng(4)
    table = table_scene(mesh, 0.04, np.random.default_rng(4), profile=PROFILES["camera"])
    walled = table_scene(mesh, 0.04, rng, profile=PROFILES["camera"], walls=1.0)
    normal, offset = walled.plane[:3], walled.plane[3]
    height = walled.points @ normal + offset
    support = walled.source == TABLE
    assert (height[support] > 0.02).sum() > 100  # wall points stand above the floor
    assert (table.points @ table.plane[:3] + table.plane[3])[table.source == TABLE].max() < 0.01
    assert (walled.source == PART).sum() > 50


def _rows(rng: np.random.Generator, group: str, count: int, shift: float) -> list[dict]:
    fit = rng.uniform(0.3, 1.0, count)
    return [
        measures(f, 0.9, 0.3, 0.0, 2048, 1.0, True)
        | {"right": bool(f + shift > 0.7), "group": group, "family": "view", "left_out": False}
        for f in fit
    ]


def test_a_held_out_group_is_scored_by_a_calibration_that_never_saw_it():
    rng = np.random.default_rng(5)
    rows = _rows(rng, "a", 200, 0.0) + _rows(rng, "b", 200, 0.0) + _rows(rng, "c", 60, 0.0)
    scores, _ = held_out(rows)
    flipped = rows[:400] + [row | {"right": not row["right"]} for row in rows[400:]]
    again, _ = held_out(flipped)
    assert np.allclose(scores[400:], again[400:])  # c's own labels never reach c's scores
    assert not np.allclose(scores[:400], again[:400])  # but they reach a's and b's
    report = transfer_report(rows, scores, np.full(len(rows), 0.9))
    assert set(report["groups"]) == {"a", "b", "c"}
    assert report["families"]["view"]["answers"] == len(rows)


def test_rows_are_reported_in_the_families_of_the_targets():
    assert family_of({"family": "so3", "left_out": True}) == "left-out"
    assert family_of({"family": "partial"}) == "full"
    assert family_of({"family": "sensor"}) == "view"
    assert family_of({"family": "table"}) == "table"
    assert family_of({"family": "left-out"}) == "left-out"


def test_a_match_is_counted_as_the_service_makes_one():
    # an answer of a bin's reading is a "match" from BIN_ACCEPT only, and one whose
    # look-alikes fit alike never is (Engine.judge, look_alikes.doubt)
    rows = [{}, {"in_bin": True}, {"in_bin": True}, {"doubted": True}, {"in_bin": False}]
    scores = np.array([0.82, 0.82, BIN_ACCEPT, 0.99, 0.79])
    assert matched(rows, scores, 0.8).tolist() == [True, False, True, False, False]
    assert matched(rows, scores, np.full(5, 0.9)).tolist() == [False, False, False, False, False]
    right = [True, True, True, False, True]
    about = [{"right": r, "family": "sensor", "group": "a"} for r in right]
    answers = [row | more for row, more in zip(rows, about, strict=True)]
    report = transfer_report(answers, scores, np.full(5, 0.8))
    assert report["all"]["precision"] == 1.0 and report["all"]["coverage"] == 0.5


def test_a_part_not_registered_counts_as_a_false_accept_not_against_precision():
    # a registered part's answers give the precision; an answer of a part not registered
    # (left out, foreign, junk) can only be wrong, and its "match" is a false accept
    answers = [
        {"right": True, "family": "sensor", "group": "a"},
        {"right": True, "family": "table", "group": "a"},
        {"right": False, "family": "so3", "left_out": True, "group": "a"},
        {"right": False, "family": "junk", "group": "a"},
    ]
    report = transfer_report(answers, np.array([0.95, 0.95, 0.95, 0.5]), np.full(4, 0.9))
    assert report["registered"]["precision"] == 1.0
    assert report["registered"]["answers"] == 2
    assert report["not_registered"]["false_accepts"] == 0.5
    assert report["all"]["precision"] == 2 / 3
