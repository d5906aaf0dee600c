"""The gallery file the service ships with: one ``.npz`` (arrays only, never pickle) with a
JSON ``meta`` entry, written by ``training.export`` and read to seed an empty store.

Every array field of a ``Reference`` is saved as ``<field>_<i>`` for reference ``i``; its other
fields (the symmetry's description) as JSON in ``described``. A file written before a field
existed loads without it, and the catalog computes what is missing.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from service.engine.reference import Reference

CORE = ("name", "scale")  # saved as the ``names`` and ``scales`` arrays


def save_gallery(path: Path, references: list[Reference], meta: dict) -> None:
    arrays: dict[str, np.ndarray] = {
        "names": np.array([r.name for r in references]),
        "scales": np.array([r.scale for r in references], dtype=np.float64),
        "meta": np.array(json.dumps(meta)),
    }
    described = []
    for i, reference in enumerate(references):
        other = {}
        for item in dataclasses.fields(reference):
            value = getattr(reference, item.name)
            if item.name in CORE or value is None:
                continue
            if isinstance(value, np.ndarray):
                arrays[f"{item.name}_{i}"] = value
            else:
                other[item.name] = value
        described.append(other)
    arrays["described"] = np.array(json.dumps(described))
    np.savez_compressed(path, **arrays)


def load_gallery(path: Path) -> tuple[list[Reference], dict]:
    names = [f.name for f in dataclasses.fields(Reference) if f.name not in CORE]
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        described = json.loads(str(data["described"])) if "described" in data else None
        references = []
        for i, name in enumerate(data["names"]):
            values = {k: data[f"{k}_{i}"] for k in names if f"{k}_{i}" in data}
            if described is not None:
                values.update({k: v for k, v in described[i].items() if k in names})
            references.append(Reference(name=str(name), scale=float(data["scales"][i]), **values))
    return references, meta
