"""Overview levels of a map: a BGRA image halved, alpha-weighted.

Level ``k + 1`` of a pyramid is level ``k`` halved: ``ceil(w / 2) x ceil(h / 2)`` pixels, each the
alpha-weighted mean of the 2 x 2 pixels under it (pixels past an odd edge count as transparent),
so that empty map pixels never darken the edges of what is mapped. Blocks whose origins are even
halve independently: a block of level ``k`` at ``(x, y)`` becomes the block at ``(x / 2, y / 2)``
of level ``k + 1``.
"""

from __future__ import annotations

import cv2
import numpy as np

from photomap.core.area import premultiplied_planes
from photomap.core.mosaic import unpremultiply


def halve(bgra: np.ndarray) -> np.ndarray:
    """``bgra`` (uint8 (h, w, 4), blue, green, red, alpha) at half size, ``((h + 1) // 2,
    (w + 1) // 2, 4)``: premultiplied float32 means of 2 x 2 pixels, finished by
    :func:`~photomap.core.mosaic.unpremultiply` (colour ``rint(sum(c a) / sum(a))``, alpha
    ``rint(mean(a))``). An opaque image of even size takes OpenCV's 8-bit 2 x 2 mean instead (the
    same values except where a mean ends in exactly .5: rounded up, not to even), a tenth of the time."""
    h, w = bgra.shape[:2]
    if h % 2 == 0 and w % 2 == 0 and bgra[..., 3].min() == 255:
        return cv2.resize(bgra, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    if h % 2 or w % 2:
        bgra = cv2.copyMakeBorder(bgra, 0, h % 2, 0, w % 2, cv2.BORDER_CONSTANT, value=(0, 0, 0, 0))
    *colour, alpha = cv2.split(bgra)  # the four planes at once: a tenth of splitting the colour view
    pre = cv2.merge(premultiplied_planes(cv2.merge(colour), alpha))
    half = cv2.resize(pre, (bgra.shape[1] // 2, bgra.shape[0] // 2), interpolation=cv2.INTER_AREA)
    return cv2.merge(unpremultiply(half))
