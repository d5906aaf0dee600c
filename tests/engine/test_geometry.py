"""The engine's numeric steps, each on a constructed case whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine.alignment import alignment_error, orthonormal
from service.engine.classifier import LinearClassifier, classifier_input
from service.engine.distance_field import DistanceField
from service.engine.grid import GRID_SIZE, grid
from service.engine.hypotheses import from_principal_axes
from service.engine.icp import Surface, icp
from service.engine.normalize import (
    lengths,
    no_larger,
    normalize,
    radius,
    radius_at_least,
    radius_bounds,
    squared_distances,
)
from service.engine.normals import estimate_normals
from service.engine.principal_axes import Frame, principal_frame
from service.engine.registration import kabsch, paper_least_squares, ransac
from service.engine.segments import cell_groups


def random_pose(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return Rotation.random(random_state=seed).as_matrix(), rng.uniform(-1, 1, 3)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))


def test_kabsch_recovers_a_known_pose_exactly():
    model = np.random.default_rng(0).normal(size=(50, 3))
    rotation, translation = random_pose(1)
    r, t = kabsch(model, model @ rotation.T + translation)
    assert np.allclose(r, rotation, atol=1e-10) and np.allclose(t, translation, atol=1e-10)
    assert np.isclose(np.linalg.det(r), 1.0)


def test_kabsch_never_returns_a_reflection():
    model = np.random.default_rng(0).normal(size=(50, 3))
    mirrored = model * np.array([1, 1, -1])
    r, _ = kabsch(model, mirrored)
    assert np.isclose(np.linalg.det(r), 1.0)


def test_paper_least_squares_recovers_a_known_pose():
    model = np.random.default_rng(2).normal(size=(100, 3))
    rotation, translation = random_pose(3)
    r, t = paper_least_squares(model, model @ rotation.T + translation)
    assert np.allclose(r, rotation, atol=1e-8) and np.allclose(t, translation, atol=1e-8)


def test_ransac_finds_the_pose_among_70_percent_wrong_pairs():
    rng = np.random.default_rng(4)
    model = rng.normal(size=(400, 3))
    rotation, translation = random_pose(5)
    scene = model @ rotation.T + translation
    wrong = rng.random(len(model)) < 0.7
    scene[wrong] = rng.normal(size=(wrong.sum(), 3)) * 2
    r, t, inliers = ransac(model, scene, 0.05, 200, rng)
    assert angle_deg(r, rotation) < 1e-6 and np.allclose(t, translation, atol=1e-6)
    assert np.array_equal(inliers, ~wrong)


def test_principal_axes_hypotheses_contain_the_true_pose(duck_points):
    rotation, translation = random_pose(6)
    scene = duck_points @ rotation.T + translation
    made = from_principal_axes(Frame.of(scene), Frame.of(duck_points))
    errors = [angle_deg(r, rotation) for r in made.rotations]
    assert min(errors) < 1.0
    assert len(errors) == 4


def test_principal_frame_turns_with_an_asymmetric_object(duck_points):
    rotation, _ = random_pose(7)
    centred = duck_points - duck_points.mean(axis=0)
    assert np.allclose(principal_frame(centred @ rotation.T), rotation @ principal_frame(centred))


def test_icp_converges_from_a_small_perturbation(duck_points):
    rotation, translation = random_pose(8)
    scene = duck_points[::2] @ rotation.T + translation
    nudge = Rotation.from_rotvec([0.1, -0.08, 0.05]).as_matrix()
    scale = radius(duck_points)
    tree = cKDTree(duck_points)
    field = DistanceField.of(duck_points, scale, tree=tree)
    surface = Surface.of(duck_points, estimate_normals(duck_points, tree=tree), field, tree)
    start = (nudge @ rotation, translation + 0.05 * scale)
    r, t, _ = icp(scene, surface, *start, noise=0.002 * scale, gate=0.3 * scale)
    assert angle_deg(r, rotation) < 0.5
    assert np.linalg.norm(t - translation) < 0.01 * scale


def test_alignment_error_is_zero_at_the_pose_and_grows_off_it(duck_points):
    rotation, translation = random_pose(9)
    tree = cKDTree(duck_points)
    scene = duck_points @ rotation.T + translation
    assert alignment_error(scene, tree, rotation, translation) < 1e-9
    shifted = translation + np.array([0.1, 0, 0]) * radius(duck_points)
    assert alignment_error(scene, tree, rotation, shifted) > 0.01 * radius(duck_points)


def test_normalize_centres_and_scales_to_unit_radius(duck_points):
    result = normalize(duck_points * 3 + 5)
    assert np.allclose(result.points.mean(axis=0), 0, atol=1e-5)
    assert np.isclose(np.linalg.norm(result.points, axis=1).max(), 1.0, atol=1e-5)
    assert np.isclose(result.scale, 3 * radius(duck_points), rtol=1e-6)


def test_grid_is_64_by_64_and_sums_to_one():
    mapped = np.random.default_rng(0).normal(size=(1000, 2))
    g = grid(mapped)
    assert g.shape == (GRID_SIZE, GRID_SIZE) and np.isclose(g.sum(), 1.0)
    assert np.allclose(grid(mapped * 7 + 3), g)  # independent of the output's scale


def test_classifier_fits_shapes_and_separates_classes():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(3, 2)) * 3
    views = [np.stack([grid(rng.normal(size=(500, 2)) + c) for _ in range(6)]) for c in centres]
    features = [classifier_input(v, blur=1.0) for v in views]
    classifier = LinearClassifier.fit(["a", "b", "c"], features, blur=1.0)
    assert classifier.weights.shape == (3, (GRID_SIZE // 2) ** 2)
    scores = classifier.scores(views[1][0])
    assert scores.shape == (3,) and np.isclose(scores.sum(), 1.0)
    assert int(np.argmax(scores)) == 1


@pytest.mark.parametrize("count", [3, 40])
def test_grid_handles_few_points(count):
    assert np.isclose(grid(np.random.default_rng(1).normal(size=(count, 2))).sum(), 1.0)


def test_refitting_the_classifier_for_100_references_needs_no_iterations():
    rng = np.random.default_rng(0)
    features = [classifier_input(rng.random((12, GRID_SIZE, GRID_SIZE)), 1.0) for _ in range(100)]
    classifier = LinearClassifier.fit([str(i) for i in range(100)], features, blur=1.0)
    hits = [
        int(np.argmax(classifier.weights @ f[0] + classifier.bias)) == i
        for i, f in enumerate(features)
    ]
    assert np.mean(hits) == 1.0  # a training view is classified as its reference


def test_a_gallery_of_one_reference_with_one_view_fits():
    features = [classifier_input(np.zeros((1, GRID_SIZE, GRID_SIZE)), 1.0)]
    classifier = LinearClassifier.fit(["only"], features, blur=1.0)
    assert np.isfinite(classifier.weights).all() and classifier.scores(
        np.zeros((64, 64))
    ).shape == (1,)


def test_an_answered_rotation_is_orthonormal_to_double_precision():
    rotation = Rotation.random(random_state=3).as_matrix()
    drifted = (rotation.astype(np.float32) @ rotation.T.astype(np.float32) @ rotation) * 1.000001
    fixed = orthonormal(drifted)
    np.testing.assert_allclose(fixed @ fixed.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(fixed) > 0 and np.abs(fixed - rotation).max() < 1e-5


def test_cell_groups_join_what_lies_within_a_cell_and_part_what_lies_far_apart():
    line = np.c_[np.arange(0, 0.1, 0.004), np.zeros(25), np.zeros(25)]  # 4 mm apart
    far = line + [0.2, 0.0, 0.0]  # 10 cm beyond its end
    labels = cell_groups(np.r_[line, far], 0.005)
    assert len(set(labels[:25])) == len(set(labels[25:])) == 1
    assert labels[0] != labels[25]
    assert len(set(cell_groups(line, 0.001))) == 25  # 4 mm apart: beyond 2 sqrt(3) mm cells


def test_cell_groups_are_the_occupied_cells_joined_to_their_26_neighbours():
    # a sparse cloud, unequal along its axes: each group is one of the occupied cells'
    # components on the dense grid (scipy's labelling with the 3 x 3 x 3 neighbourhood), so
    # one number a cell stands for its three indices whatever their spans
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 1, (400, 3)) * [0.3, 0.05, 0.12] + [-1.0, 2.0, 0.5]
    cell = 0.01
    labels = cell_groups(points, cell)
    keys = np.floor((points - points.min(axis=0)) / cell).astype(int)
    occupied = np.zeros(keys.max(axis=0) + 1, dtype=bool)
    occupied[tuple(keys.T)] = True
    components, count = ndimage.label(occupied, structure=np.ones((3, 3, 3)))
    expected = components[tuple(keys.T)]
    assert 1 < count < len(points)
    pairs = set(zip(labels.tolist(), expected.tolist(), strict=True))
    assert len(pairs) == len(set(labels.tolist())) == count  # the same partition


def test_a_clouds_radius_is_at_least_half_its_strided_span():
    """``radius_at_least`` never exceeds the radius (the frame's scales are cut by it), and on
    a wide frame it is close enough to stand for it."""
    rng = np.random.default_rng(3)
    for shape in ([1.0, 1.0, 1.0], [2.0, 0.1, 0.5], [0.01, 0.01, 3.0]):
        cloud = rng.normal(size=(20_000, 3)) * shape + rng.normal(size=3)
        assert radius(cloud) / 3 <= radius_at_least(cloud) <= radius(cloud)
    frame = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 640), np.linspace(-0.3, 0.3, 480)), -1)
    table = np.concatenate([frame.reshape(-1, 2), np.full((640 * 480, 1), 0.8)], axis=1)
    assert radius_at_least(table) == pytest.approx(radius(table), rel=0.25)


def test_the_sizes_a_frame_holds_are_those_its_exact_radius_allows():
    """``no_larger`` answers ``scales <= radius(points)`` on the bounds of ``radius_bounds``
    alone unless a scale lies between them, where it measures the radius itself: scales at,
    just inside and just outside each bound, and the radius itself, are judged as the exact
    radius judges them."""
    rng = np.random.default_rng(5)
    frame = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 320), np.linspace(-0.3, 0.3, 240)), -1)
    table = np.concatenate([frame.reshape(-1, 2), np.full((320 * 240, 1), 0.8)], axis=1)
    clouds = [rng.normal(size=(20_000, 3)) * [2.0, 0.1, 0.5] + 3.0, table]
    for cloud in clouds:
        exact = radius(cloud)
        low, high = radius_bounds(cloud)
        assert low <= exact <= high
        near = np.array([low, high, exact, 0.999 * low, 1.001 * high, 0.5 * exact, 2 * exact])
        for scales in (near, near[[3, 4, 5, 6]], np.array([exact * (1 + 1e-12)])):
            np.testing.assert_array_equal(no_larger(scales, cloud), scales <= exact)
    assert not no_larger(np.array([0.1]), np.zeros((0, 3))).any()


def test_a_frames_lengths_are_numpys_norms_to_the_bit():
    """``lengths`` stands for ``np.linalg.norm(axis=1)`` on the frame's steps: a range or a gap
    one ulp apart could move a link or a plane's inlier across its threshold."""
    rng = np.random.default_rng(5)
    for scale in (1e-3, 1.0, 1e3):
        vectors = rng.normal(size=(50_000, 3)) * scale
        np.testing.assert_array_equal(lengths(vectors), np.linalg.norm(vectors, axis=1))
    turned = rng.normal(size=(3, 2000)).T  # a view whose rows are not contiguous
    np.testing.assert_array_equal(lengths(turned), np.linalg.norm(turned, axis=1))
    # ... and on stacks of them, as ICP asks which samples face away from several cameras
    sights = rng.normal(size=(16, 5000, 3)) * 0.05
    np.testing.assert_array_equal(lengths(sights), np.linalg.norm(sights, axis=-1))
    # ... and the squared distances that pick a part's neighbourhood out of a frame
    frame, centre = rng.normal(size=(50_000, 3)), rng.normal(size=3)
    np.testing.assert_array_equal(
        squared_distances(frame, centre), np.sum((frame - centre) ** 2, axis=1)
    )
    assert radius(frame) == np.linalg.norm(frame - frame.mean(axis=0), axis=1).max()
    assert radius(frame, centre) == np.linalg.norm(frame - centre, axis=1).max()
