"""The scene layer's own rules on the real engine: the global check among instances, the
duplicates it drops, and the search's deadline."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.engine.alignment import turned_about
from service.engine.answer import AlternativePose
from service.engine.confidence import Calibration
from service.engine.engine import Engine
from service.engine.frame import Frame
from service.engine.projection import DepthImage
from service.engine.sampling import sample_surface_faces
from service.engine.scene import (
    NOTHING_AROUND,
    Instance,
    Scan,
    around,
    evidence,
    seen_through,
    settle_claims,
)
from service.engine.segments import segments
from service.engine.supports import Noise, set_aside_supports
from service.engine.tuning import (
    CLAIM_TOLERANCE,
    MIN_SEGMENT,
    SEGMENT_POINTS,
    THIN_PER_SCALE,
    THROUGH_DOUBT,
)
from service.settings import Settings
from tests.engines import engine_holding, registered
from tests.frames import frame_of, resting, shoot, spin, table

SETTINGS = Settings()


@pytest.fixture(scope="module")
def engine() -> Engine:
    return engine_holding({"box": trimesh.creation.box((0.08, 0.06, 0.04))})


@pytest.fixture(scope="module")
def one_box(engine):
    box = engine.entry("box")
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    return box, shot


def test_a_passed_deadline_answers_what_was_found_and_says_so(engine, one_box):
    _, shot = one_box
    scene = engine.detect(frame_of(shot), deadline=time.monotonic() - 1.0)
    assert not scene.complete
    assert scene.detections == []
    assert any("time budget" in reason for reason in scene.reasons)
    found = engine.detect(frame_of(shot))
    assert found.complete and found.reasons == []
    assert [d.answer.label for d in found.detections] == ["box"]


def test_overlapping_claims_are_settled_point_by_point(engine, one_box):
    box, _ = one_box
    scene = engine.detect(frame_of(one_box[1]))
    answer = scene.detections[0].answer
    a = Instance(answer, box, np.arange(0, 100), np.full(100, 0.001))
    # b claims the last 60 of a's points, nearer to 40 of them, farther from 20
    b_distance = np.r_[np.full(40, 0.0005), np.full(20, 0.002)]
    b = Instance(replace(answer, label="other"), box, np.arange(40, 100), b_distance)
    settled = settle_claims([a, b], 100, keep_share=0.5)
    assert len(settled) == 2
    first, second = settled
    assert set(first.claimed) & set(second.claimed) == set()
    assert set(second.claimed) == set(range(40, 80))  # where it is nearer
    assert set(first.claimed) == set(range(0, 40)) | set(range(80, 100))
    # one whose claim another explains better nearly everywhere is dropped
    c = Instance(replace(answer, label="other"), box, np.arange(0, 100), np.full(100, 0.0005))
    kept = settle_claims(
        [Instance(answer, box, np.arange(0, 100), np.full(100, 0.001)), c], 100, 0.5
    )
    assert [i.answer.label for i in kept] == ["other"]


def test_one_part_found_twice_at_one_pose_is_one_instance(engine, one_box):
    box, _ = one_box
    answer = engine.detect(frame_of(one_box[1])).detections[0].answer
    twin = replace(answer, confidence=(answer.confidence or 0) - 0.1)
    a = Instance(answer, box, np.arange(0, 50), np.full(50, 0.001))
    b = Instance(twin, box, np.arange(50, 100), np.full(50, 0.001))
    kept = settle_claims([a, b], 100, keep_share=0.5)
    assert kept == [a]


def test_what_is_around_an_instance_is_what_no_instance_explains_within_reach():
    # a claimed square metre; beside it, points 5 and 15 cm beyond its edge, one 10 cm over
    # it, one 30 cm beyond, and one 10 cm beyond the other edge that another instance explains
    square = np.stack(np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 1, 11)), -1)
    claimed = np.c_[square.reshape(-1, 2), np.zeros(121)]
    beside = [[1.05, 0.5, 0], [1.15, 0.5, 0], [0.5, 0.5, 0.1], [1.3, 0.5, 0], [-0.1, 0.5, 0]]
    points = np.vstack([claimed, np.array(beside, dtype=float)])
    unexplained = np.ones(len(points), dtype=bool)
    unexplained[:121] = unexplained[-1] = False
    count, share = around(points[unexplained], claimed, reach=0.2)
    assert count == 3
    assert share == pytest.approx(np.log10(3 / 121 + 0.01))
    assert around(points[unexplained], claimed, reach=0.04) == (0, NOTHING_AROUND)


def test_what_no_part_explains_around_an_instance_lowers_its_confidence(engine):
    # a cube alone on the table has nothing around it (the table is set aside); 8 mm from a
    # box nobody registered, the box's points lie around it, as the rest of a larger part
    # lies around a registered one fitted on a piece of it, and the frame's settled judgement
    # is less sure of it; refused (a threshold of 1), it says so
    calibration = Calibration.load(SETTINGS.detect_confidence_path)
    settled = calibration.settled
    assert settled is not None
    calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, calibration)
    cube, box = trimesh.creation.box((0.03, 0.025, 0.02)), trimesh.creation.box((0.16, 0.12, 0.06))
    registered(calibrated, {"cube": cube})
    found = {}
    for beside in (False, True):
        placed = [(cube, *resting(cube, spin(20), 0.0, 0.0))]
        if beside:
            placed.append((box, *resting(box, spin(0), -0.103, 0.0)))
        frame = frame_of(shoot(placed, table()))
        (detection,) = calibrated.detect(frame, min_confidence=1.0).detections
        assert detection.answer.label == "cube"
        assert detection.answer.confidence == pytest.approx(settled.confidence(detection.evidence))
        found[beside] = detection
    said = {beside: found[beside].evidence for beside in found}
    assert said[False]["around"] == NOTHING_AROUND
    assert said[True]["around"] > -1.0  # over a tenth as many points as it claims
    alone = {**said[True], "around": NOTHING_AROUND}
    assert settled.confidence(said[True]) < settled.confidence(alone)
    about = [r for d in found.values() for r in d.answer.reasons if "no part explains" in r]
    assert len(about) == 1 and about[0] in found[True].answer.reasons


def test_what_is_around_an_instance_is_said_once_however_often_it_is_judged(engine, one_box):
    # an instance judged again (a part found several times once the frame is settled) says
    # what is around it once, as measured last
    box, shot = one_box
    answer = engine.detect(frame_of(shot)).detections[0].answer
    doubted = replace(answer, verdict="uncertain", reasons=["the confidence is low"])
    instance = Instance(doubted, box, np.arange(100), evidence={"around": np.log10(0.51)})
    Scan.say_around(instance)
    instance.evidence["around"] = np.log10(0.31)
    Scan.say_around(instance)
    about = [r for r in instance.answer.reasons if "no part explains" in r]
    assert len(about) == 1 and about[0].startswith("30 of the frame's points")
    assert instance.answer.reasons[0] == "the confidence is low"


def one_fit(**changes) -> Calibration:
    """The shipped detections' calibration with ``changes``, judging every instance alone (its
    fit on the instances that may be a match set aside) and once (its settled fit, too, unless
    ``changes`` give one)."""
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    return replace(shipped, **{"eligible": None, "eligible_at": {}, "settled": None, **changes})


def test_a_part_seen_by_too_few_points_is_not_a_match(engine):
    # with the detections' calibration, a box 3.5 m away (about 110 points) is refused as
    # too small to tell from a look-alike, whatever its confidence; 2 m away it is a match
    calibrated = Engine(
        engine.mapper,
        SETTINGS.engine,
        engine.calibration,
        Calibration.load(SETTINGS.detect_confidence_path),
    )
    calibrated.load([engine.entry("box").reference])
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    verdicts = {}
    for distance in (2.0, 3.5):
        shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table(), distance=distance)
        found = calibrated.detect(frame_of(shot), min_confidence=0.0).detections
        assert [d.answer.label for d in found] == ["box"]
        verdicts[distance] = found[0].answer
    assert verdicts[2.0].verdict == "match"
    far = verdicts[3.5]
    assert far.verdict == "uncertain"
    assert any("a match needs" in reason for reason in far.reasons)


def test_a_frame_told_its_candidates_is_judged_by_the_told_calibration(engine, tmp_path):
    # the shipped detections' calibration, with a told one beside it that doubts everything
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    doubting = one_fit(bias=-50.0, about={"note": "refuses every instance"})
    path = tmp_path / "detect_confidence.json"
    replace(shipped, told=doubting).save(path)
    loaded = Calibration.load(path)
    assert loaded.told is not None and loaded.told.bias == -50.0
    assert loaded.bias == shipped.bias  # the untold one is kept as it was
    calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, loaded)
    box = engine.entry("box").reference
    other = trimesh.creation.box((0.2, 0.02, 0.02))
    points, faces = sample_surface_faces(other, 2048, 0)
    calibrated.load([box, engine.make_reference("rod", points, mesh=other, face_index=faces)])
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    frame = frame_of(shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table()))
    untold = calibrated.detect(frame).detections
    assert [(d.answer.label, d.answer.verdict) for d in untold] == [("box", "match")]
    told = calibrated.detect(frame, candidates=["box"], floor=0.0).detections
    assert [d.answer.label for d in told] == ["box"]
    assert told[0].answer.verdict == "no_match"  # judged by the told calibration
    everyone = calibrated.detect(frame, candidates=["box", "rod"]).detections
    assert [d.answer.verdict for d in everyone] == ["match"]  # naming them all is not told


def test_an_instance_that_may_match_is_judged_by_the_calibration_fitted_on_those(engine, tmp_path):
    # the shipped detections' calibration, with an eligible one beside it that doubts
    # everything: the box, which the chain is sure of on many points, is judged by it; told
    # that only a frame of 10^9 points may match, the box is judged by the one on every instance
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    doubting = one_fit(bias=-50.0)
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    frame = frame_of(shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table()))
    verdicts = {}
    for least in (2.0, 9.0):
        path = tmp_path / f"detect_confidence_{least}.json"
        floors = {"chain": 0.0, "points": least}
        replace(shipped, eligible=doubting, eligible_at=floors, settled=None).save(path)
        loaded = Calibration.load(path)
        assert loaded.eligible is not None and loaded.eligible_at == floors
        calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, loaded)
        calibrated.load([engine.entry("box").reference])
        found = calibrated.detect(frame, floor=0.0).detections
        assert [d.answer.label for d in found] == ["box"]
        verdicts[least] = (found[0].answer.verdict, found[0].answer.confidence)
    assert verdicts[2.0][0] == "no_match" and verdicts[2.0][1] < 0.01
    assert verdicts[9.0][0] == "match"


def test_a_match_needs_the_one_part_search_not_to_refuse_it(engine):
    # a frame calibration that trusts every instance: an unregistered cylinder, posed as the
    # only registered part (a box), is still refused, because the chain alone doubts it
    trusting = one_fit(bias=50.0)
    calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, trusting)
    calibrated.load([engine.entry("box").reference])
    can = trimesh.creation.cylinder(radius=0.035, height=0.07)
    frame = frame_of(shoot([(can, *resting(can, spin(10), 0.0, 0.0))], table()))
    found = [d.answer for d in calibrated.detect(frame, floor=0.0).detections]
    assert found and {a.label for a in found} == {"box"}
    for doubted in found:
        assert doubted.confidence > 0.99  # the frame's calibration alone would accept it
        assert doubted.verdict == "uncertain"
        assert any("one-part search alone" in reason for reason in doubted.reasons)
    box = trimesh.creation.box((0.08, 0.06, 0.04))
    frame = frame_of(shoot([(box, *resting(box, spin(25), 0.0, 0.0))], table()))
    assert [d.answer.verdict for d in calibrated.detect(frame).detections] == ["match"]


def counting(engine: Engine) -> list[np.ndarray]:
    """The clouds ``engine.align`` is asked about from now on (the real one answers)."""
    calls: list[np.ndarray] = []
    align = engine.align

    def counted(points, *args, **kwargs):
        calls.append(np.array(points))
        return align(points, *args, **kwargs)

    engine.align = counted
    return calls


def test_an_instance_the_frame_doubts_is_asked_about_once_more(engine, one_box):
    # a frame calibration that doubts every instance (uncertain, above the floor): the chain
    # is asked again about the points each claims; a match is asked once
    _, shot = one_box
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    for accept, asked in ((0.999, 2), (0.01, 1)):
        judged = one_fit(bias=0.0, weights=0 * shipped.weights, accept=accept)
        calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, judged)
        calibrated.load([engine.entry("box").reference])
        calls = counting(calibrated)
        found = calibrated.detect(frame_of(shot)).detections
        assert [d.answer.label for d in found] == ["box"]
        assert found[0].answer.confidence == pytest.approx(0.5)
        assert len(calls) == asked, calls


def test_a_segment_nothing_was_found_in_is_asked_about_from_another_sample(engine):
    # a frame calibration that finds every instance below the floor: the chain, asked about
    # a sample of the box's segment (close up, and thinned for a far smaller part: more
    # points than a sample), finds nothing it lists, and is asked once more about another
    # sample of the same points
    doubting = one_fit(bias=-50.0)
    calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, doubting)
    cube = trimesh.creation.box((0.02, 0.02, 0.02))
    points, faces = sample_surface_faces(cube, 2048, 0)
    small = engine.make_reference("cube", points, mesh=cube, face_index=faces)
    calibrated.load([engine.entry("box").reference, small])
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table(), distance=0.4)
    calls = counting(calibrated)
    assert calibrated.detect(frame_of(shot)).detections == []
    first, second = calls[:2]
    assert len(first) == len(second) == SEGMENT_POINTS
    together = np.unique(np.concatenate([first, second]), axis=0)
    assert SEGMENT_POINTS < len(together) < 2 * SEGMENT_POINTS  # one segment, two samples


def test_a_segment_nothing_was_found_in_is_asked_about_with_the_fragments_by_it(engine):
    # a box whose left edge a gap in depth (two columns of missing pixels) cuts off: a strip
    # too small to be searched alone, 4 % of the box's points. Nothing listed (a frame
    # calibration that doubts everything), the chain is asked once more about the box's
    # segment with the strip (docs/decisions.md#detect)
    doubting = one_fit(bias=-50.0)
    calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, doubting)
    calibrated.load([engine.entry("box").reference])
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table(), distance=1.2)
    rows, columns = np.nonzero(shot.shows == 0)
    cut = columns.min() + 2
    gap = (columns == cut) | (columns == cut + 1)
    shot.points[rows[gap], columns[gap]] = np.nan
    strip = shot.points[rows[columns < cut], columns[columns < cut]]
    assert 0 < len(strip) < MIN_SEGMENT
    calls = counting(calibrated)
    assert calibrated.detect(frame_of(shot)).detections == []
    strip = strip.astype(np.float64)

    def share_of_strip(asked: np.ndarray) -> float:
        return float(np.mean(cKDTree(asked).query(strip)[0] < 1e-6))

    assert max(share_of_strip(c) for c in calls) > 0.9, [len(c) for c in calls]


def test_a_part_found_several_times_is_looked_for_again_told_it_alone(engine):
    # two boxes and a ball nobody registered: the boxes are found, the ball's segment is not,
    # and it is asked about once more told the box alone (not the far larger drum). With one
    # box found, nothing is asked told the box alone (docs/decisions.md#detect)
    drum = trimesh.creation.cylinder(0.3, 0.2)
    points, faces = sample_surface_faces(drum, 2048, 0)
    told = Engine(engine.mapper, SETTINGS.engine, engine.calibration)
    other = engine.make_reference("drum", points, mesh=drum, face_index=faces)
    told.load([engine.entry("box").reference, other])
    box = trimesh.creation.box((0.08, 0.06, 0.04))
    ball = trimesh.creation.icosphere(3, 0.035)
    for boxes, asked_told in ((2, True), (1, False)):
        placed = [
            (box, *resting(box, spin(25 + 40 * k), 0.14 * k - 0.12, 0.08)) for k in range(boxes)
        ]
        shot = shoot([*placed, (ball, *resting(ball, spin(0), 0.05, -0.1))], table())
        candidates = asked_candidates(told)
        try:
            found = told.detect(frame_of(shot)).detections
        finally:
            del told.align
        assert [d.answer.label for d in found] == ["box"] * boxes
        assert (["box"] in candidates) is asked_told, candidates


def asked_candidates(engine: Engine) -> list[list[str]]:
    """The candidates ``engine.align`` is asked about from now on (``Scan.ask`` names them;
    the real one answers)."""
    asked: list[list[str]] = []
    align = engine.align

    def spied(points, *args, **kwargs):
        asked.append(list(args[0]))
        return align(points, *args, **kwargs)

    engine.align = spied
    return asked


@pytest.fixture(scope="module")
def box_and_cube(engine) -> tuple[Engine, dict[str, trimesh.Trimesh]]:
    """An engine judged by the shipped detections' calibration, holding a box 16 cm long and
    a cube of 3 cm; and their meshes, with a ball nobody registered."""
    meshes = {
        "box": trimesh.creation.box((0.16, 0.12, 0.06)),
        "cube": trimesh.creation.box((0.03, 0.025, 0.02)),
    }
    calibrated = Engine(
        engine.mapper,
        SETTINGS.engine,
        engine.calibration,
        Calibration.load(SETTINGS.detect_confidence_path),
    )
    return registered(calibrated, meshes), meshes | {"ball": trimesh.creation.icosphere(3, 0.02)}


def cube_beside_the_box(meshes, turn: float, distance: float):
    """The cube touching the box's end, the ball touching its other end."""
    box, cube, ball = meshes["box"], meshes["cube"], meshes["ball"]
    placed = [
        (box, *resting(box, spin(turn), 0.0, 0.0)),
        (cube, *resting(cube, spin(turn + 20), 0.095, 0.0)),
        (ball, *resting(ball, spin(0), -0.105, 0.02)),
    ]
    return shoot(placed, table(), distance=distance)


def cube_share(shot, detections) -> float:
    """The share of the cube's one "match" detection's points that show the cube."""
    (cube,) = [d for d in detections if d.answer.label == "cube" and d.answer.verdict == "match"]
    return float(np.mean(shot.shows.reshape(-1)[cube.indices] == 1))


def test_what_is_left_of_a_segment_is_searched_piece_by_piece(box_and_cube):
    # the box, the cube and the ball touch: one segment. Once the box is taken out, the cube
    # and the ball lie apart, and the cube is searched without the ball (together, the chain
    # found neither; docs/decisions.md#detect)
    engine, meshes = box_and_cube
    for turn, distance in ((0.0, 0.7), (20.0, 0.9)):
        shot = cube_beside_the_box(meshes, turn, distance)
        found = engine.detect(frame_of(shot)).detections
        matched = [d.answer.label for d in found if d.answer.verdict == "match"]
        assert matched.count("box") == 1, matched
        assert cube_share(shot, found) > 0.95


def test_a_regions_few_points_apart_from_its_bulk_are_left_out_of_its_ask(engine):
    # two boxes 16 cm apart: a region of the first box's segment and three points of the
    # second (a flying pixel, or a neighbour's leftovers, that the region holds) is asked about
    # without the three, which would double the radius the chain scales a cloud by; a region
    # of the two boxes' segments is asked whole (docs/decisions.md#a-regions-strays)
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    placed = [(mesh, *resting(mesh, spin(25 + 40 * k), 0.16 * k - 0.08, 0.0)) for k in range(2)]
    calls = counting(engine)
    try:
        scan, labels, _ = scan_of(engine, shoot(placed, table()))
        a, b = (np.flatnonzero(labels == s) for s in np.argsort(-np.bincount(labels))[:2])
        strays = b[:: len(b) // 3][:3]
        np.testing.assert_array_equal(scan.bulk(np.concatenate([a, strays])), a)
        np.testing.assert_array_equal(scan.bulk(a), a)
        both = np.concatenate([a, b])
        np.testing.assert_array_equal(scan.bulk(both), both)
        found = scan.instance(np.concatenate([a, strays]))
    finally:
        del engine.align
    assert found is not None and found.answer.label == "box"
    asked = np.concatenate(calls)
    assert cKDTree(asked).query(scan.frame.points[strays])[0].min() > 0.01  # none asked about


def test_asks_sent_ahead_to_another_process_answer_as_those_made_here(box_and_cube):
    # ``submit`` runs the chain elsewhere (here a thread of the real engine; the service's
    # worker processes): the segments' and their pieces' first asks are sent there at once,
    # and the frame's answer is the one asked here alone (docs/decisions.md#detect-on-two-cores).
    # Where a segment's whole search cannot be sent, the segments are searched here in turn
    engine, meshes = box_and_cube
    frame = frame_of(cube_beside_the_box(meshes, 0.0, 0.7))
    align, sent = engine.align, []
    asked = counting(engine)
    try:
        alone = engine.detect(frame).detections
    finally:
        del engine.align

    def submit(method, points, *args, **kwargs):
        if method != "align":  # a segment's search is refused: each is searched here, in turn
            raise RuntimeError(f"{method} is not sent")
        sent.append(len(points))
        return pool.submit(align, points, *args, **kwargs)

    here = counting(engine)
    try:
        with ThreadPoolExecutor(1) as pool:
            ahead = engine.detect(frame, submit=submit).detections
    finally:
        del engine.align
    assert len(sent) >= 2, sent  # the segment, and a piece once the box was taken out
    assert len(here) == len(asked) - len(sent), (len(here), len(asked), sent)  # none twice
    assert [(d.answer.label, d.answer.verdict) for d in ahead] == [
        (d.answer.label, d.answer.verdict) for d in alone
    ]
    for a, b in zip(ahead, alone, strict=True):
        assert a.answer.confidence == b.answer.confidence
        np.testing.assert_array_equal(a.answer.rotation, b.answer.rotation)
        np.testing.assert_array_equal(a.indices, b.indices)


def three_apart(meshes):
    """The box, the cube and the ball apart on a table: three segments."""
    box, cube, ball = meshes["box"], meshes["cube"], meshes["ball"]
    placed = [
        (box, *resting(box, spin(10), 0.0, 0.0)),
        (cube, *resting(cube, spin(40), 0.17, 0.05)),
        (ball, *resting(ball, spin(0), -0.16, -0.04)),
    ]
    return shoot(placed, table(), distance=0.8)


def outcomes(detections) -> list[tuple[str, str]]:
    """Each detection's label and verdict, sorted."""
    return sorted((d.answer.label, d.answer.verdict) for d in detections)


def test_segments_searched_in_two_processes_find_what_one_finds(box_and_cube):
    # the box, the cube and the ball apart: three segments. With ``submit`` (here a thread of
    # the real engine; the service's worker processes) some are searched there while the
    # rest are searched here, and the frame holds the same instances, no point claimed twice
    # (docs/decisions.md#segments-on-two-cores)
    engine, meshes = box_and_cube
    frame = frame_of(three_apart(meshes))
    alone = engine.detect(frame).detections
    searched = []

    def submit(method, *args, **kwargs):
        searched.append(method)
        return pool.submit(getattr(engine, method), *args, **kwargs)

    with ThreadPoolExecutor(1) as pool:
        shared = engine.detect(frame, submit=submit).detections
    assert "search_segments" in searched, searched
    assert outcomes(shared) == outcomes(alone)
    assert {"box", "cube"} <= {d.answer.label for d in shared if d.answer.verdict == "match"}
    claimed = np.concatenate([d.indices for d in shared])
    assert len(np.unique(claimed)) == len(claimed)


def test_a_segment_whose_search_elsewhere_fails_is_searched_here(box_and_cube):
    # the other process dies while it searches (its future raises): the segments it took are
    # searched here, and the frame holds what a search alone finds
    engine, meshes = box_and_cube
    frame = frame_of(three_apart(meshes))
    alone = engine.detect(frame).detections
    failed = []

    def submit(method, *args, **kwargs):
        if method == "align":
            return pool.submit(getattr(engine, method), *args, **kwargs)
        failed.append(args[5])  # the segments it was sent
        return pool.submit(lambda: 1 / 0)

    with ThreadPoolExecutor(1) as pool:
        here = engine.detect(frame, submit=submit).detections
    assert failed
    assert outcomes(here) == outcomes(alone)


def test_two_touching_boxes_are_found_whatever_the_search_draws(engine):
    """Two boxes side by side on a table, one segment: the placed views find each, under most
    of the search's seeds, not a lucky one (docs/decisions.md#two-touching-boxes-placed-again)."""
    sizes = {"box-a": (0.08, 0.06, 0.04), "box-b": (0.10, 0.04, 0.03)}
    meshes = {name: trimesh.creation.box(size) for name, size in sizes.items()}
    engine = registered(Engine(engine.mapper, SETTINGS.engine, engine.calibration), meshes)
    a = resting(meshes["box-a"], np.eye(3), 0.0, 0.0)
    b = resting(meshes["box-b"], np.eye(3), 0.0, (sizes["box-a"][1] + sizes["box-b"][1]) / 2)
    frame = frame_of(shoot([(meshes["box-a"], *a), (meshes["box-b"], *b)], table()))
    both = 0
    for seed in range(10):
        engine.settings = engine.settings.model_copy(update={"seed": seed})
        found = sorted(d.answer.label for d in engine.detect(frame).detections)
        both += found == ["box-a", "box-b"]
    assert both >= 8, f"both boxes, and nothing else, under {both} of 10 seeds"


def test_views_are_placed_over_a_segment_only_among_few_plausible_parts(engine):
    # two touching boxes, one segment: every part of a plausible size is placed while there
    # are at most TEMPLATE_POOL of them; among more, none is: the coarse ranking seldom picks
    # the right one, and a placement and its ask cost two asks
    # (docs/decisions.md#placed-views-among-few-parts)
    box = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(box, *resting(box, np.eye(3), 0.0, 0.06 * k)) for k in range(2)], table())
    few = {f"box-{k}": trimesh.creation.box((0.08 + 0.004 * k, 0.06, 0.04)) for k in range(2)}
    many = {f"box-{k}": trimesh.creation.box((0.08 + 0.004 * k, 0.06, 0.04)) for k in range(9)}
    for meshes, expected in ((few, sorted(few)), (many, [])):
        probe = registered(Engine(engine.mapper, SETTINGS.engine, engine.calibration), meshes)
        scan, labels, shows = scan_of(probe, shot)
        region = np.flatnonzero(labels == np.argmax(np.bincount(labels)))
        assert {0, 1} <= set(shows[region].tolist()), "the two boxes are not one segment"
        points = scan.frame.points[region]
        chosen = scan.template_parts(points, scan.spacing)
        assert sorted(e.reference.name for e in chosen) == expected


def test_a_pair_of_failed_segments_claimed_since_is_not_joined(engine):
    # two boxes, each its own segment, both failed; an instance found since (by the fragments
    # or an earlier join) claimed every point of both: their join is skipped, nothing asked.
    # An empty region raised in the join's width check (a 500 on a real frame)
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    placed = [(mesh, *resting(mesh, spin(25 + 40 * k), 0.14 * k - 0.07, 0.0)) for k in range(2)]
    scan, labels, _ = scan_of(engine, shoot(placed, table()))
    a, b = np.argsort(-np.bincount(labels))[:2]
    assert scan.worth_searching(np.flatnonzero((labels == a) | (labels == b)))
    scan.free[(labels == a) | (labels == b)] = False
    calls = counting(engine)
    try:
        assert scan.joined(labels, [int(a), int(b)], {(int(min(a, b)), int(max(a, b)))}, 20) == []
    finally:
        del engine.align
    assert calls == []


def scan_of(engine: Engine, shot):
    """The search ``Engine.detect`` makes of a shot's frame, its supports set aside: the scan,
    its segments' labels, and which object each of its points shows (-1: none)."""
    scan, labels, rest = frame_scan(engine, frame_of(shot))
    return scan, labels, shot.shows.ravel()[rest.index]


def frame_scan(engine: Engine, frame: Frame):
    """The search ``Engine.detect`` makes of ``frame``: the scan, its segments' labels, and
    the frame's points it searches."""
    query = engine.query(None, None, True, None, frame.viewpoint)
    scales = engine._frame_scales(query, frame)
    thin = frame.thinned(scales.min() / THIN_PER_SCALE)
    keep, supports = set_aside_supports(thin, frame.pixel_angle(), scales, query.rng)
    rest = thin.take(keep)
    noise = Noise(supports[0] if supports else None)
    sizes = (float(scales.min()), float(scales.max()))
    scan = engine._scan(query, rest, DepthImage.of(thin), noise, sizes, None, None, None, None)
    return scan, segments(rest, frame.pixel_angle()), rest


def test_a_segment_of_two_parts_one_before_the_other_is_split_finer(engine):
    # a low box 6 mm before a tall one: one segment at the usual links (the low box's top edge
    # lies within them of the tall one's face behind it), two at finer ones. A lone box is
    # not split (docs/decisions.md#a-segment-split-finer)
    low, tall = trimesh.creation.box((0.08, 0.06, 0.04)), trimesh.creation.box((0.1, 0.05, 0.1))
    placed = [
        (low, *resting(low, spin(0), 0.0, -0.036)),
        (tall, *resting(tall, spin(0), 0.0, 0.025)),
    ]
    scan, labels, shows = scan_of(
        engine, shoot(placed, table(), azimuth_deg=-60.0, elevation_deg=50.0)
    )
    region = np.flatnonzero(labels == np.argmax(np.bincount(labels)))
    assert {0, 1} <= set(shows[region].tolist()), "the two boxes are not one segment"
    pieces = scan.finer(region)
    assert len(pieces) >= 2
    for k, piece in enumerate(pieces[:2]):
        assert np.mean(shows[piece] == shows[piece][0]) > 0.95, f"piece {k} mixes the boxes"
    assert {shows[p][0] for p in pieces[:2]} == {0, 1}
    alone = shoot([placed[1]], table(), azimuth_deg=-60.0, elevation_deg=50.0)
    scan, labels, _ = scan_of(engine, alone)
    assert scan.finer(np.flatnonzero(labels == np.argmax(np.bincount(labels)))) == []


def test_a_region_an_instance_took_points_from_is_searched_again(engine):
    # of the regions of a segment where nothing was found, one an instance took points from
    # since is searched again with what is left, less the points still to be searched; one
    # nothing took from is kept as it was, and one whose rest is all to be searched anyway is
    # not searched twice (docs/decisions.md#a-region-searched-again)
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    placed = [(mesh, *resting(mesh, spin(25 + 40 * k), 0.14 * k - 0.07, 0.0)) for k in range(2)]
    scan, labels, _ = scan_of(engine, shoot(placed, table()))
    a, b = (np.flatnonzero(labels == s) for s in np.argsort(-np.bincount(labels))[:2])
    both = np.concatenate([a, b])
    pending = [a[: len(a) // 2]]
    scan.free[b] = False  # an instance took the second box
    again, kept = scan.freed([both, a, b[:10]], pending)
    assert [set(region.tolist()) for region in again] == [set(a[len(a) // 2 :].tolist())]
    assert [len(region) for region in kept] == [len(a)]  # untouched
    again, kept = scan.freed([both], [a])
    assert again == [] and kept == []


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


def three_boxes(engine: Engine) -> tuple[dict, Frame, Calibration, dict]:
    """Three boxes apart on a table and a cube elsewhere in the gallery: the meshes, the
    frame, a calibration that trusts every instance, and the changes to it that trust an
    instance by its points alone: 0.45 confident at the fewest points a box shows (uncertain),
    0.95 at the next fewest (a match)."""
    meshes = {"box": trimesh.creation.box((0.08, 0.06, 0.04))}
    meshes["cube"] = trimesh.creation.box((0.03, 0.025, 0.02))
    box = meshes["box"]
    placed = [(box, *resting(box, spin(25 + 40 * k), 0.14 * k - 0.14, 0.0)) for k in range(3)]
    frame = frame_of(shoot(placed, table()))
    trusting = one_fit(bias=50.0)
    probe = calibrated(engine, meshes, trusting)
    found = probe.detect(frame).detections
    assert [d.answer.label for d in found] == ["box"] * 3
    fewest, next_fewest = sorted(d.evidence["points"] for d in found)[:2]
    assert next_fewest > fewest
    at = trusting.features.index("points")
    weights, mean, spread = (
        np.zeros(len(trusting.features)),
        trusting.mean.copy(),
        trusting.spread.copy(),
    )
    weights[at], mean[at] = 1.0, fewest
    spread[at] = (next_fewest - fewest) / (logit(0.95) - logit(0.45))
    by_points = {"weights": weights, "mean": mean, "spread": spread, "bias": logit(0.45)}
    return meshes, frame, trusting, by_points


def calibrated(engine: Engine, meshes: dict, calibration: Calibration) -> Engine:
    """An engine holding ``meshes``, its frames judged by ``calibration``."""
    frames_calibrated = Engine(engine.mapper, SETTINGS.engine, engine.calibration, calibration)
    return registered(frames_calibrated, meshes)


def verdicts_of(engine: Engine, meshes: dict, frame: Frame, calibration: Calibration) -> list:
    """The boxes' verdicts in ``frame``, judged by the frame ``calibration``."""
    found = calibrated(engine, meshes, calibration).detect(frame).detections
    assert [d.answer.label for d in found] == ["box"] * 3
    return sorted(d.answer.verdict for d in found)


def test_a_part_the_frame_holds_several_of_is_judged_as_told(engine):
    # the three boxes, a frame calibration that trusts an instance by its points alone,
    # doubting the box seen by the fewest, and one for frames told their parts that trusts
    # every instance. Two matches make the box a part the frame holds several of, and the
    # doubted box is judged again as a frame told the box would be: a match
    # (docs/decisions.md#a-part-the-frame-holds-several-of)
    meshes, frame, trusting, by_points = three_boxes(engine)
    for told, verdicts in ((None, ["match", "match", "uncertain"]), (trusting, ["match"] * 3)):
        doubting = one_fit(**by_points, accept=0.9, told=told)
        assert verdicts_of(engine, meshes, frame, doubting) == sorted(verdicts)


def test_a_part_matched_several_times_once_settled_is_looked_for_again(engine):
    # the three boxes, a first fit that doubts every instance, and a settled fit (what is
    # left around) that trusts an instance by its points alone: the frame then holds several
    # boxes only once the search is done, and the third is judged again as a frame told the
    # box would be (docs/decisions.md#a-part-the-frame-holds-several-of)
    meshes, frame, trusting, by_points = three_boxes(engine)
    settled = one_fit(**by_points, accept=0.9)
    doubt_all = {"weights": np.zeros(len(trusting.features)), "bias": logit(0.45)}
    for told, verdicts in ((None, ["match", "match", "uncertain"]), (trusting, ["match"] * 3)):
        doubting = one_fit(**doubt_all, accept=0.9, told=told, settled=settled)
        assert verdicts_of(engine, meshes, frame, doubting) == sorted(verdicts)


def test_a_part_held_several_times_though_never_matched_is_judged_as_told(engine):
    # the three boxes and a frame calibration that trusts an instance by its points alone,
    # but whose threshold (0.99) refuses the boxes seen at 0.95 and less: two boxes at least
    # HELD_FROM confident make the box a part the frame holds several of, and the boxes are
    # judged again as a frame told the box would be (docs/decisions.md#several-likely-instances)
    meshes, frame, trusting, by_points = three_boxes(engine)
    alone = verdicts_of(engine, meshes, frame, one_fit(**by_points, accept=0.99, told=None))
    assert alone.count("match") <= 1  # the boxes seen at 0.45 and at 0.95 refused
    told = one_fit(**by_points, accept=0.99, told=trusting)
    assert verdicts_of(engine, meshes, frame, told) == ["match"] * 3


def test_a_doubted_other_part_on_a_part_held_several_times_is_searched_again(engine):
    # the three boxes, each a match, but one's points taken by a doubted pose of the cube (as
    # another part's pose may take a bin's part): the box, held several times, is looked for
    # again told alone, there too, and found (docs/decisions.md#several-likely-instances)
    meshes, frame, trusting, _ = three_boxes(engine)
    probe = calibrated(engine, meshes, trusting)
    scan, labels, _ = frame_scan(probe, frame)
    found = scan.instances(labels, 20)
    assert [i.answer.label for i in found] == ["box"] * 3
    doubted = found[0]
    doubted.answer.label, doubted.answer.verdict = "cube", "uncertain"
    doubted.entry = probe.entry("cube")
    more = probe._found_again(scan, found, labels, 20, ["box"])
    assert [i.answer.label for i in more] == ["box"]
    assert np.isin(more[0].claimed, doubted.claimed).mean() > 0.9


def test_what_nearer_parts_hide_is_not_missed_by_the_chain(engine, one_box):
    # a third of the box hidden by something nearer (its pixels' points brought a fifth of
    # the way to the camera): the chain, asked about what is left, counts the hidden third as
    # missed; the frame shows it is hidden, so the chain's confidence in a frame rises
    entry, shot = one_box
    hidden = (shot.shows == 0) & (np.arange(shot.shows.shape[1]) < box_column(shot, 0.3))
    points = shot.points.copy()
    points[hidden] *= 0.8
    frame = frame_of(replace(shot, points=points))
    seen = shot.points[(shot.shows == 0) & ~hidden].astype(np.float64)
    answer = engine.align(seen, viewpoint=np.zeros(3), surroundings=False)
    assert answer.label == "box"
    tolerance = CLAIM_TOLERANCE * engine.settings.tolerance * entry.reference.scale
    chain = np.log(answer.confidence / (1 - answer.confidence))
    said = evidence(
        answer, entry, len(seen), len(seen), frame.viewpoint, DepthImage.of(frame), tolerance,
        engine.seen_as,
    )  # fmt: skip
    assert said["seen"] > answer.coverage + 0.1 and said["through"] <= THROUGH_DOUBT
    assert said["chain"] > chain + 0.5
    unorganized = evidence(
        answer, entry, len(seen), len(seen), frame.viewpoint, None, tolerance, engine.seen_as
    )
    assert unorganized["chain"] == pytest.approx(chain)


def box_column(shot, share: float) -> float:
    """The column left of which ``share`` of the pixels showing the shot's first part lie."""
    return float(np.quantile(np.nonzero(shot.shows == 0)[1], share))


def stepped_bar() -> trimesh.Trimesh:
    """A bar with a low step on one end: turned end for end, it nearly fits itself (its
    ``symmetry.near``), but the camera sees the table through where the step would be."""
    bar = trimesh.creation.box((0.08, 0.03, 0.03))
    step = trimesh.creation.box((0.02, 0.03, 0.006))
    step.apply_translation((0.03, 0.0, 0.018))
    return trimesh.util.concatenate([bar, step])


def angle_deg(first: np.ndarray, second: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(first @ second.T) - 1) / 2, -1, 1))))


def bar_answered(engine: Engine, mesh: trimesh.Trimesh):
    """``mesh`` registered alone as "bar" (the shipped scene calibration), shot lying on a
    table, and the chain's answer for its points as the frame's search asks: its entry, the
    scan, the bar's region and the sensor's noise there, the answer, and the true pose."""
    points, faces = sample_surface_faces(mesh, 2048, 0)
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    bars = Engine(engine.mapper, SETTINGS.engine, engine.calibration, shipped)
    bars.load([bars.make_reference("bar", points, mesh=mesh, face_index=faces)])
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    scan, _, shows = scan_of(bars, shot)
    region = np.flatnonzero(shows == 0)  # the bar's points
    sigma = scan.noise.at(scan.frame.points[region], scan.frame.viewpoint)
    answer = scan.answer_for(scan.frame.points[region], sigma)
    return bars.entry("bar"), scan, region, sigma, answer, shot.poses[0]


def test_a_near_turn_the_camera_sees_through_is_posed_again(engine):
    # the chain's answer for the bar, placed at the near turn the camera sees through most
    # (the step at the other end): the frame doubts it, and the claim poses it again at the
    # turn the camera sees through least, the true pose
    entry, scan, region, sigma, answer, (rotation, translation) = bar_answered(
        engine, stepped_bar()
    )
    assert len(entry.symmetry.near)
    assert answer.label == "bar" and angle_deg(answer.rotation, rotation) < 5
    rest = scan.frame

    turns, centre = entry.symmetry.near, entry.symmetry.centroid
    rotations, translations = turned_about(rotation, translation, turns, centre)
    tolerance = CLAIM_TOLERANCE * scan.part_tolerance(entry, sigma)  # the evidence's
    _, through = seen_through(
        entry, rotations, translations, rest.viewpoint, scan.camera, tolerance
    )
    worst = int(np.argmax(through))
    assert through[worst] > 2 * THROUGH_DOUBT
    turned = replace(answer, rotation=rotations[worst], translation=translations[worst])
    instance = scan.claim(region, turned, sigma, again=False)
    assert instance is not None and angle_deg(instance.answer.rotation, rotation) < 5
    assert instance.evidence["through"] < through[worst] / 2


def bar_with_block(bar: tuple, block: tuple) -> trimesh.Trimesh:
    """A box ``bar`` with a box ``block`` on its top at one end: no near turn."""
    knob = trimesh.creation.box(block)
    knob.apply_translation((bar[0] / 2 - block[0] / 2, 0.0, bar[2] / 2 + block[2] / 2))
    return trimesh.util.concatenate([trimesh.creation.box(bar), knob])


def turned_claim(engine, bar: tuple, block: tuple, turn: np.ndarray, about, alike=False):
    """A bar with a block on one end (no near turn) answered by the chain, that answer turned
    by ``turn`` about ``about(entry)`` (model frame), with no alternatives and (``alike``) the
    chain's own answer as the other pose it found fitting alike (``closest``), and claimed.
    The instance, the share of the turned answer the camera sees through (at the tolerance of a
    claim's evidence), and the true rotation."""
    entry, scan, region, sigma, answer, (rotation, _) = bar_answered(
        engine, bar_with_block(bar, block)
    )
    assert not len(entry.symmetry.near)
    assert answer.label == "bar" and angle_deg(answer.rotation, rotation) < 5

    closest = AlternativePose(answer.rotation, answer.translation, 0.5) if alike else None
    (turned,), (moved,) = turned_about(
        answer.rotation, answer.translation, turn[None], about(entry)
    )
    wrong = replace(answer, rotation=turned, translation=moved, closest=closest, alternatives=[])
    tolerance = CLAIM_TOLERANCE * scan.part_tolerance(entry, sigma)
    _, (through,) = seen_through(
        entry, turned[None], moved[None], scan.frame.viewpoint, scan.camera, tolerance
    )
    assert through > 2 * THROUGH_DOUBT
    return scan.claim(region, wrong, sigma, again=False), through, rotation


def test_a_pose_the_chain_found_alike_the_camera_sees_through_less_is_posed_again(engine):
    # a bar with a block on one end has no near turn; the chain's answer for it, turned end
    # for end (the block where the camera sees the table), with the true pose as the other
    # pose the chain found fitting alike (``closest``): the frame doubts the answer, and the
    # claim poses it again at that other pose
    end_for_end = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    instance, through, rotation = turned_claim(
        engine, (0.08, 0.03, 0.02), (0.02, 0.03, 0.02), end_for_end,
        lambda entry: entry.symmetry.centroid, alike=True,
    )  # fmt: skip
    assert instance is not None and angle_deg(instance.answer.rotation, rotation) < 5
    assert instance.evidence["through"] < through / 2


def test_a_part_posed_a_quarter_turn_off_about_its_length_is_turned_over(engine):
    # a bar nearly square across with a low block on one end, answered turned a quarter about
    # its length (the block out to one side, where the camera sees the table) with no near turn
    # and no other pose of the chain's to turn to: the frame doubts it, and the claim turns it
    # over to the true pose, a match
    quarter = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    instance, through, rotation = turned_claim(
        engine, (0.08, 0.03, 0.028), (0.02, 0.03, 0.01), quarter, lambda entry: entry.frame.centroid
    )
    assert instance is not None and angle_deg(instance.answer.rotation, rotation) < 5
    assert instance.answer.verdict == "match" and instance.evidence["through"] < through / 2


def look_alikes_shot(engine: Engine, shown: str):
    """A bar with a step on one end ("stepped") and the bar alone ("bar"), registered as
    look-alikes (as a registration check that could not tell them apart stores them), and
    ``shown`` of them lying on a table: the scan, its region, the sensor's noise there, and
    the chain's answer as it gives one for look-alikes that fit alike, the other part's
    pose an alternative with its label: ``said`` at the true pose."""
    meshes = {"stepped": stepped_bar(), "bar": trimesh.creation.box((0.08, 0.03, 0.03))}
    shipped = Calibration.load(SETTINGS.detect_confidence_path)
    alike = Engine(engine.mapper, SETTINGS.engine, engine.calibration, shipped)
    references = {}
    for name, mesh in meshes.items():
        points, faces = sample_surface_faces(mesh, 2048, 0)
        references[name] = alike.make_reference(name, points, mesh=mesh, face_index=faces)
    stepped, bar = references["stepped"], references["bar"]
    alike.load([replace(stepped, look_alikes={"bar": bar.points_sha256}), bar])
    assert alike.look_alikes("bar") == ("stepped",)

    mesh = meshes[shown]
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    scan, _, shows = scan_of(alike, shot)
    region = np.flatnonzero(shows == 0)
    sigma = scan.noise.at(scan.frame.points[region], scan.frame.viewpoint)
    rotation, translation = shot.poses[0]

    def said(label: str):
        other = "bar" if label == "stepped" else "stepped"
        answer = scan.answer_for(scan.frame.points[region], sigma)
        return replace(
            answer,
            label=label,
            rotation=rotation,
            translation=translation,
            confidence=0.45,
            look_alikes=[other],
            alternatives=[AlternativePose(rotation, translation, 0.0, label=other)],
            ambiguous=True,
        )

    return scan, region, sigma, said


def test_look_alikes_the_frame_tells_apart_are_answered_as_the_part_shown(engine):
    # the step explains points the bar alone cannot: the frame tells the stepped bar from the
    # bar, whichever the chain named, and the answer is no longer doubted
    scan, region, sigma, said = look_alikes_shot(engine, "stepped")
    for named in ("bar", "stepped"):
        instance = scan.claim(region, said(named), sigma, again=False)
        assert instance is not None and instance.answer.label == "stepped"
        assert not instance.answer.look_alikes
        assert not any("look-alike" in reason for reason in instance.answer.reasons)


def test_look_alikes_are_told_apart_by_a_face_in_a_piece_beside_the_region(engine):
    # the stepped bar's step in a piece of its own (as a crease or a jump in depth may leave
    # it): in the region searched both parts explain every point, but the stepped bar's claim
    # also holds the step's free points beside it, which the bar's surface does not come near
    # (docs/decisions.md#a-face-one-look-alike-lacks)
    scan, region, sigma, said = look_alikes_shot(engine, "stepped")
    on_step = step_of(scan, region, said)
    assert on_step.mean() > 0.05  # the step is in view
    for named in ("bar", "stepped"):
        instance = scan.claim(region[~on_step], said(named), sigma, again=False)
        assert instance is not None and instance.answer.label == "stepped"
        assert not instance.answer.look_alikes
        assert np.isin(region[on_step], instance.claimed).mean() > 0.8


def test_look_alikes_the_frame_cannot_tell_apart_stay_doubted(engine):
    # the bar alone: the stepped bar explains its points as well, so nothing tells them apart
    scan, region, sigma, said = look_alikes_shot(engine, "bar")
    instance = scan.claim(region, said("bar"), sigma, again=False)
    assert instance is not None and instance.answer.label == "bar"
    assert instance.answer.look_alikes == ["stepped"] and instance.answer.ambiguous
    assert instance.answer.verdict != "match"


def test_look_alikes_are_not_told_apart_in_a_region_a_crease_split(engine):
    # a crease may cut off the very face two look-alikes differ by: where the search split
    # the region at one and the step's points are out of reach (a neighbour took them), the
    # frame does not tell them apart, and the doubt stands
    # (docs/decisions.md#touching-parts-split-at-a-crease)
    scan, region, sigma, said = look_alikes_shot(engine, "stepped")
    on_step = step_of(scan, region, said)
    scan.cut[region] = True  # as ``Scan.creased`` marks the region it split
    scan.free[region[on_step]] = False
    for answer in (said("bar"), replace(said("bar"), look_alikes=[], alternatives=[])):
        instance = scan.claim(region[~on_step], answer, sigma, again=False)
        assert instance is not None and instance.answer.look_alikes == ["stepped"]
        assert instance.answer.verdict != "match"


def test_look_alikes_in_a_region_a_crease_split_are_told_apart_by_a_face_in_view(engine):
    # the region split at a crease, the step's points still free: whichever part the chain
    # named, alone or with its look-alike, the other is posed too (told it alone where the
    # chain did not name it), and the stepped bar's claim shows the step the bar lacks
    # (docs/decisions.md#a-face-one-look-alike-lacks)
    scan, region, sigma, said = look_alikes_shot(engine, "stepped")
    scan.cut[region] = True
    points, asking = scan.frame.points[region], scan.asking(sigma)[1]
    for named in ("bar", "stepped"):
        alone = scan.align(points, [named], **asking)  # the chain's pose, no look-alike named
        assert alone.label == named and not alone.look_alikes
        for answer in (said(named), alone):
            instance = scan.claim(region, answer, sigma, again=False)
            assert instance is not None and instance.answer.label == "stepped"
            assert not instance.answer.look_alikes


def test_a_face_is_not_counted_against_a_pose_the_camera_sees_through(engine):
    # a look-alike asked about alone may be posed poorly, and any pose shows a face a poor one
    # lacks: the stepped bar shows its step against the bar posed on the points, but not
    # against the bar moved 2 cm towards the camera, which the camera sees through
    # (docs/decisions.md#a-face-one-look-alike-lacks)
    scan, region, sigma, said = look_alikes_shot(engine, "stepped")
    stepped, bar = (
        scan.claim(region, replace(said(name), look_alikes=[], alternatives=[]), sigma, False)
        for name in ("stepped", "bar")
    )
    assert scan.shows_face(stepped, bar, sigma)
    answer = replace(bar.answer)
    answer.translation = answer.translation * (1 - 0.02 / np.linalg.norm(answer.translation))
    moved = replace(bar, answer=answer, evidence=dict(bar.evidence))
    tolerance = scan.claim_tolerance(bar.entry, sigma)
    poses = answer.rotation[None], answer.translation[None]
    _, through = seen_through(bar.entry, *poses, scan.frame.viewpoint, scan.camera, tolerance)
    moved.evidence["through"] = float(through[0])
    assert moved.evidence["through"] > stepped.evidence["through"] + 0.5
    assert not scan.shows_face(stepped, moved, sigma)


def step_of(scan, region: np.ndarray, said) -> np.ndarray:
    """Which of the stepped bar's ``region`` points lie on its step (the bar's top lies at
    0.015, the step's at 0.021), at its true pose."""
    truth = said("stepped")
    model = (scan.frame.points[region] - truth.translation) @ truth.rotation
    return model[:, 2] > 0.0165
