"""The evaluation's case families: deterministic, the right poses, shares and views."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from evaluation.cases import (
    CAMERA_DISTANCE_SCALES,
    KEEP_SHARES,
    NO_MATCH,
    NOISE_SCALE_SHARE,
    TRAINING_ANGLE_STEP,
    UNIT_FACTOR,
    make_cases,
    object_scale,
    paper_poses,
    rotation_from_angles,
    uniform_rotations,
)
from evaluation.metrics import geodesic_deg
from evaluation.scenes import JUNK_KINDS, surface_gap
from service.engine.sampling import load_mesh, sample_surface


def pybullet_mesh(relative: str) -> trimesh.Trimesh:
    pybullet_data = pytest.importorskip("pybullet_data")
    return load_mesh(Path(pybullet_data.getDataPath()) / relative)


@pytest.fixture(scope="module")
def objects():
    """Two real meshes and their scales (radius of the seed-0 reference)."""
    meshes = {
        "duck": pybullet_mesh("duck.obj"),
        "link_3": pybullet_mesh("kuka_iiwa/meshes/link_3.obj"),
    }
    references = {name: sample_surface(mesh, 2048, 0) for name, mesh in meshes.items()}
    return meshes, references, {n: object_scale(p) for n, p in references.items()}


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    return {"sphere": mesh}, {"sphere": 1.0}


def test_rotation_from_angles_turns_about_x_then_y_then_z():
    ax, ay, az = 0.3, -0.7, 1.1
    expected = Rotation.from_euler("xyz", [ax, ay, az]).as_matrix()  # extrinsic x, y, z
    np.testing.assert_allclose(rotation_from_angles(ax, ay, az), expected, atol=1e-12)
    # about x alone: y goes to z for a quarter turn
    np.testing.assert_allclose(
        rotation_from_angles(np.pi / 2, 0, 0) @ [0, 1, 0], [0, 0, 1], atol=1e-12
    )


def test_paper_poses_are_125_untrained_poses():
    poses = paper_poses()
    assert poses.shape == (125, 3)
    assert len({tuple(p) for p in np.round(poses, 9)}) == 125
    nonzero = poses[poses > 0]
    steps = nonzero / TRAINING_ANGLE_STEP
    assert np.all(np.abs(steps - np.round(steps)) > 0.1)  # 2.4, 4.8, 7.2, 9.6 steps
    # no pose but the identity is a rotation the training grid (π/24 steps over 0..π/2) holds
    grid = np.arange(13) * TRAINING_ANGLE_STEP
    trained = [rotation_from_angles(*a) for a in itertools.product(grid, repeat=3)]
    trained = np.stack(trained)
    for angles in poses:
        rotation = rotation_from_angles(*angles)
        cosines = (np.einsum("kij,ij->k", trained, rotation) - 1) / 2
        nearest = np.degrees(np.arccos(np.clip(cosines.max(), -1, 1)))
        if np.any(angles):
            assert nearest > 1.0
        else:
            assert nearest < 1e-6


def test_uniform_rotations_are_rotations_spread_over_so3():
    rotations = uniform_rotations(2000, np.random.default_rng(3))
    assert rotations.shape == (2000, 3, 3)
    np.testing.assert_allclose(
        rotations @ rotations.transpose(0, 2, 1), np.eye(3)[None].repeat(2000, 0), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)
    assert np.abs(rotations.mean(axis=0)).max() < 0.05  # a uniform rotation averages to zero
    angles = [geodesic_deg(r, np.eye(3)) for r in rotations]
    # the angle of a uniform rotation has the CDF (θ - sin θ) / π: its median is 132.3°
    assert 128 < np.median(angles) < 137


@pytest.mark.parametrize("family", ["paper-poses", "sparse", "so3", "noisy", "partial"])
def test_families_are_deterministic_and_never_the_reference(objects, family):
    meshes, references, scales = objects
    one = make_cases(family, meshes, scales, n_points=512, seed=7, poses_per_object=2)
    two = make_cases(family, meshes, scales, n_points=512, seed=7, poses_per_object=2)
    other = make_cases(family, meshes, scales, n_points=512, seed=8, poses_per_object=2)
    assert len(one) == len(two) == len(other) > 0
    for a, b, c in zip(one, two, other, strict=True):
        assert a.family == family and a.object_name in meshes
        assert a.points.dtype == np.float32 and a.points.shape[1] == 3
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.rotation, b.rotation)
        assert a.points.shape != c.points.shape or not np.array_equal(a.points, c.points)
        # resampled: the case's points, carried back to the model frame, are not the reference's
        model_frame = (a.points.astype(np.float64) - a.translation) @ a.rotation
        distances, _ = cKDTree(references[a.object_name]).query(model_frame)
        assert np.mean(distances < 1e-6 * scales[a.object_name]) < 0.01


def test_paper_poses_family_covers_the_poses(objects):
    meshes, _, scales = objects
    cases = make_cases("paper-poses", {"duck": meshes["duck"]}, scales, n_points=64)
    assert len(cases) == 125
    assert {c.params["pose_index"] for c in cases} == set(range(125))
    for case in cases[:10]:
        np.testing.assert_allclose(case.rotation, rotation_from_angles(*case.params["angles"]))
        np.testing.assert_array_equal(case.translation, np.zeros(3))
    subset = make_cases("paper-poses", meshes, scales, n_points=64, poses_per_object=5)
    assert len(subset) == 10 and len({c.params["pose_index"] for c in subset}) > 1


def test_sparse_keeps_the_share(objects):
    meshes, _, scales = objects
    cases = make_cases(
        "sparse", {"duck": meshes["duck"]}, scales, n_points=1000, poses_per_object=2
    )
    assert len(cases) == 2 * len(KEEP_SHARES)
    for case in cases:
        assert len(case.points) == round(case.params["keep_share"] * 1000)
    assert sorted({c.params["keep_share"] for c in cases}) == sorted(KEEP_SHARES)


def test_so3_translation_lies_within_twice_the_scale(objects):
    meshes, _, scales = objects
    cases = make_cases("so3", meshes, scales, n_points=64, poses_per_object=40)
    norms = np.array([np.linalg.norm(c.translation) / scales[c.object_name] for c in cases])
    assert np.all(norms <= 2.0) and norms.max() > 1.0
    angles = [geodesic_deg(c.rotation, np.eye(3)) for c in cases]
    assert max(angles) > 90  # rotations reach beyond the paper's quarter turn


def test_noisy_is_so3_plus_one_percent_noise(sphere):
    meshes, scales = sphere
    clean = make_cases("so3", meshes, scales, n_points=4096, poses_per_object=2)
    noisy = make_cases("noisy", meshes, scales, n_points=4096, poses_per_object=2)
    for a, b in zip(clean, noisy, strict=True):
        np.testing.assert_array_equal(a.rotation, b.rotation)
        np.testing.assert_array_equal(a.translation, b.translation)
        radial = np.linalg.norm(b.points - b.translation, axis=1) - 1.0  # unit sphere at t
        assert abs(np.std(radial) - NOISE_SCALE_SHARE) < 0.002
        assert b.params["noise_sigma"] == pytest.approx(NOISE_SCALE_SHARE)


def test_partial_keeps_the_camera_facing_half(sphere, objects):
    meshes, scales = sphere
    cases = make_cases("partial", meshes, scales, n_points=1024, poses_per_object=3)
    for case in cases:
        assert 0.4 < case.params["visible_share"] < 0.55
        assert len(case.points) == 1024
        camera = np.array(case.params["camera"])
        assert camera[2] - case.translation[2] == pytest.approx(CAMERA_DISTANCE_SCALES, rel=0.05)
        outward = case.points - case.translation  # unit sphere about t: the outward normal
        toward = camera - case.points
        cosines = np.einsum("ij,ij->i", outward, toward) / np.linalg.norm(toward, axis=1)
        assert cosines.min() > -0.1  # nothing from the far side, a few points on the rim
        assert np.mean(cosines > 0) > 0.95
    meshes, _, scales = objects
    for case in make_cases("partial", meshes, scales, n_points=512, poses_per_object=2):
        assert 0.2 < case.params["visible_share"] < 0.6


def test_sensor_family_is_deterministic_with_a_viewpoint_at_the_camera(objects):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    meshes, _, scales = objects
    first = make_cases("sensor", meshes, scales, seed=2, poses_per_object=2)
    again = make_cases("sensor", meshes, scales, seed=2, poses_per_object=2)
    other = make_cases("sensor", meshes, scales, seed=3, poses_per_object=2)
    assert len(first) == 4
    for a, b, c in zip(first, again, other, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
        assert not np.array_equal(a.rotation, c.rotation)
        assert a.family == "sensor" and a.params["expected"] == a.object_name
        assert a.params["viewpoint"] == [0.0, 0.0, 0.0]
        assert 4.0 <= a.params["distance_scales"] <= 8.0
        assert 100 < len(a.points) < 20_000
        centre_distance = np.linalg.norm(a.points.mean(axis=0))  # the near side: a bit closer
        expected = a.params["distance_scales"] * scales[a.object_name]
        assert 0.75 * expected < centre_distance < 1.05 * expected


def test_foreign_and_junk_expect_no_match(objects):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    meshes, _, scales = objects
    foreign = make_cases("foreign", meshes, scales, n_points=256, seed=1, poses_per_object=1)
    assert [(c.object_name, c.params["view"]) for c in foreign] == [
        (name, view) for name in meshes for view in ("full", "sensor")
    ]
    assert {c.params["expected"] for c in foreign} == {NO_MATCH}
    assert len(foreign[0].points) == 256 and "viewpoint" in foreign[1].params
    junk = make_cases("junk", meshes, scales, n_points=300, seed=1, poses_per_object=2)
    assert len(junk) == 2 * len(JUNK_KINDS)
    assert {c.params["kind"] for c in junk} == set(JUNK_KINDS)
    for case in junk:
        assert case.params["expected"] == NO_MATCH and case.object_name not in meshes
        assert case.params["size"] in scales.values()  # the size of a registered part
        spread = np.linalg.norm(case.points - case.points.mean(axis=0), axis=1).max()
        assert 0.5 * case.params["size"] < spread < 2 * case.params["size"]


def test_units_are_millimetres_of_the_same_pose(objects):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    meshes, _, scales = objects
    units = make_cases("units", meshes, scales, n_points=512, seed=4, poses_per_object=1)
    so3 = make_cases("so3", meshes, scales, n_points=512, seed=4, poses_per_object=1)
    full = [c for c in units if c.params["view"] == "full"]
    for mm, metres in zip(full, so3, strict=True):
        assert mm.params["unit_factor"] == UNIT_FACTOR and mm.params["right_refusal"] == "units"
        assert mm.params["expected"] == mm.object_name
        np.testing.assert_array_equal(mm.rotation, metres.rotation)
        np.testing.assert_allclose(mm.translation, UNIT_FACTOR * metres.translation)
        distances, _ = cKDTree(metres.points).query(mm.points / UNIT_FACTOR)
        assert distances.max() < 1e-6 * scales[mm.object_name]
    for case in (c for c in units if c.params["view"] == "sensor"):
        centre = np.linalg.norm(case.points.mean(axis=0)) / UNIT_FACTOR
        assert 3 * scales[case.object_name] < centre < 8 * scales[case.object_name]


def test_table_cases_hold_the_part_the_table_and_strays(objects):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    meshes, _, scales = objects
    cases = make_cases("table", {"duck": meshes["duck"]}, scales, seed=1, poses_per_object=2)
    for case in cases:
        params = case.params
        assert params["expected"] == "duck" and params["viewpoint"] == [0.0, 0.0, 0.0]
        total = params["part_points"] + params["table_points"] + params["stray_points"]
        assert total == len(case.points) and params["part_points"] > 300
        assert params["stray_points"] == round(0.02 * (total - params["stray_points"]))


def test_symmetric_groups_turn_one_surface_about_its_axis():
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    meshes = {
        "torus": pybullet_mesh("torus/torus_textured.obj"),
        "lego": pybullet_mesh("lego/lego.obj"),
    }
    scales = {name: object_scale(sample_surface(m, 2048, 0)) for name, m in meshes.items()}
    orders = {"torus": 0, "lego": 4}
    cases = make_cases("symmetric", meshes, scales, 2048, seed=1, poses_per_object=1, orders=orders)
    groups: dict[str, list] = {}
    for case in cases:
        groups.setdefault(case.params["group"], []).append(case)
    assert sorted(groups) == ["lego/0/full", "lego/0/sensor", "torus/0/full", "torus/0/sensor"]
    assert len(groups["torus/0/full"]) == 6 and len(groups["lego/0/full"]) == 4
    for group, members in groups.items():
        first, mesh = members[0], meshes[members[0].object_name]
        scale = scales[first.object_name]
        resampled = sample_surface(mesh, 2048, 5), sample_surface(mesh, 2048, 6)
        floor = surface_gap(*resampled) / scale  # two samples of one surface at one pose
        for member in members[1:]:
            turn = member.params["turn_deg"] % 360
            angle = geodesic_deg(member.rotation, first.rotation)
            assert angle == pytest.approx(min(turn, 360 - turn), abs=1e-6)
            gap = surface_gap(member.points, first.points) / scale  # the same surface
            assert gap < (1.1 * floor if group.endswith("full") else 0.025), group
