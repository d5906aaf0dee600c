"""Segments on an organized frame (``service.engine.segments``): a part's lower rim, given back
from the support's band, joins the part above it and never two parts; two parts touching
without a jump in depth are split at the crease between them, a convex part never."""

from __future__ import annotations

import numpy as np

from service.engine.frame import Frame
from service.engine.segments import creases, nearest_pixel, segments
from tests.frames import box, frame_of, resting, shoot, spin


def test_rim_pixels_join_the_nearest_segment_and_never_bridge_two():
    # two flat blocks of pixels 2 mm apart at 1 m, 10 columns between them, and one row of rim
    # pixels across that gap: linked as any pixels, the row makes the blocks one segment
    height, width, angle = 20, 40, 0.002
    rows, columns = np.mgrid[0:height, 0:width]
    blocks = (columns < 15) | (columns >= 25)
    bridge = (rows == 10) & ~blocks
    valid = (blocks | bridge).ravel()
    grid = np.stack([(columns - 20) * angle, (rows - 10) * angle, np.ones_like(rows)], axis=-1)
    index = np.flatnonzero(valid)
    frame = Frame.of(grid.reshape(-1, 3)[index].astype(float), index, (height, width))
    rims = bridge.ravel()[index]

    assert len(np.unique(segments(frame, angle))) == 1

    labels = segments(frame, angle, rims=rims)
    left, right = labels[columns.ravel()[index] == 0][0], labels[columns.ravel()[index] == 39][0]
    assert left != right
    assert len(np.unique(labels)) == 2
    across = columns.ravel()[index][rims]
    assert np.all(labels[rims][across < 20] == left)
    assert np.all(labels[rims][across >= 20] == right)


def test_a_point_farther_than_a_rim_reaches_still_joins_its_nearest_pixel():
    # the window round each point is searched first; past it, the whole grid is
    height, width = 10, 30
    valid = np.zeros((height, width), dtype=bool)
    valid[:, :5] = True  # a block at the left
    valid[:, 25:] = True  # one at the right
    valid[5, 12] = valid[5, 18] = True  # two lone points, 7 pixels from either block
    rows, columns = np.nonzero(valid)
    index = rows * width + columns
    points = np.stack([columns * 0.002, rows * 0.002, np.ones(len(rows))], axis=1)
    frame = Frame.of(points.astype(float), index, (height, width))
    of = (columns == 12) | (columns == 18)
    found = nearest_pixel(frame, ~of, of)
    among_columns = columns[~of]
    assert among_columns[found[0]] == 4 and among_columns[found[1]] == 25


def test_two_parts_touching_without_a_jump_are_split_at_the_crease_a_convex_one_never():
    # a low box against a tall one: the low one's top meets the tall one's side in a valley,
    # one surface at the usual links (docs/decisions.md#touching-parts-split-at-a-crease)
    low, tall = box((0.12, 0.10, 0.03), (0, 0, 0)), box((0.06, 0.10, 0.12), (0, 0, 0))
    placed = [(low, *resting(low, spin(0), 0.0, 0.0)), (tall, *resting(tall, spin(0), 0.09, 0.0))]
    shot = shoot(placed, [], elevation_deg=45.0, azimuth_deg=180.0)
    frame = frame_of(shot)
    shows = shot.shows.ravel()[frame.index]
    assert len(np.unique(segments(frame, frame.pixel_angle()))) == 1

    labels = creases(frame)
    assert len(np.unique(labels)) == 2
    for part in range(2):
        mine = labels[shows == part]
        assert np.mean(mine == np.bincount(mine).argmax()) > 0.99
    assert labels[shows == 0][0] != labels[shows == 1][0]

    # seen from where its edges are all convex, the tall box alone is one piece
    alone = shoot([(tall, *resting(tall, spin(20), 0.0, 0.0))], [], elevation_deg=45.0)
    assert len(np.unique(creases(frame_of(alone)))) == 1
