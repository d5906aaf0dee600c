"""``benchmarks/symmetric.py``: the symmetric family on more draws, and why a group misses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("pybullet_data")

from benchmarks import symmetric  # noqa: E402
from service.engine.symmetry import Symmetry  # noqa: E402

QUARTER_TURNS = Symmetry(
    "discrete",
    np.zeros(3),
    Rotation.from_rotvec(np.outer(np.arange(4) * np.pi / 2, [0.0, 0.0, 1.0])).as_matrix(),
)  # a square brick's symmetry about z


def answer(degrees: float, axis=(0.0, 0.0, 1.0), right: bool = True) -> dict:
    turn = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis)).as_matrix()
    return {"rotation": turn, "right": right, "match": True}


def test_two_answers_apart_are_told_by_what_parts_them():
    same = answer(0.0)
    # one pose, given as two representatives of the part's symmetry
    assert symmetric.cause(same, answer(91.0), QUARTER_TURNS) == "representative"
    # another turn of the part that its symmetry does not make the same pose
    assert symmetric.cause(same, answer(45.0), QUARTER_TURNS) == "near-turn"
    # a few degrees apart at the same turn
    assert symmetric.cause(same, answer(3.0, (1.0, 0.0, 0.0)), QUARTER_TURNS) == "refinement"
    # an answer of another part, or far from the truth
    assert symmetric.cause(same, answer(3.0, right=False), QUARTER_TURNS) == "wrong"


@pytest.mark.slow
def test_one_draw_of_every_symmetric_part_is_answered_and_summed(tmp_path):
    out = tmp_path / "symmetric.json"
    summary = symmetric.main(["--seeds", "0", "--groups", "1", "--json", str(out)])
    written = json.loads(out.read_text())
    assert written["summary"] == summary
    groups = written["groups"]
    # each part once as full clouds and once as one camera's views
    assert len(groups) == summary["groups"] == 2 * len(symmetric.SYMMETRIC_PARTS)
    missed = [g for g in groups if g["spread_deg"] > symmetric.WITHIN_DEG]
    assert summary["within"] == len(groups) - len(missed)
    assert all(g["cause"] is not None for g in missed)
    assert all(g["cause"] is None for g in groups if g not in missed)
    assert 0 <= summary["flagged"] <= len(missed)
    # each answer of the right part measured against the truth, up to the symmetry
    assert all(len(g["truth_deg"]) >= 2 for g in groups)
    angles = [a for g in groups for a in g["truth_deg"] if a is not None]
    assert angles and all(0.0 <= a <= 180.0 for a in angles)
    full = summary["truth_deg"]["full"]
    assert full[0] <= full[1] and 0.0 <= full[2] <= 1.0
    # full clouds of the symmetric parts are answered as one pose (every draw measured so far)
    assert all(g["spread_deg"] <= symmetric.WITHIN_DEG for g in groups if "/full" in g["group"])
