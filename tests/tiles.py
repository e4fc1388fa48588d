"""Map tiles read back as a viewer reads them: a PNG without an alpha channel is opaque."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def tile_bgra(data: bytes | Path) -> np.ndarray:
    """A tile's pixels as BGRA uint8 (alpha 255 where the PNG has none), from its bytes or file."""
    raw = np.frombuffer(data if isinstance(data, bytes) else Path(data).read_bytes(), np.uint8)
    tile = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    assert tile is not None, "not a picture"
    assert tile.ndim == 3 and tile.shape[2] in (3, 4), f"a tile of shape {tile.shape}"
    return tile if tile.shape[2] == 4 else cv2.cvtColor(tile, cv2.COLOR_BGR2BGRA)
