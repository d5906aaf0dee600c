"""Segments on an organized frame (``service.engine.segments``): a part's lower rim, given back
from the support's band, joins the part above it and never two parts."""

from __future__ import annotations

import numpy as np

from service.engine.frame import Frame
from service.engine.segments import segments


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
