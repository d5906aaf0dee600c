"""The depth image read back from an organized frame's own points: the pinhole that made it,
fitted on a sample of them, and refused where the pixels fit no pinhole."""

import numpy as np

from service.engine.frame import Frame
from service.engine.projection import DepthImage
from service.engine.tuning import PINHOLE_POINTS
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
