"""What happens to a frame where it enters the pipeline: lens undistortion and the frame mask.

:class:`FramePrep` is set up once, at the first frame's size, from the ``camera`` section (a
calibration file or the distortion keys, :mod:`photomap.geo.lens`) and ``capture.mask`` (a mask
image, black = ignore, in the raw frame's pixels, scaled to the frame size). Each frame is then

1. undistorted with maps computed once (``cv2.remap``) into the ideal pinhole view: square
   pixels, principal point at the centre, focal length :attr:`FramePrep.fx` (the camera model
   the telemetry's tilt rectification and metric scale use);
2. filled with the mean of its valid pixels where :attr:`FramePrep.mask` is 0 (pixels the lens
   does not cover, masked pixels): neutral for registration, like a rectified view's border.

:attr:`FramePrep.mask` (255 = valid, in the undistorted view's pixels; the user mask is
undistorted with the same maps) goes with the frame to the painter (and so to the kept frames
that re-render the map) and, at the working size, into the registrar's apodization window
(:meth:`FramePrep.window`): a masked pixel never reaches the map or a registration.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from photomap.config import Config
from photomap.errors import InputError
from photomap.geo.georef import focal_px
from photomap.geo.lens import LensModel, Undistortion, folds_inside
from photomap.io.camera_files import read_calibration, read_mask

log = logging.getLogger(__name__)



def fill_invalid(image: np.ndarray, valid: np.ndarray, invalid: np.ndarray | None = None) -> None:
    """Fill the pixels of ``image`` where the uint8 mask ``valid`` is 0 with the mean of the valid
    ones, in place (registration then sees no edge there). ``invalid``: ``valid == 0`` when the
    caller keeps it (a mask fixed for the flight)."""
    fill = cv2.mean(image, mask=valid)[:1 if image.ndim == 2 else image.shape[2]]
    image[valid == 0 if invalid is None else invalid] = np.round(fill).astype(image.dtype)

class FramePrep:
    """Undistortion and mask of the frames of one run (see the module docstring).

    ``camera``: the ``camera`` keys (``model``, ``fx_px``, ``hfov_deg``, ``fy_px``, ``cx_px``,
    ``cy_px``, ``k1`` ... ``k4``) at the input size; ``calibration``: the lens read from
    ``camera.calibration`` instead (None: the keys); ``mask``: the mask image (255 = use, any
    size), or None.
    """

    def __init__(self, camera: dict, calibration: LensModel | None = None,
                 mask: np.ndarray | None = None) -> None:
        self.camera = dict(camera)
        self.calibration = calibration
        self.user_mask = mask
        self.undistortion: Undistortion | None = None
        self.mask: np.ndarray | None = None  # uint8 (h, w), 255 = valid; None: every pixel
        self._invalid: np.ndarray | None = None  # bool (h, w): the mask's invalid pixels (made once)
        self.fx: float | None = None  # focal length of the frames after undistortion (None: unknown)
        self.size: tuple[int, int] | None = None

    @classmethod
    def from_config(cls, cfg: Config) -> FramePrep | None:
        """The run's frame preparation, or None when there is nothing to do (no lens
        distortion, no mask). Reads the calibration and mask files now: a bad file is an
        InputError before the first frame."""
        cam, mask_path = cfg.camera, cfg.capture.mask
        keys = ("model", "fx_px", "hfov_deg", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4")
        camera = {k: getattr(cam, k) for k in keys}
        distorted = any(camera[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4"))
        if not distorted and not cam.calibration and not mask_path:
            return None
        calibration = read_calibration(Path(cam.calibration).expanduser()) if cam.calibration else None
        mask = read_mask(Path(mask_path).expanduser()) if mask_path else None
        return cls(camera if distorted else {}, calibration, mask)

    def lens(self, width: int, height: int) -> LensModel | None:
        """The lens at frames of ``width x height`` (None: no distortion configured)."""
        if self.calibration is not None:
            return self.calibration.scaled(width, height)
        c = self.camera
        if not c:
            return None
        fx = focal_px(width, c["fx_px"], c["hfov_deg"])
        if fx is None:
            raise InputError("camera distortion (camera.k1 ...) needs the focal length: set camera.fx_px or "
                             "camera.hfov_deg, or give a camera.calibration file")
        cx = c["cx_px"] or (width - 1) / 2.0
        cy = c["cy_px"] or (height - 1) / 2.0
        keys = ("k1", "k2", "k3", "k4") if c["model"] == "fisheye" else ("k1", "k2", "p1", "p2", "k3")
        return LensModel(c["model"], width, height, fx, c["fy_px"] or fx, cx, cy, tuple(c[k] for k in keys))

    def setup(self, width: int, height: int) -> None:
        """Maps and mask for frames of ``width x height`` (the first frame's size)."""
        self.size = (width, height)
        lens = self.lens(width, height)
        valid = None
        if lens is not None:
            if folds_inside(lens):
                log.warning("the lens model's radial distortion folds back before the frame's corners: "
                            "the corners are not undistorted (a calibration used beyond what it was fitted on)")
            self.undistortion = Undistortion.of(lens)
            self.fx = self.undistortion.fx
            valid = self.undistortion.valid
            log.info("lens: %s model, fx %.1f px at %dx%d, distortion %s; frames are undistorted",
                     lens.model, lens.fx, width, height, " ".join(f"{v:g}" for v in lens.dist))
        if self.user_mask is not None:
            mh, mw = self.user_mask.shape
            if abs(mw / mh - width / height) > 0.01 * width / height:
                log.warning("the frame mask is %dx%d, the frames %dx%d (another aspect ratio): it is stretched "
                            "to the frames", mw, mh, width, height)
            user = cv2.resize(self.user_mask, (width, height), interpolation=cv2.INTER_NEAREST) \
                if self.user_mask.shape != (height, width) else self.user_mask
            valid = self.undistortion.apply_mask(user) if self.undistortion is not None else user
            log.info("frame mask: %.1f %% of each frame ignored", 100.0 * (1.0 - cv2.countNonZero(valid) / valid.size))
        if valid is not None and cv2.countNonZero(valid) == valid.size:
            valid = None
        if valid is not None and cv2.countNonZero(valid) < 0.05 * valid.size:
            raise InputError("the frame mask (with the lens model) leaves less than 5 % of each frame: "
                             "nothing to map")
        self.mask = valid
        self._invalid = None if valid is None else valid == 0

    def summary(self) -> dict:
        """For run.json: the lens the frames were undistorted with (None: none) and the share of
        each frame's pixels that were masked."""
        und = self.undistortion
        lens = None if und is None else {
            "model": und.lens.model, "size": [und.lens.width, und.lens.height], "fx": und.lens.fx,
            "fy": und.lens.fy, "cx": und.lens.cx, "cy": und.lens.cy, "distortion": list(und.lens.dist),
            "fx_undistorted": und.fx, "source": "calibration" if self.calibration is not None else "config"}
        masked = 0.0 if self.mask is None else 1.0 - cv2.countNonZero(self.mask) / self.mask.size
        return {"lens": lens, "mask": self.user_mask is not None, "masked_fraction": round(masked, 4)}

    def apply(self, image: np.ndarray) -> np.ndarray:
        """The frame as the map sees it: undistorted, masked pixels filled with the valid ones' mean."""
        if self.undistortion is not None:
            image = self.undistortion.apply(image)  # a new array
        elif self.mask is not None:
            image = image.copy()  # the source's frame stays as it was (the viewer shows it)
        if self.mask is not None:
            fill_invalid(image, self.mask, self._invalid)
        return image

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Input frame pixels (n, 2) -> pixels of the undistorted view (:meth:`apply`'s frame);
        the same pixels without a lens model."""
        if self.undistortion is None:
            return np.asarray(uv, np.float64)
        return self.undistortion.lens.undistort_points(uv)

    def window(self, size: tuple[int, int]) -> np.ndarray | None:
        """The mask at the working size ``(w, h)`` as registration weights in [0, 1] (a pixel
        is 0 where any of the input pixels under it is masked, then the edge is tapered over
        a few pixels so that the window adds no edge of its own); None: no mask."""
        if self.mask is None:
            return None
        small = cv2.resize(self.mask, size, interpolation=cv2.INTER_AREA)
        keep = np.where(small == 255, np.uint8(255), np.uint8(0))
        dist = cv2.distanceTransform(keep, cv2.DIST_L2, 3)
        taper = max(2.0, 0.02 * max(size))
        return np.clip(dist / taper, 0.0, 1.0).astype(np.float32)


def view_points(prep: FramePrep | None,
                homography: np.ndarray | None) -> Callable[[np.ndarray], np.ndarray] | None:
    """Input frame pixels (n, 2) -> pixels of the view the map got of the frame, i.e. the pixels
    its pose maps: undistorted by ``prep``'s lens, then through the telemetry's rectifying
    ``homography`` (3x3 undistorted pixels -> view pixels; None: not rectified). None when the
    view is the input frame itself."""
    lens = prep is not None and prep.undistortion is not None
    if not lens and homography is None:
        return None

    def to_view(uv: np.ndarray) -> np.ndarray:
        p = prep.undistort_points(uv) if lens else np.asarray(uv, np.float64).reshape(-1, 2)
        if homography is None:
            return p
        q = np.c_[p, np.ones(len(p))] @ np.asarray(homography, np.float64).T
        return q[:, :2] / q[:, 2:3]
    return to_view
