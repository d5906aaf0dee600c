"""PCD files (PCL's format) to points, read by pypcd4: DATA ascii, binary and binary_compressed.

pypcd4 trusts the header, so the header is read first (by pypcd4's own ``MetaData``) and held
to what the file can hold before the data is: no more than ``max_points`` points, a binary body
as long as the header says, a compressed block that decompresses to exactly the points' bytes.
NaN marks a point without a return in PCL's clouds (an organised cloud's empty pixels), so
points with a NaN coordinate are dropped; infinity is left for the validation to refuse, but
in an organized cloud (HEIGHT > 1) it is a missing pixel too, and the grid is kept
(``service.api.clouds``): only its valid points count against the limit.
"""

from __future__ import annotations

import io
import struct

import numpy as np
from pydantic import ValidationError
from pypcd4 import Encoding, MetaData, PointCloud

from service.api.clouds import Cloud, organized
from service.errors import InvalidPoints

HEADER_LINES = 10  # VERSION FIELDS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA
MAX_VALUES = 4096  # values one point may carry (PCL's largest descriptor has 1,980)
MAX_PIXELS = 4096 * 4096  # an organized cloud's grid, valid pixels or not


def read_pcd(data: bytes, max_points: int) -> Cloud:
    """The x y z of the points of a PCD file, (N, 3), without the NaN points; an organized
    one's valid pixels, with where each lies in its grid."""
    metadata, offset = read_header(data)
    grid = metadata.height > 1 and metadata.width * metadata.height == metadata.points
    check_fits(metadata, data[offset:], MAX_PIXELS if grid else max_points)
    try:
        cloud = PointCloud.from_fileobj(io.BytesIO(data))
        table = cloud.pc_data
    except Exception as error:  # numpy and lzf raise many types for damaged data
        raise InvalidPoints(f"the PCD data is unreadable: {error}") from error
    rows = np.atleast_1d(table)  # loadtxt answers a single row as a 0-d array
    if len(rows) != metadata.points:
        raise InvalidPoints(
            f"the PCD data holds {len(rows)} points, the header's POINTS says {metadata.points}"
        )
    points = np.stack([rows[axis] for axis in "xyz"], axis=1)
    if grid:
        return organized(points.reshape(metadata.height, metadata.width, 3), max_points, "PCD")
    kept = points[~np.isnan(points).any(axis=1)]
    if not len(kept) and len(points):
        raise InvalidPoints(f"the PCD's {len(points)} points are all NaN: no point is left")
    return Cloud(kept)


def read_header(data: bytes) -> tuple[MetaData, int]:
    """The header, parsed by pypcd4, and the offset of the first data byte."""
    lines: list[str] = []
    offset = 0
    while not lines or not lines[-1].startswith("DATA"):
        if len(lines) == HEADER_LINES:
            raise InvalidPoints(f"the PCD header has no DATA line in its {HEADER_LINES} lines")
        end = data.find(b"\n", offset)
        if end < 0:
            raise InvalidPoints("the PCD file has no DATA line")
        line = data[offset:end].decode("utf-8", errors="replace").strip()
        offset = end + 1
        if line and not line.startswith("#"):
            lines.append(line)
    try:
        metadata = MetaData.parse_header(lines)
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'][:1])).upper()}: {e['msg']} (got {e.get('input')!r})"
            for e in error.errors()
        )
        raise InvalidPoints(f"the PCD header is invalid: {problems}") from None
    except (ValueError, IndexError) as error:  # a count or size that is not a whole number
        raise InvalidPoints(f"the PCD header has a value that is unusable: {error}") from None
    return metadata, offset


def check_fits(metadata: MetaData, body: bytes, max_points: int) -> None:
    """Refuse, before reading, what the header promises but the body cannot hold."""
    fields = metadata.fields
    if not len(fields) == len(metadata.size) == len(metadata.type) == len(metadata.count):
        raise InvalidPoints("the PCD header's FIELDS, SIZE, TYPE and COUNT differ in length")
    for axis in "xyz":
        if axis not in fields:
            raise InvalidPoints(f"the PCD file has no '{axis}' field (FIELDS {' '.join(fields)})")
        if metadata.count[fields.index(axis)] != 1:
            raise InvalidPoints(f"the PCD field '{axis}' has COUNT above 1")
    if len(set(fields)) != len(fields):
        raise InvalidPoints(f"the PCD header names a field twice (FIELDS {' '.join(fields)})")
    if sum(metadata.count) > MAX_VALUES:
        raise InvalidPoints(f"the PCD points carry more than {MAX_VALUES} values each")
    if metadata.points > max_points:
        raise InvalidPoints(
            f"{metadata.points} points given, more than the maximum of {max_points}: "
            "subsample the cloud"
        )
    try:
        size = metadata.build_dtype().itemsize * metadata.points
    except (KeyError, TypeError, ValueError) as error:  # a TYPE and SIZE numpy has no type for
        raise InvalidPoints(f"the PCD header's SIZE and TYPE do not fit: {error}") from None
    if metadata.data == Encoding.BINARY and len(body) < size:
        raise InvalidPoints(
            f"the binary PCD data is {len(body)} bytes, {metadata.points} points need {size}"
        )
    if metadata.data in (Encoding.BINARY_COMPRESSED, Encoding.BINARYSCOMPRESSED):
        if len(body) < 8:
            raise InvalidPoints("the compressed PCD data has no sizes")
        compressed, uncompressed = struct.unpack("<II", body[:8])
        if uncompressed != size or compressed > len(body) - 8:
            raise InvalidPoints(
                f"the compressed PCD data says {compressed} bytes that expand to {uncompressed}; "
                f"the file has {len(body) - 8} and {metadata.points} points need {size}"
            )
