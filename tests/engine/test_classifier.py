"""Eq. (4)'s classifier fitted from sums, and the Gram the engine keeps across changes."""

from __future__ import annotations

import numpy as np

from service.engine.classifier import LinearClassifier, classifier_input, view_gram
from service.engine.engine import Engine
from service.engine.grid import GRID_SIZE
from service.engine.mapping import Mapper
from service.engine.reference import Reference
from service.settings import EngineSettings
from tests.servers import MODEL, needs_model

RIDGE = 1e-3


def stacked_ridge(view_features: list[np.ndarray], ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge regression to one-hot targets written out on the stacked views: the oracle."""
    x = np.concatenate(view_features).astype(np.float64)
    y = np.zeros((len(x), len(view_features)))
    row = 0
    for label, features in enumerate(view_features):
        y[row : row + len(features), label] = 1.0
        row += len(features)
    x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - x_mean, y - y_mean
    scatter = xc.T @ xc
    scatter[np.diag_indices_from(scatter)] += ridge * np.trace(scatter) / len(scatter)
    weights = np.linalg.solve(scatter, xc.T @ yc)
    return weights.T, y_mean - x_mean @ weights


def random_features(rng: np.random.Generator, count: int) -> list[np.ndarray]:
    views = rng.integers(3, 9, count)  # references may have different numbers of views
    return [classifier_input(rng.random((v, GRID_SIZE, GRID_SIZE)), 1.0) for v in views]


def test_the_fit_from_sums_is_ridge_regression_on_the_stacked_views():
    features = random_features(np.random.default_rng(0), 12)
    classifier = LinearClassifier.fit([str(i) for i in range(12)], features, RIDGE, 1.0)
    weights, bias = stacked_ridge(features, RIDGE)
    scale = np.abs(weights).max()
    assert np.allclose(classifier.weights, weights, atol=1e-5 * scale)
    assert np.allclose(classifier.bias, bias, atol=1e-5)


def test_view_gram_sums_over_chunks_whatever_their_size():
    features = random_features(np.random.default_rng(1), 700)  # ~3,900 views: several chunks
    stacked = np.concatenate(features).astype(np.float64)
    assert np.allclose(view_gram(features), stacked.T @ stacked, rtol=1e-12, atol=0)


@needs_model
def test_the_engine_keeps_its_gram_through_many_changes():
    """Additions, replacements and removals update the Gram by sums; after hundreds of them it
    and the classifier are what a fit from scratch gives, and emptying the gallery resets it."""
    rng = np.random.default_rng(2)
    engine = Engine(Mapper(MODEL.path), EngineSettings(grid_blur=1.0))

    # one real reference's geometry (views, distance field, ...) under every name; the
    # classifier's full-view grids, what this test is about, drawn at random for each
    template = engine.make_reference("template", rng.normal(size=(64, 3)).astype(np.float32))

    def reference(name: str) -> Reference:
        views = rng.random((int(rng.integers(2, 6)), GRID_SIZE, GRID_SIZE)).astype(np.float32)
        return template.with_(name=name, view_grids=views)

    engine.load([reference(f"seed-{i}") for i in range(5)])
    names = [f"seed-{i}" for i in range(5)]
    for step in range(60):  # about 20 of each; the rounding after 400 was still ~1e-13
        action = rng.choice(["add", "replace", "remove"]) if len(names) > 2 else "add"
        if action == "add":
            names.append(f"r-{step}")
            engine.add(reference(names[-1]))
        elif action == "replace":
            engine.add(reference(str(rng.choice(names))))
        else:
            name = str(rng.choice(names))
            names.remove(name)
            engine.remove(name)

    snapshot = engine._snapshot
    features = [entry.view_features for entry in snapshot.entries.values()]
    assert sorted(snapshot.entries) == sorted(names)
    scratch = view_gram(features)
    assert np.allclose(snapshot.gram, scratch, rtol=1e-10, atol=1e-12 * np.abs(scratch).max())
    fresh = LinearClassifier.fit(list(snapshot.entries), features, engine.settings.classifier_ridge)
    assert snapshot.classifier.labels == fresh.labels
    assert np.allclose(snapshot.classifier.weights, fresh.weights, rtol=1e-4, atol=1e-6)

    for name in names:
        engine.remove(name)
    assert engine._snapshot.gram is None and engine._snapshot.classifier is None
    engine.add(reference("again"))
    assert np.array_equal(
        engine._snapshot.gram, view_gram([engine._snapshot.entries["again"].view_features])
    )


def test_the_same_gallery_is_held_alike_whatever_order_it_was_registered_in():
    """The snapshot lists the parts by name, as the store loads them: the order breaks ties
    among parts, so a worker that loaded the store and the service that registered the parts
    one by one (new and replaced ones last) answer alike (docs/decisions.md#a-second-core)."""
    rng = np.random.default_rng(3)
    settings = EngineSettings(grid_blur=1.0)
    template = Engine(Mapper(MODEL.path), settings).make_reference(
        "template", rng.normal(size=(64, 3)).astype(np.float32)
    )
    views = {name: rng.random((3, GRID_SIZE, GRID_SIZE)).astype(np.float32) for name in "dbca"}
    parts = {name: template.with_(name=name, view_grids=grids) for name, grids in views.items()}
    loaded = Engine(Mapper(MODEL.path), settings)
    loaded.load([parts[name] for name in sorted(parts)])
    registered = Engine(Mapper(MODEL.path), settings)
    registered.load([parts["d"], parts["b"]])
    for name in ("c", "a", "d"):  # d replaced: it kept its place before
        registered.add(parts[name])
    assert registered.names() == loaded.names() == ["a", "b", "c", "d"]
    assert registered._snapshot.classifier.labels == loaded._snapshot.classifier.labels
    assert np.allclose(registered._snapshot.classifier.weights, loaded._snapshot.classifier.weights)
