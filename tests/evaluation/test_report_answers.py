"""The report on answers to act on, from records whose figures are known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluation.report_answers import (
    answer_targets,
    answers_report,
    calibration,
    plot_reliability,
    readme_lines,
    step_latency,
    symmetric_rows,
    verdict_rows,
)


def record(family: str, right: bool, accepted: bool, **extra) -> dict:
    """One engine answer on the full gallery, right (label and ADD-S 0.01) or wrong."""
    base = {
        "study": "full-gallery",
        "system": "engine",
        "family": family,
        "set": "unseen",
        "view": "full",
        "label_ok": right,
        "add_s": 0.01 if right else 0.5,
        "rot_err_deg": 1.0,
        "align_err": 0.03,
        "align_err_floor": 0.03,
        "latency_ms": 10.0,
        "accepted": accepted,
        "success": right,
        "outcome_ok": right and accepted,
        "confidence": None,
        "timings_ms": {},
    }
    return base | extra


def turned(degrees: float) -> list:
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix().tolist()


def test_verdicts_per_family_view_and_set():
    records = [
        record("so3", True, True),
        record("so3", False, True),
        record("junk", False, False, set="junk", outcome_ok=True),
        record("junk", False, True, set="junk"),
        record("foreign", False, True, view="sensor"),
        record("so3", True, True, system="ppf"),  # not the full gallery's engine: left out
    ]
    rows = {(r["family"], r["view"], r["set"]): r for r in verdict_rows(records)}
    assert set(rows) == {("so3", "full", "unseen"), ("junk", "full", "junk"),
                         ("foreign", "sensor", "unseen")}  # fmt: skip
    assert rows[("so3", "full", "unseen")]["precision_accepted"] == pytest.approx(0.5)
    assert rows[("junk", "full", "junk")]["false_accepts"] == pytest.approx(0.5)
    assert rows[("junk", "full", "junk")]["outcome_ok"] == pytest.approx(0.5)
    assert rows[("foreign", "sensor", "unseen")]["coverage"] == 1.0


def test_symmetric_spread_per_group_and_step_latency():
    records = [
        record("symmetric", True, True, group="can/0/full", rotation=turned(a)) for a in (0, 1, 3)
    ] + [
        record("symmetric", True, a != 90, group="can/0/sensor", rotation=turned(a))
        for a in (0, 2, 90)
    ]
    rows = symmetric_rows(records)
    spreads = {r["group"]: r["spread_deg"] for r in rows}
    assert spreads == pytest.approx({"can/0/full": 3.0, "can/0/sensor": 90.0})
    matches = {r["group"]: r["spread_match_deg"] for r in rows}  # the refused 90° left out
    assert matches == pytest.approx({"can/0/full": 3.0, "can/0/sensor": 2.0})
    (target,) = [t for t in answer_targets(records, rows) if t["target"].startswith("symmetric")]
    assert target["figure"] == (
        '0 of 2 groups within; largest spread 90.0° (1 of 2 groups within among "match" answers)'
    )
    timed = [record("sensor", True, True, timings_ms={"map": m, "total": 2 * m}) for m in (1, 3, 8)]
    steps = {r["step"]: r for r in step_latency(timed)}
    assert list(steps) == ["map", "total"]
    assert steps["map"]["median"] == 3.0 and steps["total"]["median"] == 6.0


def test_calibration_pools_and_the_reliability_diagram(tmp_path: Path):
    rng = np.random.default_rng(0)
    confidence = rng.random(400)
    right = rng.random(400) < confidence  # calibrated by construction
    records = [
        record("so3", bool(r), True, confidence=float(c), set="seen" if i % 2 else "unseen")
        for i, (c, r) in enumerate(zip(confidence, right, strict=True))
    ]
    pools = calibration(records)
    assert pools["all"]["cases"] == 400 and pools["all"]["with_confidence"] == 400
    assert pools["all"]["ece"] < 0.08 and pools["all"]["auroc"] > 0.75
    assert pools["seen"]["cases"] == 200
    plot_reliability(pools, tmp_path / "reliability.png")
    assert (tmp_path / "reliability.png").stat().st_size > 1000
    plot_reliability(calibration([record("so3", True, True)]), tmp_path / "none.png")
    assert (tmp_path / "none.png").stat().st_size > 1000  # says that no confidence was given


def test_targets_say_met_or_missed():
    records = [record("sensor", True, True, set=s) for s in ("seen", "unseen")]
    records += [record("junk", False, True, set="junk"), record("junk", False, False, set="junk")]
    symmetric = [{"system": "engine", "spread_deg": 1.5}]
    rows = {row["target"]: row for row in answer_targets(records, symmetric)}
    assert rows["sensor, with viewpoint: success ≥ 90%"]["met"]
    assert (
        rows["sensor, with viewpoint: success ≥ 90%"]["figure"] == "seen 100.0 % / unseen 100.0 %"
    )
    assert not rows["false accepts on junk ≤ 0%"]["met"]
    assert rows["false accepts on junk ≤ 0%"]["figure"] == "50.0 %"
    assert rows["symmetric: answered rotations within 2° of each other"]["met"]
    assert not rows["sensor, without viewpoint: success ≥ 85%"]["met"]  # no such answers
    lines = "\n".join(readme_lines(answers_report(records)))
    assert "| 16 | false accepts on junk ≤ 0% | 50.0 % | MISSED |" in lines


ROTATION = (
    "so3/noisy/paper-poses: rotation error < 2° for ≥ 95% of the answers on parts without a"
    " symmetry"
)


def test_precise_pose_targets_leave_out_the_parts_an_answer_showed_symmetric():
    records = [
        record("so3", True, True, object="bracket", set=s, add_s=0.003, rot_err_deg=0.5)
        for s in ("seen", "unseen")
    ]
    # a gear answered a tooth away: its ADD-S is tiny, its rotation error large
    records += [record("so3", True, True, object="gear", add_s=0.006, rot_err_deg=36.0)]
    rows = {row["target"]: row for row in answer_targets(records, [])}
    rotation = rows[ROTATION]
    assert rotation["met"] and rotation["figure"].startswith("seen 100.0 % / unseen 100.0 %")
    assert "1 parts left out as symmetric" in rotation["figure"] and "gear" in rotation["figure"]
    assert rows["so3: precise ≥ 95%"]["met"]  # so3: every answer under 0.02
    records += [record("so3", True, True, object="bracket", add_s=0.03, rot_err_deg=9.0)] * 2
    rows = {row["target"]: row for row in answer_targets(records, [])}
    rotation = rows[ROTATION]
    assert not rotation["met"] and not rows["so3: precise ≥ 95%"]["met"]
