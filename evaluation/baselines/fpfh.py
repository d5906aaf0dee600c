"""FPFH features + RANSAC global registration + point-to-plane ICP, with Open3D.

Open3D's global-registration pipeline (its tutorial's settings, scaled to each reference),
run once per reference: the scene is registered onto the reference (so that fitness is the
share of the scene the reference explains, whole or partial view alike), and the label is
the reference with the best ICP fitness, ties broken by the lower inlier RMSE. Needs
``open3d`` (its wheel needs Debian's ``libusb-1.0-0``).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from evaluation.baselines import orient_normals

# Settings: Open3D's global-registration tutorial, with every distance relative to the
# reference's scale (its radius) through the voxel size. On 9 pybullet meshes (2,048-point
# references, resampled 2,048-point cases, 27 per family) they gave recognition / success
# 1.00 / 1.00 on so3, 0.96 / 0.96 on noisy, 0.93 / 0.93 on partial, 2-5 s per query against
# the 9 references on a loaded 2-core machine. The normal radius grows with the spacing of a
# sparse cloud (10 % of the points: success 0.50 -> 0.78 on 18 cases); dense clouds keep
# the tutorial's 2 voxels.
VOXEL_SCALES = 1 / 20  # voxel size = scale / 20
NORMAL_RADIUS_VOXELS = 2.0  # normals: hybrid search radius 2 voxels, at most 30 neighbours
NORMAL_MAX_NN = 30
NORMAL_RADIUS_SPACINGS = 2.5  # ... or 2.5 median point spacings, whichever is larger
FEATURE_RADIUS_VOXELS = 5.0  # FPFH: radius 5 voxels, at most 100 neighbours
FEATURE_MAX_NN = 100
RANSAC_DISTANCE_VOXELS = 1.5  # RANSAC inlier distance and distance checker
RANSAC_EDGE_LENGTH = 0.9  # edge-length checker's similarity
RANSAC_N = 3  # correspondences per hypothesis
RANSAC_MAX_ITERATIONS = 100_000  # RANSACConvergenceCriteria(max_iteration, confidence)
RANSAC_CONFIDENCE = 0.999
ICP_DISTANCE_VOXELS = 0.4  # point-to-plane ICP correspondence distance, on the full clouds
ICP_MAX_ITERATIONS = 50
SEED = 0  # Open3D's RANSAC draws from a global generator: seeded per query for repeatability


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    return cloud


def _with_normals(cloud: o3d.geometry.PointCloud, voxel: float, viewpoint) -> None:
    spacing = float(np.median(np.asarray(cloud.compute_nearest_neighbor_distance())))
    radius = max(NORMAL_RADIUS_VOXELS * voxel, NORMAL_RADIUS_SPACINGS * spacing)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=NORMAL_MAX_NN)
    )
    points = np.asarray(cloud.points)
    cloud.normals = o3d.utility.Vector3dVector(
        orient_normals(points, np.asarray(cloud.normals), viewpoint)
    )


def _prepare(points: np.ndarray, voxel: float, viewpoint=None):
    """The full cloud with normals, its voxel-downsampled copy with normals, and its FPFH."""
    full = _cloud(points)
    _with_normals(full, voxel, viewpoint)
    down = full.voxel_down_sample(voxel)
    _with_normals(down, voxel, viewpoint)
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        down,
        o3d.geometry.KDTreeSearchParamHybrid(
            radius=FEATURE_RADIUS_VOXELS * voxel, max_nn=FEATURE_MAX_NN
        ),
    )
    return full, down, feature


class FPFHRecognizer:
    """One FPFH + RANSAC + ICP registration per reference; the label has the best fitness."""

    def __init__(self, references: dict[str, np.ndarray]):
        if not references:
            raise ValueError("FPFHRecognizer needs at least one reference")
        # Open3D warns on every query whose mutual filter leaves few matches: not news here.
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        self.voxels: dict[str, float] = {}
        self.prepared = {}
        for name, points in references.items():
            points = np.asarray(points, dtype=np.float64)
            scale = float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())
            self.voxels[name] = VOXEL_SCALES * scale
            self.prepared[name] = _prepare(points, self.voxels[name])

    def _register(self, name: str, scene_prepared, voxel: float):
        """Scene -> reference: RANSAC on FPFH matches, then point-to-plane ICP."""
        registration = o3d.pipelines.registration
        scene_full, scene_down, scene_feature = scene_prepared
        ref_full, ref_down, ref_feature = self.prepared[name]
        distance = RANSAC_DISTANCE_VOXELS * voxel
        coarse = registration.registration_ransac_based_on_feature_matching(
            scene_down,
            ref_down,
            scene_feature,
            ref_feature,
            True,  # mutual filter
            distance,
            registration.TransformationEstimationPointToPoint(False),
            RANSAC_N,
            [
                registration.CorrespondenceCheckerBasedOnEdgeLength(RANSAC_EDGE_LENGTH),
                registration.CorrespondenceCheckerBasedOnDistance(distance),
            ],
            registration.RANSACConvergenceCriteria(RANSAC_MAX_ITERATIONS, RANSAC_CONFIDENCE),
        )
        return registration.registration_icp(
            scene_full,
            ref_full,
            ICP_DISTANCE_VOXELS * voxel,
            coarse.transformation,
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=ICP_MAX_ITERATIONS),
        )

    def align(self, points: np.ndarray, viewpoint: np.ndarray | None = None) -> dict:
        """Recognise the scene and estimate the pose ``scene = R @ model + t``.

        ``viewpoint``: the depth camera's position for a single-view cloud (normals are then
        oriented toward it); None for a full cloud.
        """
        points = np.asarray(points, dtype=np.float64)
        o3d.utility.random.seed(SEED)
        scenes = {}  # the scene prepared once per voxel size
        best = None  # (fitness, -rmse, name, scene-to-model transform)
        for name, voxel in self.voxels.items():
            if voxel not in scenes:
                scenes[voxel] = _prepare(points, voxel, viewpoint)
            result = self._register(name, scenes[voxel], voxel)
            key = (result.fitness, -result.inlier_rmse)
            if best is None or key > best[:2]:
                best = (*key, name, np.asarray(result.transformation))
        fitness, negative_rmse, name, scene_to_model = best
        model_to_scene = np.linalg.inv(scene_to_model)
        return {
            "label": name,
            "rotation": model_to_scene[:3, :3].copy(),
            "translation": model_to_scene[:3, 3].copy(),
            "score": float(fitness),
            "inlier_rmse": float(-negative_rmse),
        }


# --- whole frames: several instances of one part ---------------------------------------------

FRAME_VOXEL_MIN = 0.004  # a frame's voxel: the reference's, but no finer than a VGA pixel at 1 m
PLANE_DISTANCE_VOXELS = 1.5  # a support plane: points within this of it (RANSAC, Open3D)
PLANE_SHARE = 0.1  # ... set aside while it holds this share of the frame's points ...
PLANE_MAX = 3  # ... at most this many (the table, the floor, a bin's floor)
EXPLAINED_VOXELS = 2.0  # a found instance takes out the frame's points this near it
MIN_FRAME_POINTS = 30


def _thin_frame(points: np.ndarray, voxel: float) -> np.ndarray:
    """The frame thinned to ``voxel``, its large planes set aside."""
    scene = _cloud(points).voxel_down_sample(voxel)
    total = len(scene.points)
    for _ in range(PLANE_MAX):
        if len(scene.points) < MIN_FRAME_POINTS:
            break
        o3d.utility.random.seed(SEED)
        _, inliers = scene.segment_plane(PLANE_DISTANCE_VOXELS * voxel, 3, 1000)
        if len(inliers) < PLANE_SHARE * total:
            break
        scene = scene.select_by_index(inliers, invert=True)
    return np.asarray(scene.points)


def locate_instances(
    frame_points: np.ndarray,
    reference_points: np.ndarray,
    count: int,
    viewpoint: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses ``scene = R @ model + t`` of up to ``count`` instances of one reference in a whole
    frame: the frame thinned to the reference's voxel (``FRAME_VOXEL_MIN`` at least) and its
    large planes set aside, its FPFH computed once; then per instance RANSAC on FPFH matches
    (the reference onto what is left of the frame) and point-to-plane ICP, and the frame's
    points the placed reference explains taken out before the next instance."""
    from scipy.spatial import cKDTree

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    registration = o3d.pipelines.registration
    reference = np.asarray(reference_points, dtype=np.float64)
    scale = float(np.linalg.norm(reference - reference.mean(axis=0), axis=1).max())
    voxel = max(VOXEL_SCALES * scale, FRAME_VOXEL_MIN)
    _, ref_down, ref_feature = _prepare(reference, voxel)
    ref_full = _cloud(reference)
    scene = _thin_frame(frame_points, voxel)
    if len(scene) < MIN_FRAME_POINTS:
        return []
    cloud, _, _ = _prepare(scene, voxel, viewpoint)  # the thinned frame with its normals
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        cloud,
        o3d.geometry.KDTreeSearchParamHybrid(
            radius=FEATURE_RADIUS_VOXELS * voxel, max_nn=FEATURE_MAX_NN
        ),
    )
    features = np.asarray(feature.data)
    left = np.arange(len(scene))
    distance = RANSAC_DISTANCE_VOXELS * voxel
    poses = []
    for _ in range(count):
        if len(left) < MIN_FRAME_POINTS:
            break
        o3d.utility.random.seed(SEED)
        target = cloud.select_by_index(left.tolist())
        target_feature = registration.Feature()
        target_feature.data = features[:, left]
        coarse = registration.registration_ransac_based_on_feature_matching(
            ref_down,
            target,
            ref_feature,
            target_feature,
            True,  # mutual filter
            distance,
            registration.TransformationEstimationPointToPoint(False),
            RANSAC_N,
            [
                registration.CorrespondenceCheckerBasedOnEdgeLength(RANSAC_EDGE_LENGTH),
                registration.CorrespondenceCheckerBasedOnDistance(distance),
            ],
            registration.RANSACConvergenceCriteria(RANSAC_MAX_ITERATIONS, RANSAC_CONFIDENCE),
        )
        fine = registration.registration_icp(
            ref_full,
            target,
            ICP_DISTANCE_VOXELS * voxel,
            coarse.transformation,
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=ICP_MAX_ITERATIONS),
        )
        pose = np.asarray(fine.transformation)
        poses.append((pose[:3, :3].copy(), pose[:3, 3].copy()))
        placed = reference @ pose[:3, :3].T + pose[:3, 3]
        near, _ = cKDTree(placed).query(scene[left], distance_upper_bound=EXPLAINED_VOXELS * voxel)
        left = left[~np.isfinite(near)]
    return poses
