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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from service import memory
from service.engine.engine import Engine
from service.engine.reference import Reference, points_sha256
from service.engine.symmetry import Symmetry
from service.errors import ReferenceExists
from service.gallery import backup
from service.gallery.backup import Copy
from service.gallery.gallery_file import load_gallery
from service.gallery.store import SEEDED_KEY, GalleryStore, StoredReference

__all__ = ["CREATED", "IDENTICAL", "REPLACED", "SEEDED_KEY", "Catalog", "GalleryFull", "Part"]

CREATED, REPLACED, IDENTICAL = "created", "replaced", "identical"  # a registration's outcome

log = logging.getLogger(__name__)


class GalleryFull(RuntimeError):
    """The gallery holds ``max_references`` references (409)."""


@dataclass(frozen=True)
class Part:
    """One part to register: its points, sampled on ``mesh``'s faces ``face_index`` when it
    came as a mesh."""

    name: str
    points: np.ndarray
    mesh: trimesh.Trimesh | None = None
    face_index: np.ndarray | None = None
    reference: Reference | None = None  # computed already (an imported one)
    symmetry: dict | None = None  # the symmetry its operator declared (Engine.make_reference)


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

    def load(self, seed_gallery: Path | None, writer: bool = True) -> None:
        """Seed the store on its first start, refresh stale references, fill the engine; not
        a ``writer`` (an engine worker process), only fill the engine."""
        if writer and self.store.get_meta(SEEDED_KEY) is None:
            self._seed(seed_gallery)
        references, held = [], {}
        for record in self.store.load_records():
            reference, held[record.name] = self._usable(record, write_back=writer)
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
            declared = Symmetry.declared_in(record.values.get("symmetry"))
            reference = self.engine.make_reference(record.name, record.points, symmetry=declared)
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
        symmetry: dict | None = None,
    ) -> tuple[Reference, str, list[dict] | None]:
        """Compute, store and add a reference (with the ``symmetry`` its operator declared);
        returns it, the outcome (``CREATED``, ``REPLACED`` or ``IDENTICAL``) and its self-check.

        The same name with the same points (``points_sha256``) and no ``replace`` is
        ``IDENTICAL``: nothing is computed or stored, so a client may send a registration again
        when it cannot tell whether the first one was committed (a proxy's 502, a dropped
        connection). ``points`` were sampled on ``mesh``'s faces ``face_index`` when it came as
        a mesh. ``commit`` is called just before the durable write and may raise to stop it.
        """
        part = Part(name, points, mesh, face_index, symmetry=symmetry)
        return self.register_many([part], replace, self_check_poses, commit)[0]

    def register_many(
        self,
        parts: list[Part],
        replace: bool = False,
        self_check_poses: int = 0,
        commit: Callable[[], None] = lambda: None,
    ) -> list[tuple[Reference, str, list[dict] | None]]:
        """``register`` for several parts (of distinct names), all or none: one store
        transaction and one refit of the classifier; then each part's self-check against the
        whole gallery, the batch included."""
        digests = {p.name: points_sha256(np.asarray(p.points, dtype=np.float32)) for p in parts}
        declared = {p.name: p.symmetry for p in parts}
        same = self._identical(digests, replace, declared)  # fail fast, before the slow part
        made = {p.name: self._make(p) for p in parts if p.name not in same}
        with self._write_lock:
            same = self._identical(digests, replace, declared)
            fresh = [made[p.name] for p in parts if p.name not in same]
            previous = {r.name: self.engine.get(r.name) for r in fresh}
            if fresh:
                commit()
                checksums = self._put(fresh, digests, replace, same)
                fresh = [r for r in fresh if r.name not in same]
                try:
                    self.engine.add_many(fresh)
                except BaseException:  # the store must not keep what the engine refused
                    for reference in fresh:
                        self._restore(reference.name, previous[reference.name])
                    raise
                self._held.update(checksums)
        results = []
        for part in parts:
            if part.name in same:
                results.append((same[part.name], IDENTICAL, None))
                continue
            reference = made[part.name]
            checks = None
            if self_check_poses:
                checks, others = self.engine.registration_check(
                    reference, self_check_poses, part.mesh
                )
                if others:
                    reference = self.note_look_alikes(part.name, others) or reference
            outcome = CREATED if previous[part.name] is None else REPLACED
            results.append((reference, outcome, checks))
        memory.release_free_heap()
        return results

    def _make(self, part: Part) -> Reference:
        if part.reference is not None:
            return part.reference
        return self.engine.make_reference(
            part.name, part.points, mesh=part.mesh, face_index=part.face_index,
            symmetry=part.symmetry,
        )  # fmt: skip

    def restore(
        self,
        copy: Copy,
        source: str,
        replace_all: bool = False,
        commit: Callable[[], None] = lambda: None,
    ) -> str:
        """Put a gallery copy in the store, every row as it was, into an empty store or in
        place of everything (``replace_all``); every row is checked as read back before the
        write commits, then the engine holds the copy's references (recomputed where they were
        computed with another model). ``IDENTICAL`` when the store holds exactly the copy
        already (a restore sent again), else ``CREATED``."""
        with self._write_lock:
            if self.store.checksums() == copy.checksums:
                return IDENTICAL
            commit()
            self.store.restore(
                copy.rows, source, replace_all, lambda rows: backup.check(rows, copy.entries)
            )
            references, held = [], {}
            for record in self.store.load_records():
                reference, held[record.name] = self._usable(record, write_back=True)
                references.append(reference)
            self.engine.load(references)
            self._held = held
        memory.release_free_heap()
        log.info("restored %d references from %s", len(copy.rows), source)
        return CREATED

    def import_references(
        self,
        copy: Copy,
        replace: bool = False,
        commit: Callable[[], None] = lambda: None,
    ) -> list[tuple[Reference, str, list[dict] | None]]:
        """Add the references of another service's export, all or none, as ``register_many``
        (the same name and points again: ``IDENTICAL``); a reference computed with this model
        is taken as it is, one computed with another is recomputed from its points."""
        parts = []
        for record in copy.records():
            reference = self._usable(record, write_back=False)[0]
            parts.append(Part(record.name, reference.points, reference=reference))
        return self.register_many(parts, replace, 0, commit)

    def _put(
        self,
        references: list[Reference],
        digests: dict[str, str],
        replace: bool,
        same: dict[str, Reference],
    ) -> dict[str, str]:
        """Store the references in one transaction; their rows' checksums. A name another
        replica has stored meanwhile (not followed here yet) with the same points joins
        ``same``, and the rest is stored; other points under it are ``ReferenceExists``."""
        try:
            return self.store.put_many(references, self.model_hash, replace=replace)
        except ReferenceExists:
            if replace:
                raise
            stored = self.store.load_records([r.name for r in references])
            for record in stored:
                if points_sha256(record.points) != digests[record.name]:
                    raise
            for record in stored:
                same[record.name] = self._usable(record, write_back=False)[0]
            rest = [r for r in references if r.name not in same]
            return self.store.put_many(rest, self.model_hash) if rest else {}

    def _identical(
        self, digests: dict[str, str], replace: bool, declared: dict[str, dict | None]
    ) -> dict[str, Reference]:
        """The references held under these names with these points and the same ``declared``
        symmetry (none with ``replace``); raises if one of the others may not be
        (re)registered, or they would not fit."""
        same = {}
        if not replace:
            for name, digest in digests.items():
                existing = self.engine.get(name)
                if existing is None or existing.points_sha256 != digest:
                    continue
                if Symmetry.declared_in(existing.symmetry) == declared.get(name):
                    same[name] = existing
        self._check_can_add([name for name in digests if name not in same], replace)
        return same

    def note_look_alikes(self, name: str, others: list[str]) -> Reference | None:
        """Store with the reference ``name`` that its registration check could not tell it from
        ``others`` (``service.engine.look_alikes``, with their points now); the reference as
        noted, or None when it changed meanwhile (replaced, removed, or another replica's)."""
        with self._write_lock:
            noted = self.engine.claiming(name, others)
            if noted is None:
                return None
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

    def _check_can_add(self, names: list[str], replace: bool) -> None:
        """Raises if one of ``names`` exists and not ``replace``, or the new ones would not fit."""
        for name in names:
            if self.engine.get(name) is not None and not replace:
                raise ReferenceExists(
                    f"a reference named '{name}' exists with other points: pick another name "
                    "or pass replace=true (the same points again are answered 200, identical)"
                )
        new = sum(self.engine.get(name) is None for name in names)
        if new and len(self.engine) + new > self.max_references:
            room = max(0, self.max_references - len(self.engine))
            raise GalleryFull(
                f"the gallery holds {len(self.engine)} references, its maximum is "
                f"{self.max_references}: {'it' if new == 1 else f'{new} new ones'} would not fit "
                f"(room for {room}); delete some first"
            )
