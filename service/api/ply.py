"""A PLY file's header, and its body held to it before trimesh reads it.

trimesh reads an ASCII PLY's first rows whatever the header declares (9,983 vertices declared,
3,000 held: 3,000 read, no error) and fails on a short row in numpy's words; a binary PLY's
length it checks, without saying what it expected. So the header is read here, and a body that
cannot hold what it declares is refused naming the element, the row and what it needed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from service.errors import InvalidPoints

# bytes a value of each PLY type takes (the PLY names and their sized aliases)
TYPE_SIZES = {
    **dict.fromkeys(("char", "uchar", "int8", "uint8"), 1),
    **dict.fromkeys(("short", "ushort", "int16", "uint16"), 2),
    **dict.fromkeys(("int", "uint", "int32", "uint32", "float", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}
WHITESPACE = np.frombuffer(b" \t\r\v\f", np.uint8)


@dataclass(frozen=True)
class Element:
    name: str
    count: int
    properties: tuple[str, ...]  # their names
    row_bytes: int | None  # bytes a row takes in a binary body; None with a list property


@dataclass(frozen=True)
class Header:
    format: str  # "ascii", "binary_little_endian" or "binary_big_endian"
    elements: tuple[Element, ...]
    body: int  # offset of the first byte after the header
    lines: int  # lines the header takes (so a row's line in the file can be named)

    @property
    def has_faces(self) -> bool:
        """Whether it declares at least one face (a mesh) rather than only vertices."""
        return any(e.name == "face" and e.count > 0 for e in self.elements)


def read_header(data: bytes) -> Header:
    """The header's format and elements; ``InvalidPoints`` when it has no ``end_header``."""
    end = re.search(rb"^end_header[ \t]*\r?\n?", data[:65536], flags=re.MULTILINE)
    if end is None:
        raise InvalidPoints("the PLY file has no 'end_header' line")
    text = data[: end.start()].decode("ascii", errors="replace")
    form = re.search(r"^format\s+(\S+)", text, flags=re.MULTILINE)
    elements: list[Element] = []
    for name, count, block in re.findall(
        r"^element\s+(\S+)\s+(\d+)[^\n]*\n((?:(?!element\s)[^\n]*\n?)*)", text, re.MULTILINE
    ):
        properties = re.findall(r"^property\s+(.+?)\s*$", block, flags=re.MULTILINE)
        names = tuple(p.split()[-1] for p in properties if p.split())
        sizes = [TYPE_SIZES.get(p.split()[0]) for p in properties if p.split()]
        fixed = all(s is not None for s in sizes)  # a list property's rows vary in length
        elements.append(Element(name, int(count), names, sum(sizes) if fixed else None))
    lines = data[: end.end()].count(b"\n")
    return Header(form.group(1) if form else "", tuple(elements), end.end(), lines)


def check_body(header: Header, data: bytes) -> None:
    """Refuse a body that does not hold the rows its header declares."""
    if header.format == "ascii":
        _check_rows(header, data[header.body :])
    elif all(e.row_bytes is not None for e in header.elements):  # else trimesh checks it
        need = sum(e.count * e.row_bytes for e in header.elements)
        held = len(data) - header.body
        if held < need:
            declared = ", ".join(
                f"{e.count} {e.name} rows of {e.row_bytes} bytes" for e in header.elements
            )
            raise InvalidPoints(
                f"the binary PLY data is {held} bytes, but its header declares {declared} "
                f"({need} bytes): the file is cut short, or its header's counts are wrong"
            )


def _check_rows(header: Header, body: bytes) -> None:
    """An ASCII body: as many rows as the elements declare, each element's rows of as many
    values as it has properties (unless it has a list property)."""
    values = _values_per_line(body)
    rows = np.flatnonzero(values)  # blank lines are no rows
    declared = sum(e.count for e in header.elements)
    if len(rows) != declared:
        said = ", ".join(f"element {e.name} {e.count}" for e in header.elements)
        raise InvalidPoints(
            f"the ASCII PLY file holds {len(rows)} rows of data, but its header declares "
            f"{declared} ({said}): the file is cut short, or its header's counts are wrong"
        )
    start = 0
    for element in header.elements:
        block = rows[start : start + element.count]
        start += element.count
        if element.row_bytes is None:
            continue
        width = len(element.properties)
        wrong = np.flatnonzero(values[block] != width)
        if len(wrong):
            row = int(wrong[0])
            got = int(values[block[row]])
            raise InvalidPoints(
                f"row {row + 1} of the PLY's {element.name} data (line "
                f"{header.lines + int(block[row]) + 1} of the file) has {got} value"
                f"{'s' * (got != 1)}, but the header declares {width} properties "
                f"({' '.join(element.properties)}) for each {element.name}"
            )


def _values_per_line(body: bytes) -> np.ndarray:
    """How many whitespace-separated values each line of ``body`` holds, without a Python loop
    over the lines (an ASCII cloud may have millions)."""
    text = np.frombuffer(body, np.uint8)
    if not len(text):
        return np.zeros(1, np.intp)
    newline = text == ord("\n")
    blank = newline | np.isin(text, WHITESPACE)
    starts = ~blank & np.concatenate(([True], blank[:-1]))  # a value begins after a blank
    line = np.concatenate(([0], np.cumsum(newline)[:-1]))  # each byte's line
    return np.bincount(line[starts], minlength=int(newline.sum()) + 1)
