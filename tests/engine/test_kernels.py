"""The compiled loops (``service.engine.kernels``) against their numpy twins: the same poses,
iterations, samples and distances on real surfaces, the bracket's mesh and its scanned cloud."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.engine import kernels
from service.engine.icp import Start, icp, icp_many
from service.engine.normalize import radius
from service.engine.sampling import sample_surface_faces
from service.engine.verification import Occupancy, coverage, fit, surface_distance
from tests.engine.test_surface import l_bracket, surface_of

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba (the fast extra) is absent")


@pytest.fixture(scope="module")
def surfaces():
    return surface_of(l_bracket()), surface_of(l_bracket(), from_mesh=False)


@pytest.fixture
def both():
    """Runs a function with the compiled loops and with numpy's; the switch as it was after."""
    was = kernels.switch.enabled

    def run(function):
        try:
            return [(kernels.use(on), function())[1] for on in (True, False)]
        finally:
            kernels.use(was)

    return run


def starts_on(surfaces, scene_pose, count=12, seed=3):
    """Starts about the truth on both surfaces, told a camera or not, each with its budget;
    the last one too far from the points to pair with any."""
    rotation, translation = scene_pose
    rng = np.random.default_rng(seed)
    scale = radius(surfaces[0].points)
    starts = []
    for k in range(count):
        turn = Rotation.from_rotvec(rng.normal(size=3) * 0.2).as_matrix()
        shift = translation + rng.normal(scale=0.05 * scale, size=3)
        if k == count - 1:
            shift = translation + 10 * scale
        camera = None if k % 2 else translation + np.array([0.0, 0.0, -0.5])
        starts.append(
            Start(
                surfaces[1 if k % 3 == 0 else 0],  # every third on the scanned cloud
                turn @ rotation,
                shift,
                1e-3 * scale,
                0.3 * scale,
                4 + k,
                camera,
            )
        )
    return starts


def test_compiled_refinement_gives_numpys_poses_and_iterations(surfaces, both):
    rotation = Rotation.random(random_state=4).as_matrix()
    translation = np.array([0.1, 0.0, 0.4])
    scene = sample_surface_faces(l_bracket(), 384, 9)[0] @ rotation.T + translation
    starts = starts_on(surfaces, (rotation, translation))
    compiled, plain = both(lambda: icp_many(scene, starts))
    for (r1, t1, n1), (r2, t2, n2) in zip(compiled, plain, strict=True):
        assert n1 == n2
        np.testing.assert_allclose(r1, r2, atol=1e-8)
        np.testing.assert_allclose(t1, t2, atol=1e-8)
    assert compiled[-1][2] == 1  # too far: stopped where it was
    assert sum(n < s.iterations for (_, _, n), s in zip(compiled, starts, strict=True)) >= 3
    one = starts[0]  # one start alone, as the symmetry's refinement asks
    alone = both(lambda: icp(scene, one.surface, one.rotation, one.translation, 1e-4, 0.05))
    np.testing.assert_allclose(alone[0][0], alone[1][0], atol=1e-8)
    assert alone[0][2] == alone[1][2]


def test_compiled_refinement_of_a_start_on_its_own_points(surfaces, both):
    """A scene a start (H, M, 3), as a frame's placed views are refined."""
    rotation = Rotation.random(random_state=6).as_matrix()
    scenes = np.stack(
        [
            sample_surface_faces(l_bracket(), 300, 20 + k)[0] @ rotation.T + [0.1 * k, 0, 0.5]
            for k in range(3)
        ]
    )
    starts = starts_on(surfaces, (rotation, np.array([0.1, 0.0, 0.5])), count=3)
    compiled, plain = both(lambda: icp_many(scenes, starts))
    for (r1, t1, n1), (r2, t2, n2) in zip(compiled, plain, strict=True):
        assert n1 == n2
        np.testing.assert_allclose(r1, r2, atol=1e-8)
        np.testing.assert_allclose(t1, t2, atol=1e-8)


@pytest.mark.parametrize("lookup", ["field", "nearest", "facing"])
def test_compiled_distances_are_numpys(surfaces, both, lookup):
    rng = np.random.default_rng(8)
    for surface in surfaces:
        points = surface.points[rng.integers(0, len(surface.points), (5, 400))]
        points = points + rng.normal(scale=2 * surface.spacing, size=points.shape)
        points[0, :10] = 5.0  # past the field's edge
        (d1, s1), (d2, s2) = both(lambda s=surface, p=points: surface_distance(s, p, lookup))
        assert d1.shape == s1.shape == (5, 400)
        np.testing.assert_array_equal(s1, s2)
        np.testing.assert_allclose(d1, d2, rtol=1e-12, atol=1e-15)
    rotations = Rotation.random(4, random_state=1).as_matrix()
    shares = both(lambda: fit(surfaces[0], points[0], rotations, np.zeros((4, 3)), 0.01, lookup))
    np.testing.assert_array_equal(shares[0], shares[1])


def test_compiled_fit_and_coverage_are_numpys(surfaces, both):
    """Hypotheses about the truth and far from it: the same shares, to the point."""
    bracket = surfaces[0]
    rotation = Rotation.random(random_state=2).as_matrix()
    translation = np.array([0.05, -0.02, 0.6])
    observed = sample_surface_faces(l_bracket(), 600, 5)[0] @ rotation.T + translation
    rng = np.random.default_rng(4)
    turns = Rotation.from_rotvec(rng.normal(size=(16, 3)) * 0.3).as_matrix()
    rotations = turns @ rotation
    translations = translation + rng.normal(scale=0.01, size=(16, 3))
    tolerance = 0.02 * radius(bracket.points)
    occupancy = Occupancy.around(observed, tolerance, bracket.spacing)
    expected = bracket.points[rng.integers(0, len(bracket.points), (16, 256))]
    for lookup in ("field", "nearest", "facing"):
        fits = both(
            lambda lk=lookup: fit(bracket, observed, rotations, translations, tolerance, lk)
        )
        np.testing.assert_array_equal(fits[0], fits[1])
        assert 0 < fits[0].min() < fits[0].max() <= 1  # some fit, some do not
    covered = both(lambda: coverage(expected, rotations, translations, occupancy))
    np.testing.assert_array_equal(covered[0], covered[1])
    assert 0 < covered[0].min() < covered[0].max() <= 1


def test_the_median_and_the_solve_are_numpys():
    rng = np.random.default_rng(0)
    for count in range(1, 80):
        values = rng.normal(size=count + 5)
        if count % 3 == 0:
            values = np.round(values, 1)  # ties
        assert kernels._median(values.copy(), count) == np.median(values[:count])
    for _ in range(100):
        matrix = rng.normal(size=(6, 6))
        right = rng.normal(size=6)
        solved = kernels._solve(matrix.copy(), right.copy())
        np.testing.assert_allclose(solved, np.linalg.solve(matrix, right), rtol=1e-8, atol=1e-10)


def test_the_switch_runs_numpy_where_told():
    was = kernels.switch.enabled
    try:
        assert kernels.use(False) is False
        assert "DPC_ENGINE__COMPILED=false" in kernels.describe()
        assert kernels.use(True) is True
        assert "compiled" in kernels.describe()
    finally:
        kernels.use(was)


def test_an_engine_set_not_to_compile_answers_as_the_compiled_one(duck_points):
    """``DPC_ENGINE__COMPILED=false``: the engine runs numpy's loops, to the same answer."""
    from service.engine.engine import Engine
    from tests.engines import SETTINGS, engine_holding
    from tests.meshes import pybullet_mesh

    was = kernels.switch.enabled
    try:
        compiled = engine_holding(
            {"duck": pybullet_mesh("duck.obj"), "mug": pybullet_mesh("objects/mug.obj")}
        )
        assert kernels.switch.enabled
        rotation = Rotation.random(random_state=3).as_matrix()
        view = duck_points[duck_points[:, 2] > np.median(duck_points[:, 2])] @ rotation.T
        first = compiled.align(view, viewpoint=np.array([0.0, 0.0, 1.0]))
        plain = Engine(
            compiled.mapper,
            SETTINGS.engine.model_copy(update={"compiled": False}),
            compiled.calibration,
        )
        plain.load([entry.reference for entry in compiled._snapshot.entries.values()])
        assert not kernels.switch.enabled
        second = plain.align(view, viewpoint=np.array([0.0, 0.0, 1.0]))
        assert (
            (first.label, first.verdict)
            == (second.label, second.verdict)
            == ("duck", first.verdict)
        )
        np.testing.assert_allclose(first.rotation, second.rotation, atol=1e-6)
        assert first.confidence == pytest.approx(second.confidence, abs=1e-6)
    finally:
        kernels.use(was)


WARMED = """
import numpy as np
from scipy.spatial.transform import Rotation
from service.engine import kernels
from service.engine.icp import Start, icp_many
from service.engine.verification import Occupancy, coverage, fit, surface_distance
from tests.engine.test_surface import l_bracket, surface_of

from service.engine.frame import Frame
from service.engine.segments import segments
from service.engine.supports import set_aside_supports

kernels.warm()
loops = (kernels.refine, kernels.distances, kernels.shares, kernels.covered, kernels.grid_labels,
         kernels.msac_votes, kernels.squared_distances, kernels.pair_cosines)
before = [len(loop.signatures) for loop in loops]
bracket = surface_of(l_bracket())
scene = (bracket.points[:300] @ Rotation.random(random_state=1).as_matrix().T).astype(np.float32)
poses = np.stack([np.eye(3)] * 2), np.zeros((2, 3))
starts = [Start(bracket, np.eye(3), np.zeros(3), 1e-4, 0.05, 3, v) for v in (None, np.ones(3))]
icp_many(scene, starts)
icp_many(np.stack([scene, scene]), starts)
for lookup in ("field", "nearest", "facing"):
    surface_distance(bracket, scene, lookup)
    fit(bracket, scene, *poses, 0.01, lookup)
occupancy = Occupancy.around(scene, 0.01, bracket.spacing)
coverage(bracket.points[None, :100].repeat(2, 0), *poses, occupancy)
v, u = np.mgrid[0:120, 0:160]  # a camera's frame: a square block before a wall
rays = np.stack([(u - 79.5) / 130, (v - 59.5) / 130, np.ones(u.shape)], -1).reshape(-1, 3)
depth = np.where((abs(u - 80) < 15) & (abs(v - 60) < 15), 0.9, 1.0).ravel()
frame = Frame.of((rays * depth[:, None]).astype(np.float32), np.arange(len(rays)), (120, 160))
angle = frame.pixel_angle()
keep, _ = set_aside_supports(frame, angle, np.array([0.05]), np.random.default_rng(0))
segments(frame.take(keep), angle)
segments(frame.every(2), angle)
print([len(loop.signatures) for loop in loops] == before, before)
"""


def test_warming_compiles_every_loop_for_what_the_engine_passes():
    """``kernels.warm`` at a start leaves nothing to compile for a request's calls (float32
    points, a camera or none, a scene a start; a camera's frame), in a fresh process."""
    import subprocess
    import sys

    from tests.servers import REPO

    done = subprocess.run(
        [sys.executable, "-c", WARMED], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("True"), done.stdout


def test_where_no_cache_can_be_written_the_loops_compile_in_each_process():
    """A read-only image (Kubernetes' readOnlyRootFilesystem, no writable NUMBA_CACHE_DIR):
    numba finds nowhere to cache, and the loops still compile and run."""
    import subprocess
    import sys

    from tests.servers import REPO

    script = (
        "import numba.core.caching as caching\n"
        "impl = getattr(caching, 'CacheImpl', None) or caching._CacheImpl  # numba 0.68 / older\n"
        "impl._locator_classes = []  # no cache locator can be used\n"
        "from service.engine import kernels\n"
        "kernels.warm()\n"
        "print(kernels.switch.enabled, kernels.refine.signatures != [])\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["True", "True"], done.stdout


def test_compiled_frame_steps_are_numpys(both):
    """Two boxes touching and one apart on a table, at full resolution and every other pixel:
    the same pixel angle and ranges to the bit, the same segment for every point, numbered
    alike."""
    pytest.importorskip("open3d")
    from service.engine.segments import segments
    from service.engine.supports import set_aside_supports
    from tests.frames import box, frame_of, resting, shoot, spin, table

    block = box((0.08, 0.06, 0.05), (0.0, 0.0, 0.0))
    parts = [
        (block, *resting(block, spin(0), -0.04, 0.0)),
        (block, *resting(block, spin(90), 0.0395, 0.0)),  # touching the first
        (block, *resting(block, spin(30), 0.0, 0.15)),
    ]
    shot = shoot(parts, table())
    angles = both(lambda: [frame_of(shot).pixel_angle(), frame_of(shot).every(2).pixel_angle()])
    assert angles[0] == angles[1]
    ranges = both(lambda: frame_of(shot).ranges())
    np.testing.assert_array_equal(ranges[0], ranges[1])
    frame = frame_of(shot)
    angle = frame.pixel_angle()
    keep, _ = set_aside_supports(frame, angle, np.array([0.05]), np.random.default_rng(0))
    rest = frame.take(keep)
    for grid in (rest, rest.every(2)):
        labels = both(lambda g=grid: segments(g, angle))
        np.testing.assert_array_equal(labels[0], labels[1])
        assert labels[0].max() >= 1  # the parts apart from each other


def test_compiled_msac_votes_choose_numpys_plane(both):
    """A table's points and a box's face: the same plane wins, by votes within float32's."""
    from service.engine.supports import msac_votes

    rng = np.random.default_rng(5)
    table = np.column_stack([rng.uniform(-0.3, 0.3, (1500, 2)), rng.normal(0, 1e-3, 1500)])
    face = np.column_stack([rng.uniform(-0.05, 0.05, (500, 2)), np.full(500, 0.04)])
    sample = np.concatenate([table, face])
    triples = sample[rng.integers(0, len(sample), (200, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = np.einsum("ij,ij->i", normals, triples[:, 0])
    slack = np.full(len(sample), 3e-3)
    votes = both(lambda: msac_votes(sample, normals, offsets, slack))
    assert votes[0].argmax() == votes[1].argmax()
    np.testing.assert_allclose(votes[0], votes[1], rtol=1e-4, atol=1e-2)
    assert votes[0].max() > 1000  # the table's plane, through most of the sample
