"""What must hold before the service answers anything, checked once at start.

``prepare(settings)`` loads the model and opens the gallery store, or raises ``StartupError``
with one message that says what to fix: a missing, unreadable or corrupt model file (its
sha256 against the manifest beside it, when there is one), a seed gallery that does not match
the manifest, a data directory that cannot be written, a database that is not a gallery or
was written by a newer version of the service (an older one is migrated), a setting naming what
the engine does not have (``CHOICES``: the hypothesis sources). A PostgreSQL server that cannot
be reached yet is waited for instead. ``python -m service`` turns that into one line
on stderr and exit status 2; the app's lifespan calls it too, so an app built in-process
fails to start the same way. References computed with another model file are not an error:
the catalog recomputes them from their stored points when the gallery loads.
"""

from __future__ import annotations

import difflib
import json
import logging
import sqlite3
import tempfile
from collections.abc import Mapping
from pathlib import Path

import onnxruntime as ort

from service.engine.confidence import Calibration
from service.engine.engine import Engine
from service.engine.hypotheses import SOURCES
from service.engine.mapping import Mapper, file_sha256
from service.errors import StoreFull, StoreUnavailable
from service.gallery.open_store import open_store
from service.gallery.sqlite_store import FILENAME
from service.gallery.store import GalleryStore, StoreIncompatible
from service.settings import GallerySettings, Settings

log = logging.getLogger(__name__)

EXIT_STATUS = 2


class StartupError(RuntimeError):
    """The service cannot start; the message says why and what to change."""


def prepare(settings: Settings) -> tuple[Mapper, GalleryStore]:
    """The loaded model and the open store, after every check."""
    check_choices(settings)
    model_hash = check_model_files(settings)
    mapper = load_model(settings, model_hash)
    return mapper, open_gallery_store(settings.gallery)


def open_gallery_store(gallery: GallerySettings) -> GalleryStore:
    """The store with its schema checked (and migrated). A PostgreSQL server that cannot be
    reached yet is no reason to stop: the service waits for it, not ready until then."""
    if not gallery.url:
        check_data_dir(gallery.data_dir)
    try:
        store = open_store(gallery)
        store.check()
    except StoreIncompatible as error:
        raise StartupError(str(error)) from None
    except StoreFull as error:
        raise StartupError(
            f"cannot open the gallery in {gallery.data_dir}: its disk is full ({error.__cause__}):"
            " free space there, then start again"
        ) from None
    except StoreUnavailable as error:
        if not gallery.url:
            raise StartupError(f"cannot open the gallery in {gallery.data_dir}: {error}") from None
        log.warning("the gallery store cannot be reached yet (%s): waiting for it", error)
    except (OSError, sqlite3.Error) as error:
        raise StartupError(f"cannot open the gallery in {gallery.data_dir}: {error}") from None
    return store


# Settings whose values are names the engine defines (pydantic checks the Literal ones):
# (group, field) -> the allowed names, taken from where the engine keeps them
CHOICES = {("engine", "hypotheses"): SOURCES}


def check_choices(settings: Settings) -> None:
    """Each setting of ``CHOICES`` holds only allowed names (one, or a list of them)."""
    for (group, field), allowed in CHOICES.items():
        value = getattr(getattr(settings, group), field)
        values = (value,) if isinstance(value, str) else value
        unknown = [v for v in values if v not in allowed]
        if unknown or not values:
            variable = f"DPC_{group}__{field}".upper()
            default = type(getattr(settings, group)).model_fields[field].default
            example = default if isinstance(default, str) else f"'{json.dumps(list(default))}'"
            problem = f"{', '.join(map(repr, unknown))} is not allowed" if unknown else "empty"
            raise StartupError(
                f"invalid settings: {variable}: {problem}; the allowed values are "
                f"{', '.join(map(repr, allowed))} (e.g. {variable}={example})"
            )


def unknown_variables(environ: Mapping[str, str]) -> list[str]:
    """A warning for each ``DPC_`` variable that names no setting (it would be ignored)."""
    known = setting_variables()
    warnings = []
    for name in sorted(environ):
        upper = name.upper()  # pydantic-settings reads names in any case
        if not upper.startswith("DPC_") or upper in known:
            continue
        if any(upper.startswith(f"{variable}__") for variable in known if "__" in variable):
            continue  # a key inside a group's value, e.g. DPC_AUTH__KEYS__<key>
        closest = difflib.get_close_matches(upper, known, n=1)
        hint = f"; did you mean {closest[0]}?" if closest else ""
        warnings.append(f"the environment variable {name} names no setting and is ignored{hint}")
    return warnings


def setting_variables() -> list[str]:
    """Every variable a setting is read from: DPC_<GROUP> (JSON) and DPC_<GROUP>__<FIELD>."""
    names = []
    for group, info in Settings.model_fields.items():
        names.append(f"DPC_{group}".upper())
        names += [f"DPC_{group}__{field}".upper() for field in info.annotation.model_fields]
    return names


def check_model_files(settings: Settings) -> str:
    """The model exists and is readable; it and the seed gallery match the manifest, if any.

    Returns the model's sha256, so that it is read once.
    """
    model = settings.model.path
    if not model.is_file():
        raise StartupError(f"no ONNX model at {model}: set DPC_MODEL__PATH")
    try:
        model_hash = file_sha256(model)
    except OSError as error:
        raise StartupError(f"cannot read the model {model}: {error.strerror}") from None
    manifest_path = settings.manifest_path
    if not manifest_path.exists():
        return model_hash
    try:
        files = json.loads(manifest_path.read_text())["files"]
        expected = files[model.name]["sha256"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise StartupError(
            f"the manifest {manifest_path} is unreadable or does not list {model.name} "
            f"({type(error).__name__}: {error}): restore it from the model's release"
        ) from None
    if model_hash != expected:
        raise StartupError(
            f"the model {model} is damaged or not the released one: its sha256 is "
            f"{model_hash[:12]}..., the manifest {manifest_path} says {expected[:12]}...; "
            "restore both files from the same release"
        )
    gallery = settings.model.gallery
    listed = files.get(gallery.name) if isinstance(files, dict) else None
    same_release = gallery.parent.resolve() == manifest_path.parent.resolve()
    if same_release and gallery.is_file() and isinstance(listed, dict) and "sha256" in listed:
        if file_sha256(gallery) != listed["sha256"]:
            raise StartupError(
                f"the seed gallery {gallery} does not match the manifest {manifest_path}: "
                "restore both files from the same release"
            )
    return model_hash


def load_model(settings: Settings, model_hash: str | None = None) -> Mapper:
    try:
        return Mapper.from_settings(settings.model, model_hash)
    except Exception as error:  # onnxruntime raises its own types for an unusable file
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise StartupError(
            f"the model {settings.model.path} is not a usable ONNX model ({first_line}): "
            "restore it from the model's release"
        ) from None


def check_data_dir(data_dir: Path) -> None:
    """The data directory exists (or can be made) and a file can be written in it."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=data_dir, prefix=".write-check-"):
            pass
    except OSError as error:
        reason = error.strerror or str(error)
        raise StartupError(
            f"the data directory {data_dir} is not a writable directory ({reason}): "
            f"set DPC_GALLERY__DATA_DIR to a directory this user may write ({FILENAME} "
            "lives there)"
        ) from None


def quiet_onnxruntime() -> None:
    """onnxruntime's own log lines would add to the one-line message of a failed start."""
    ort.set_default_logger_severity(3)


def load_calibration(settings: Settings, detections: bool = False) -> Calibration | None:
    """The confidence calibration beside the model (with ``detections``: POST /detect's), None
    when there is none (every answer is then "uncertain", every detection takes the chain's
    confidence, and the log says why); a file that cannot be read stops the start."""
    path = settings.detect_confidence_path if detections else settings.confidence_path
    if not path.exists():
        if detections:
            log.warning("no detection calibration at %s: detections take the chain's", path)
        else:
            log.warning("no confidence calibration at %s: every answer will be 'uncertain'", path)
        return None
    try:
        return Calibration.load(path)
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise StartupError(
            f"the confidence calibration {path} is unreadable ({error}): restore it from the "
            "model's release, or refit it with python -m evaluation.calibrate"
            + ("_detect" if detections else "")
        ) from None


def make_engine(settings: Settings, mapper: Mapper) -> Engine:
    """The engine on ``mapper`` with both calibrations beside the model: the service's own, and
    each engine worker process's (``service.api.engine_processes``)."""
    return Engine(
        mapper,
        settings.engine,
        load_calibration(settings),
        load_calibration(settings, detections=True),
    )
