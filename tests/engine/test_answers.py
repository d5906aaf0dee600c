"""The engine's answers, end to end on the shipped model and gallery: single views, what
surrounds a part, units, the verdict and its confidence, and what registration derives."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from evaluation.metrics import add_s, diameter, geodesic_deg
from service.engine.confidence import Calibration, measures
from service.engine.engine import Engine
from service.engine.fits import Fit
from service.engine.mapping import Mapper
from service.engine.sampling import sample_surface_faces
from service.engine.surroundings import set_aside_surroundings
from service.engine.tuning import ALIKE, RIGHT_EITHER_WAY
from service.engine.views import directions
from service.gallery.gallery_file import load_gallery
from service.settings import Settings
from tests.meshes import pybullet_mesh
from tests.servers import needs_model

SETTINGS = Settings()
needs_calibration = pytest.mark.skipif(
    not SETTINGS.confidence_path.exists(), reason=f"no calibration at {SETTINGS.confidence_path}"
)


@pytest.fixture(scope="module")
def engine() -> Engine:
    calibration = (
        Calibration.load(SETTINGS.confidence_path) if SETTINGS.confidence_path.exists() else None
    )
    engine = Engine(Mapper(SETTINGS.model.path, use_cuda=False), SETTINGS.engine, calibration)
    references, _ = load_gallery(SETTINGS.model.gallery)
    engine.load(references)
    return engine


def placed(points: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rotation = Rotation.random(random_state=seed).as_matrix()
    translation = np.random.default_rng(seed).uniform(-0.2, 0.2, 3) + [0, 0, 0.6]
    return points @ rotation.T + translation, rotation, translation


def right(engine: Engine, name: str, answer, rotation, translation) -> bool:
    points = np.asarray(engine.get(name).points, np.float64)
    error = add_s(
        points, answer.rotation, answer.translation, rotation, translation, diameter(points)
    )
    return answer.label == name and error < 0.1


@needs_model
def test_a_depth_camera_view_of_a_registered_part_is_recognised_and_posed(engine):
    pytest.importorskip("open3d", exc_type=ImportError)
    from evaluation.scenes import sensor_view

    mesh = pybullet_mesh("lego/lego.obj")  # the seen "lego-brick"
    rotation = Rotation.random(random_state=3).as_matrix()
    scale = engine.get("lego-brick").scale
    view = sensor_view(mesh, rotation, 6 * scale, np.random.default_rng(3))
    assert 200 < len(view.points) < 20000
    answer = engine.align(view.points, viewpoint=view.viewpoint)
    assert right(engine, "lego-brick", answer, view.rotation, view.translation)
    assert answer.hypothesis in ("views", "principal-axes", "mapped")
    assert {"surroundings", "map", "classify", "hypothesise", "verify", "refine"} <= set(
        answer.timings_ms
    )


def part_on_table(extents, count: int, rng: np.random.Generator):
    """A box of ``extents`` resting on z = 0, ``count`` points sampled on its surface (those on
    the table left out), and a disc of table around it, 2.5 times its radius, as dense."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation((0, 0, extents[2] / 2))  # resting on z = 0
    part = sample_surface_faces(box, count, 1)[0].astype(np.float64)
    part = part[part[:, 2] > 0.001]  # the face on the table is not seen
    density = len(part) / (box.area - extents[0] * extents[1])  # the camera's, on both
    radius = np.linalg.norm(part - part.mean(axis=0), axis=1).max()
    disc = rng.uniform(-2.5 * radius, 2.5 * radius, size=(round(density * 25 * radius**2), 2))
    disc = disc[np.linalg.norm(disc, axis=1) < 2.5 * radius]
    table = np.column_stack([disc, rng.normal(scale=1e-4, size=len(disc))])
    return part, table, radius


def share_kept(reading, points: np.ndarray) -> float:
    kept = {tuple(p) for p in np.round(reading.points, 9)}
    return float(np.mean([tuple(p) in kept for p in np.round(points, 9)]))


@pytest.mark.parametrize(
    "extents",
    [(0.06, 0.04, 0.05), (0.12, 0.015, 0.015)],  # a box, a fifth of the points; a thin bar, a
    ids=["box", "thin-bar"],  # twentieth: fewer than the strays once the table is set aside
)
def test_the_table_and_two_percent_strays_are_set_aside_from_a_part_on_it(extents):
    rng = np.random.default_rng(0)
    part, table, radius = part_on_table(extents, 3000, rng)
    cloud = np.vstack([part, table])
    count = round(0.02 * len(cloud))  # 2 % strays, as the evaluation's table family
    strays = rng.uniform(cloud.min(axis=0) - radius, cloud.max(axis=0) + radius, (count, 3))
    scene = np.vstack([cloud, strays])
    camera = np.array([0.0, -0.3, 0.4])  # above the table, looking down at it obliquely
    (reading, with_plane) = set_aside_surroundings(scene, rng, camera)
    assert share_kept(reading, part) > 0.9 and share_kept(reading, table) < 0.02
    assert share_kept(reading, strays) < 0.1
    assert reading.support is not None and abs(reading.support[2]) > 0.99
    assert len(with_plane.points) > len(reading.points)  # the other reading keeps the plane
    assert reading.set_aside == len(scene) - len(reading.points)


@pytest.mark.parametrize("count", [800, 3000, 12000])  # the part: 650, 2,500, 10,000 points
def test_without_a_viewpoint_a_table_holding_most_points_is_set_aside(count):
    """However many points the part has: its own points were once counted from a sample of
    1,024 against the table's share of another, and a part of more than ~1,000 points kept a
    table holding four fifths of the cloud."""
    rng = np.random.default_rng(1)
    part, table, _ = part_on_table((0.06, 0.04, 0.05), count, rng)
    (reading, _) = set_aside_surroundings(np.vstack([part, table]), rng)
    assert share_kept(reading, part) > 0.9 and share_kept(reading, table) < 0.02


def test_without_a_viewpoint_a_plane_holding_less_than_half_the_points_is_kept():
    rng = np.random.default_rng(2)
    part, table, _ = part_on_table((0.06, 0.04, 0.05), 12000, rng)
    table = table[: len(part) // 2]  # a third of the cloud: may be a face of a larger part
    (reading,) = set_aside_surroundings(np.vstack([part, table]), rng)
    assert reading.support is None and share_kept(reading, part) > 0.99


@needs_model
def test_a_clean_cloud_sets_nothing_aside(engine):
    sample = np.asarray(engine.get("mug").points, np.float64)
    (reading,) = set_aside_surroundings(sample, np.random.default_rng(0))
    assert reading.set_aside == 0 and len(reading.points) == len(sample)


@needs_model
@pytest.mark.parametrize("part", ["mug", "kuka-link-0"])  # kuka-link-0 in mm: near no part's
def test_a_millimetre_cloud_is_no_match_naming_the_units(engine, part):  # size, yet a big one's
    scene, _, _ = placed(np.asarray(engine.get(part).points, np.float64), 4)
    answer = engine.align(scene * 1000)
    assert answer.verdict == "no_match"
    assert any("millimetres" in reason for reason in answer.reasons), answer.reasons
    assert np.isfinite(answer.alignment_error) and np.isfinite(answer.rotation).all()


@needs_model
@needs_calibration
def test_min_confidence_is_honoured(engine):
    points = np.asarray(engine.get("bunny").points, np.float64)
    rng = np.random.default_rng(5)
    scene, rotation, translation = placed(points + rng.normal(scale=1e-4, size=points.shape), 5)
    plain = engine.align(scene)
    assert right(engine, "bunny", plain, rotation, translation)
    assert plain.verdict == "match" and plain.confidence >= engine.calibration.accept
    strict = engine.align(scene, min_confidence=min(1.0, plain.confidence + 1e-6))
    assert strict.verdict != "match" and strict.reasons
    assert engine.align(scene, min_confidence=0.0).verdict == "match"


@needs_model
def test_the_answer_s_pose_is_finished_where_the_search_stopped_short(engine):
    """With the search's ICP cut to two iterations, the answer's pose is finished on every
    observed point: nearer the truth than without the polish, with the same verdict and
    confidence (the polish moves the pose alone)."""
    references = [engine.get(name) for name in engine.names()]
    points = np.asarray(engine.get("bunny").points, np.float64)
    rng = np.random.default_rng(6)
    scene, rotation, _ = placed(points + rng.normal(scale=3e-4, size=points.shape), 6)
    answers = {}
    for extra in (0, 24):
        settings = SETTINGS.engine.model_copy(
            update={"icp_iterations": 2, "polish_iterations": extra}
        )
        short = Engine(engine.mapper, settings, engine.calibration)
        short.load(references)
        answers[extra] = short.align(scene)
    error = {k: geodesic_deg(a.rotation, rotation) for k, a in answers.items()}
    assert error[24] < 0.5 * error[0] and error[24] < 0.5, error
    assert answers[24].confidence == answers[0].confidence
    assert answers[24].verdict == answers[0].verdict and answers[24].label == "bunny"
    assert answers[24].alignment_error < answers[0].alignment_error


@needs_calibration
def test_confidence_is_monotone_in_the_fit():
    calibration = Calibration.load(SETTINGS.confidence_path)
    previous = -1.0
    for share in np.linspace(0.0, 1.0, 21):
        value = calibration.confidence(measures(share, 0.9, 0.2, 0.0, 2048, 1.0))
        assert value >= previous
        previous = value


@needs_model
@needs_calibration
def test_noise_is_no_match(engine):
    rng = np.random.default_rng(6)
    scale = engine.get("mug").scale
    junk = rng.uniform(-scale, scale, size=(2000, 3)) + [0, 0, 0.5]
    answer = engine.align(junk)
    assert answer.verdict != "match" and answer.reasons


@needs_model
@needs_calibration
def test_a_right_but_uncertain_answer_is_not_told_to_change_units(engine):
    # the evaluation's second table view of kuka-link-6 (registered at run time, as there):
    # the part fits 76 % of the cloud; its reasons once said that at 100 times its size the
    # cloud would be a registered part's (the gallery holds parts in millimetres)
    from evaluation.cases import make_cases
    from training.objects import load_manifest, load_object_meshes

    name = "kuka-link-6"
    meshes = load_object_meshes([spec for spec in load_manifest() if spec.name == name])
    points, faces = sample_surface_faces(meshes[name], 2048, 0)
    made = engine.make_reference(name, points, mesh=meshes[name], face_index=faces)
    calibration = Calibration.load(SETTINGS.confidence_path)
    # on every point of the view: from the shipped sample of 8,192 it is a "match"
    whole = SETTINGS.engine.model_copy(update={"align_points": 65536})
    registered = Engine(engine.mapper, whole, calibration)
    registered.load([*load_gallery(SETTINGS.model.gallery)[0], made])
    case = make_cases("table", meshes, {name: made.scale}, 2048, 0, 2)[1]
    answer = registered.align(case.points, viewpoint=np.asarray(case.params["viewpoint"]))
    assert answer.label == name and answer.verdict == "uncertain"
    assert answer.fit < 0.8  # poor: what once brought the hint
    assert not any("its size" in reason for reason in answer.reasons), answer.reasons


@needs_model
def test_a_view_answered_half_a_turn_off_is_turned_back(engine):
    # the evaluation's first table view of franka-link-3: the views' frames matched it upside
    # down (174 degrees off, 74 % fit) and refinement stayed there; the truth fits 99 %
    from evaluation.cases import make_cases
    from training.objects import load_manifest, load_object_meshes

    name = "franka-link-3"
    meshes = load_object_meshes([spec for spec in load_manifest() if spec.name == name])
    case = make_cases("table", meshes, {name: engine.get(name).scale}, 2048, 0, 2)[0]
    answer = engine.align(case.points, viewpoint=np.asarray(case.params["viewpoint"]))
    assert answer.label == name and answer.hypothesis == "flip"
    assert geodesic_deg(answer.rotation, case.rotation) < 2 and answer.fit > 0.95


@needs_model
def test_points_at_one_place_once_strays_are_set_aside_are_no_match(engine):
    # found by fuzzing the API: the strays gave the cloud its extent, the rest had none, and
    # normalising it divided by zero (a 500 on the way)
    for place in ([0.0, 0.0, 0.0], [5.0, 5.0, 5.0]):
        cloud = np.vstack([np.tile(place, (200, 1)), [[1, 1, 1], [2, 2, 2], [-1, 3, 0]]])
        with np.errstate(all="raise"):
            answer = engine.align(cloud)
        assert answer.verdict == "no_match" and answer.points_set_aside == 3
        assert "lie at one place" in answer.reasons[0]


@needs_model
def test_the_part_eq4_likes_best_is_refined_before_another_part_wins():
    # found in the evaluation: a noisy full cloud of random-250 was answered as random-075,
    # accepted, whose pose was refined first and fit "excellently" (0.91); random-250's own
    # pose, never refined, fits 0.99 once it is. Eq. (4) put random-250 first
    from evaluation.cases import make_cases

    engine = Engine(Mapper(SETTINGS.model.path, use_cuda=False), SETTINGS.engine)
    references, _ = load_gallery(SETTINGS.model.gallery)
    other = pybullet_mesh("random_urdfs/075/075.obj")  # registered at run time, as there
    points, faces = sample_surface_faces(other, 2048, 0)
    made = engine.make_reference("random-075", points, mesh=other, face_index=faces)
    engine.load([*references, made])
    mesh = pybullet_mesh("random_urdfs/250/250.obj")
    scale = engine.get("random-250").scale
    for cloud in make_cases("noisy", {"random-250": mesh}, {"random-250": scale}, 2048, 0, 2):
        answer = engine.align(cloud.points)
        assert right(engine, "random-250", answer, cloud.rotation, cloud.translation), answer.label


@needs_model
def test_a_part_whose_right_pose_verifies_worse_before_refinement_can_be_rescued():
    # found in the evaluation: random-750's fourth depth-camera view (seed 0) was answered as
    # random-900, whose best pose verified better before refinement; told the part, the
    # engine finds a pose that fits 98 % of the view. With rescued_parts (4 by default) the
    # search finds it too
    pytest.importorskip("open3d", exc_type=ImportError)
    from evaluation.cases import make_cases

    assert SETTINGS.engine.rescued_parts
    engine = Engine(Mapper(SETTINGS.model.path, use_cuda=False), SETTINGS.engine)
    references, _ = load_gallery(SETTINGS.model.gallery)
    mesh = pybullet_mesh("random_urdfs/750/750.obj")
    points, faces = sample_surface_faces(mesh, 2048, 0)
    made = engine.make_reference("random-750", points, mesh=mesh, face_index=faces)
    engine.load([*references, made])
    scale = engine.get("random-750").scale
    view = make_cases("sensor", {"random-750": mesh}, {"random-750": scale}, 2048, 0, 4)[3]
    answer = engine.align(view.points, viewpoint=np.asarray(view.params["viewpoint"]))
    assert right(engine, "random-750", answer, view.rotation, view.translation), answer.label


@needs_model
@needs_calibration
def test_one_flat_face_is_never_a_match(engine):
    # a flat disc as big as kuka-link-0's base: the base seen from below shows nothing else,
    # and its turn about the normal is anybody's guess; a robot must not act on it
    rng = np.random.default_rng(7)
    scale = engine.get("kuka-link-0").scale
    disc = rng.uniform(-scale, scale, size=(6000, 2))
    disc = disc[np.linalg.norm(disc, axis=1) < scale][:2048]
    flat = np.column_stack([disc, rng.normal(scale=0.002 * scale, size=len(disc))])
    for seed in range(3):
        points, _, _ = placed(flat, seed)
        answer = engine.align(points, candidates=["kuka-link-0"])
        assert answer.verdict != "match"
        assert any("one plane" in reason for reason in answer.reasons)
    # the same part seen whole still is
    whole, rotation, translation = placed(np.asarray(engine.get("kuka-link-0").points), 8)
    answer = engine.align(whole, candidates=["kuka-link-0"])
    assert answer.verdict == "match" and right(engine, "kuka-link-0", answer, rotation, translation)


@needs_model
@pytest.mark.parametrize("as_mesh", [True, False], ids=["mesh", "cloud"])
def test_registration_of_a_mesh_and_of_a_cloud_produces_views(engine, as_mesh):
    mesh = pybullet_mesh("duck.obj")
    points, faces = sample_surface_faces(mesh, 2048, 0)
    reference = engine.make_reference(
        "duck", points, mesh=mesh if as_mesh else None, face_index=faces if as_mesh else None
    )
    views = engine.settings.views
    assert not reference.missing
    assert reference.visible().shape == (views, len(points))
    seen = reference.visible().mean(axis=1)
    assert 0.15 < np.median(seen) < 0.6  # a camera sees about a third to half of a part
    assert reference.view_features.shape == (views, 256)
    assert reference.symmetry["kind"] == "none"  # a duck has no symmetry
    # unit normals, facing the cameras that see their points
    normals = reference.normals.astype(np.float64)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-3)
    visible, ways = reference.visible(), directions(views)
    facing = [normals[visible[k]] @ ways[k] > 0 for k in range(views)]
    assert np.mean(np.concatenate(facing)) > 0.93


@needs_model
def test_a_flange_that_only_a_notch_tells_apart_is_answered_at_the_right_turn():
    """The KUKA flange is round but for a notch (1.7 % of its surface): a turn about its axis
    nearly fits. Its near-symmetries, found at registration, are tried at the best pose and
    the one nearest the surface wins; without them, most answers are turned 18-71 degrees."""
    (flange,) = [r for r in load_gallery(SETTINGS.model.gallery)[0] if r.name == "kuka-link-7"]
    assert len(flange.symmetry["near"]) > 0
    bare = {k: v for k, v in flange.symmetry.items() if k != "near"}
    mesh = pybullet_mesh("kuka_iiwa/meshes/link_7.obj")
    mapper = Mapper(SETTINGS.model.path, use_cuda=False)
    within = {}
    for kind, reference in (("near", flange), ("bare", flange.with_(symmetry=bare))):
        engine = Engine(mapper, SETTINGS.engine)
        engine.load([reference])
        symmetry = engine.entry("kuka-link-7").symmetry
        errors = []
        for seed in range(8):
            points, _ = sample_surface_faces(mesh, 2048, 100 + seed)
            rotation = Rotation.random(random_state=seed).as_matrix()
            answer = engine.align(points.astype(np.float64) @ rotation.T + [0, 0, 0.6])
            errors.append(symmetry.distance_deg(answer.rotation, rotation))
        within[kind] = sum(e < 2.0 for e in errors)
    assert within["near"] >= 6 and within["bare"] <= 3, within


def symmetric_cases(
    engine: Engine, name: str, mesh_path: str | None, order: int, mesh=None
) -> list:
    """The evaluation's symmetric cases of a registered part (seed 0, two groups): one pose
    turned about its axis by every 360/order degrees, as full clouds and depth views."""
    from evaluation.cases import make_cases

    scales = {name: engine.get(name).scale}
    meshes = {name: mesh if mesh is not None else pybullet_mesh(mesh_path)}
    return make_cases("symmetric", meshes, scales, 2048, 0, 2, orders={name: order})


@needs_model
def test_the_flange_turned_by_its_half_turn_gets_one_answer_whole_and_in_depth_views(engine):
    """The evaluation's symmetric cases of the KUKA flange: one pose turned by 0, 180 and 360
    degrees about its axis (the same surface), as full clouds and depth views. Every member
    of a group is answered within 2 degrees of the others, the depth views also when the
    viewpoint is not given. Found in the evaluation: its best turn was 4-9 degrees off a near
    turn, which ICP does not turn back (answers 45-135 degrees apart), and on its 384-point
    sample the right turn did not stand out; never told the viewpoint, a turned pose's
    coverage was measured against the view the unturned pose expected (45-135 degrees)."""
    from evaluation.metrics import symmetric_spread

    cases = symmetric_cases(engine, "kuka-link-7", "kuka_iiwa/meshes/link_7.obj", 2)
    groups: dict[str, list] = {}
    for case in cases:
        viewpoint = case.params.get("viewpoint")
        answer = engine.align(
            case.points, viewpoint=None if viewpoint is None else np.asarray(viewpoint)
        )
        assert answer.label == "kuka-link-7"
        groups.setdefault(case.params["group"], []).append(answer.rotation)
        if viewpoint is not None:  # and never told where the camera was
            answer = engine.align(case.points)
            assert answer.label == "kuka-link-7"
            groups.setdefault(case.params["group"] + "/blind", []).append(answer.rotation)
    assert len(groups) == 6
    spreads = {group: symmetric_spread(rotations) for group, rotations in groups.items()}
    assert max(spreads.values()) < 2.0, spreads


@needs_model
def test_a_flange_s_depth_view_posed_at_a_near_turn_says_it_is_ambiguous(engine):
    """The KUKA flange's depth views of ``benchmarks.symmetric``'s seed 2: a view whose first
    pose lies far from the truth about the flange's axis is turned by its near turns, chosen
    on that pose. One of them won 72.6 degrees off the truth, a ``"match"`` not flagged, and
    the turn near the truth was never refined. The winner's own turns are now tried once more:
    each answer lies within 2 degrees of the truth or says other poses fit alike
    (docs/decisions.md#beyond-the-evaluations-draw)."""
    from evaluation.cases import make_cases

    entry = engine.entry("kuka-link-7")
    meshes = {"kuka-link-7": pybullet_mesh("kuka_iiwa/meshes/link_7.obj")}
    cases = make_cases(
        "symmetric", meshes, {"kuka-link-7": entry.reference.scale}, 2048, 2, 3,
        orders={"kuka-link-7": 2},
    )  # fmt: skip
    views = [c for c in cases if c.params["group"] == "kuka-link-7/1/sensor"]
    assert len(views) == 3
    for case in views:
        answer = engine.align(case.points, viewpoint=np.asarray(case.params["viewpoint"]))
        assert answer.label == "kuka-link-7"
        off = entry.symmetry.distance_deg(answer.rotation, case.rotation)
        assert off < 2.0 or answer.ambiguous, (off, answer.verdict, answer.confidence)


@needs_model
def test_a_view_hypothesis_takes_the_camera_its_view_was_rendered_from(engine):
    """Never told the viewpoint, refinement takes the camera of the rendered view a pose was
    hypothesised from: where registration rendered it, carried into the scene by the pose."""
    from service.engine.search import view_camera
    from service.engine.views import cameras

    entry = engine.entry("lego-brick")
    points = entry.reference.points.astype(np.float64)
    rendered = cameras(points, entry.reference.scale, len(entry.views.directions))
    rotation = Rotation.random(random_state=4).as_matrix()
    translation = np.array([0.1, -0.2, 0.7])
    for view in (0, 7, len(rendered) - 1):
        placed = view_camera(entry, view, rotation, translation)
        assert np.allclose(placed, rotation @ rendered[view] + translation)


@needs_model
def test_a_brick_seen_from_one_side_without_its_viewpoint_is_one_answer(engine):
    """The evaluation's first group of the lego brick's depth views, never told where the
    camera was: each turned by a quarter turn of the brick (the same surface). Refinement
    takes the camera of the view each pose was hypothesised from and pairs no point with the
    inside of the brick's thin walls: the four answers within a degree of each other (1.3
    degrees apart before)."""
    from evaluation.metrics import symmetric_spread

    cases = symmetric_cases(engine, "lego-brick", "lego/lego.obj", 4)
    views = [c for c in cases if c.params["group"] == "lego-brick/0/sensor"]
    assert len(views) == 4
    answers = [engine.align(case.points) for case in views]
    assert all(a.label == "lego-brick" for a in answers)
    assert symmetric_spread(a.rotation for a in answers) < 1.0


@needs_model
def test_the_shaft_seen_from_one_side_is_answered_at_its_own_end(engine):
    """The differential's stepped shaft (a part the model never saw, registered from its mesh
    as the evaluation does) in the evaluation's second symmetric group: one pose turned by 0,
    180 and 360 degrees about its axis, as depth views. Each is answered at the right end and
    turn. Found in the evaluation: the first view was answered flipped end for end (180
    degrees off, ADD-S 0.008): the shaft's many turns about its axis, alike all round, took
    every place the near-symmetry step screens in, and its flip was never refined."""
    from training.objects import load_manifest, load_object_meshes

    (spec,) = [s for s in load_manifest(split="unseen") if s.name == "diff-shaft"]
    mesh = load_object_meshes([spec])[spec.name]
    points, faces = sample_surface_faces(mesh, 2048, 0)
    shaft = engine.make_reference(spec.name, points, mesh=mesh, face_index=faces)
    gallery = Engine(engine.mapper, engine.settings, engine.calibration)
    gallery.load([engine.entry(name).reference for name in engine.names()] + [shaft])
    symmetry = gallery.entry("diff-shaft").symmetry
    assert symmetry.round_axis is not None and symmetry.near_reversing.any()
    cases = symmetric_cases(gallery, "diff-shaft", None, 2, mesh)
    views = [c for c in cases if c.params["group"] == "diff-shaft/1/sensor"]
    assert len(views) == 3
    for case in views:
        answer = gallery.align(case.points, viewpoint=np.asarray(case.params["viewpoint"]))
        assert answer.label == "diff-shaft"
        assert symmetry.distance_deg(answer.rotation, case.rotation) < 2.0, case.params


@needs_model
def test_a_square_brick_is_posed_right_side_up_whatever_its_turn_about_its_axis(engine):
    """The lego brick's evaluation group turned by its quarter turns, as full clouds: its two
    horizontal spreads are alike, so the principal axes in that plane are any two and the
    four principal-axes matches may all be turned up to 45 degrees off; found in the
    evaluation, refinement then left the brick upside down (fit 0.75, "uncertain"). Each
    match is now also tried turned by 45, 90 and 135 degrees about the brick's axis."""
    cases = symmetric_cases(engine, "lego-brick", "lego/lego.obj", 4)
    symmetry = engine.entry("lego-brick").symmetry
    full = [c for c in cases if c.params["view"] == "full"]
    assert len(full) == 8
    for case in full:
        answer = engine.align(case.points)
        assert answer.label == "lego-brick"
        assert symmetry.distance_deg(answer.rotation, case.rotation) < 2.0, case.params


@needs_model
def test_another_pose_that_would_be_right_too_does_not_lower_the_confidence(engine):
    """A pose turned by one of the flange's near-symmetries places the part almost where the
    answer does (were it the truth, the answer would still be precise): its gap to the answer
    is under ``RIGHT_EITHER_WAY``, which the confidence's ``alike`` leaves out; the part turned
    by 90 degrees across their axis is far (0.14 of its scale). A full cloud of the flange is
    answered with such poses as alternatives, which its ``alike`` does not count."""
    entry = engine.entry("kuka-link-7")
    centre = np.asarray(entry.reference.symmetry["centre"])
    rotation = Rotation.random(random_state=3).as_matrix()
    translation = np.array([0.0, 0.1, 0.6])

    def pose(turn: np.ndarray) -> Fit:  # the answer's pose turned by ``turn`` about the centre
        return Fit(
            0, rotation @ turn, rotation @ (centre - turn @ centre) + translation, "", -1, 1, 1
        )

    answer = pose(np.eye(3))
    near = [np.asarray(turn) for turn in entry.reference.symmetry["near"]]
    along = Rotation.from_matrix(near[0]).as_rotvec()  # the axis the near turns are about
    perpendicular = np.cross(
        along, [1.0, 0, 0] if abs(along[0]) < 0.9 * np.linalg.norm(along) else [0, 1.0, 0]
    )
    across = Rotation.from_rotvec(np.pi / 2 * perpendicular / np.linalg.norm(perpendicular))
    assert entry.gap(answer, answer) < 1e-3
    assert max(entry.gap(answer, pose(turn)) for turn in near) < RIGHT_EITHER_WAY
    assert entry.gap(answer, pose(across.as_matrix())) > 5 * RIGHT_EITHER_WAY

    points, _ = sample_surface_faces(pybullet_mesh("kuka_iiwa/meshes/link_7.obj"), 2048, 103)
    found = engine.align(points.astype(np.float64) @ rotation.T + translation)
    assert found.label == "kuka-link-7" and found.ambiguous
    winner = Fit(0, found.rotation, found.translation, "", -1, 1, 1)
    for other in found.alternatives:
        turned = Fit(0, other.rotation, other.translation, "", -1, 1, 1)
        assert entry.gap(winner, turned) < RIGHT_EITHER_WAY
    assert found.alike < ALIKE * found.fit * found.coverage


@needs_model
@needs_calibration
def test_a_view_that_cannot_tell_two_poses_apart_is_ambiguous_not_a_bare_uncertain(engine):
    """The diff stand's depth view (the calibration's seed 7) fits its answered pose and
    another alike: only that other pose keeps it from a "match", so it is listed."""
    pytest.importorskip("open3d", exc_type=ImportError)
    from evaluation.cases import make_cases
    from training.objects import load_manifest, load_object_meshes

    meshes = load_object_meshes([s for s in load_manifest() if s.name == "diff-stand"])
    scales = {"diff-stand": engine.get("diff-stand").scale}
    cases = make_cases("sensor", meshes, scales, 2048, 7, 4)
    case = max(cases, key=lambda c: c.params["distance_scales"])  # the farthest: 7.9 scales
    answer = engine.align(case.points, viewpoint=np.asarray(case.params["viewpoint"]))
    assert answer.verdict == "uncertain" and answer.ambiguous
    assert right(engine, "diff-stand", answer, case.rotation, case.translation)
    assert [a.confidence for a in answer.alternatives] == [answer.confidence]
    other = answer.alternatives[0]
    assert geodesic_deg(other.rotation, answer.rotation) > 5  # another pose, not a nudge
    assert any("fit alike" in reason for reason in answer.reasons)
