"""Camera files: lens calibrations in the formats users have, and frame masks.

:func:`read_calibration` reads, by content (not by name):

- what ``cv2.FileStorage`` writes, YAML (``%YAML:1.0``, ``!!opencv-matrix``) or JSON
  (``camera_matrix``, ``distortion_coefficients`` as ``{rows, cols, dt, data}``,
  ``image_width``/``image_height``; ``distortion_model`` when present, else Brown-Conrady), as
  OpenCV's calibration sample and :func:`write_calibration` (``photomap calibrate``) write it;
- ROS ``camera_info`` YAML (``camera_matrix: {rows, cols, data}``, ``distortion_model:
  plumb_bob | rational_polynomial | equidistant``, ``distortion_coefficients``,
  ``image_width``/``image_height``);
- OpenSfM / OpenDroneMap ``cameras.json`` (one camera: ``projection_type`` ``perspective``,
  ``brown``, ``fisheye`` or ``fisheye_opencv``; focal lengths and principal-point offsets
  normalised by ``max(width, height)``, offsets from the image centre).

Every reader returns a :class:`~photomap.geo.lens.LensModel` at the file's image size; a file
that is none of these, or misses a value, is one InputError line naming the file.
:func:`read_mask` reads a frame mask image (black = ignore).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from photomap.errors import InputError
from photomap.geo.lens import LensModel
from photomap.io.trajectory_files import read_text_input

__all__ = ["read_calibration", "write_calibration", "read_mask"]

_ROS_MODELS = {"plumb_bob": "brown", "rational_polynomial": "brown", "radtan": "brown", "brown": "brown",
               "equidistant": "fisheye", "fisheye": "fisheye", "kannala_brandt": "fisheye"}


class _OpenCVLoader(yaml.SafeLoader):
    """YAML loader for cv2.FileStorage files: ``!!opencv-matrix`` nodes become plain mappings."""


_OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                              lambda loader, node: loader.construct_mapping(node, deep=True))
_OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix",
                              lambda loader, node: loader.construct_mapping(node, deep=True))


def read_calibration(path: str | Path) -> LensModel:
    """The lens model in the calibration file ``path`` (see the module docstring)."""
    p = Path(path)
    text = read_text_input(p, "camera calibration file", reason=lambda exc: getattr(exc, "strerror", None) or exc)
    try:
        data = _parse(text)
    except (yaml.YAMLError, json.JSONDecodeError, ValueError):
        raise InputError(f"camera calibration file {p} is not YAML or JSON") from None
    if not isinstance(data, dict):
        raise InputError(f"camera calibration file {p} holds no camera (expected a mapping)")
    try:
        if "camera_matrix" in data or "K" in data or "cameraMatrix" in data:
            return _from_matrix_file(data)
        cams = [v for v in data.values() if isinstance(v, dict) and "projection_type" in v]
        if "projection_type" in data:
            cams = [data]
        if len(cams) == 1:
            return _from_opensfm(cams[0])
        if len(cams) > 1:
            raise ValueError(f"it holds {len(cams)} OpenSfM cameras; keep the one of this video")
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        what = f"misses {exc}" if isinstance(exc, KeyError) else str(exc)
        raise InputError(f"camera calibration file {p}: {what}") from None
    except InputError as exc:
        raise InputError(f"camera calibration file {p}: {exc}") from None
    raise InputError(f"camera calibration file {p} is not a cv2.FileStorage, ROS camera_info or OpenSfM "
                     f"cameras.json file (no camera_matrix or projection_type)")


def _parse(text: str) -> Any:
    stripped = text.lstrip()
    if stripped.startswith("{"):
        return json.loads(text)
    if stripped.startswith("%YAML"):  # cv2.FileStorage's directive is not YAML 1.1 syntax
        text = stripped.split("\n", 1)[1] if "\n" in stripped else ""
        if text.lstrip().startswith("---"):
            text = text.lstrip()[3:]
    return yaml.load(text, Loader=_OpenCVLoader)


def _matrix(node: Any, name: str) -> np.ndarray:
    """A ``{rows, cols, data}`` node (FileStorage, ROS) or a plain (nested) list as an array."""
    if isinstance(node, dict):
        data = np.asarray(node["data"], float)
        rows, cols = int(node.get("rows", 1)), int(node.get("cols", data.size))
        if data.size != rows * cols:
            raise ValueError(f"{name} has {data.size} values for {rows}x{cols}")
        return data.reshape(rows, cols)
    return np.asarray(node, float)


def _first(data: dict, *names: str) -> Any:
    for n in names:
        if n in data:
            return data[n]
    raise KeyError(names[0])


def _from_matrix_file(data: dict) -> LensModel:
    k = _matrix(_first(data, "camera_matrix", "K", "cameraMatrix"), "camera_matrix")
    if k.size != 9:
        raise ValueError(f"camera_matrix has {k.size} values, not 9")
    k = k.reshape(3, 3)
    try:
        d = _matrix(_first(data, "distortion_coefficients", "D", "dist_coeffs", "distCoeffs"), "distortion").ravel()
    except KeyError:
        d = np.zeros(0)
    name = str(data.get("distortion_model", "")).strip().lower()
    if name and name not in _ROS_MODELS:
        raise ValueError(f"distortion_model {name!r} is not supported (plumb_bob, rational_polynomial, equidistant)")
    model = _ROS_MODELS.get(name, "brown")
    if model == "brown" and d.size > 8:
        if np.any(d[8:] != 0):
            raise ValueError(f"{d.size} distortion coefficients: only k1 k2 p1 p2 k3 k4 k5 k6 are supported")
        d = d[:8]
    if model == "brown" and d.size not in (0, 4, 5, 8):
        d = np.concatenate([d, np.zeros(5 - d.size)]) if d.size < 5 else d[:5]
    width, height = int(_first(data, "image_width", "width")), int(_first(data, "image_height", "height"))
    return LensModel(model, width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                     tuple(float(v) for v in d))


def _from_opensfm(cam: dict) -> LensModel:
    kind = str(cam["projection_type"])
    w, h = int(cam["width"]), int(cam["height"])
    size = float(max(w, h))
    if "focal_x" in cam:
        fx, fy = float(cam["focal_x"]) * size, float(cam["focal_y"]) * size
    else:
        fx = fy = float(cam["focal"]) * size
    cx = (w - 1) / 2.0 + float(cam.get("c_x", 0.0)) * size
    cy = (h - 1) / 2.0 + float(cam.get("c_y", 0.0)) * size
    get = lambda key: float(cam.get(key, 0.0))  # noqa: E731
    if kind in ("perspective", "brown"):
        dist = (get("k1"), get("k2"), get("p1"), get("p2"), get("k3"))
        return LensModel("brown", w, h, fx, fy, cx, cy, dist)
    if kind == "fisheye_opencv":
        return LensModel("fisheye", w, h, fx, fy, cx, cy, (get("k1"), get("k2"), get("k3"), get("k4")))
    if kind == "fisheye":  # OpenSfM's fisheye: theta_d = theta (1 + k1 theta^2 + k2 theta^4)
        return LensModel("fisheye", w, h, fx, fy, cx, cy, (get("k1"), get("k2"), 0.0, 0.0))
    raise ValueError(f"OpenSfM projection_type {kind!r} is not supported (perspective, brown, fisheye, "
                     f"fisheye_opencv)")


def write_calibration(path: str | Path, lens: LensModel, *, rms_px: float | None = None,
                      views: int | None = None, board: str | None = None, square_m: float | None = None) -> None:
    """Write ``lens`` as a cv2.FileStorage YAML file (``camera_matrix``, ``distortion_coefficients``,
    ``distortion_model`` in ROS names, ``image_width``/``image_height``, and what the calibration
    measured: ``avg_reprojection_error`` in pixels, the views, the board)."""
    p = Path(path)
    suffix = p.suffix.lower()
    tmp = p.with_name(p.name + ".tmp" + (suffix if suffix in (".yaml", ".yml", ".json", ".xml") else ".yaml"))
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | (cv2.FILE_STORAGE_FORMAT_JSON if suffix == ".json" else 0))
    if not fs.isOpened():
        raise InputError(f"cannot write the calibration file {p}")
    try:
        fs.write("image_width", int(lens.width))
        fs.write("image_height", int(lens.height))
        fs.write("distortion_model", "equidistant" if lens.model == "fisheye" else "plumb_bob")
        fs.write("camera_matrix", lens.K)
        fs.write("distortion_coefficients", lens.D.reshape(1, -1))
        if rms_px is not None and math.isfinite(rms_px):
            fs.write("avg_reprojection_error", float(rms_px))
        if views is not None:
            fs.write("nr_of_frames", int(views))
        if board:
            fs.write("board", str(board))
        if square_m:
            fs.write("square_size_m", float(square_m))
    finally:
        fs.release()
    try:
        tmp.replace(p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise InputError(f"cannot write the calibration file {p}: {exc.strerror}") from None


def read_mask(path: str | Path) -> np.ndarray:
    """A frame mask image as uint8 (h, w): 255 where pixels are used, 0 where they are ignored
    (black, or transparent in a PNG with alpha). Any size: the caller scales it to the frames."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"mask image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"mask image {p} could not be read (not an image)")
    if img.dtype != np.uint8:
        img = (img.astype(np.float64) * (255.0 / max(float(np.iinfo(img.dtype).max), 1.0))).astype(np.uint8) \
            if np.issubdtype(img.dtype, np.integer) else np.clip(img * 255.0, 0, 255).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        use = (img[:, :, 3] >= 128) & (img[:, :, :3].max(axis=2) >= 128)
    elif img.ndim == 3:
        use = img.max(axis=2) >= 128
    else:
        use = img >= 128
    if not use.any():
        raise InputError(f"mask image {p} is black everywhere: nothing would be mapped")
    return np.where(use, np.uint8(255), np.uint8(0))
