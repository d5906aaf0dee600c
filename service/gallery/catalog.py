"""The registered references, kept in step: the durable store and the engine's gallery.

Every change goes to the store first (durable) and then to the engine, under one lock, so
the two never disagree; then the heap's free pages go back to the system (``service.memory``).
On start the store is seeded once from the shipped gallery, and references whose mapped
coordinates came from another model file, or that were stored without a field this version's
``Reference`` has, are recomputed from their points and written back. Other replicas' changes
arrive through ``sync``: the catalog remembers the checksum of the stored row each of its
references came from, and loads what differs.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from service import memory
from service.engine.engine import Engine
from service.engine.look_alikes import confused
from service.engine.reference import Reference
from service.engine.symmetry import Symmetry
from service.errors import ReferenceExists
from service.gallery.gallery_file import load_gallery
from service.gallery.store import SEEDED_KEY, GalleryStore, StoredReference

__all__ = ["SEEDED_KEY", "Catalog", "GalleryFull"]

log = logging.getLogger(__name__)


class GalleryFull(RuntimeError):
    """The gallery holds ``max_references`` references (409)."""


class Catalog:
    def __init__(self, engine: Engine, store: GalleryStore, max_references: int):
        self.engine = engine
        self.store = store
        self.max_references = max_references
        self._write_lock = threading.Lock()
        self._held: dict[str, str] = {}  # name -> checksum of the stored row it came from

    @property
    def model_hash(self) -> str:
        return self.engine.mapper.model_hash

    def load(self, seed_gallery: Path | None) -> None:
        """Seed the store on its first start, refresh stale references, fill the engine."""
        if self.store.get_meta(SEEDED_KEY) is None:
            self._seed(seed_gallery)
        references, held = [], {}
        for record in self.store.load_records():
            reference, held[record.name] = self._usable(record, write_back=True)
            references.append(reference)
        with self._write_lock:
            self.engine.load(references)
            self._held = held
        memory.release_free_heap()
        log.info("gallery loaded: %d references", len(references))

    def sync(self) -> int:
        """Follow what other replicas changed in the store; returns how many references
        changed here (added, replaced or removed)."""
        with self._write_lock:
            stored = self.store.checksums()
            gone = [name for name in self._held if name not in stored]
            changed = [name for name, sha in stored.items() if self._held.get(name) != sha]
            for name in gone:
                if self.engine.get(name) is not None:
                    self.engine.remove(name)
                del self._held[name]
            for record in self.store.load_records(changed):  # those still there
                reference, self._held[record.name] = self._usable(record, write_back=False)
                self.engine.add(reference)
        if gone or changed:
            log.info(
                "followed the store: %d added or replaced, %d removed", len(changed), len(gone)
            )
            memory.release_free_heap()
        return len(gone) + len(changed)

    def _usable(self, record: StoredReference, write_back: bool) -> tuple[Reference, str]:
        """The record's reference, recomputed from its points when it was stored for another
        model or without a field this version needs, its symmetry alone found again when an
        earlier rule found it (and then, with ``write_back``, stored unless another replica
        changed it meanwhile); and the checksum of the row it stands for."""
        if not record.missing and record.model_hash == self.model_hash:
            if not Symmetry.outdated(record.reference.symmetry):
                return record.reference, record.sha256
            log.info("finding the symmetry of reference %r again: an earlier rule", record.name)
            reference = self.engine.refind_symmetry(record.reference)
        else:
            why = "another model"
            if record.missing:
                why = f"stored without {', '.join(record.missing)}"
            log.info("recomputing reference %r: %s", record.name, why)
            reference = self.engine.make_reference(record.name, record.points)
        if write_back:
            rewritten = self.store.rewrite(reference, self.model_hash, was=record.sha256)
            return reference, rewritten or record.sha256
        return reference, record.sha256

    def _seed(self, gallery: Path | None) -> None:
        if gallery is None or not Path(gallery).exists():
            if self.store.is_empty():
                log.warning("no gallery to seed the store from (%s): starting empty", gallery)
            return
        references, meta = load_gallery(Path(gallery))
        model_hash = meta.get("model_sha256") or meta.get("model_hash") or self.model_hash
        if self.store.seed(references, model_hash, str(gallery)):
            log.info("seeded the store with %d references from %s", len(references), gallery)

    def register(
        self,
        name: str,
        points: np.ndarray,
        replace: bool = False,
        self_check_poses: int = 0,
        commit: Callable[[], None] = lambda: None,
        mesh: trimesh.Trimesh | None = None,
        face_index: np.ndarray | None = None,
    ) -> tuple[Reference, bool, list[dict] | None]:
        """Compute, store and add a reference; returns it, whether it was new, its self-check.

        ``points`` were sampled on ``mesh``'s faces ``face_index`` when it came as a mesh.
        ``commit`` is called just before the durable write and may raise to stop it.
        """
        self._check_can_add(name, replace)  # fail fast, before the slow part
        reference = self.engine.make_reference(name, points, mesh=mesh, face_index=face_index)
        with self._write_lock:
            existed = self._check_can_add(name, replace)
            previous = self.engine.get(name)
            commit()
            checksum = self.store.put(reference, self.model_hash, replace=replace)
            try:
                self.engine.add(reference)
            except BaseException:  # the store must not keep what the engine refused
                self._restore(name, previous)
                raise
            self._held[name] = checksum
        checks = (
            self.engine.self_check(reference, self_check_poses, mesh) if self_check_poses else None
        )
        if others := confused(name, checks):
            reference = self.note_look_alikes(name, others) or reference
        memory.release_free_heap()
        return reference, not existed, checks

    def note_look_alikes(self, name: str, others: list[str]) -> Reference | None:
        """Store with the reference ``name`` that its registration check could not tell it from
        ``others`` (``service.engine.look_alikes``, with their points now); the reference as
        noted, or None when it changed meanwhile (replaced, removed, or another replica's)."""
        with self._write_lock:
            reference = self.engine.get(name)
            if reference is None:
                return None
            claims = dict(reference.look_alikes or {})
            for other in others:
                if (held := self.engine.get(other)) is not None and other != name:
                    claims[other] = held.points_sha256
            noted = reference.with_(look_alikes=claims)
            checksum = self.store.rewrite(noted, self.model_hash, was=self._held.get(name, ""))
            if checksum is None:
                return None
            self.engine.annotate(noted)
            self._held[name] = checksum
        return noted

    def remove(self, name: str, commit: Callable[[], None] = lambda: None) -> None:
        """Delete a reference from the store and the engine; ``commit`` as for ``register``.
        ``UnknownReference`` when the store has none of that name."""
        with self._write_lock:
            previous = self.engine.get(name)
            commit()
            self.store.delete(name)
            try:
                if previous is not None:  # else another replica's, not followed yet
                    self.engine.remove(name)
            except BaseException:
                self._restore(name, previous)
                raise
            self._held.pop(name, None)
        memory.release_free_heap()

    def _restore(self, name: str, previous: Reference | None) -> None:
        """Undo a store write the engine could not follow: the store keeps what it had."""
        if previous is None:
            self.store.delete(name)
            self._held.pop(name, None)
        else:
            self._held[name] = self.store.put(previous, self.model_hash, replace=True)

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
