"""The evaluation's metrics on clouds whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluation.metrics import (
    ADD_S_POINTS,
    PRECISE_ADD_S,
    add_s,
    alignment_error_normalized,
    alignment_floor,
    auroc,
    coverage,
    diameter,
    expected_calibration_error,
    false_accepts,
    geodesic_deg,
    precision_of_accepted,
    reliability_bins,
    summarize,
    symmetric_spread,
)
from evaluation.records import Truth
from service.engine.sampling import sample_surface


def rotation_z(degrees: float) -> np.ndarray:
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


def test_geodesic_of_a_known_rotation():
    assert geodesic_deg(rotation_z(30), np.eye(3)) == pytest.approx(30)
    assert geodesic_deg(np.eye(3), rotation_z(-75)) == pytest.approx(75)
    assert geodesic_deg(rotation_z(180), np.eye(3)) == pytest.approx(180)
    base = Rotation.random(random_state=1).as_matrix()
    turn = Rotation.from_rotvec([0.0, 0.6, 0.0]).as_matrix()
    assert geodesic_deg(turn @ base, base) == pytest.approx(np.degrees(0.6))


def test_diameter_of_a_cube_and_of_a_flat_square():
    cube = np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T.astype(float)
    inside = np.random.default_rng(0).random((200, 3))
    assert diameter(np.vstack([cube, inside])) == pytest.approx(np.sqrt(3))
    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0]], float)
    assert diameter(square) == pytest.approx(np.sqrt(2))


def test_add_s_is_zero_at_the_true_pose_and_known_for_an_offset():
    points = sample_surface(trimesh.creation.box((1.0, 2.0, 3.0)), 500, 1)
    rotation, translation = Rotation.random(random_state=2).as_matrix(), np.array([1.0, 2, 3])
    assert add_s(points, rotation, translation, rotation, translation, 1.0) == pytest.approx(0)
    two = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    shifted = add_s(two, np.eye(3), [0, 1.0, 0], np.eye(3), np.zeros(3), diameter(two))
    assert shifted == pytest.approx(0.1)


def test_add_s_forgives_symmetry_but_not_a_wrong_rotation():
    sphere = sample_surface(trimesh.creation.icosphere(5, 1.0), 3000, 1)
    wrong = Rotation.random(random_state=3).as_matrix()
    # any rotation of a sphere is a symmetry: only the resampling spacing is left (precise)
    assert add_s(sphere, wrong, np.zeros(3), np.eye(3), np.zeros(3), 2.0) < PRECISE_ADD_S
    box = sample_surface(trimesh.creation.box((1.0, 2.0, 4.0)), 3000, 1)
    tilt = Rotation.from_euler("y", 60, degrees=True).as_matrix()
    assert add_s(box, tilt, np.zeros(3), np.eye(3), np.zeros(3), diameter(box)) > 0.1
    # a half turn about an axis of the box is one of its symmetries
    flip = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    assert add_s(box, flip, np.zeros(3), np.eye(3), np.zeros(3), diameter(box)) < PRECISE_ADD_S


def test_add_s_of_a_symmetric_answer_falls_with_the_model_points_density():
    # a gear-like part: a 10-fold ring of teeth; a turn by one tooth is a symmetry
    teeth = [
        trimesh.creation.box((0.2, 0.1, 0.3)).apply_translation((1.0, 0, 0)) for _ in range(10)
    ]
    for k, tooth in enumerate(teeth):
        tooth.apply_transform(trimesh.transformations.rotation_matrix(k * np.pi / 5, (0, 0, 1)))
    gear = trimesh.util.concatenate([trimesh.creation.cylinder(0.9, 0.3, 40), *teeth])
    one_tooth = Rotation.from_euler("z", 36, degrees=True).as_matrix()
    pose = Rotation.random(random_state=4).as_matrix(), np.array([0.5, -1.0, 2.0])
    answer = pose[0] @ one_tooth, pose[1]
    errors = []
    for count in (2048, ADD_S_POINTS):
        points = sample_surface(gear, count, 1)
        error = add_s(points, *answer, *pose, diameter(points))
        tree = cKDTree(points)  # built once per object, the same figure
        assert add_s(points, *answer, *pose, diameter(points), tree) == pytest.approx(error)
        truth = Truth(points, 1.0, diameter(points), "seen", model_points=points)
        assert truth.add_s(*answer, *pose) == pytest.approx(error)
        errors.append(error)
    sparse, dense = errors
    assert dense < sparse / 2 and dense < PRECISE_ADD_S / 2


def test_alignment_error_of_identical_and_offset_clouds():
    grid = np.array(np.meshgrid(np.arange(20), np.arange(20), [0.0])).reshape(3, -1).T * 0.1
    scale = float(np.linalg.norm(grid - grid.mean(0), axis=1).max())
    assert alignment_error_normalized(grid, grid, np.eye(3), np.zeros(3), scale) == 0.0
    # the observation lies 0.02 above the plane of the reference: every point 0.02 away
    lifted = grid + [0, 0, 0.02]
    error = alignment_error_normalized(lifted, grid, np.eye(3), np.zeros(3), scale)
    assert error == pytest.approx(0.02 / scale)
    # the same at any pose: scene = R @ model + t
    rotation, translation = Rotation.random(random_state=4).as_matrix(), np.array([5.0, -1, 2])
    scene = lifted @ rotation.T + translation
    assert alignment_error_normalized(scene, grid, rotation, translation, scale) == pytest.approx(
        0.02 / scale
    )


def test_alignment_floor_of_a_resampled_cloud_is_small_but_not_zero():
    mesh = trimesh.creation.icosphere(4, 1.0)
    reference, observed = sample_surface(mesh, 2048, 0), sample_surface(mesh, 2048, 5)
    floor = alignment_floor(observed, reference, 1.0)
    assert 0.005 < floor < 0.05
    assert alignment_floor(reference, reference, 1.0) == 0.0


def test_summarize_counts_success_precise_and_medians():
    records = [
        dict(
            label_ok=True,
            add_s=0.01,
            rot_err_deg=1.0,
            align_err=0.03,
            align_err_floor=0.026,
            latency_ms=10.0,
        ),
        dict(
            label_ok=True,
            add_s=0.05,
            rot_err_deg=3.0,
            align_err=0.05,
            align_err_floor=0.026,
            latency_ms=20.0,
        ),
        dict(
            label_ok=False,
            add_s=0.01,
            rot_err_deg=2.0,
            align_err=0.04,
            align_err_floor=0.030,
            latency_ms=30.0,
        ),
        dict(
            label_ok=True,
            add_s=None,
            rot_err_deg=None,
            align_err=None,
            align_err_floor=0.030,
            latency_ms=40.0,
        ),
    ]
    summary = summarize(records)
    assert summary["cases"] == 4
    assert summary["accuracy"] == pytest.approx(0.75)
    assert summary["success"] == pytest.approx(0.5)  # a wrong label never succeeds
    assert summary["precise"] == pytest.approx(0.25)
    assert summary["median_rot_err_deg"] == pytest.approx(2.0)
    assert summary["median_add_s"] == pytest.approx(0.01)
    assert summary["median_align_err"] == pytest.approx(0.04)
    assert summary["median_align_err_floor"] == pytest.approx(0.028)
    assert summary["latency_ms_median"] == pytest.approx(25.0)
    assert summary["latency_ms_p95"] == pytest.approx(np.percentile([10, 20, 30, 40], 95))
    assert summarize([]) == {"cases": 0}


def test_coverage_false_accepts_and_precision_of_accepted_answers():
    accepted = [True, True, False, True, False]
    right = [True, False, False, False, True]  # the last: right, but refused
    assert coverage(accepted) == pytest.approx(0.6)
    assert false_accepts(accepted, right) == pytest.approx(0.4)  # accepted and wrong
    assert precision_of_accepted(accepted, right) == pytest.approx(1 / 3)
    # on no_match cases nothing is right: false accepts are every "match"
    assert false_accepts([True, False, False, False], [False] * 4) == pytest.approx(0.25)
    assert np.isnan(precision_of_accepted([False, False], [True, True]))


def test_calibration_error_of_hand_made_confidences():
    confidence = [0.95, 0.95, 0.15, 0.15, None]  # None: no confidence given, left out
    right = [True, False, False, False, True]
    # bin 0.9-1.0: mean 0.95, half right: gap 0.45; bin 0.1-0.2: mean 0.15, none right: 0.15
    assert expected_calibration_error(confidence, right) == pytest.approx((2 * 0.45 + 2 * 0.15) / 4)
    bins = reliability_bins(confidence, right)
    assert [(b["low"], b["count"], b["right"]) for b in bins] == [(0.1, 2, 0.0), (0.9, 2, 0.5)]
    # calibrated: 7 of 10 answers given 0.7 are right; 1.0 lands in the last bin
    assert expected_calibration_error([0.7] * 10, [True] * 7 + [False] * 3) == pytest.approx(0)
    assert reliability_bins([1.0], [True])[0]["low"] == pytest.approx(0.9)
    assert np.isnan(expected_calibration_error([None, None], [True, False]))


def test_auroc_of_a_hand_computed_case():
    # right answers score 0.35 and 0.8, wrong ones 0.1 and 0.4: 3 of the 4 pairs ordered
    assert auroc([0.1, 0.4, 0.35, 0.8], [False, False, True, True]) == pytest.approx(0.75)
    assert auroc([0.5, 0.5], [True, False]) == pytest.approx(0.5)  # a tie counts half
    assert auroc([0.9, 0.2, None], [True, False, False]) == pytest.approx(1.0)
    assert auroc([0.1, 0.9], [True, False]) == pytest.approx(0.0)
    assert np.isnan(auroc([0.3, 0.4], [True, True]))
    rng = np.random.default_rng(0)
    scores, right = rng.integers(0, 5, 60) / 4, rng.random(60) < 0.5  # many ties
    pairs = [
        1.0 if p > n else 0.5 if p == n else 0.0 for p in scores[right] for n in scores[~right]
    ]
    assert auroc(scores, right) == pytest.approx(np.mean(pairs))


def test_symmetric_spread_is_the_largest_angle_between_answers():
    answers = [rotation_z(0), rotation_z(10), rotation_z(-20), None]
    assert symmetric_spread(answers) == pytest.approx(30)
    assert symmetric_spread([rotation_z(5)] * 3) == pytest.approx(0, abs=1e-5)
    assert np.isnan(symmetric_spread([rotation_z(5)]))
