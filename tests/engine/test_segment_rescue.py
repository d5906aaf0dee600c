"""How many parts a frame's segment is tried against before its ask gives up
(``SEGMENT_RESCUED``; docs/decisions.md#more-parts-tried-for-a-segment)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.engine.tuning import SEGMENT_RESCUED
from tests.servers import needs_model

pytest.importorskip("pybullet")
frames = pytest.importorskip("evaluation.frames")

SEGMENT = Path(__file__).parents[1] / "data" / "segments" / "duck-side.npy"
# the parts the report's search compared with that segment, at the report's sizes
PARTS = [
    "tray", "a1-trunk", "shape-sorter", "kuka-link-6", "franka-link-3", "franka-link-6",
    "kuka-link-5", "xarm-link-3", "xarm-link-2", "xarm-base", "mini-cheetah-body", "duck",
    "kuka-link-1",
]  # fmt: skip


@needs_model
def test_a_segment_is_tried_against_more_parts_than_a_lone_cloud():
    """The duck seen from one side, 0.85 of its radius: the network's grid ranks it low, and
    the four parts a lone cloud rescues do not reach it (the tray's pose fits 0.88 of the
    points); a frame's segment tries ``SEGMENT_RESCUED``, and the duck fits all of them."""
    from evaluation.calibrate_detect import gallery_engine

    registered, _ = frames.manifest_parts(registered=PARTS, foreign=[])
    engine = gallery_engine(registered)
    points = np.load(SEGMENT).astype(np.float64)
    ask = {"viewpoint": np.zeros(3), "surroundings": False, "noise": 6.5e-4}
    lone = engine.align(points, **ask)
    segment = engine.align(points, **ask, rescued=SEGMENT_RESCUED)
    assert lone.label != "duck"
    assert segment.label == "duck" and segment.fit > 0.95
    assert segment.fit * segment.coverage > lone.fit * lone.coverage
