"""More of a part's own poses refined where the camera sees through its answer
(``Search.refine_apart``; docs/decisions.md#seen-through-searched-again)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.engine.tuning import APART_REFINED
from tests.servers import needs_model

pytest.importorskip("pybullet")
frames = pytest.importorskip("evaluation.frames")

SEGMENT = Path(__file__).parents[1] / "data" / "segments" / "kuka-link-6-end.npz"


def degrees_off(rotation: np.ndarray, truth: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(truth.T @ rotation).magnitude()))


@needs_model
def test_a_link_whose_ends_look_alike_is_posed_by_more_of_its_own_poses_refined():
    """A kuka-link-6 seen in a bin: its two ends look alike before refinement, so the two
    poses the search refines of it land 95 degrees off, fitting 0.79 of the points. With
    ``APART_REFINED`` more of its hypotheses refined, each well apart from those, the true
    pose is among them and fits every point."""
    from evaluation.calibrate_detect import gallery_engine

    parts, _ = frames.manifest_parts(
        registered=["kuka-link-6", "franka-link-6", "toy-cylinder"], foreign=[]
    )
    engine = gallery_engine(parts)
    segment = np.load(SEGMENT)
    points, truth = segment["points"].astype(np.float64), segment["rotation"]
    ask = {"viewpoint": np.zeros(3), "surroundings": False}
    plain = engine.align(points, **ask)
    apart = engine.align(points, **ask, apart=APART_REFINED)
    assert plain.label == "kuka-link-6" and degrees_off(plain.rotation, truth) > 45
    assert plain.verdict != "match"
    assert apart.label == "kuka-link-6" and degrees_off(apart.rotation, truth) < 2
    assert apart.verdict == "match" and apart.fit > 0.95
