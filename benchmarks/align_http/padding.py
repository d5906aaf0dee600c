"""Padding references: galleries larger than the shipped one, made from it and cached.

A size over the shipped gallery's adds padding references made from the shipped ones: padding
``i`` is shipped reference ``i mod 45`` turned by a random rotation and stretched along x, y and
z by random factors in 0.7-1.3, the largest at least 1.4 times the smallest (seeded by ``i``: a
distinct shape each, neither a copy in another pose nor the part resized), computed with the
engine's own ``Engine.make_reference`` as a registration computes it (1-3 s each on a busy
2-core machine). They are cached on disk (``--padding-cache``, in chunks of 50, so an
interrupted run keeps what it computed) under a key of the model's hash, the engine's settings,
the recipe and the shipped points; the run prints how long the computation took when it had to
compute them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from service.engine.engine import Engine
from service.engine.mapping import Mapper
from service.engine.reference import Reference
from service.gallery.gallery_file import load_gallery, save_gallery
from service.settings import EngineSettings

REPO = Path(__file__).resolve().parents[2]
PADDING_RECIPE = 2  # bump when padding_points changes: the cache key follows it
PADDING_SEED = 1000
PADDING_STRETCH = (0.7, 1.3)
# the largest stretch over the smallest, at least: a nearly even stretch only resizes the part
# (a size variant the engine may take for its base: 16 of 80 clouds were, with no such bound)
PADDING_ANISOTROPY = 1.4
PADDING_CHUNK = 50  # references per cache file


def padding_points(shipped: list[Reference], index: int) -> tuple[str, np.ndarray]:
    """Padding reference ``index``: shipped reference ``index mod len(shipped)``, turned by a
    random rotation, then stretched along x, y and z by random factors, one at least
    ``PADDING_ANISOTROPY`` times another (a distinct shape, not the part resized)."""
    base = shipped[index % len(shipped)]
    rng = np.random.default_rng([PADDING_SEED, index])
    turn = Rotation.random(random_state=rng).as_matrix()
    stretch = rng.uniform(*PADDING_STRETCH, 3)
    while stretch.max() < PADDING_ANISOTROPY * stretch.min():
        stretch = rng.uniform(*PADDING_STRETCH, 3)
    points = (np.asarray(base.points, dtype=np.float64) @ turn.T) * stretch
    return f"pad-{index:04d}-{base.name}", points.astype(np.float32)


def padding_key(shipped: list[Reference], model_hash: str, engine: EngineSettings) -> str:
    """What the padding references depend on: the recipe, the model, the engine's settings,
    the shipped points and the fields a reference has."""
    described = {
        "recipe": PADDING_RECIPE,
        "model_sha256": model_hash,
        "engine": engine.model_dump(mode="json"),
        "shipped": [r.points_sha256 for r in shipped],
        "fields": [f.name for f in dataclasses.fields(Reference)],
    }
    return hashlib.sha256(json.dumps(described, sort_keys=True).encode()).hexdigest()[:16]


def engine_code_hash() -> str:
    """The engine's source: padding computed by other code is used, with a warning."""
    digest = hashlib.sha256()
    for path in sorted((REPO / "service" / "engine").glob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


_worker_engine: Engine | None = None


def _start_worker(model: str, engine_settings: dict) -> None:
    global _worker_engine
    mapper = Mapper(Path(model), 1, 1, False)
    _worker_engine = Engine(mapper, EngineSettings(**engine_settings))


def _make_reference(named: tuple[str, np.ndarray]) -> Reference:
    return _worker_engine.make_reference(*named)


def padding_references(
    engine: Engine,
    shipped: list[Reference],
    count: int,
    cache_dir: Path | None,
    workers: int = 1,
    progress: Callable[[str], None] = print,
) -> tuple[list[Reference], int, float | None]:
    """``count`` padding references (``padding_points``), computed with ``engine`` (or as many
    worker processes with the same model and settings) and cached in ``cache_dir``.

    Returns them, how many were computed (not in the cache) and the seconds that took.
    """
    if count <= 0:
        return [], 0, None
    key = padding_key(shipped, engine.mapper.model_hash, engine.settings)
    code = engine_code_hash()
    chunks = range(0, count, PADDING_CHUNK)
    held: dict[int, list[Reference]] = {}
    for start in chunks:
        held[start] = []
        path = None if cache_dir is None else cache_dir / f"padding-{key}-{start:05d}.npz"
        if path is not None and path.exists():
            references, meta = load_gallery(path)
            if meta.get("key") == key:
                held[start] = references
                if meta.get("engine_code") != code:
                    progress(f"  padding {path.name}: computed by other engine code, used as is")
    missing = [
        start + i
        for start in chunks
        for i in range(len(held[start]), min(PADDING_CHUNK, count - start))
    ]
    if not missing:
        return [r for start in chunks for r in held[start]][:count], 0, None
    progress(f"computing {len(missing)} padding references ({workers} process(es)) ...")
    began = time.perf_counter()
    done = 0
    for index, reference in _compute(engine, shipped, missing, workers):
        start = index - index % PADDING_CHUNK
        held[start].append(reference)
        done += 1
        full = len(held[start]) == min(PADDING_CHUNK, count - start)
        if full and cache_dir is not None:
            cache_dir.mkdir(parents=True, exist_ok=True)
            path = cache_dir / f"padding-{key}-{start:05d}.npz"
            partial_path = path.with_name(path.stem + ".partial.npz")
            save_gallery(partial_path, held[start], {"key": key, "engine_code": code})
            partial_path.replace(path)
        if done % 25 == 0 or done == len(missing):
            elapsed = time.perf_counter() - began
            progress(f"  padding: {done}/{len(missing)} computed in {elapsed:.0f} s")
    seconds = time.perf_counter() - began
    return [r for start in chunks for r in held[start]][:count], len(missing), seconds


def _compute(
    engine: Engine, shipped: list[Reference], indices: list[int], workers: int
) -> Iterator[tuple[int, Reference]]:
    """(index, padding reference) in the order of ``indices``."""
    named = (padding_points(shipped, index) for index in indices)
    if workers <= 1:
        yield from zip(indices, (engine.make_reference(*n) for n in named), strict=True)
        return
    context = multiprocessing.get_context("spawn")  # no onnxruntime threads forked
    initargs = (str(engine.mapper.path), engine.settings.model_dump())
    with ProcessPoolExecutor(workers, context, _start_worker, initargs) as pool:
        yield from zip(indices, pool.map(_make_reference, named), strict=True)
