"""Keyframe images on disk, so that memory stays bounded over a long flight.

Each keyframe keeps up to three files in the store's folder: ``kf{index:07d}.png``, the grey frame
at the working resolution (what loop closure registers); ``kf{index:07d}.jpg``, the frame as it was
painted into the map (at the map's resolution: what re-renders the map after a pose-graph
correction), unless the input gives that image back itself (:meth:`KeyframeStore.put_source`:
a still painted as decoded is read again from its file, no JPEG encoded and no JPEG loss); and
``kf{index:07d}_mask.png`` when only part of that image is valid. Different indices may be
written from different threads.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from photomap.io.trajectory_files import atomic_write_bytes


class KeyframeStore:
    """Keyframe images by frame index in ``folder`` (created). ``read_again(index)``: the
    input's frame ``index`` as it was painted, read again (any thread), or None; used for the
    frames kept by :meth:`put_source`."""

    def __init__(self, folder: str | Path, jpeg_quality: int = 92,
                 read_again: Callable[[int], np.ndarray | None] | None = None) -> None:
        self.folder = Path(folder)
        self.read_again = read_again
        self._sourced: set[int] = set()  # frames whose image read_again gives back
        self.folder.mkdir(parents=True, exist_ok=True)
        self._dir = str(self.folder)  # file names as str: pathlib would intern each one it parses
        self._jpeg = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        self._unsaved: dict[int, np.ndarray] = {}  # working images the disk refused (disk full)
        self.failures = 0

    def _path(self, index: int, kind: str) -> str:
        """``kind``: "png", "jpg" or "mask" (``kf{index:07d}_mask.png``)."""
        name = f"kf{index:07d}_mask.png" if kind == "mask" else f"kf{index:07d}.{kind}"
        return os.path.join(self._dir, name)

    def put(self, index: int, small: np.ndarray, image: np.ndarray | None = None) -> None:
        """Keep keyframe ``index``: ``small`` (working resolution, grey or BGR) and, if given,
        ``image`` (as :meth:`put_image`)."""
        gray = small if small.ndim == 2 else cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
        if not self._write(self._path(index, "png"), ".png", gray):
            # e.g. disk full: loop closure still needs it (a small grey image), keep it here
            self._unsaved[index] = gray.copy()
            self.failures += 1
            return
        if image is not None:
            self.put_image(index, image)

    def put_image(self, index: int, image: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Keep the image of frame ``index`` that re-renders the map (JPEG), and where it is
        valid (``mask`` non-zero; None: everywhere). A write that fails (disk full) counts in
        ``failures``: no re-render from this frame (:meth:`image` gives None)."""
        self._sourced.discard(index)
        if not self._write(self._path(index, "jpg"), ".jpg", image, self._jpeg):
            self.failures += 1
            return
        mask_path = self._path(index, "mask")
        if mask is not None:
            if not self._write(mask_path, ".png", np.where(np.asarray(mask) != 0, np.uint8(255), np.uint8(0))):
                _unlink(self._path(index, "jpg"))  # no image rather than one without its mask
                self.failures += 1
        else:
            _unlink(mask_path)

    def put_source(self, index: int) -> None:
        """Keep the image of frame ``index`` by reference: :meth:`image` reads it again from the
        input (``read_again``), valid everywhere. Nothing is written."""
        if self.read_again is None:
            raise ValueError("this store has no read_again: keep the image with put_image")
        _unlink(self._path(index, "jpg"))
        _unlink(self._path(index, "mask"))
        self._sourced.add(index)

    @staticmethod
    def _write(path: str, ext: str, image: np.ndarray, params: list[int] | None = None) -> bool:
        """Encode in memory, then write (a temporary file renamed): a full disk is an OSError
        here (False), not libpng's message on stderr; a partial file is removed."""
        try:
            ok, buf = cv2.imencode(ext, image, params or [])
        except cv2.error:
            return False
        if not ok:
            return False
        try:  # a kill leaves no partial file under the keyframe's name (no fsync per keyframe)
            atomic_write_bytes(path, buf.tobytes(), sync=False)
        except OSError:
            return False
        return True

    def small(self, index: int) -> np.ndarray:
        """The grey working-resolution image of keyframe ``index``; FileNotFoundError if lost."""
        if index in self._unsaved:
            return self._unsaved[index]
        img = cv2.imread(self._path(index, "png"), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(self._path(index, "png"))
        return img

    def image(self, index: int) -> np.ndarray | None:
        """The image of frame ``index`` kept by :meth:`put_image` (BGR) or :meth:`put_source`, or
        None if it cannot be read."""
        if index in self._sourced:
            return self.read_again(index)
        path = self._path(index, "jpg")  # (imread warns on stderr about a missing file)
        return cv2.imread(path, cv2.IMREAD_COLOR) if os.path.isfile(path) else None

    def mask(self, index: int) -> np.ndarray | None:
        """Where the image of frame ``index`` is valid (uint8, 255 valid), or None: all of it."""
        path = self._path(index, "mask")
        return cv2.imread(path, cv2.IMREAD_GRAYSCALE) if os.path.isfile(path) else None

    def discard(self, index: int) -> None:
        """Forget keyframe ``index`` (its files too)."""
        self._unsaved.pop(index, None)
        self._sourced.discard(index)
        for kind in ("png", "jpg", "mask"):
            _unlink(self._path(index, kind))


def _unlink(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
