"""A whole frame in another unit than the references' (a camera that writes millimetres, a
depth image read at the wrong depth_scale): no registered part could cover the pixels a
part is searched on, and the answer says so and names the likely unit, instead of an empty
list like that of a frame holding no part (docs/decisions.md#a-frame-in-millimetres)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.engine.engine import Engine
from service.engine.frame import Frame
from service.engine.tuning import MIN_SEGMENT
from service.engine.units import frame_scale_reason
from tests.engines import engine_holding
from tests.frames import frame_of, resting, shoot, spin, table

ANGLE = 1 / 525  # a VGA depth camera's pixel


@pytest.fixture(scope="module")
def engine() -> Engine:
    return engine_holding({"box": trimesh.creation.box((0.08, 0.06, 0.04))})


def scaled(shot, factor: float) -> Frame:
    frame = frame_of(shot)
    return Frame.of(frame.points * factor, frame.index, frame.shape)


def test_a_frame_in_millimetres_is_answered_so(engine):
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    metres = engine.detect(scaled(shot, 1.0))
    assert [d.answer.verdict for d in metres.detections] == ["match"] and not metres.reasons
    millimetres = engine.detect(scaled(shot, 1000.0))
    assert millimetres.detections == []
    (said,) = millimetres.reasons
    assert "probably in millimetres" in said and "send it in metres" in said
    assert millimetres.unexplained == millimetres.num_points == len(frame_of(shot))


def test_a_depth_image_read_at_the_wrong_scale_is_answered_so(engine):
    # a depth image in tenths of a millimetre read as millimetres: ten times too far
    mesh = trimesh.creation.box((0.08, 0.06, 0.04))
    shot = shoot([(mesh, *resting(mesh, spin(25), 0.0, 0.0))], table())
    (said,) = engine.detect(scaled(shot, 10.0)).reasons
    assert "check the frame's unit" in said and "depth_scale" in said


def test_a_part_a_camera_sees_is_not_doubted():
    ranges = np.full(1000, 1.0)
    assert frame_scale_reason(ranges, ANGLE, 0.01, MIN_SEGMENT) is None  # 1 cm at 1 m
    assert frame_scale_reason(ranges * 3, ANGLE, 0.05, MIN_SEGMENT) is None  # 5 cm at 3 m
    # 5 mm at 2 m covers too few pixels, but no unit brings it into a camera's range
    said = frame_scale_reason(ranges * 2, ANGLE, 0.005, MIN_SEGMENT)
    assert "bring the camera nearer" in said and "probably" not in said
