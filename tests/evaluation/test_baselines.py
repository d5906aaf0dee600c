"""The two baselines recognise real objects and recover their pose on so3 cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evaluation.cases import make_cases, object_scale
from evaluation.metrics import add_s, diameter
from service.engine.sampling import load_mesh, sample_surface

OBJECTS = {
    "duck": "duck.obj",
    "link_3": "kuka_iiwa/meshes/link_3.obj",
    "mug": "objects/mug.obj",
}


@pytest.fixture(scope="module")
def gallery():
    pybullet_data = pytest.importorskip("pybullet_data")
    meshes = {n: load_mesh(Path(pybullet_data.getDataPath()) / p) for n, p in OBJECTS.items()}
    references = {name: sample_surface(mesh, 2048, 0) for name, mesh in meshes.items()}
    scales = {name: object_scale(points) for name, points in references.items()}
    cases = make_cases("so3", meshes, scales, n_points=2048, seed=3, poses_per_object=1)
    return references, cases


def check(recognizer, references, cases):
    for case in cases:
        answer = recognizer.align(case.points)
        assert answer["label"] == case.object_name
        rotation, translation = np.asarray(answer["rotation"]), np.asarray(answer["translation"])
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
        reference = references[case.object_name]
        error = add_s(
            reference, rotation, translation, case.rotation, case.translation, diameter(reference)
        )
        assert error < 0.1, f"{case.object_name}: ADD-S {error:.3f}"


@pytest.mark.slow
def test_ppf_recognises_and_poses(gallery):
    pytest.importorskip("cv2")
    from evaluation.baselines.ppf import PPFRecognizer

    references, cases = gallery
    check(PPFRecognizer(references), references, cases)


@pytest.mark.slow
def test_fpfh_recognises_and_poses(gallery):
    pytest.importorskip("open3d", exc_type=ImportError)  # its wheel needs libusb
    from evaluation.baselines.fpfh import FPFHRecognizer

    references, cases = gallery
    check(FPFHRecognizer(references), references, cases)
