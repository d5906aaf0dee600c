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
