"""An observation's size against the references': which is nearest, and the unit a cloud
is likely in when it fits none (millimetres, centimetres against metres)."""

from __future__ import annotations

import numpy as np


def nearest_sized(ratio: np.ndarray) -> int:
    """Which of these observed-size-over-scale ratios is nearest 1 (a ratio of 0, an
    observation at one place, is the smallest scale's)."""
    return int(np.argmin(np.abs(np.log(np.maximum(ratio, np.finfo(float).tiny)))))


UNIT_FACTORS = (1000.0, 0.001, 100.0, 0.01)  # millimetres, metres, centimetres, metres


def size_reason(factor: float, also: bool = False) -> str:
    """Why an observation of ``factor`` times the nearest reference's size matches nothing;
    with ``also``: it fitted no part of its own size, but ``factor`` times smaller (or larger)
    it would be a registered part's size."""
    named = unit_ratio(factor)
    if named is None:
        return (
            f"no registered part has this size: the cloud's radius is {factor:.2g} times the "
            "nearest reference's scale"
        )
    ratio, unit, other = named
    small, big = (unit, "metres") if ratio > 1 else ("metres", unit)
    if also:
        scaled = f"1/{factor:,.0f} of" if ratio > 1 else f"{1 / factor:,.0f} times"
        return (
            f"at {scaled} its size the cloud would be a registered part's size: it may "
            f"be in {small} while the references are in {big}; send {other}"
        )
    times = f"{factor:,.0f} times" if ratio > 1 else f"1/{1 / factor:,.0f} of"
    return (
        f"the cloud is {times} the size of the nearest reference: it is probably in "
        f"{small} while the references are in {big}; send {other}"
    )


def unit_ratio(factor: float) -> tuple[float, str, str] | None:
    """The unit ratio a size ``factor`` is near (within 2x): (ratio, the other unit, what to
    send); None when it is near none of millimetres, centimetres against metres."""
    for unit_factor, unit in ((1000.0, "millimetres"), (100.0, "centimetres")):
        for ratio, other in ((unit_factor, "metres"), (1 / unit_factor, unit)):
            if 0.5 * ratio <= factor <= 2 * ratio:
                return ratio, unit, other
    return None


# --- the unit of a whole frame ---------------------------------------------------------------

NEAR_SHARE = 10  # percent: a frame's nearest points, where its parts lie before the background
CAMERA_RANGE = (0.1, 10.0)  # metres from a depth camera to what it sees
TYPICAL_RANGE = 1.0  # metres: of two units that both fit, the one nearer this is named
FRAME_UNITS = (("millimetres", 1000.0), ("centimetres", 100.0))  # units a camera's frame is in


def frame_scale_reason(ranges: np.ndarray, angle: float, largest: float, least: int) -> str | None:
    """Why no registered part can be found in a frame whose points lie at ``ranges`` from its
    camera (in the references' unit, metres), ``angle`` between neighbouring pixels: at its
    nearest points the largest part (radius ``largest``) would cover fewer than ``least``
    pixels, the fewest a part is searched on. Names the unit the frame is likely in: one that
    brings its nearest points into a camera's range with the part covering enough pixels, the
    nearest a metre away of those (docs/decisions.md#a-frame-in-millimetres). None where a
    part could be found."""
    sample = ranges[:: max(1, len(ranges) // 4096)]
    near = float(np.percentile(sample, NEAR_SHARE)) if len(sample) else 0.0
    if near <= 0 or angle <= 0:
        return None
    radius = largest / (near * angle)  # in pixels
    covered = np.pi * radius**2
    if covered >= least:
        return None
    said = (
        f"the frame's nearest points are {near:,.3g} from its camera, read in metres as the "
        f"references are: there the largest registered part would cover {covered:.2g} pixels, "
        f"fewer than the {least} a part is searched on"
    )
    low, high = CAMERA_RANGE  # a unit where the frame lies in a camera's range, the part seen
    units = [
        (abs(np.log(near / factor / TYPICAL_RANGE)), unit)
        for unit, factor in FRAME_UNITS
        if low <= near / factor <= high and covered * factor**2 >= least
    ]
    depth = "a depth image: set its depth_scale, the metres a unit of its pixels is"
    if not units:
        return f"{said}; check the frame's unit ({depth}), or bring the camera nearer"
    _, unit = min(units)  # the one that puts the camera nearest a cell's metre
    return f"{said}: the frame is probably in {unit}; send it in metres ({depth})"


# --- the units a part is registered in --------------------------------------------------------

UNITS = {"m": 1.0, "mm": 0.001, "cm": 0.01, "in": 0.0254}  # metres a unit
UNIT_WORDS = {"m": "metres", "mm": "millimetres", "cm": "centimetres", "in": "inches"}
LIKELY_FIRST = ("mm", "cm", "m", "in")  # CAD exports ship millimetres most, inches least
WORKING_RANGE = (0.005, 2.0)  # radii in metres a depth camera's part has (5 mm to 2 m)
FAR_OFF = 30.0  # a part this many times larger (or smaller) than every other is doubted


def size_warnings(
    name: str, scale: float, units: str | None, others: dict[str, float]
) -> list[str]:
    """A registration's warning when the part's radius ``scale`` (metres, as stored, its points
    read in ``units``) is outside a camera's working range or ``FAR_OFF`` times every other
    part's (``others``: name -> scale), naming the unit its points are likely in."""
    off = _size_doubts(scale, others)
    if not off:
        return []
    given = units or "m"
    sent = scale / UNITS[given]  # the radius in the numbers the caller sent
    likely = next(
        (u for u in LIKELY_FIRST if u != given and not _size_doubts(sent * UNITS[u], others)),
        None,
    )
    read = f" (its points read as {UNIT_WORDS[given]})" if units else ""
    said = f"{name}'s radius is {scale:.3g} m{read}: {' and '.join(off)}"
    if likely is None:
        return [f"{said}; check which unit its points are in (units: m, mm, cm or in)"]
    return [
        f"{said}; its points are probably in {UNIT_WORDS[likely]}: register it again with "
        f"units={likely} (and replace=true), so that it is stored in metres"
    ]


def _size_doubts(scale: float, others: dict[str, float]) -> list[str]:
    """What is doubtful about a part of radius ``scale`` metres among parts of ``others``."""
    doubts = []
    low, high = WORKING_RANGE
    if not low <= scale <= high:
        doubts.append("outside a camera's working range (a radius of 5 mm to 2 m)")
    if others:
        nearest = min(others, key=lambda other: abs(np.log(scale / others[other])))
        ratio = scale / others[nearest]
        if not 1 / FAR_OFF < ratio < FAR_OFF:
            times = f"{ratio:,.0f} times" if ratio > 1 else f"1/{1 / ratio:,.0f} of"
            doubts.append(
                f"{times} the radius of the nearest-sized registered part ({nearest}, "
                f"{others[nearest]:.3g} m)"
            )
    return doubts
