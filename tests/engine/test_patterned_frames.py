"""Frames whose pixels are missing in a pattern: a depth image registered to a larger colour
image (a point on one pixel in four, in a pattern that drifts), an interlaced camera (every
other row), a checkerboard of dropouts. They are thinned to a point a block, their pixel
angle read across the gaps, and searched as the whole frame is
(docs/decisions.md#pixels-missing-in-a-pattern)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.engine.engine import Engine
from service.engine.frame import Frame
from tests.engines import engine_holding
from tests.frames import frame_of, registered, resting, shoot, spin, table, without

HEIGHT, WIDTH, FOCAL = 480, 640, 525.0
ROWS, COLUMNS = np.mgrid[0:HEIGHT, 0:WIDTH]
PATTERNS = {
    "every other row": ROWS % 2 == 0,
    "every other column": COLUMNS % 2 == 0,
    "checkerboard": (ROWS + COLUMNS) % 2 == 0,
    "one pixel in four": (ROWS % 2 == 0) | (COLUMNS % 2 == 0),
}


def wall(missing: np.ndarray | None = None, scale: float = 1.0) -> Frame:
    """A wavy wall a metre away, every pixel's point but the ``missing`` ones, on a grid
    ``scale`` times the camera's (registered: see ``tests.frames.registered``)."""
    depth = 1.0 + 0.1 * np.sin(COLUMNS / 40.0)
    points = np.stack(
        [(COLUMNS - WIDTH / 2) / FOCAL * depth, (ROWS - HEIGHT / 2) / FOCAL * depth, depth], -1
    ).reshape(-1, 3)
    keep = np.ones(HEIGHT * WIDTH, bool) if missing is None else ~missing.ravel()
    if scale == 1.0:
        return Frame.of(points[keep], np.flatnonzero(keep), (HEIGHT, WIDTH))
    tall, wide = int(np.ceil(HEIGHT * scale)) + 1, int(np.ceil(WIDTH * scale)) + 1
    rows = np.floor(ROWS.ravel() * scale + 0.5).astype(int)
    columns = np.floor(COLUMNS.ravel() * scale + 0.5).astype(int)
    return Frame.of(points, rows * wide + columns, (tall, wide))


def blocks_held(frame: Frame, stride: int) -> set[tuple[int, int]]:
    rows, columns = np.divmod(frame.index, frame.shape[1])
    return set(zip((rows // stride).tolist(), (columns // stride).tolist(), strict=True))


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("stride", [2, 3])
def test_a_frame_missing_pixels_in_a_pattern_is_thinned_to_a_point_a_block(pattern, stride):
    frame = wall(PATTERNS[pattern])
    thin = frame.every(stride)
    assert len(thin) == len(blocks_held(thin, stride)), "one point a block"
    assert blocks_held(thin, stride) == blocks_held(frame, stride), "every block with a point"
    coarser = thin.every(2)  # a thinned frame thinned again (the supports' coarser copy)
    assert blocks_held(coarser, 2 * stride) == blocks_held(frame, 2 * stride)


def test_a_whole_frame_is_thinned_to_the_first_pixel_of_each_block():
    thin = wall().every(3)
    rows, columns = np.divmod(thin.index, WIDTH)
    assert np.all(rows % 3 == 0) and np.all(columns % 3 == 0)
    assert len(thin) == len(blocks_held(wall(), 3))


@pytest.mark.parametrize("pattern", [*PATTERNS, "registered 1.5", "registered 2.1"])
def test_a_frames_pixel_angle_is_read_across_missing_pixels(pattern):
    whole = wall().pixel_angle()
    if pattern.startswith("registered"):
        scale = float(pattern.split()[1])
        angle, expected = wall(scale=scale).pixel_angle(), whole / scale
    else:
        angle, expected = wall(PATTERNS[pattern]).pixel_angle(), whole
    assert angle == pytest.approx(expected, rel=0.03)


def test_a_frame_registered_to_a_larger_image_is_searched_at_its_own_density():
    dropouts = np.random.default_rng(0).random((HEIGHT, WIDTH)) < 0.25
    assert wall().sparse_step() == 1
    assert wall(dropouts).sparse_step() == 1
    assert wall(PATTERNS["checkerboard"]).sparse_step() == 1  # a gap of one is linked across
    assert wall(scale=2.1).sparse_step() == 2
    assert wall(scale=3.2).sparse_step() == 3


@pytest.fixture(scope="module")
def engine() -> Engine:
    return engine_holding({"box": trimesh.creation.box((0.08, 0.06, 0.04))})


def patterned(shot, pattern: str):
    if pattern == "registered 2.1":
        return registered(shot, 2.1)
    return without(shot, PATTERNS[pattern])


@pytest.mark.parametrize("pattern", ["every other row", "checkerboard", "registered 2.1"])
def test_a_frame_missing_pixels_in_a_pattern_finds_what_the_whole_frame_finds(engine, pattern):
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    (whole,) = engine.detect(frame_of(shot)).detections
    assert whole.answer.verdict == "match"
    answer = engine.detect(frame_of(patterned(shot, pattern)))
    assert [d.answer.verdict for d in answer.detections] == ["match"], answer.detections
    (found,) = answer.detections
    assert np.linalg.norm(found.answer.translation - shot.poses[0][1]) < 0.01
    width = patterned(shot, pattern).shows.shape[1]
    shows = patterned(shot, pattern).shows
    assert np.mean(shows[found.indices // width, found.indices % width] == 0) > 0.9
    assert answer.supports, "the table is set aside"


@pytest.mark.parametrize("pattern", ["every other row", "checkerboard", "registered 2.1"])
def test_a_bare_table_missing_pixels_in_a_pattern_holds_nothing(engine, pattern):
    answer = engine.detect(frame_of(patterned(shoot([], table()), pattern)))
    assert answer.detections == []
    assert answer.supports
