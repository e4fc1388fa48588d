"""Replay a folder (or glob) of stills, timed by their EXIF capture time when they carry one."""

from __future__ import annotations

import calendar
import glob
import logging
import mmap
import re
import struct
from datetime import datetime
from pathlib import Path
from typing import Iterator

import cv2

from photomap.errors import InputError

from photomap.drivers.capture import CaptureStats, Frame, SourceBase

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")

_TAG_DATETIME = 0x0132  # IFD0 DateTime (last modification): fallback only
_TAG_EXIF_IFD = 0x8769
_TAG_DATETIME_ORIGINAL = 0x9003
_TAG_OFFSET_TIME_ORIGINAL = 0x9011
_TAG_SUBSEC_TIME_ORIGINAL = 0x9291
_ASCII = 2
_OFFSET = re.compile(r"^([+-])(\d\d):(\d\d)$")
_GLOB_CHARS = re.compile(r"[*?\[]")
#: Stills with a side shorter than this (pixels) are skipped: too small to register.
MIN_SIDE = 16


def parse_exif_datetime(text: str, subsec: str | None = None, offset: str | None = None) -> float:
    """Seconds since the Unix epoch of an EXIF date/time.

    Parameters
    ----------
    text : str
        ``"YYYY:MM:DD HH:MM:SS"`` (EXIF DateTimeOriginal).
    subsec : str, optional
        EXIF SubSecTimeOriginal: the digits of the decimal fraction (``"25"`` = 0.25 s).
    offset : str, optional
        EXIF OffsetTimeOriginal, ``"+HH:MM"``. Without it the clock is taken as UTC (EXIF
        times are the camera's local time; only differences matter within one flight).

    Raises
    ------
    ValueError
        ``text`` (or ``offset``) is not in EXIF format.
    """
    stamp = datetime.strptime(text.strip(), "%Y:%m:%d %H:%M:%S")
    seconds = float(calendar.timegm(stamp.timetuple()))
    digits = (subsec or "").strip()
    if digits.isdigit():
        seconds += int(digits) / 10 ** len(digits)
    if offset and offset.strip():
        m = _OFFSET.match(offset.strip())
        if m is None:
            raise ValueError(f"bad EXIF time offset {offset!r}")
        sign = 1 if m.group(1) == "+" else -1
        seconds -= sign * (int(m.group(2)) * 3600 + int(m.group(3)) * 60)
    return seconds


def exif_time(path: str | Path) -> float | None:
    """Capture time of a JPEG or TIFF still from its EXIF, in seconds since the Unix epoch.

    Uses DateTimeOriginal (+ SubSecTimeOriginal, OffsetTimeOriginal), falling back to the
    IFD0 DateTime. Reads only the EXIF block. Returns None when the file has no (valid) EXIF
    time; never raises for malformed EXIF.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(4)
            if head[:2] == b"\xff\xd8":
                tiff = _jpeg_exif_block(f)
                return None if tiff is None else _tiff_time(tiff)
            if head in (b"II*\x00", b"MM\x00*"):
                with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                    return _tiff_time(data)
    except (OSError, ValueError, struct.error) as exc:
        log.debug("%s: no usable EXIF time (%s)", path, exc)
    return None


def _jpeg_exif_block(f) -> bytes | None:
    """The TIFF structure inside a JPEG's APP1 "Exif" segment, or None."""
    f.seek(2)
    while True:
        marker = f.read(4)
        if len(marker) < 4 or marker[0] != 0xFF:
            return None
        kind, length = marker[1], struct.unpack(">H", marker[2:])[0]
        if kind in (0xDA, 0xD9) or length < 2:  # start of scan / end of image: no EXIF before the data
            return None
        payload = f.read(length - 2)
        if kind == 0xE1 and payload[:6] == b"Exif\x00\x00":
            return payload[6:]


def _tiff_time(data) -> float | None:
    order = {b"II": "<", b"MM": ">"}.get(bytes(data[:2]))
    if order is None:
        return None
    ifd0 = _read_ifd(data, order, struct.unpack(order + "I", data[4:8])[0])
    exif: dict[int, tuple[int, int, bytes]] = {}
    if _TAG_EXIF_IFD in ifd0:
        _, _, raw = ifd0[_TAG_EXIF_IFD]
        exif = _read_ifd(data, order, struct.unpack(order + "I", raw)[0])
    text = _ascii(data, order, exif.get(_TAG_DATETIME_ORIGINAL))
    subsec = _ascii(data, order, exif.get(_TAG_SUBSEC_TIME_ORIGINAL))
    offset = _ascii(data, order, exif.get(_TAG_OFFSET_TIME_ORIGINAL))
    if not text:
        text, subsec, offset = _ascii(data, order, ifd0.get(_TAG_DATETIME)), None, None
    if not text:
        return None
    return parse_exif_datetime(text, subsec, offset)


def _read_ifd(data, order: str, offset: int) -> dict[int, tuple[int, int, bytes]]:
    """Entries of the IFD at ``offset``: tag -> (type, count, raw 4-byte value/offset field)."""
    (n,) = struct.unpack(order + "H", data[offset:offset + 2])
    entries = {}
    for i in range(n):
        start = offset + 2 + 12 * i
        tag, kind, count = struct.unpack(order + "HHI", data[start:start + 8])
        entries[tag] = (kind, count, bytes(data[start + 8:start + 12]))
    return entries


def _ascii(data, order: str, entry: tuple[int, int, bytes] | None) -> str | None:
    if entry is None or entry[0] != _ASCII:
        return None
    _, count, raw = entry
    if count <= 4:
        value = raw[:count]
    else:
        (start,) = struct.unpack(order + "I", raw)
        value = bytes(data[start:start + count])
        if len(value) < count:
            return None
    return value.split(b"\x00", 1)[0].decode("ascii", "replace").strip() or None


def list_images(folder_or_glob: str | Path) -> list[Path]:
    """Still images (jpg, jpeg, png, tif, tiff; any case) of a folder or glob, sorted by path.

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

    Parameters
    ----------
    folder_or_glob : str or Path
        A directory or a glob pattern such as ``"flight/*.JPG"``.
    rate : float
        Nominal stills per second, used when the stills carry no EXIF time.

    Attributes
    ----------
    paths : list of Path
        The stills in frame order.
    times : list of float
        ``Frame.t`` of each still, in the same order.
    exif_times : bool
        True when ``times`` come from EXIF.

    Raises
    ------
    InputError
        The folder does not exist, or holds no still image.
    """

    live = False

    def __init__(self, folder_or_glob: str | Path, *, rate: float = 1.0) -> None:
        if rate <= 0:
            raise InputError(f"image rate must be positive, got {rate}")
        spec = str(folder_or_glob)
        self.stats = CaptureStats()
        self.paths = list_images(spec)
        if not self.paths:
            if not Path(spec).is_dir() and not _GLOB_CHARS.search(spec):
                raise InputError(f"image folder not found: {spec}")
            raise InputError(f"no images (jpg, png, tif) in {spec}")
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

    def __iter__(self) -> Iterator[Frame]:
        for index, (path, t) in enumerate(zip(self.paths, self.times)):
            if self._closed:
                return
            image = cv2.imread(str(path), cv2.IMREAD_ANYCOLOR)
            if image is None:
                log.warning("skipping %s: not a readable image", path)
                self.stats.corrupt += 1
                continue
            if min(image.shape[:2]) < MIN_SIDE:
                log.warning("skipping %s: %dx%d pixels, too small to register (less than %d on a "
                            "side)", path, image.shape[1], image.shape[0], MIN_SIDE)
                self.stats.corrupt += 1
                continue
            self.stats.read += 1
            yield Frame(index=index, t=t, image=image, source=path.name)

    def close(self) -> None:
        """Stop iteration at the next frame."""
        self._closed = True
