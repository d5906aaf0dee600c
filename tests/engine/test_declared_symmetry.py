"""A symmetry the operator declares at registration (issue 33): the KUKA flange registered as
a cloud, whose estimated normals hide its symmetry from the self-fit at this draw, answers one
pose for one surface once its roundness is declared; a declaration that does not fit is
refused, and the declaration survives the symmetry being found again
(docs/decisions.md#declared-at-registration)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from evaluation.cases import make_cases
from evaluation.metrics import symmetric_spread
from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.sampling import sample_surface_faces
from service.engine.symmetry import Symmetry
from service.errors import InvalidPoints
from service.gallery.gallery_file import load_gallery
from service.settings import Settings
from tests.meshes import pybullet_mesh
from tests.servers import needs_model

SETTINGS = Settings()
FLANGE = "kuka_iiwa/meshes/link_7.obj"
ROUND = {"kind": "revolution", "axis": [0.0, 0.0, 1.0]}
HALF_TURN = {"kind": "discrete", "axis": [0.0, 0.0, 1.0], "order": 2}


@pytest.fixture(scope="module")
def flange() -> tuple:
    mesh = pybullet_mesh(FLANGE)
    points, _ = sample_surface_faces(mesh, 2048, 0)  # a draw whose half turn is not found
    return mesh, points


@pytest.fixture(scope="module")
def engine() -> Engine:
    return Engine(Mapper(SETTINGS.model.path, use_cuda=False), SETTINGS.engine)


@needs_model
def test_a_declared_half_turn_joins_what_the_cloud_shows(engine, flange):
    _, points = flange
    found = engine.make_reference("flange", points).symmetry
    assert found["kind"] == "none" and "declared" not in found
    declared = engine.make_reference("flange", points, symmetry=HALF_TURN).symmetry
    assert declared["kind"] == "discrete" and declared["declared"] == HALF_TURN
    half = np.asarray(declared["rotations"])[1]
    assert np.allclose(half, np.diag([-1.0, -1.0, 1.0]), atol=1e-6)
    assert np.linalg.norm(np.asarray(declared["centre"])[:2]) < 1e-3  # on the flange's axis
    again = Symmetry.from_description(declared, np.zeros(3))
    assert again.declared == HALF_TURN and len(again.rotations) == 2


@needs_model
def test_a_declared_turn_that_does_not_fit_is_refused_naming_it(engine, flange):
    _, points = flange
    sideways = {"kind": "discrete", "axis": [1.0, 0.0, 0.0], "order": 2}
    with pytest.raises(InvalidPoints, match=r"does not fit the part: turned by 180 degrees"):
        engine.make_reference("flange", points, symmetry=sideways)


@needs_model
def test_the_declaration_survives_the_symmetry_found_again(engine, flange):
    _, points = flange
    reference = engine.make_reference("flange", points, symmetry=ROUND)
    refound = engine.refind_symmetry(reference.with_(symmetry={"kind": "none", "rule": 1}
                                                     | {"declared": ROUND}))  # fmt: skip
    assert refound.symmetry["kind"] == "revolution" and refound.symmetry["declared"] == ROUND


@needs_model
def test_the_flange_declared_round_gets_one_pose_for_one_surface(flange):
    """The evaluation's symmetric cases of the flange (seed 0, two poses, each turned by its
    half turn, full clouds and depth views): registered as this cloud, whose half turn the
    self-fit does not confirm, each group's answers lie 175-180 degrees apart; declared round
    (the notch left to the cell), within 1.4 degrees. Declared a half turn, two of the four
    groups are within 2 degrees: the notch's other turns still part them."""
    mesh, points = flange
    mapper = Mapper(SETTINGS.model.path, use_cuda=False)
    shipped = [r for r in load_gallery(SETTINGS.model.gallery)[0] if r.name != "kuka-link-7"]
    spreads = {}
    for kind, declared in (("found", None), ("declared", ROUND)):
        engine = Engine(mapper, SETTINGS.engine)
        reference = engine.make_reference("kuka-link-7", points, symmetry=declared)
        engine.load([*shipped, reference])
        cases = make_cases(
            "symmetric", {"kuka-link-7": mesh}, {"kuka-link-7": reference.scale}, 2048, 0, 2,
            orders={"kuka-link-7": 2},
        )  # fmt: skip
        groups: dict[str, list] = {}
        for case in cases:
            viewpoint = case.params.get("viewpoint")
            answer = engine.align(case.points, viewpoint=viewpoint and np.asarray(viewpoint))
            groups.setdefault(case.params["group"], []).append(answer.rotation)
        spreads[kind] = [symmetric_spread(r) for r in groups.values()]
    print(spreads)
    assert len(spreads["declared"]) == 4 and max(spreads["declared"]) < 2.0, spreads
    assert sum(s < 2.0 for s in spreads["found"]) <= 1, spreads


@needs_model
def test_a_declared_half_turn_across_a_round_part_is_its_flip(engine):
    """A cylinder's flip end for end joins the revolution found (the self-fit at this draw
    finds the revolution alone); a cone's is refused."""
    across = {"kind": "discrete", "axis": [1.0, 0.0, 0.0], "order": 2}
    for name, mesh in (("cylinder", trimesh.creation.cylinder(0.03, 0.12)),
                       ("cone", trimesh.creation.cone(0.04, 0.08))):  # fmt: skip
        points, faces = sample_surface_faces(mesh, 2048, 0)
        found = engine.make_reference(name, points, mesh=mesh, face_index=faces).symmetry
        assert found["kind"] == "revolution" and not found["flip"]
        if name == "cone":
            with pytest.raises(InvalidPoints, match="does not fit"):
                engine.make_reference(name, points, mesh=mesh, face_index=faces, symmetry=across)
            continue
        declared = engine.make_reference(
            name, points, mesh=mesh, face_index=faces, symmetry=across
        ).symmetry
        assert declared["kind"] == "revolution" and declared["flip"]
        assert abs(abs(declared["axis"][2]) - 1) < 1e-3
