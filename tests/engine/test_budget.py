"""What the engine spends on a cloud: a large one is answered from a sample, and a cloud that
nothing registered fits stops its search early (docs/decisions.md#at-camera-scale)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.align_http.clouds import resample
from service.engine.confidence import Calibration
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.gallery.gallery_file import load_gallery
from service.settings import EngineSettings, Settings
from tests.servers import needs_model

SETTINGS = Settings()


@pytest.fixture(scope="module")
def references():
    return load_gallery(SETTINGS.model.gallery)[0]


@pytest.fixture(scope="module")
def engine_with(references):
    """An engine of the shipped gallery under the shipped settings with some changed, every
    one on one network session."""
    mapper = Mapper(SETTINGS.model.path, use_cuda=False)
    path = SETTINGS.confidence_path
    calibration = Calibration.load(path) if path.exists() else None

    def made(**settings) -> Engine:
        chosen = EngineSettings(**{**SETTINGS.engine.model_dump(), **settings})
        engine = Engine(mapper, chosen, calibration)
        engine.load(references)
        return engine

    return made


def posed(reference, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=rng).as_matrix()
    points = resample(reference.points, reference.normals, count, rng)
    return points @ rotation.T + [0.1, -0.2, 0.7], rotation


@needs_model
def test_a_large_cloud_is_answered_from_a_sample_as_a_small_one_is(references, engine_with):
    engine = engine_with(align_points=4096)
    reference = references[2]
    small, rotation = posed(reference, 3000, 1)
    large, _ = posed(reference, 40_000, 1)  # the same pose (the seed's first draw)
    for cloud, expected in ((small, 3000), (large, 4096)):
        answer = engine.align(cloud)
        assert answer.points == expected
        assert answer.label == reference.name
        turned = Rotation.from_matrix(answer.rotation @ rotation.T).magnitude()
        assert np.degrees(turned) < 5 or answer.alike  # a symmetric part may turn


@needs_model
def test_a_cloud_nothing_fits_stops_before_the_mapped_pairs_and_the_finish(engine_with):
    turns = np.linspace(0, 30, 2048)  # a coiled wire: nothing registered is one
    junk = np.stack([0.03 * np.cos(turns), 0.03 * np.sin(turns), 0.003 * turns], axis=1)
    junk += np.random.default_rng(4).normal(scale=0.001, size=junk.shape) + [0, 0, 0.8]
    stopping = engine_with(hopeless=0.3).align(junk)
    going_on = engine_with(hopeless=0.0).align(junk)
    assert going_on.fit * going_on.coverage < 0.3  # hopeless, wherever the search went
    assert stopping.verdict != "match" and going_on.verdict != "match"
    assert "flips" in going_on.timings_ms
    assert "flips" not in stopping.timings_ms and "near-symmetries" not in stopping.timings_ms


@needs_model
def test_a_search_of_the_mapped_pairs_alone_is_never_hopeless_before_it_starts(
    references, engine_with
):
    """Nothing refined before the mapped pairs (the paper's own hypotheses alone): the
    search goes on to them rather than stop at nothing."""
    engine = engine_with(hypotheses=("mapped",), hopeless=0.3)
    reference = references[2]
    cloud, _ = posed(reference, 2048, 5)
    answer = engine.align(cloud)
    assert answer.label == reference.name and answer.hypothesis == "mapped"
    assert answer.fit * answer.coverage > 0.3


def blob() -> np.ndarray:
    """A cloud no registered part is: a Gaussian blob 0.8 m in front of the camera."""
    rng = np.random.default_rng(8)
    return rng.normal(size=(2048, 3)) * [0.04, 0.03, 0.02] + [0, 0, 0.8]


def searched(engine, cloud: np.ndarray) -> tuple:
    """The query, observation and fits of ``engine``'s search passes for ``cloud``."""
    from service.engine.grid import grid
    from service.engine.search import Search

    query = engine.query(None, None, True, None, None)
    observed = engine.normalise(query, engine.set_aside(query, cloud)[0])
    observed.mapped = engine.map(observed.points)
    observed.grid = grid(observed.mapped)
    ranking = engine.classify(query, observed)
    fits = engine.search(query, observed, ranking, Search(engine.settings, query, observed))
    return query, observed, fits


@needs_model
def test_the_mapped_pairs_follow_single_views_that_fit_well_enough(engine_with):
    """A cloud whose single views fit it under ``mapped_from``: the search does not go on to
    the mapped pairs (no refined fit of theirs); with 0 it does."""
    sources = {}
    for floor in (0.0, 0.99):
        _, _, fits = searched(engine_with(mapped_from=floor, hopeless=0.01), blob())
        assert max(f.score for f in fits if f.refined) < 0.99  # not excellent: a third pass
        sources[floor] = {f.source for f in fits if f.refined}
    assert "mapped" in sources[0.0] and "mapped" not in sources[0.99]


@needs_model
def test_where_no_part_fits_well_the_next_parts_views_are_searched(engine_with):
    """A cloud no part fits well: the search goes on to the parts whose rendered views rank
    next (``more_views``), and to those alone; with 0 it does not."""
    from service.engine.tuning import MORE_VIEWS_BELOW

    rows = {}
    for more in (0, 4):
        # a blob hides much of itself from every side: searched as a view all the same
        engine = engine_with(more_views=more, hopeless=0.01, mapped_from=0.99, whole_hidden=1.0)
        query, observed, fits = searched(engine, blob())
        assert max(f.score for f in fits if f.refined) < MORE_VIEWS_BELOW  # none fits well
        rows[more] = {f.row for f in fits}
        nearest = engine._nearest_views(
            query.snapshot, observed.grid, observed.size, query.allowed, 6 + more
        )
    added = rows[4] - rows[0]
    assert added and added <= set(nearest[6:])


@needs_model
def test_poses_refined_together_end_their_turn_where_one_by_one_would(engine_with, references):
    """``Search.refine_in_turn`` refines a pass's fits together, yet each refined one is posed
    as refining it alone would, and the fits past where the turn stops are left as they were
    (docs/decisions.md#refinements-together)."""
    import copy

    from service.engine.grid import grid
    from service.engine.search import Search

    engine = engine_with(whole_hidden=1.0)  # a whole cloud's single views: many fits
    cloud, _ = posed(references[3], 2048, 5)
    query = engine.query(None, None, True, None, None)
    observed = engine.normalise(query, engine.set_aside(query, cloud)[0])
    observed.mapped = engine.map(observed.points)
    observed.grid = grid(observed.mapped)
    ranking = engine.classify(query, observed)
    search = Search(engine.settings, query, observed)
    plan = engine._single_views(query, observed, ranking, [])
    fits = search.verify(search.hypothesise(plan), plan)[:6]
    alone = copy.deepcopy(fits)
    for fit in alone:
        search.refine_all([fit])  # one by one
    # a turn that stops once a refined fit reaches the third's refined score
    floor = alone[2].score
    expected = next(k for k in range(len(alone)) if max(f.score for f in alone[: k + 1]) >= floor)
    together = copy.deepcopy(fits)
    done = search.refine_in_turn(together, lambda _, best: best >= floor)
    assert done == together[: expected + 1]
    for mine, one in zip(done, alone, strict=False):
        assert mine.refined
        np.testing.assert_allclose(mine.rotation, one.rotation, atol=1e-9)
        assert mine.score == pytest.approx(one.score, abs=1e-9)
    for mine, before in zip(together[expected + 1 :], fits[expected + 1 :], strict=True):
        assert not mine.refined
        np.testing.assert_array_equal(mine.rotation, before.rotation)


def view_of(reference, seed: int) -> np.ndarray:
    """One camera's view of ``reference``'s points: those it sees from a random side, ten of
    its radii away (the evaluation's partial views)."""
    from service.engine.visibility import random_camera, visible_points

    rng = np.random.default_rng(seed)
    points = resample(reference.points, reference.normals, 4096, rng)
    return points[visible_points(points, random_camera(points, 10.0, rng))]


@needs_model
def test_a_whole_parts_cloud_hides_much_of_itself_from_every_side_and_a_view_none(references):
    from service.engine.visibility import hidden_share

    rng = np.random.default_rng(0)
    for k, reference in enumerate(references[:5]):
        whole, _ = posed(reference, 2048, k)
        assert hidden_share(whole, rng) >= SETTINGS.engine.whole_hidden, reference.name
        assert hidden_share(view_of(reference, k), rng) < 0.1, reference.name  # 0-0.07 here


@needs_model
def test_a_whole_cloud_of_a_part_not_registered_is_refused_without_its_single_views(
    references, engine_with
):
    """A whole cloud no registered part fits is not searched as one camera's view (no refined
    fit of the rendered views), and is refused as it was; a view of a registered part, told
    of no camera, is still searched and found."""
    left_out = references[-1]
    cloud, _ = posed(left_out, 2048, 3)
    sources = {}
    for whole_hidden in (SETTINGS.engine.whole_hidden, 1.0):
        engine = engine_with(whole_hidden=whole_hidden)
        engine.load(references[:-1])
        answer = engine.align(cloud)
        assert answer.verdict != "match"
        _, _, fits = searched(engine, cloud)
        sources[whole_hidden] = {f.source for f in fits if f.refined}
    assert "views" in sources[1.0] and "views" not in sources[SETTINGS.engine.whole_hidden]
    engine = engine_with()
    reference = references[1]
    answer = engine.align(view_of(reference, 7))
    assert answer.label == reference.name and answer.verdict == "match"


@needs_model
def test_a_whole_cloud_searched_by_its_views_alone_is_still_searched(references, engine_with):
    """Asked to hypothesise from the rendered views alone, a whole cloud is searched by them:
    the whole-part search it would stand on is not asked for."""
    reference = references[4]
    cloud, _ = posed(reference, 2048, 11)
    answer = engine_with().align(cloud, hypotheses=("views",))
    assert answer.hypothesis != "none"  # searched, not refused for its size
    assert answer.label == reference.name
