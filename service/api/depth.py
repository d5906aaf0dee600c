"""A depth image and its camera's intrinsics to a cloud in the camera's frame (a pinhole model).

For every pixel with a depth (column ``u``, row ``v``, counted from the top-left pixel as OpenCV
and Open3D count them): ``z = depth * depth_scale``, ``x = (u - cx) * z / fx``,
``y = (v - cy) * z / fy``. A 16-bit image holds millimetres (``depth_scale`` 0.001 gives
metres), a 32-bit float one metres (``depth_scale`` 1); 0, NaN and infinity mean no return.
Images are PNG or TIFF (Pillow) or a 2-D NPY array; a mask of the same size keeps the pixels
where it is not 0. The camera sits at the origin of the cloud: the viewpoint is ``[0, 0, 0]``.
"""

from __future__ import annotations

import io
import warnings
from pathlib import PurePath

import numpy as np
from PIL import Image, UnidentifiedImageError

from service.api.clouds import Cloud
from service.api.schemas import DepthCamera
from service.errors import InvalidPoints

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
MAX_PIXELS = 4096 * 4096  # before decoding: a small PNG can announce billions of pixels
MILLIMETRES = 0.001  # the default depth_scale of a 16-bit image
MIN_FOCAL = 10.0  # pixels: no depth camera's focal length is shorter
FAR_CENTRE = 10  # images: a principal point farther than this from the image's is a mistake


def depth_points(
    depth: np.ndarray, camera: DepthCamera, mask: np.ndarray | None, max_points: int
) -> np.ndarray:
    """The (N, 3) points of the pixels with a depth (and in the mask), in the camera's frame."""
    return depth_cloud(depth, camera, mask, max_points).points


def depth_cloud(
    depth: np.ndarray, camera: DepthCamera, mask: np.ndarray | None, max_points: int
) -> Cloud:
    """The points of the pixels with a depth (and in the mask), in the camera's frame, with
    each one's pixel in the image's grid."""
    check_intrinsics(camera, depth.shape)
    scale = camera.depth_scale or (MILLIMETRES if depth.dtype.kind in "iu" else 1.0)
    z = depth.astype(np.float64) * scale
    valid = np.isfinite(z) & (z > 0)
    if mask is not None:
        if mask.shape != depth.shape:
            raise InvalidPoints(
                f"the mask is {mask.shape[1]}x{mask.shape[0]} pixels, the depth image "
                f"{depth.shape[1]}x{depth.shape[0]}: send a mask of the image's size"
            )
        valid &= mask != 0
    count = int(valid.sum())
    if not count:
        where = " inside the mask" if mask is not None else ""
        raise InvalidPoints(
            f"the depth image ({depth.shape[1]}x{depth.shape[0]} pixels) has no pixel with a "
            f"depth{where}: every one is 0 or not finite; check the camera (and the mask), "
            "and depth_scale"
        )
    if count > max_points:
        raise InvalidPoints(
            f"the depth image has {count} pixels with a depth, more than the maximum of "
            f"{max_points} points: send a mask of the part's pixels, crop the image, or send "
            "POST /detect a region of interest (roi): only the points inside it count then"
        )
    rows, columns = np.nonzero(valid)
    z = z[rows, columns]
    x = (columns - camera.cx) * z / camera.fx
    y = (rows - camera.cy) * z / camera.fy
    index = rows.astype(np.int64) * depth.shape[1] + columns
    return Cloud(np.stack([x, y, z], axis=1), index, (depth.shape[0], depth.shape[1]))


def check_intrinsics(camera: DepthCamera, shape: tuple[int, int]) -> None:
    """Intrinsics in pixels of an image of ``shape`` (height, width), or a 422 naming which
    is not: a focal length under ``MIN_FOCAL`` pixels (intrinsics normalized by the image's
    size give about 1), or a principal point ``FAR_CENTRE`` images away from the image's."""
    height, width = shape
    for name, focal in (("fx", camera.fx), ("fy", camera.fy)):
        if focal < MIN_FOCAL:
            raise InvalidPoints(
                f"{name} = {focal:g} is no focal length in pixels (a depth camera's is some "
                "hundreds): intrinsics divided by the image's size? send fx, fy, cx and cy in "
                "pixels"
            )
    for name, centre, size in (("cx", camera.cx, width), ("cy", camera.cy, height)):
        if abs(centre - size / 2) > FAR_CENTRE * max(width, height):
            raise InvalidPoints(
                f"{name} = {centre:g} lies far outside the {width}x{height} image: send the "
                f"principal point in pixels (near {size / 2:g})"
            )


def read_image(data: bytes, filename: str | None, what: str) -> np.ndarray:
    """A single-channel image, (H, W): PNG or TIFF by content, or a 2-D NPY array."""
    if not data:
        raise InvalidPoints(f"the {what} file is empty")
    if data.startswith(b"\x93NUMPY"):
        return _npy_image(data, what)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data), formats=("PNG", "TIFF"))
            width, height = image.size
            if width * height > MAX_PIXELS:
                raise InvalidPoints(
                    f"the {what} is {width}x{height} pixels, more than {MAX_PIXELS}: crop it"
                )
            array = np.asarray(image)
    except InvalidPoints:
        raise
    except UnidentifiedImageError:
        named = f"'{filename}'" if filename else "the file"
        raise InvalidPoints(
            f"{named} cannot be read as a PNG or TIFF image or an NPY array: send the {what} as one"
        ) from None
    except Exception as error:  # a damaged image: Pillow raises many types
        raise InvalidPoints(f"the {what} is unreadable: {error}") from error
    if array.ndim != 2:
        raise InvalidPoints(
            f"the {what} has {array.shape[2] if array.ndim == 3 else 'no'} channels "
            f"(mode {image.mode}): send a single-channel image"
        )
    return array


def read_depth(data: bytes, filename: str | None) -> np.ndarray:
    """The depth image: 16-bit integers or 32/64-bit floats, (H, W)."""
    depth = read_image(data, filename, "depth image")
    if depth.dtype.kind == "b" or depth.dtype.itemsize < 2:
        raise InvalidPoints(
            f"the depth image holds {depth.dtype} values: save depth as a 16-bit PNG in "
            "millimetres or as 32-bit floats in metres (TIFF, NPY)"
        )
    if depth.shape[1] <= 3:
        raise InvalidPoints(
            f"the depth image is {depth.shape[1]} pixels wide: if it is a cloud of (N, 3) "
            "points, send it without fx, fy, cx and cy"
        )
    return depth


def is_image(data: bytes, filename: str | None) -> bool:
    """Whether a file is an image by its suffix or its first bytes (PNG, TIFF)."""
    suffix = PurePath(filename or "").suffix.lower()
    return suffix in IMAGE_SUFFIXES or data[:8] == b"\x89PNG\r\n\x1a\n" or data[:4] in TIFF


TIFF = (b"II*\x00", b"MM\x00*")


def _npy_image(data: bytes, what: str) -> np.ndarray:
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as error:  # object arrays, bad headers, truncated data
        raise InvalidPoints(f"the {what} (NPY) is unreadable: {error}") from error
    if not isinstance(array, np.ndarray) or array.ndim != 2:
        shape = getattr(array, "shape", None)
        raise InvalidPoints(f"the {what} (NPY) has shape {shape}, not (height, width)")
    if array.dtype.kind not in "biuf":
        raise InvalidPoints(f"the {what} (NPY) holds {array.dtype}, not numbers")
    if array.size > MAX_PIXELS:
        raise InvalidPoints(f"the {what} has {array.size} pixels, more than {MAX_PIXELS}")
    return array
