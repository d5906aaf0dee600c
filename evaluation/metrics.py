"""The metrics of shared/EVALUATION.md, for one case at a time and summed over many.

Poses follow ``scene_point = R @ model_point + t`` everywhere.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import pdist

from service.engine.alignment import alignment_error

SUCCESS_ADD_S = 0.10  # success: right label and ADD-S below this share of the diameter
PRECISE_ADD_S = 0.02  # precise: right label and ADD-S below this


def geodesic_deg(rotation_estimated: np.ndarray, rotation_true: np.ndarray) -> float:
    """The angle of the rotation that takes one rotation to the other, in degrees (0 to 180)."""
    relative = np.asarray(rotation_estimated, np.float64) @ np.asarray(rotation_true, np.float64).T
    cosine = (np.trace(relative) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def diameter(points: np.ndarray) -> float:
    """The largest distance between two points (over the convex hull's vertices, for speed)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return 0.0
    try:
        points = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # flat or degenerate clouds: every pair
        pass
    return float(pdist(points).max())


def place(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    return np.asarray(points, np.float64) @ np.asarray(rotation, np.float64).T + np.asarray(
        translation, np.float64
    )


def add_s(
    model_points: np.ndarray,
    rotation_estimated: np.ndarray,
    translation_estimated: np.ndarray,
    rotation_true: np.ndarray,
    translation_true: np.ndarray,
    object_diameter: float,
) -> float:
    """ADD-S over the diameter: mean distance from each model point at the estimated pose to
    the nearest model point at the true pose, divided by ``object_diameter``.

    Symmetry-aware: a pose that differs from the truth by a symmetry of the model scores 0.
    """
    estimated = place(model_points, rotation_estimated, translation_estimated)
    true = place(model_points, rotation_true, translation_true)
    distances, _ = cKDTree(true).query(estimated, k=1)
    return float(distances.mean() / object_diameter)


def alignment_error_normalized(
    scene_points: np.ndarray,
    reference_points: np.ndarray,
    rotation: np.ndarray,
    translation: np.ndarray,
    scale: float,
) -> float:
    """The paper's alignment error (Fig. 6) over the scale: mean distance from each observed
    point to the nearest reference point placed at the pose, divided by the reference's radius.
    The service's own ``service.engine.alignment.alignment_error``, so both measure alike.
    """
    reference_tree = cKDTree(np.asarray(reference_points, np.float64))
    scene = np.asarray(scene_points, np.float64)
    rotation = np.asarray(rotation, np.float64)
    translation = np.asarray(translation, np.float64)
    return alignment_error(scene, reference_tree, rotation, translation) / scale


def alignment_floor(
    case_points_in_model_frame: np.ndarray, reference_points: np.ndarray, scale: float
) -> float:
    """The alignment error at the true pose: the floor that resampling (and noise) set.

    ``case_points_in_model_frame`` is the case's cloud moved back by the true pose,
    ``R.T @ (p - t)``.
    """
    return alignment_error_normalized(
        case_points_in_model_frame, reference_points, np.eye(3), np.zeros(3), scale
    )


def _median(values: list[float]) -> float:
    finite = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(finite)) if finite else float("nan")


def summarize(records: Iterable[dict]) -> dict:
    """Sum per-case results into the figures of a report row.

    Each record holds ``label_ok`` (bool), ``add_s``, ``rot_err_deg``, ``align_err``,
    ``align_err_floor`` and ``latency_ms``; a metric that is None or NaN (no pose answered)
    counts as a failure for success and precise and is left out of the medians.
    """
    records = list(records)
    n = len(records)
    if n == 0:
        return {"cases": 0}

    def column(key: str) -> list[float]:
        return [np.nan if r.get(key) is None else float(r[key]) for r in records]

    label_ok = np.array([bool(r["label_ok"]) for r in records])
    add_s_values = np.array(column("add_s"))
    with np.errstate(invalid="ignore"):
        success = label_ok & (add_s_values < SUCCESS_ADD_S)
        precise = label_ok & (add_s_values < PRECISE_ADD_S)
    latency = [v for v in column("latency_ms") if np.isfinite(v)]
    return {
        "cases": n,
        "accuracy": float(label_ok.mean()),
        "success": float(success.mean()),
        "precise": float(precise.mean()),
        "median_rot_err_deg": _median(column("rot_err_deg")),
        "median_add_s": _median(column("add_s")),
        "median_align_err": _median(column("align_err")),
        "median_align_err_floor": _median(column("align_err_floor")),
        "latency_ms_median": float(np.median(latency)) if latency else float("nan"),
        "latency_ms_p95": float(np.percentile(latency, 95)) if latency else float("nan"),
    }
