"""A registration sent again to another replica before that replica has followed the first:
two catalogs on one store (SQLite, then PostgreSQL) are two replicas. The second finds the
name taken in the store, not yet in its snapshot, and answers identical for the same points,
``ReferenceExists`` for others; a batch with one such part stores the rest."""

from __future__ import annotations

import pytest

from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.errors import ReferenceExists
from service.gallery.catalog import CREATED, IDENTICAL, Catalog, Part
from service.settings import EngineSettings
from tests.ledger import sha
from tests.ledger import varied_cloud as cloud
from tests.servers import MODEL

pytestmark = pytest.mark.skipif(not MODEL.path.exists(), reason=f"no ONNX model at {MODEL.path}")


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    return Mapper(MODEL.path)


@pytest.fixture
def replicas(backend, mapper):
    location = backend.new()
    stores = [location.store(), location.store()]
    catalogs = []
    for store in stores:
        catalog = Catalog(Engine(mapper, EngineSettings(view_grids=2)), store, 100)
        catalog.load(None)
        catalogs.append(catalog)
    yield catalogs
    for store in stores:
        store.close()


def test_the_same_points_on_a_replica_that_has_not_followed_are_identical(replicas):
    a, b = replicas
    a.register("part", cloud(1))
    assert b.engine.get("part") is None  # b has not followed yet
    before = b.store.checksums()
    reference, outcome, checks = b.register("part", cloud(1), self_check_poses=1)
    assert outcome == IDENTICAL and checks is None and sha(reference.points) == sha(cloud(1))
    assert b.store.checksums() == before
    with pytest.raises(ReferenceExists):
        b.register("part", cloud(2))
    assert b.store.checksums() == before
    results = b.register_many([Part("part", cloud(1)), Part("more", cloud(3))])
    assert [outcome for _, outcome, _ in results] == [IDENTICAL, CREATED]
    assert sorted(b.store.checksums()) == ["more", "part"]
    assert b.store.checksums()["part"] == before["part"]  # the first one's row, untouched
