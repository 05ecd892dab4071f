"""Pixel checks for tests of pictures: text ink in a box, ramp ends, camera towards a direction."""

from __future__ import annotations

import numpy as np

from recon_cli.eval.figure import TEXT_COLOR


def ink(img: np.ndarray, box, tol: int = 40) -> int:
    """Pixels of the text colour (within ``tol`` per channel) inside ``box``."""
    x0, y0, x1, y1 = box
    part = img[y0:y1, x0:x1].astype(int)
    return int((np.abs(part - np.array(TEXT_COLOR)).max(axis=2) <= tol).sum())


def is_red(px) -> bool:
    """Whether a pixel is clearly red (red well above green and blue)."""
    r, g, b = (int(c) for c in px)
    return r > 140 and r > 2 * g and r > 2 * b


def is_blue(px) -> bool:
    """Whether a pixel is clearly blue (blue well above red, above green)."""
    r, g, b = (int(c) for c in px)
    return b > 90 and b > 1.5 * r and b > g


def view_towards(direction) -> tuple[float, float]:
    """(azimuth, elevation) of a camera looking from ``direction`` at the centre."""
    x, y, z = direction
    return float(np.degrees(np.arctan2(x, z))), float(np.degrees(np.arcsin(np.clip(y, -1, 1))))
