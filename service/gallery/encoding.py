"""A reference as a stored row, whatever fields ``Reference`` has.

Every numpy-array field goes into one blob, little-endian, one after another, with its name,
dtype and shape in ``layout`` (JSON); every other field but the name goes into ``extras``
(JSON). The sha256 covers the name, the layout, the extras and the bytes, and is checked on
every decode. Adding a field to ``Reference`` needs no change here: a row written before the
field existed decodes without it, and ``missing`` names it (the catalog recomputes such a
reference from its points).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.engine.reference import DERIVED, Reference


class StoreCorrupted(RuntimeError):
    """A stored reference whose checksum does not match its data."""


@dataclass(frozen=True)
class Row:
    """What the store keeps of one reference."""

    name: str
    arrays: bytes  # the array fields' little-endian bytes, in the order of ``layout``
    layout: str  # JSON: [{"field": "points", "dtype": "<f4", "shape": [N, 3]}, ...]
    extras: str  # JSON: the other fields, e.g. {"scale": 0.12}
    sha256: str


def encode(reference: Any) -> Row:
    """The row of a ``Reference`` (or of any dataclass with a ``name``)."""
    values = {f.name: getattr(reference, f.name) for f in dataclasses.fields(reference)}
    return encode_values(values.pop("name"), values)


def encode_values(name: str, values: dict[str, Any]) -> Row:
    """The row of a reference given as its fields' values (the name apart)."""
    arrays = {k: _little_endian(v) for k, v in values.items() if isinstance(v, np.ndarray)}
    extras = {k: v for k, v in values.items() if k not in arrays}
    layout = json.dumps(
        [{"field": k, "dtype": a.dtype.str, "shape": list(a.shape)} for k, a in arrays.items()]
    )
    extras_json = json.dumps(extras, sort_keys=True, default=_plain)
    blob = b"".join(array.tobytes() for array in arrays.values())
    return Row(name, blob, layout, extras_json, checksum(name, blob, layout, extras_json))


def decode(row: Row) -> dict[str, Any]:
    """Every stored field's value, the name included; ``StoreCorrupted`` if the row is damaged."""
    if checksum(row.name, row.arrays, row.layout, row.extras) != row.sha256:
        raise StoreCorrupted(
            f"reference '{row.name}': checksum mismatch, the stored data is damaged"
        )
    values: dict[str, Any] = {"name": row.name}
    try:
        offset = 0
        for item in json.loads(row.layout):
            dtype, shape = np.dtype(item["dtype"]), tuple(item["shape"])
            size = dtype.itemsize * int(np.prod(shape, dtype=np.int64))
            if offset + size > len(row.arrays):
                raise ValueError("the arrays are shorter than their layout")
            chunk = row.arrays[offset : offset + size]
            values[item["field"]] = np.frombuffer(chunk, dtype).reshape(shape).copy()
            offset += size
        if offset != len(row.arrays):
            raise ValueError("the arrays are longer than their layout")
        values.update(json.loads(row.extras))
    except (KeyError, TypeError, ValueError) as error:
        raise StoreCorrupted(
            f"reference '{row.name}': its arrays do not match their layout"
        ) from error
    return values


REQUIRED = tuple(  # the fields a Reference cannot be made without
    f.name
    for f in dataclasses.fields(Reference)
    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
)


def missing(values: dict[str, Any]) -> tuple[str, ...]:
    """The fields of ``Reference`` that stored values lack, or hold as None (written by an older
    version, or seeded from a gallery file made before the field existed), among those it
    cannot be used without: the required ones and those registration derives (``DERIVED``);
    an optional one (``look_alikes``) is no reason to recompute a reference."""
    needed = (*REQUIRED, *DERIVED)
    return tuple(
        f.name
        for f in dataclasses.fields(Reference)
        if f.name in needed and values.get(f.name) is None
    )


def to_reference(values: dict[str, Any]) -> Reference:
    """The ``Reference`` of complete stored values; fields it does not know are left out."""
    known = {f.name for f in dataclasses.fields(Reference)}
    return Reference(**{k: v for k, v in values.items() if k in known})


def checksum(name: str, arrays: bytes, layout: str, extras: str) -> str:
    digest = hashlib.sha256()
    for part in (name.encode(), layout.encode(), extras.encode(), arrays):
        digest.update(len(part).to_bytes(8, "little"))  # so that no part can spill into the next
        digest.update(part)
    return digest.hexdigest()


def _little_endian(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    little = array.dtype.newbyteorder("<")
    return array if array.dtype == little else array.astype(little)


def _plain(value: Any) -> Any:
    """JSON for numpy values inside the extras (a scale as ``np.float32``, say)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"a reference field of type {type(value).__name__} cannot be stored as JSON")
