"""Point Pair Features (Drost et al. 2010), the paper's baseline, with OpenCV's detector.

One ``cv2.ppf_match_3d_PPF3DDetector`` per reference, trained on the reference with normals;
a query runs every detector on the scene, refines each one's best-voted poses with OpenCV's
ICP (as OpenCV's ``ppf_load_match`` sample does) and labels the scene with the reference
whose best pose got the most votes. Needs ``opencv-contrib-python-headless``.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from evaluation.baselines import orient_normals
from service.engine.alignment import to_model_frame

# Settings, tuned on 9 pybullet meshes (2,048-point references, resampled 2,048-point
# cases, 27 per family): recognition / success 1.00 / 1.00 on so3, 1.00 / 1.00 on noisy,
# 1.00 / 0.81 on partial (normals toward the camera), 2-3 s per query against the 9
# references on a loaded 2-core machine. A model sampling step of 0.05 (OpenCV's sample uses
# 0.025) cost ~15 s of training and ~4 s of matching per reference without a gain in
# recognition; a scene step of 0.2 (every 5th point votes) lost 11 points of so3 success.
# Labelling by the votes beat labelling by the inlier share (0.89) or by ICP's residual (0.30).
MODEL_SAMPLING_STEP = 0.1  # relativeSamplingStep: model subsampling, share of its diameter
DISTANCE_STEP = 0.05  # relativeDistanceStep: the point-pair distance quantum, share of diameter
NUM_ANGLES = 30  # numAngles: quantisation of the feature angles and of the voting angle
SCENE_SAMPLE_STEP = 0.5  # relativeSceneSampleStep: every 2nd subsampled scene point votes
SCENE_DISTANCE = MODEL_SAMPLING_STEP  # relativeSceneDistance: scene subsampling as the model's
POSES_TO_REFINE = 5  # the best-voted poses of each detector that ICP refines
ICP_ITERATIONS = 100  # cv2.ppf_match_3d_ICP(iterations, tolerance, rejectionScale, numLevels)
ICP_TOLERANCE = 0.005
ICP_REJECTION_SCALE = 2.5
ICP_LEVELS = 8
NORMAL_NEIGHBOURS = 10  # k of the plane fit in cv2.ppf_match_3d.computeNormalsPC3d
INLIER_SCALES = 0.05  # pose choice: a scene point is explained within this share of the scale


def with_normals(points: np.ndarray, viewpoint: np.ndarray | None = None) -> np.ndarray:
    """(N, 6) float32: the points and their oriented plane-fit normals, OpenCV's layout."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    _, cloud = cv2.ppf_match_3d.computeNormalsPC3d(points, NORMAL_NEIGHBOURS, False, (0, 0, 0))
    normals = orient_normals(points, cloud[:, 3:6], viewpoint)
    return np.hstack([points, normals]).astype(np.float32)


class PPFRecognizer:
    """One PPF detector per reference; the label is the reference with the most votes."""

    def __init__(self, references: dict[str, np.ndarray]):
        if not references:
            raise ValueError("PPFRecognizer needs at least one reference")
        self.references = {n: np.asarray(p, dtype=np.float64) for n, p in references.items()}
        self.scales = {
            n: float(np.linalg.norm(p - p.mean(axis=0), axis=1).max())
            for n, p in self.references.items()
        }
        self.trees = {n: cKDTree(p) for n, p in self.references.items()}
        self.models: dict[str, np.ndarray] = {}
        self.detectors = {}
        for name, points in self.references.items():
            model = with_normals(points)
            detector = cv2.ppf_match_3d_PPF3DDetector(
                MODEL_SAMPLING_STEP, DISTANCE_STEP, NUM_ANGLES
            )
            detector.trainModel(model)
            self.models[name] = model
            self.detectors[name] = detector
        self.icp = cv2.ppf_match_3d_ICP(
            ICP_ITERATIONS, ICP_TOLERANCE, ICP_REJECTION_SCALE, ICP_LEVELS
        )

    def _inlier_share(self, name: str, scene: np.ndarray, pose: np.ndarray) -> float:
        """Share of scene points within INLIER_SCALES × scale of the reference at ``pose``."""
        model_frame = to_model_frame(scene, pose[:3, :3], pose[:3, 3])
        distances, _ = self.trees[name].query(model_frame, k=1)
        return float((distances < INLIER_SCALES * self.scales[name]).mean())

    def align(self, points: np.ndarray, viewpoint: np.ndarray | None = None) -> dict:
        """Recognise the scene and estimate the pose ``scene = R @ model + t``.

        ``viewpoint``: the depth camera's position for a single-view cloud (normals are then
        oriented toward it, as a sensor's are); None for a full cloud.
        """
        scene_points = np.asarray(points, dtype=np.float64)
        scene = with_normals(scene_points, viewpoint)
        best = None  # (votes, inlier share, name, pose)
        for name, detector in self.detectors.items():
            poses = detector.match(scene, SCENE_SAMPLE_STEP, SCENE_DISTANCE)[:POSES_TO_REFINE]
            if not poses:
                continue
            votes = max(pose.numVotes for pose in poses)  # ranked before refinement
            _, poses = self.icp.registerModelToScene(self.models[name], scene, poses)
            # Within a reference, keep the refined pose that explains most of the scene.
            share, pose = max(
                ((self._inlier_share(name, scene_points, p.pose), p.pose) for p in poses),
                key=lambda item: item[0],
            )
            if best is None or (votes, share) > (best[0], best[1]):
                best = (votes, share, name, np.asarray(pose, dtype=np.float64))
        if best is None:
            raise RuntimeError("no detector found a pose in the scene")
        votes, share, name, pose = best
        return {
            "label": name,
            "rotation": pose[:3, :3].copy(),
            "translation": pose[:3, 3].copy(),
            "score": float(votes),
            "inlier_share": share,
        }
