"""A registration's size warning (``service.engine.units.size_warnings``): outside a camera's
working range (a radius of 5 mm to 2 m) or 30 times every other part's, naming the unit the
points are likely in; silent for a part of a camera's size among parts like it."""

from __future__ import annotations

from service.engine.units import size_warnings

GALLERY = {"bracket": 0.05, "housing": 0.2}


def test_a_part_of_a_cameras_size_is_not_warned_about():
    assert size_warnings("pin", 0.01, None, GALLERY) == []
    assert size_warnings("pin", 0.01, "mm", {}) == []


def test_millimetres_sent_as_metres():
    (said,) = size_warnings("flange", 45.0, None, GALLERY)
    assert "working range" in said and "225 times" in said and "(housing, 0.2 m)" in said
    assert "probably in millimetres" in said and "units=mm" in said


def test_metres_sent_as_millimetres():
    (said,) = size_warnings("flange", 0.045e-3, "mm", GALLERY)
    assert "read as millimetres" in said and "probably in metres" in said and "units=m " in said


def test_without_a_gallery_only_the_working_range_counts():
    (said,) = size_warnings("frame", 3.0, None, {})
    assert "working range" in said and "nearest" not in said and "units=cm" in said


def test_far_from_every_part_while_in_range():
    (said,) = size_warnings("washer", 0.006, None, {"crate": 0.9})
    assert "working range" not in said and "1/150 of" in said
    assert "check which unit" in said  # no unit brings it within 30 times of the crate


def test_no_unit_fits_a_point_like_part():
    (said,) = size_warnings("dust", 1e-9, None, GALLERY)
    assert "check which unit its points are in" in said
