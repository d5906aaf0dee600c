"""Which planes of a whole frame are supports (``service.engine.supports``): ray-cast frames
of a table seen from beyond its edge, and of a bin standing on a table, with a gallery whose
largest part is far larger than anything in view (so that no plane is a support by its size
alone)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.engine import supports as supports_module
from service.engine.supports import set_aside_supports, tolerances
from tests.frames import box, frame_of, resting, shoot, spin, table

# the parts a frame may hold: small ones, and one (a tray) that reaches past the table
SCALES = np.array([0.04, 0.06, 0.9])
FLOOR = box((6.0, 6.0, 0.02), (0.0, 0.0, -0.76))  # the room's floor, 0.75 m under the table
TOP = box((0.6, 0.5, 0.03), (0.0, 0.0, -0.015))  # a table top, its surface at z = 0


def raised_bin(part, inside: float = 0.3, wall: float = 0.01, height: float = 0.1):
    """A bin standing on the table, its floor a slab ``wall`` thick, and two of ``part`` in
    it: the bin's meshes, and the parts placed (mesh, world R, world t)."""
    half = inside / 2 + wall / 2
    meshes = [
        box((inside + 2 * wall, inside + 2 * wall, wall), (0.0, 0.0, wall / 2)),  # its floor
        box((inside + 2 * wall, wall, height), (0.0, half, wall + height / 2)),
        box((inside + 2 * wall, wall, height), (0.0, -half, wall + height / 2)),
        box((wall, inside, height), (half, 0.0, wall + height / 2)),
        box((wall, inside, height), (-half, 0.0, wall + height / 2)),
    ]
    placed = [
        (part, *resting(part, spin(10), -0.06, 0.05, wall)),
        (part, *resting(part, spin(70), 0.07, -0.04, wall)),
    ]
    return meshes, placed


def supports_of(shot, scales=SCALES):
    frame = frame_of(shot).thinned(0.002)
    keep, supports = set_aside_supports(
        frame, frame.pixel_angle(), scales, np.random.default_rng(0)
    )
    return frame, keep, supports


def over_table(frame, shot, supports, low: float, high: float = np.inf) -> np.ndarray:
    """Which of the frame's support pixels (not a part's) lie ``low``-``high`` over the
    table (the first support)."""
    table = supports[0].plane
    height = frame.points @ table[:3] - table[3]
    bare = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == -1))
    return bare & (height > low) & (height < high)


@pytest.fixture(scope="module")
def parts():
    small = box((0.08, 0.06, 0.04), (0.0, 0.0, 0.0))
    return small


def test_a_table_seen_past_its_edge_is_set_aside_with_the_floor_under_it(parts):
    # the camera stands beyond the table's edge: it sees the floor under the table's rim,
    # which lies behind the table's cells but apart from it (not the rest of a part)
    placed = [(parts, *resting(parts, spin(20), 0.05, 0.0))]
    top = box((1.2, 1.0, 0.03), (0.0, 0.0, -0.015))  # the largest plane in view
    shot = shoot(placed, [top, FLOOR], elevation_deg=35.0, distance=1.1)
    floor_seen = np.isfinite(shot.points[..., 2]) & (shot.shows < 0)
    assert floor_seen.any()
    frame, keep, supports = supports_of(shot)
    assert supports, "the table was not taken as a support"
    first = supports[0]
    # the first support is the table (the box's pixels lie just over it), not the floor
    box_points = frame.points[np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == 0))]
    heights = box_points @ first.plane[:3] - first.plane[3]
    assert np.median(heights) > 0.005 and np.max(heights) < 0.06
    # the box is left for the search; the floor, 0.75 m behind the table, is set aside
    left = frame.points[keep] @ first.plane[:3] - first.plane[3]
    assert left.min() > -0.05
    assert keep[np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == 0))].mean() > 0.9


def test_a_bins_floor_on_a_table_is_a_support_and_the_parts_in_it_are_left(parts):
    bin_meshes, placed = raised_bin(parts)
    shot = shoot(placed, [TOP, FLOOR, *bin_meshes], elevation_deg=70.0, distance=0.9)
    frame, keep, supports = supports_of(shot)
    assert len(supports) >= 2, "the bin's floor was not taken as a support"
    table, floor = supports[0], supports[1]
    assert abs(table.plane[:3] @ floor.plane[:3]) > 0.99  # level with the table
    shown = frame.index
    for k in range(len(placed)):  # each box is left whole for the search
        mine = np.isin(shown, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9
    # the bin's floor itself is set aside: few points left lie on it
    on_floor = np.abs(frame.points @ floor.plane[:3] - floor.plane[3]) < 0.003
    assert (keep & on_floor).sum() < 0.1 * on_floor.sum()


def test_a_bins_walls_are_set_aside_though_they_reach_less_than_a_large_part(parts):
    # a registered part of 15 cm: the walls (30 cm long) reach less than WALL_REACH times it,
    # but they stand round the bin's floor found before them
    bin_meshes, placed = raised_bin(parts)
    shot = shoot(placed, [TOP, FLOOR, *bin_meshes], elevation_deg=55.0, distance=0.9)
    frame, keep, supports = supports_of(shot, np.array([0.04, 0.06, 0.15, 0.9]))
    walls = over_table(frame, shot, supports, 0.02)
    assert walls.sum() > 500
    assert keep[walls].mean() < 0.03, "the bin's walls were kept"
    for k in range(len(placed)):  # the boxes in the bin are left whole for the search
        mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9


def test_a_parts_top_face_level_with_the_table_is_not_a_bins_floor(parts):
    # a tall box's top: level with the table, but far higher above it than a bin's floor
    tall = box((0.16, 0.14, 0.06), (0.0, 0.0, 0.0))
    placed = [
        (tall, *resting(tall, spin(15), 0.0, 0.0)),
        (parts, *resting(parts, spin(0), 0.0, 0.0, 0.06)),
    ]
    shot = shoot(placed, [TOP, FLOOR], elevation_deg=80.0, distance=0.8)
    radius = float(np.linalg.norm([0.08, 0.07, 0.03]))  # the tall box is a registered part
    frame, keep, supports = supports_of(shot, np.append(SCALES, radius))
    top = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == 0))
    assert keep[top].mean() > 0.9, "the tall box's top was set aside as a support"


def test_a_table_over_a_floor_seen_more_than_it_is_set_aside(parts):
    # from 2 m the room's floor is the largest plane, found first; the table over it holds a
    # third as many points and reaches less far than the gallery's largest part (1 m), so it
    # is no support by its reach: lying parallel over the floor, carrying, it is one
    placed = [(parts, *resting(parts, spin(20), 0.05, 0.0))]
    top = box((1.4, 1.0, 0.03), (0.0, 0.0, -0.015))
    shot = shoot(placed, [top, FLOOR], elevation_deg=45.0, distance=2.0)
    frame, keep, supports = supports_of(shot, np.array([0.04, 0.06, 1.0]))
    part = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == 0))
    assert len(supports) >= 2
    floor, table = supports[:2]
    assert floor.plane[3] < table.plane[3]  # the floor, farther from the camera, came first
    assert floor.points > 2 * table.points
    assert keep[~part].mean() < 0.05, "the table was kept as a part's face"
    assert keep[part].mean() > 0.85


@pytest.mark.parametrize("elevation", [55.0, 65.0, 75.0])
def test_a_bins_walls_and_rims_are_set_aside_round_its_floor(parts, elevation):
    # seen from high up, the walls hold too few points to be planes of their own, and the
    # rims (their tops) are level with the table like a part's top face: both stand round
    # the floor's outline. From lower, the walls are planes (and the floor merges with the
    # table's plane)
    bin_meshes, placed = raised_bin(parts)
    shot = shoot(placed, [TOP, FLOOR, *bin_meshes], elevation_deg=elevation, distance=0.9)
    frame, keep, supports = supports_of(shot)
    walls = over_table(frame, shot, supports, 0.02)  # higher than the bin's floor: 1 cm
    assert walls.sum() > 500
    assert keep[walls].mean() < 0.03, "the bin's walls or rims were left for the search"
    for k in range(len(placed)):  # the boxes in the bin are left whole
        mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9


def test_a_mat_on_the_table_sets_aside_no_band_and_a_part_beside_it_is_left(parts):
    # a mat: level on the table, just above it, with nothing standing round it but a part
    # (16 cm long: as tall over the mat as a bin's wall) on the table by one of its edges
    mat = box((0.3, 0.3, 0.01), (0.0, 0.0, 0.005))
    tall = box((0.16, 0.08, 0.06), (0.0, 0.0, 0.0))
    placed = [
        (parts, *resting(parts, spin(10), -0.05, 0.04, 0.01)),  # on the mat
        (tall, *resting(tall, spin(90), 0.2, 0.0)),  # on the table, by the mat's edge
    ]
    shot = shoot(placed, [TOP, FLOOR, mat], elevation_deg=65.0, distance=0.9)
    frame, keep, supports = supports_of(shot)
    assert len(supports) >= 2, "the mat was not taken as a support"
    assert all(s.band is None for s in supports)
    for k in range(len(placed)):
        mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9


def test_supports_found_on_a_coarser_copy_are_those_of_the_whole_frame(parts, monkeypatch):
    # a VGA frame holds about four times SUPPORT_POINTS: the supports are found on every
    # other row and column, judged at the whole frame's tolerances, and set aside on it
    bin_meshes, placed = raised_bin(parts)
    shot = shoot(placed, [TOP, FLOOR, *bin_meshes], elevation_deg=65.0, distance=0.9)
    frame = frame_of(shot).thinned(0.002)
    coarse = frame.at_most(supports_module.SUPPORT_POINTS, np.random.default_rng(0))
    assert len(coarse) <= supports_module.SUPPORT_POINTS < len(frame)
    assert coarse.step > frame.step and np.all(coarse.rows % coarse.step == 0)
    _, keep, supports = supports_of(shot)
    monkeypatch.setattr(supports_module, "SUPPORT_POINTS", len(frame))  # the whole frame
    _, whole_keep, whole = supports_of(shot)
    assert len(supports) == len(whole) >= 2
    for mine, theirs in zip(supports, whole, strict=True):
        assert mine.plane[:3] @ theirs.plane[:3] > np.cos(np.radians(0.5))
        assert abs(mine.plane[3] - theirs.plane[3]) < 0.002
        assert abs(mine.points - theirs.points) < 0.05 * theirs.points
    assert np.mean(keep == whole_keep) > 0.99
    for k in range(len(placed)):
        part = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[part].mean() > 0.9


@pytest.mark.parametrize("lift", [0.03, 0.012])
def test_two_parts_faces_in_one_tilted_plane_are_not_a_support(parts, lift):
    # two plates lying side by side, tilted the same way, a box on one: their top faces make
    # one plane that reaches farther than either plate and carries the box, but it is not
    # level with the table, as a bin's floor would be, nor a wall: no support. Lifted 12 mm,
    # the plane lies as low over the table as a bin's floor, but tilted 6 degrees from it
    # (docs/decisions.md#a-bins-floor-level-with-the-table)
    plate = box((0.24, 0.15, 0.01), (0.0, 0.0, 0.0))
    tilt = Rotation.from_euler("y", 6.0, degrees=True).as_matrix()
    lift = np.array([0.0, 0.0, lift])
    placed = [
        (plate, tilt, tilt @ np.array([0.0, -0.076, 0.0]) + lift),
        (plate, tilt, tilt @ np.array([0.0, 0.076, 0.0]) + lift),
        (parts, tilt, tilt @ np.array([0.02, -0.07, 0.025]) + lift),
    ]
    shot = shoot(placed, [TOP, FLOOR], elevation_deg=65.0, distance=0.8)
    scales = np.array([0.054, float(np.linalg.norm([0.12, 0.075, 0.005]))])
    frame, keep, supports = supports_of(shot, scales)
    assert len(supports) >= 1  # the table
    for k in range(2):
        mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9, f"plate {k} was set aside as a support"


def test_a_thin_parts_lower_rim_is_kept_and_the_tables_noise_set_aside():
    # a plate 8 mm thick lying flat: its sides' lower millimetres lie in the table's band
    # (4.6 mm here); those clearly over the table's noise touch the plate and are given back,
    # while the table's own noise stays set aside (docs/decisions.md#a-supports-rim-given-back)
    plate = box((0.07, 0.05, 0.008), (0.0, 0.0, 0.0))
    shot = shoot([(plate, *resting(plate, spin(25), 0.0, 0.0))], table(), elevation_deg=50.0)
    frame, keep, supports = supports_of(shot)
    first = supports[0]
    height = frame.points @ first.plane[:3] - first.plane[3]
    band = tolerances(frame, frame.pixel_angle())
    mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == 0))
    rim = mine & (height > 3.5 * first.noise) & (height < band)
    assert rim.sum() >= 10, "the plate has no rim in the table's band"
    assert keep[rim].all()
    bare = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == -1))
    assert (keep & bare).sum() < 1e-4 * bare.sum()


def test_in_a_bin_the_parts_rims_on_its_floor_are_kept_and_the_tables_band_set_aside(parts):
    # the parts rest on the bin's floor, not on the table: their lower rims in the floor's
    # band are given back; the table's band round the bin holds only the bin's outer walls,
    # and stays set aside (docs/decisions.md#a-supports-rim-given-back)
    bin_meshes, placed = raised_bin(parts)
    shot = shoot(placed, [*table(), *bin_meshes], elevation_deg=55.0, distance=0.9)
    frame, keep, supports = supports_of(shot, np.array([0.03, 0.06, 0.15]))
    floor = next(s for s in supports if s.band is not None)
    band = tolerances(frame, frame.pixel_angle())
    bare = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == -1))
    over_floor = frame.points @ floor.plane[:3] - floor.plane[3]
    rim = ~bare & (over_floor > 3.5 * floor.noise) & (over_floor < band)
    assert rim.sum() >= 10, "the parts have no rim in the floor's band"
    assert keep[rim].all()
    table_plane = supports[0].plane
    in_table_band = np.abs(frame.points @ table_plane[:3] - table_plane[3]) < band
    assert not (keep & bare & in_table_band).any()


def test_flat_parts_tops_level_over_a_bins_floor_are_not_another_floor(parts):
    # four plates 13 mm thick lying side by side on a bin's floor, a box on one: their tops
    # make a plane level with the floor, just above it, that carries the box, as a bin's
    # floor over a table would; but a floor on a floor is parts lying on it
    # (docs/decisions.md#flat-parts-tops-over-a-bins-floor)
    bin_meshes, _ = raised_bin(parts)
    plate = box((0.12, 0.06, 0.013), (0.0, 0.0, 0.0))
    wall = 0.01
    placed = [
        (plate, *resting(plate, spin(0), x, y, wall))
        for x, y in ((-0.065, -0.035), (0.065, -0.035), (-0.065, 0.035), (0.065, 0.035))
    ]
    placed.append((parts, *resting(parts, spin(30), -0.06, -0.035, wall + 0.013)))
    shot = shoot(placed, [*table(), *bin_meshes], elevation_deg=60.0, distance=0.9)
    frame, keep, supports = supports_of(shot, np.array([0.03, 0.07, 0.15]))
    assert any(s.band is not None for s in supports)  # the bin's floor
    for k in range(4):
        mine = np.isin(frame.index, np.flatnonzero(shot.shows.ravel() == k))
        assert keep[mine].mean() > 0.9, f"plate {k} was set aside as a floor"
