"""Replay a folder (or glob) of stills, timed by their EXIF capture time when they carry one.

Every format this OpenCV build reads is taken (:func:`photomap.drivers.imread.image_suffixes`:
JPEG, PNG, TIFF, BMP, PGM/PPM/PBM, WebP, JPEG 2000 ...), at its own depth: 16-bit and float
stills are brought to 8 bits by one :class:`~photomap.core.stretch.RunningStretch` per flight,
and the image libraries' warnings are summarised once per kind with a count at the end.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from photomap.core.stretch import RunningStretch, to_8bit
from photomap.errors import InputError

from photomap.core.bands import robust_range_16bit, texture_energy
from photomap.drivers.captures import BAND_ALIASES, Capture, band_folders, group_band_folders, group_captures, read_band
from photomap.drivers.exif import parse_exif_datetime, read_capture_time
from photomap.drivers.frames import CaptureStats, Frame, SourceBase
from photomap.drivers.imread import ImageReader, image_suffixes

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = image_suffixes()

_GLOB_CHARS = re.compile(r"[*?\[]")
#: Stills with a side shorter than this (pixels) are skipped: too small to register.
MIN_SIDE = 16
_READ_FLAGS = cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH  # stills at their own depth and colour
#: Captures whose registering band sets a multi-band flight's 16-bit range (spread over the flight).
RANGE_SAMPLES = 8

__all__ = ["IMAGE_SUFFIXES", "ImageFolderSource", "exif_time", "list_images", "parse_exif_datetime"]


def exif_time(path: str | Path) -> float | None:
    """Capture time of a still from its EXIF, in seconds since the Unix epoch.

    Uses DateTimeOriginal (+ SubSecTimeOriginal, OffsetTimeOriginal), falling back to the
    IFD0 DateTime (see :func:`photomap.drivers.exif.parse_exif_datetime`); read with Pillow
    (JPEG, TIFF, PNG eXIf, WebP). Returns None when the file has no (valid) EXIF time; never
    raises for malformed EXIF.
    """
    return read_capture_time(path)


def list_images(folder_or_glob: str | Path) -> list[Path]:
    """Still images (:data:`IMAGE_SUFFIXES`, any case) of a folder or glob, sorted by path.

    Raises
    ------
    InputError
        The folder cannot be listed (permissions, I/O error).
    """
    text = str(folder_or_glob)
    try:
        if Path(text).is_dir():
            candidates = list(Path(text).iterdir())
        else:
            candidates = [Path(p) for p in glob.glob(text)]
        paths = [p for p in candidates if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
    except OSError as exc:
        raise InputError(f"cannot read image folder {text}: {exc.strerror or exc}") from None
    return sorted(paths, key=str)


class ImageFolderSource(SourceBase):
    """Stills of a folder or a glob pattern, sorted by path (by name in a folder); never drops.

    ``Frame.t`` is the EXIF capture time (seconds since the Unix epoch, see
    :func:`parse_exif_datetime`) when *every* still carries one; otherwise ``index / rate``
    for all of them (one warning), so a run never mixes two clocks. ``Frame.index`` is the
    position in the sorted list: an unusable file (unreadable, not an image, or smaller than
    ``MIN_SIDE`` pixels on a side: too small to register) is skipped with one logged line,
    counted in ``stats.corrupt``, and leaves a gap; so the first *usable* still is the first
    frame (the one that sets the map's frame size).

    Multi-band captures (:mod:`photomap.drivers.captures`: MicaSense, DJI multispectral, Sentera)
    are one frame each: the frame is the registering band (``band``; default the band with the
    most texture in the first capture, :func:`photomap.core.bands.texture_energy`), 16-bit bands
    stretched to 8 bits over one range for the whole flight
    (:func:`photomap.core.bands.robust_range_16bit` of a few captures spread over it); ``paths``
    and ``times`` are those of the registering band's files, ``captures`` the captures (the other
    bands are mapped at the end of the run: :mod:`photomap.mapping.band_maps`).

    Parameters
    ----------
    folder_or_glob : str or Path
        A directory or a glob pattern such as ``"flight/*.JPG"``.
    rate : float
        Nominal stills per second, used when the stills carry no EXIF time.
    band : str
        Multi-band captures: the band that registers, by name (``NIR``, ``red edge``) or number
        (1 = the first in the camera's order); "" = the band with the most texture.

    Attributes
    ----------
    paths : list of Path
        The stills in frame order.
    times : list of float
        ``Frame.t`` of each still, in the same order.
    exif_times : bool
        True when ``times`` come from EXIF.
    captures : list of Capture or None
        The multi-band captures in frame order (None: single-band stills).
    band : str or None
        The registering band's name (multi-band captures).
    band_range : tuple of float or None
        The registering band's 16-bit range mapped to 0..255 (None: 8-bit bands, as stored).

    Raises
    ------
    InputError
        The folder does not exist, or holds no still image.
    """

    live = False

    def __init__(self, folder_or_glob: str | Path, *, rate: float = 1.0, band: str = "") -> None:
        if rate <= 0:
            raise InputError(f"image rate must be positive, got {rate}")
        spec = str(folder_or_glob)
        self.stats = CaptureStats()
        self.paths = list_images(spec)
        self.captures: list[Capture] | None = None
        self.band: str | None = None
        self.band_range: tuple[float, float] | None = None
        per_band = band_folders(Path(spec), IMAGE_SUFFIXES) if not self.paths and Path(spec).is_dir() else None
        if per_band:
            self.captures = group_band_folders(per_band)
        elif self.paths:
            self.captures = group_captures(self.paths)
        if not self.paths and not self.captures:
            if not Path(spec).is_dir() and not _GLOB_CHARS.search(spec):
                raise InputError(f"image folder not found: {spec}")
            formats = ", ".join(s.lstrip(".") for s in IMAGE_SUFFIXES)
            raise InputError(f"no images in {spec} (formats read: {formats})")
        if self.captures:
            self._choose_band(band, spec)
        stamps = [exif_time(p) for p in self.paths]
        missing = sum(s is None for s in stamps)
        self.exif_times = missing == 0
        if self.exif_times:
            self.times = [float(s) for s in stamps]
        else:
            level = logging.WARNING if missing < len(stamps) else logging.INFO
            log.log(level, "%d of %d stills in %s carry no EXIF time: timing all by index at "
                    "%g per second", missing, len(stamps), spec, rate)
            self.times = [i / rate for i in range(len(self.paths))]
        self._closed = False
        self.stretch = RunningStretch()   # 16-bit / float stills: one range for the flight
        self._again: set[int] = set()  # frames read_again gives back as they were yielded

    def _choose_band(self, spec: str, where: str) -> None:
        """The registering band, its files as ``paths``, and its 16-bit range (multi-band)."""
        names = max((c.bands for c in self.captures), key=len)
        first: dict[Path, np.ndarray | None] = {}  # the first capture's bands, read once
        if spec:
            self.band = select_band(spec, names)
        else:
            first = {f.path: read_band(f.path) for f in self.captures[0].files}
            scored = [(texture_energy(img), f.band) for f in self.captures[0].files
                      if (img := first[f.path]) is not None]
            if not scored:
                raise InputError(f"{where}: the first capture's band files are unreadable")
            self.band = max(scored)[1]
        kept = [c for c in self.captures if c.path(self.band) is not None]
        if len(kept) < len(self.captures):
            log.warning("%d of %d captures have no %s band file: left out", len(self.captures) - len(kept),
                        len(self.captures), self.band)
        self.captures = kept
        self.paths = [c.path(self.band) for c in kept]
        if not self.paths:
            raise InputError(f"no capture in {where} has a {self.band} band")
        step = max(1, len(self.paths) // RANGE_SAMPLES)
        sample = [img for p in self.paths[::step][:RANGE_SAMPLES]
                  if (img := first[p] if p in first else read_band(p)) is not None]
        if any(img.dtype == np.uint16 for img in sample):
            self.band_range = robust_range_16bit(sample)
        log.info("%d captures of %d bands (%s) in %s: %s registers%s", len(kept), len(names), ", ".join(names),
                 where, self.band, "" if self.band_range is None else
                 f" (16-bit, {self.band_range[0]:.0f}..{self.band_range[1]:.0f} -> 0..255)")

    def _read(self, path: Path, reader: ImageReader) -> np.ndarray | None:
        """A still as stored (deep ones are stretched by the caller), or a multi-band capture's
        registering band in 8 bits."""
        if self.captures is None:
            return reader.read(path)
        image = read_band(path)
        if image is not None and image.dtype != np.uint8:
            image = to_8bit(image, self.band_range or (0.0, 65535.0))
        return image

    def raw_frame(self, index: int) -> np.ndarray | None:
        """Single-band stills: frame ``index``'s pixels as stored when they are 16-bit (uint16, gray
        or BGR; read again), else None (8-bit or float stills, multi-band captures, unreadable): the
        raw values of ``map_raw.tif`` (:func:`photomap.mapping.band_maps.write_raw_map`)."""
        if self.captures is not None or not self.stretch.frames or not 0 <= index < len(self.paths):
            return None  # no still deeper than 8 bits came: nothing read again
        reader = ImageReader()  # its library warnings were said when the still was first read
        try:
            image = reader.read(self.paths[index])
        finally:
            reader.close()
        if image is None or image.dtype != np.uint16:
            return None
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR) if image.ndim == 3 and image.shape[2] == 4 else image

    def readable_again(self, index: int) -> bool:
        """Whether :meth:`read_again` gives frame ``index``'s pixels back exactly as it was
        yielded: an 8-bit single-band still whose read printed nothing."""
        return index in self._again

    def read_again(self, index: int) -> np.ndarray | None:
        """Frame ``index``'s image read again from its file, the same pixels as when it was
        yielded (:meth:`readable_again`; ``cv2.imread``, safe from any thread), or None (not such
        a frame, or the file cannot be read any more)."""
        path = str(self.paths[index]) if index in self._again else None
        if path is None or not os.path.isfile(path):  # (imread warns on stderr about a missing file)
            return None
        image = cv2.imread(path, _READ_FLAGS)
        if image is None or image.dtype != np.uint8:
            return None
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR) if image.ndim == 3 and image.shape[2] == 4 else image

    def __iter__(self) -> Iterator[Frame]:
        reader = ImageReader(_READ_FLAGS)
        try:
            yield from self._frames(reader)
        finally:
            for line in reader.summary():
                log.info("%s", line)
            if self.stretch.frames:
                log.info("%d still(s) deeper than 8 bits stretched to 8 bits (range %s)",
                         self.stretch.frames, self.stretch.describe())
            reader.close()

    def _frames(self, reader: ImageReader) -> Iterator[Frame]:
        for index, (path, t) in enumerate(zip(self.paths, self.times)):
            if self._closed:
                return
            image = self._read(path, reader)
            if image is None:
                log.warning("skipping %s: not a readable image", path)
                self.stats.corrupt += 1
                continue
            if min(image.shape[:2]) < MIN_SIDE:
                log.warning("skipping %s: %dx%d pixels, too small to register (less than %d on a "
                            "side)", path, image.shape[1], image.shape[0], MIN_SIDE)
                self.stats.corrupt += 1
                continue
            if self.captures is None and reader.quiet and image.dtype == np.uint8:
                self._again.add(index)
            if image.ndim == 3 and image.shape[2] == 4:
                image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
            self.stats.read += 1
            yield Frame(index=index, t=t, image=self.stretch(image), source=path.name)

    def close(self) -> None:
        """Stop iteration at the next frame."""
        self._closed = True


def select_band(spec: str, names: tuple[str, ...]) -> str:
    """The band ``spec`` names among ``names``: a name (any case; ``rededge``/``RE`` for
    ``Red edge``) or a number from 1 in the camera's band order.

    Raises
    ------
    InputError
        No such band (the message names ``capture.band`` and the bands there are).
    """
    text = spec.strip()
    if text.isdigit() and 1 <= int(text) <= len(names):
        return names[int(text) - 1]
    want = BAND_ALIASES.get(text.lower(), text).lower()
    for name in names:
        if name.lower() in (want, text.lower()):
            return name
    raise InputError(f"capture.band: no band {spec!r} in these captures (bands: {', '.join(names)})")
