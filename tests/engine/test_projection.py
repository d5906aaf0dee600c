"""What an organized frame's own points say of its camera: the pinhole that made it, fitted on
a sample of them (refused where the pixels fit no pinhole), and the angle between neighbouring
pixels' rays, the median of a sample of their pairs."""

import numpy as np
import pytest

from service.engine.frame import Frame
from service.engine.projection import DepthImage
from service.engine.tuning import PINHOLE_POINTS, PIXEL_PAIRS
from tests.frames import VGA, frame_of, resting, shoot, spin, table

WIDTH, HEIGHT, FOCAL = VGA


def box_on_table() -> Frame:
    import trimesh

    box = trimesh.creation.box((0.08, 0.06, 0.04))
    return frame_of(shoot([(box, *resting(box, spin(30), 0.0, 0.0))], table()))


def test_a_frames_pinhole_is_read_back_from_its_points_at_every_step():
    # a 640 x 480 frame (far more points than the fit's sample) and its every 3rd row and
    # column: the focal length and centre of the grid, and every point's pixel found again
    frame = box_on_table()
    assert len(frame) > 10 * PINHOLE_POINTS
    for step in (1, 3):
        thin = frame.every(step)
        image = DepthImage.of(thin)
        assert image is not None
        np.testing.assert_allclose(image.focal, [FOCAL / step] * 2, rtol=1e-5)
        np.testing.assert_allclose(
            image.centre, [(WIDTH - 1) / 2 / step, (HEIGHT - 1) / 2 / step], atol=1e-3
        )
        depth = image.depth_at(thin.points)
        np.testing.assert_array_equal(depth, thin.points[:, 2])
        assert np.isfinite(image.depth).sum() == len(thin)


def test_a_frame_whose_pixels_fit_no_pinhole_has_no_depth_image():
    # the same frame with its rays bent outward (a strong radial distortion left in): no
    # pinhole fits its pixels within PINHOLE_RESIDUAL_PX, so nothing is checked against it
    frame = box_on_table()
    ratio = frame.points[:, :2] / frame.points[:, 2:3]
    bent = ratio * (1 + 0.3 * (ratio**2).sum(axis=1, keepdims=True))
    points = np.column_stack([bent * frame.points[:, 2:3], frame.points[:, 2]])
    distorted = Frame.of(points, frame.index, frame.shape)
    assert DepthImage.of(distorted) is None


def all_pairs_angle(frame: Frame) -> float:
    """The median angle between the rays of every pair of horizontally neighbouring pixels of
    ``frame`` (written out over all of them), per pixel of the full grid."""
    rays = frame.points / np.linalg.norm(frame.points, axis=1, keepdims=True)
    beside = np.diff(frame.index) == frame.step
    cosine = np.einsum("ij,ij->i", rays[:-1], rays[1:])[beside]
    return float(np.median(np.arccos(np.clip(cosine, -1, 1)))) / frame.step


def test_a_frames_pixel_angle_is_the_median_of_its_neighbours_from_a_sample():
    # 640 x 480 (more pairs than PIXEL_PAIRS: a sample of them), its every 3rd row and column,
    # and a crop of few pixels (every pair): the median angle between neighbouring rays
    frame = box_on_table()
    assert len(frame) > 2 * PIXEL_PAIRS
    for thin in (frame, frame.every(3)):
        assert thin.pixel_angle() == pytest.approx(all_pairs_angle(thin), rel=2e-3)
    small = frame.take(np.flatnonzero(frame.rows < 40))
    assert len(small) < PIXEL_PAIRS
    assert small.pixel_angle() == pytest.approx(all_pairs_angle(small), rel=1e-12)
