"""Map-relative registration: a new keyframe registered against the map rendered at its pose.

Chained registrations accumulate error; the map already holds every earlier frame, so while the
drone flies over mapped ground, registering against the map patch seen from the predicted pose
stops the error from growing. Pure: a mosaic and arrays in, a correction out.

Conventions: poses are 3x3, input-frame pixels -> map pixels; a correction ``C`` maps map pixels to
map pixels (``C @ pose`` is the corrected pose).
"""

from __future__ import annotations

import cv2
import numpy as np

from photomap.core.ifmi import Prior, Registrar
from photomap.core.mosaic import TiledMosaic
from photomap.geometry import scaling


def map_patch(mosaic: TiledMosaic, pose: np.ndarray, frame_size: tuple[int, int]
              ) -> tuple[np.ndarray, float] | None:
    """The map seen through ``pose`` as a frame-sized grey image, and its covered fraction."""
    w, h = frame_size
    corners = pose[:2] @ np.array([[0, w - 1, w - 1, 0], [0, 0, h - 1, h - 1], [1, 1, 1, 1.0]])
    x0, y0 = np.floor(corners.min(axis=1)).astype(int) - 2
    x1, y1 = np.ceil(corners.max(axis=1)).astype(int) + 2
    image, alpha, origin = mosaic.render(bounds=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)))
    if image.size == 0:
        return None
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    to_image = np.array([[1, 0, -origin[0]], [0, 1, -origin[1]], [0, 0, 1.0]]) @ pose  # frame px -> image px
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    patch = cv2.warpAffine(gray, to_image[:2], (w, h), flags=flags, borderValue=0)
    cover = cv2.warpAffine(alpha, to_image[:2], (w, h), flags=flags, borderValue=0)
    covered = cover > 250
    fraction = float(covered.mean())
    if fraction > 0:
        patch[~covered] = int(np.median(patch[covered]))  # no edge where the map ends
    return patch, fraction


def map_correction(registrar: Registrar, mosaic: TiledMosaic, pose: np.ndarray, frame_small: np.ndarray,
                   frame_size: tuple[int, int], working_scale: float, *, min_coverage: float = 0.6,
                   min_confidence: float = 0.25, max_shift_px: float = 8.0) -> np.ndarray | None:
    """Correction of ``pose`` from registering the frame against the map, or None.

    ``frame_small`` is the frame at the working resolution. The registration is restricted to
    small motions (the pose is already close) and must be confident.
    """
    found = map_patch(mosaic, pose, frame_size)
    if found is None or found[1] < min_coverage:
        return None
    small_size = (frame_small.shape[1], frame_small.shape[0])
    patch = cv2.resize(found[0], small_size, interpolation=cv2.INTER_AREA)
    reg = registrar.register(patch, frame_small, Prior(angle_deg=0.0, angle_tol_deg=3.0, scale=1.0,
                                                       scale_tol=0.03, shift=(0.0, 0.0),
                                                       shift_tol=max_shift_px * working_scale))
    if reg.confidence < min_confidence:
        return None
    to_small = scaling(working_scale)
    rel = np.linalg.inv(to_small) @ np.vstack([reg.matrix, [0, 0, 1]]) @ to_small  # frame px -> predicted
    w, h = frame_size
    corners = np.array([[0, w - 1, w - 1, 0], [0, 0, h - 1, h - 1], [1, 1, 1, 1.0]])
    if np.abs((rel - np.eye(3)) @ corners)[:2].max() > max_shift_px:
        return None
    return pose @ rel @ np.linalg.inv(pose)


__all__ = ["map_patch", "map_correction"]
