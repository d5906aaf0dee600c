"""The gallery file the service ships with: one ``.npz`` (arrays only, never pickle) with a
JSON ``meta`` entry, written by ``training.export`` and read to seed an empty store."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.engine.reference import Reference


def save_gallery(path: Path, references: list[Reference], meta: dict) -> None:
    arrays: dict[str, np.ndarray] = {
        "names": np.array([r.name for r in references]),
        "scales": np.array([r.scale for r in references], dtype=np.float64),
        "meta": np.array(json.dumps(meta)),
    }
    for i, reference in enumerate(references):
        arrays[f"points_{i}"] = reference.points.astype(np.float32)
        arrays[f"mapped_{i}"] = reference.mapped.astype(np.float32)
        arrays[f"view_grids_{i}"] = reference.view_grids.astype(np.float32)
    np.savez_compressed(path, **arrays)


def load_gallery(path: Path) -> tuple[list[Reference], dict]:
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        references = [
            Reference(
                name=str(name),
                points=data[f"points_{i}"],
                mapped=data[f"mapped_{i}"],
                view_grids=data[f"view_grids_{i}"],
                scale=float(data["scales"][i]),
            )
            for i, name in enumerate(data["names"])
        ]
    return references, meta
