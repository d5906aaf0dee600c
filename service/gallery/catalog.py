"""The registered references, kept in step: the durable store and the engine's gallery.

Every change goes to the store first (durable) and then to the engine, under one lock, so
the two never disagree; then the heap's free pages go back to the system (``service.memory``).
On start the store is seeded once from the shipped gallery, and references whose mapped
coordinates came from another model file are recomputed.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

from service import memory
from service.engine.engine import Engine
from service.engine.reference import Reference
from service.errors import ReferenceExists, UnknownReference
from service.gallery.gallery_file import load_gallery
from service.gallery.store import GalleryStore

log = logging.getLogger(__name__)

SEEDED_KEY = "seeded_from"  # meta: the gallery file the store was seeded from, once


class GalleryFull(RuntimeError):
    """The gallery holds ``max_references`` references (409)."""


class Catalog:
    def __init__(self, engine: Engine, store: GalleryStore, max_references: int):
        self.engine = engine
        self.store = store
        self.max_references = max_references
        self._write_lock = threading.Lock()

    @property
    def model_hash(self) -> str:
        return self.engine.mapper.model_hash

    def load(self, seed_gallery: Path | None) -> None:
        """Seed the store on its first start, refresh stale references, fill the engine."""
        if self.store.get_meta(SEEDED_KEY) is None:
            self._seed(seed_gallery)
        references = []
        for record in self.store.load_records():
            reference = record.reference
            if record.model_hash != self.model_hash:
                log.info("recomputing reference %r: stored for another model", reference.name)
                reference = self.engine.make_reference(reference.name, reference.points)
                self.store.put(reference, self.model_hash, replace=True)
            references.append(reference)
        self.engine.load(references)
        memory.release_free_heap()
        log.info("gallery loaded: %d references", len(references))

    def _seed(self, gallery: Path | None) -> None:
        if not self.store.is_empty():  # registered before seeding existed: never seed over it
            self.store.set_meta(SEEDED_KEY, "")
            return
        if gallery is None or not Path(gallery).exists():
            log.warning("no gallery to seed the store from (%s): starting empty", gallery)
            return
        references, meta = load_gallery(Path(gallery))
        model_hash = meta.get("model_sha256") or meta.get("model_hash") or self.model_hash
        self.store.put_many(references, model_hash, meta={SEEDED_KEY: str(gallery)})
        log.info("seeded the store with %d references from %s", len(references), gallery)

    def register(
        self,
        name: str,
        points: np.ndarray,
        replace: bool = False,
        self_check_poses: int = 0,
        commit: Callable[[], None] = lambda: None,
    ) -> tuple[Reference, bool, list[dict] | None]:
        """Compute, store and add a reference; returns it, whether it was new, its self-check.

        ``commit`` is called just before the durable write and may raise to stop it.
        """
        self._check_can_add(name, replace)  # fail fast, before the slow part
        reference = self.engine.make_reference(name, points)
        with self._write_lock:
            existed = self._check_can_add(name, replace)
            previous = self.engine.get(name)
            commit()
            self.store.put(reference, self.model_hash, replace=replace)
            try:
                self.engine.add(reference)
            except BaseException:  # the store must not keep what the engine refused
                self._restore(name, previous)
                raise
        checks = self.engine.self_check(reference, self_check_poses) if self_check_poses else None
        memory.release_free_heap()
        return reference, not existed, checks

    def remove(self, name: str, commit: Callable[[], None] = lambda: None) -> None:
        """Delete a reference from the store and the engine; ``commit`` as for ``register``."""
        with self._write_lock:
            previous = self.engine.get(name)
            if previous is None:
                raise UnknownReference(f"no reference named '{name}'")
            commit()
            self.store.delete(name)
            try:
                self.engine.remove(name)
            except BaseException:
                self._restore(name, previous)
                raise
        memory.release_free_heap()

    def _restore(self, name: str, previous: Reference | None) -> None:
        """Undo a store write the engine could not follow: the store keeps what it had."""
        if previous is None:
            self.store.delete(name)
        else:
            self.store.put(previous, self.model_hash, replace=True)

    def _check_can_add(self, name: str, replace: bool) -> bool:
        """Whether ``name`` exists; raises if it may not be added."""
        existed = self.engine.get(name) is not None
        if existed and not replace:
            raise ReferenceExists(
                f"a reference named '{name}' exists: pick another name or pass replace=true"
            )
        if not existed and len(self.engine) >= self.max_references:
            raise GalleryFull(
                f"the gallery holds its maximum of {self.max_references} references: "
                "delete one first"
            )
        return existed
