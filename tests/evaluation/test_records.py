"""One answer's record: right poses accepted, refusals where no registered part is, units."""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.cases import make_cases, object_scale
from evaluation.metrics import diameter, summarize
from evaluation.records import NO_ANSWER, Answer, Truth, case_record
from service.engine.sampling import sample_surface
from tests.meshes import pybullet_mesh

pytest.importorskip("open3d", exc_type=ImportError)  # sensor views: its wheel needs libusb


@pytest.fixture(scope="module")
def world():
    """The duck registered, the mug kept out of the gallery (its truth known all the same)."""
    meshes = {"duck": pybullet_mesh("duck.obj"), "mug": pybullet_mesh("objects/mug.obj")}
    truths = {}
    for name, mesh in meshes.items():
        points = sample_surface(mesh, 2048, 0).astype(np.float64)
        split = "seen" if name == "duck" else "unseen"
        truths[name] = Truth(points, object_scale(points), diameter(points), split)
    scales = {name: truth.scale for name, truth in truths.items()}
    return meshes, truths, scales


def oracle(case) -> Answer:
    return Answer(case.object_name, case.rotation, case.translation, confidence=1.0)


def test_an_oracle_is_right_on_views_millimetres_tables_and_symmetric_parts(world):
    meshes, truths, scales = world
    duck = {"duck": meshes["duck"]}
    cases = []
    for family in ("sensor", "units", "table"):
        cases += make_cases(family, duck, scales, 512, seed=2, poses_per_object=1)
    cases += make_cases("symmetric", duck, scales, 512, 2, 1, orders={"duck": 2})
    records = [case_record(case, truths, oracle(case), 5.0, True) for case in cases]
    for record in records:
        assert record["success"] and record["outcome_ok"] and record["accepted"]
        assert record["add_s"] < 1e-6 and record["viewpoint_given"]
        assert record["align_err"] == pytest.approx(record["align_err_floor"], abs=1e-9)
    summary = summarize(records)
    assert summary["coverage"] == summary["precision_accepted"] == summary["outcome_ok"] == 1.0
    assert summary["false_accepts"] == 0.0 and summary["confidence_given"] == 1.0
    # a millimetre cloud answered with the translation in metres is a wrong pose
    units = next(c for c in cases if c.family == "units")
    metres = Answer("duck", units.rotation, units.translation / 1000)
    record = case_record(units, truths, metres, 5.0)
    assert record["add_s"] > 0.1 and not record["outcome_ok"]
    assert record["accepted"] and not record["success"]  # a false accept


def test_refusals_are_right_where_no_registered_part_is(world):
    meshes, truths, scales = world
    foreign = make_cases("foreign", {"mug": meshes["mug"]}, scales, 512, 2, 1)
    junk = make_cases("junk", {}, {"duck": scales["duck"]}, 512, 2, 1)
    refuse = Answer("duck", np.eye(3), np.zeros(3), verdict="no_match", confidence=0.1)
    accept = Answer("duck", np.eye(3), np.zeros(3), verdict="match", confidence=0.9)
    unsure = Answer("duck", np.eye(3), np.zeros(3), verdict="uncertain", confidence=0.5)
    refused = [case_record(c, truths, refuse, 5.0) for c in foreign + junk]
    accepted = [case_record(c, truths, accept, 5.0) for c in foreign + junk]
    assert all(r["outcome_ok"] and not r["accepted"] for r in refused)
    assert not any(r["outcome_ok"] or r["success"] for r in accepted)
    assert summarize(accepted)["false_accepts"] == 1.0
    assert summarize(refused)["false_accepts"] == 0.0
    assert np.isnan(summarize(refused)["precision_accepted"])  # nothing accepted
    unsure_record = case_record(junk[0], truths, unsure, 5.0)
    assert not unsure_record["accepted"] and not unsure_record["outcome_ok"]
    assert refused[0]["set"] == "unseen" and refused[-1]["set"] == "junk"
    assert refused[-1]["align_err_floor"] is None and refused[-1]["add_s"] is None
    nothing = case_record(junk[0], truths, NO_ANSWER, 5.0)
    assert nothing["verdict"] is None and not nothing["outcome_ok"]


def test_a_millimetre_cloud_may_be_refused_naming_the_units(world):
    meshes, truths, scales = world
    case = make_cases("units", {"duck": meshes["duck"]}, scales, 512, 2, 1)[0]
    named = Answer("duck", None, None, "no_match", reasons=["about 1,000 times too large"])
    vague = Answer("duck", None, None, "no_match", reasons=["no part fits"])
    assert case_record(case, truths, named, 5.0)["outcome_ok"]
    assert not case_record(case, truths, vague, 5.0)["outcome_ok"]
