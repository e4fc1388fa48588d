"""Multi-band captures: the files that one trigger of a multispectral camera writes, grouped.

A multispectral camera writes one file per band for each capture. The files of one capture are
one frame of the map (:class:`~photomap.drivers.images.ImageFolderSource`); this module finds
them and reads their bands.

Recognised, XMP first and the file name otherwise:

- MicaSense RedEdge / Altum: ``IMG_NNNN_B.tif`` (``B`` = band number from 1); XMP
  ``MicaSense:CaptureId`` (shared by the bands of a capture), ``Camera:BandName``,
  ``Camera:RigCameraIndex`` (band order), ``Camera:CentralWavelength``.
- DJI P4 Multispectral / Mavic 3M: ``DJI_..._MS_G.TIF``, ``_MS_R``, ``_MS_RE``, ``_MS_NIR`` (and
  ``_MS_B``); XMP ``Camera:BandName`` and ``drone-dji:CaptureUUID`` where present (a P4
  Multispectral numbers its band files in sequence: they are grouped by ``CaptureUUID``).
- Sentera (and any camera that does the same): one folder per band (``Blue/``, ``NIR/``, ...;
  the folder names the band), the files of one capture having the same name in each; or a band
  suffix ``_NIR``, ``_RE``, ``_R``, ``_G``, ``_B`` on the file name.

A folder is taken as multi-band when its files form at least one group of two or more bands and
at least half the files are in such groups; the groups are its captures (a group missing a band
that the others have is still a capture: its missing band leaves a hole in that band's map).
Reading never raises for bad metadata: a file without usable XMP is grouped by its name.
"""

from __future__ import annotations

import logging
import re
import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from PIL import Image

from photomap.drivers.exif import xmp_packet

log = logging.getLogger(__name__)

#: Band names of the suffixes and folders of DJI and Sentera (lower case) -> the name used.
BAND_ALIASES = {"b": "Blue", "blue": "Blue", "g": "Green", "green": "Green", "r": "Red", "red": "Red",
                "re": "Red edge", "rededge": "Red edge", "red edge": "Red edge", "red_edge": "Red edge",
                "nir": "NIR", "lwir": "LWIR", "pan": "Panchro", "panchro": "Panchro"}
#: Typical central wavelengths (nm) to order bands that carry no rig index.
_WAVELENGTH = {"Blue": 475, "Green": 560, "Red": 668, "Red edge": 717, "NIR": 840, "Panchro": 634, "LWIR": 11000}

_MICASENSE = re.compile(r"^(?P<stem>.+_\d+)_(?P<band>\d{1,2})$")
_DJI_MS = re.compile(r"^(?P<stem>.+)_MS_(?P<band>G|R|RE|NIR|B)$", re.IGNORECASE)
_SUFFIX = re.compile(r"^(?P<stem>.+)[_-](?P<band>NIR|RE|RED|GREEN|BLUE|REDEDGE)$", re.IGNORECASE)
_XMP_FIELD = {name: re.compile(rb"<(?:[\w-]+):" + name.encode() + rb">\s*([^<]*?)\s*</|(?:[\w-]+):"
                               + name.encode() + rb"=\"([^\"]*)\"")
              for name in ("BandName", "CaptureId", "CaptureUUID", "RigCameraIndex", "CentralWavelength")}


@dataclass(frozen=True)
class BandFile:
    """One band's file of a capture: ``band`` its name (``"NIR"``; the number as text when the
    file tells nothing more), ``order`` its place in the camera's band order."""

    path: Path
    band: str
    order: float


@dataclass(frozen=True)
class Capture:
    """The files of one capture, in band order; ``key`` the capture id or the shared name stem."""

    key: str
    files: tuple[BandFile, ...]

    def path(self, band: str) -> Path | None:
        """The file of ``band`` (a name of :attr:`bands`), or None when this capture lacks it."""
        for f in self.files:
            if f.band == band:
                return f.path
        return None

    @property
    def bands(self) -> tuple[str, ...]:
        return tuple(f.band for f in self.files)


def band_xmp(path: Path) -> dict[str, str]:
    """``BandName``, ``CaptureId`` / ``CaptureUUID``, ``RigCameraIndex``, ``CentralWavelength`` of a
    file's XMP (any namespace prefix: MicaSense's ``Camera:``/``MicaSense:``, DJI's), ``{}`` when
    it has none; never raises."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                packet = xmp_packet(im)
    except Exception:  # noqa: BLE001 - untrusted file: no XMP then
        return {}
    out = {}
    for name, rx in _XMP_FIELD.items():
        m = rx.search(packet or b"")
        if m:
            value = (m.group(1) or m.group(2) or b"").decode("utf-8", "replace").strip()
            if value:
                out[name] = value
    return out


def _band_name(text: str) -> str:
    return BAND_ALIASES.get(text.strip().lower(), text.strip())


def _order(name: str, fallback: float) -> float:
    return float(_WAVELENGTH.get(name, fallback))


def _by_name(path: Path) -> tuple[str, str, float] | None:
    """(capture stem, band name, order) from a band file's name, or None."""
    stem = path.stem
    m = _MICASENSE.match(stem)
    if m:
        return m.group("stem"), m.group("band"), float(m.group("band"))
    m = _DJI_MS.match(stem) or _SUFFIX.match(stem)
    if m:
        name = _band_name(m.group("band"))
        return m.group("stem"), name, _order(name, 0.0)
    return None


def group_captures(paths: Sequence[Path]) -> list[Capture] | None:
    """The captures of ``paths`` (sorted by their first file), or None when they are not multi-band
    (see the module docstring). XMP is read from TIFF files only (multispectral cameras write
    TIFF; a folder of JPEG stills is never read twice)."""
    paths = list(paths)
    if len(paths) < 2:
        return None
    groups: dict[str, list[BandFile]] = defaultdict(list)
    for p in paths:
        xmp = band_xmp(p) if p.suffix.lower() in (".tif", ".tiff") else {}
        named = _by_name(p)
        cid = xmp.get("CaptureId") or xmp.get("CaptureUUID")
        if cid is None and named is None:
            groups[f"\0{p}"].append(BandFile(p, "", 0.0))  # a file of its own
            continue
        key = cid or f"{p.parent}/{named[0]}"
        band = _band_name(xmp["BandName"]) if "BandName" in xmp else (named[1] if named else p.stem)
        try:
            order = float(xmp["RigCameraIndex"]) if "RigCameraIndex" in xmp else (
                named[2] if named and named[2] else _order(band, float(xmp.get("CentralWavelength", 0) or 0)))
        except ValueError:
            order = named[2] if named else 0.0
        groups[key].append(BandFile(p, band, order))
    multi = {k: v for k, v in groups.items() if len(v) >= 2}
    if not multi or sum(len(v) for v in multi.values()) * 2 < len(paths):
        return None
    captures = []
    for key, files in multi.items():
        files = sorted(files, key=lambda f: (f.order, f.band, str(f.path)))
        seen = Counter(f.band for f in files)
        if any(c > 1 for c in seen.values()):  # two files claim one band: keep the first
            kept, names = [], set()
            for f in files:
                if f.band not in names:
                    kept.append(f)
                    names.add(f.band)
            files = kept
        captures.append(Capture(key, tuple(files)))
    captures.sort(key=lambda c: str(c.files[0].path))
    singles = len(paths) - sum(len(c.files) for c in captures)
    if singles:
        log.warning("%d file(s) belong to no multi-band capture: left out", singles)
    return captures


def band_folders(folder: Path, suffixes: Sequence[str]) -> list[Path] | None:
    """The files of a folder holding one subfolder per band (Sentera style: ``NIR/``, ``Red/``, ...)
    as ``band folder / name`` paths, or None when ``folder`` is not laid out so."""
    try:
        subs = [d for d in folder.iterdir() if d.is_dir() and d.name.lower() in BAND_ALIASES]
    except OSError:
        return None
    if len(subs) < 2:
        return None
    return sorted((p for d in subs for p in d.iterdir() if p.is_file() and p.suffix.lower() in suffixes), key=str)


def group_band_folders(paths: Sequence[Path]) -> list[Capture]:
    """Captures of band-folder files (:func:`band_folders`): the files of the same name."""
    groups: dict[str, list[BandFile]] = defaultdict(list)
    for p in paths:
        name = _band_name(p.parent.name)
        groups[p.name].append(BandFile(p, name, _order(name, 0.0)))
    return [Capture(k, tuple(sorted(v, key=lambda f: (f.order, f.band)))) for k, v in sorted(groups.items())]


def read_band(path: Path) -> np.ndarray | None:
    """A band file's pixels as they are stored (uint8 or uint16, 2-D; a colour file is made gray),
    or None when unreadable. TIFFs are read with Pillow (no libtiff warnings about the private
    tags multispectral cameras write), anything else with OpenCV."""
    image = None
    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with Image.open(path) as im:
                    image = np.array(im)
        except Exception:  # noqa: BLE001 - untrusted file: OpenCV may still read it
            image = None
    if image is None or image.dtype not in (np.uint8, np.uint16):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)
    if image.dtype not in (np.uint8, np.uint16):
        image = np.clip(image, 0, 65535).astype(np.uint16)
    return image
