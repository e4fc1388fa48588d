"""Read still images with OpenCV at their full depth, and keep the image libraries' warnings off
the terminal.

libtiff, libjpeg, libpng and OpenCV's loaders print their warnings straight to the process's
stderr (file descriptor 2), not through Python: a MicaSense TIFF makes libtiff print
``TIFFReadDirectory: Unknown field with tag ...`` four times, a survey of 400 of them 1600 lines.
:class:`ImageReader` points fd 2 at a temporary file for the duration of each ``cv2.imread``,
counts the warnings it caught by kind (numbers replaced by ``N`` and quoted names by ``'...'``, so
the four tags are one kind),
writes anything else that reached fd 2 meanwhile (another thread's log line) back to the real
stderr, and :meth:`ImageReader.summary` gives one line per kind with its count.

Which formats this OpenCV build reads: :func:`image_suffixes`.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from photomap.drivers.native_log import opencv_log

#: Suffixes of the formats every OpenCV build reads.
_ALWAYS = (".jpg", ".jpeg", ".jpe", ".png", ".tif", ".tiff", ".bmp", ".dib",
           ".pgm", ".ppm", ".pbm", ".pnm")
#: Suffixes whose codec is optional in a build, keyed by the suffix that probes it.
_OPTIONAL = {".webp": (".webp",), ".jp2": (".jp2", ".j2k", ".j2c", ".jpf", ".jpx"), ".avif": (".avif",),
             ".exr": (".exr",), ".hdr": (".hdr", ".pic"), ".pfm": (".pfm",), ".sr": (".sr", ".ras")}

_QUOTED = re.compile(r"'[^']*'")
_DIGITS = re.compile(r"\b(0x[0-9a-fA-F]+|\d+)\b")
_FD_LOCK = threading.Lock()


def image_suffixes() -> tuple[str, ...]:
    """Lower-case suffixes of the still formats this OpenCV build reads: JPEG, PNG, TIFF, BMP,
    PGM/PPM/PBM/PNM always; WebP, JPEG 2000, AVIF, OpenEXR, Radiance HDR, PFM and Sun raster
    where the build has the codec (probed with ``cv2.haveImageWriter``: OpenCV builds a format's
    reader and writer together)."""
    out = list(_ALWAYS)
    for probe, suffixes in _OPTIONAL.items():
        try:
            ok = cv2.haveImageWriter("probe" + probe)
        except cv2.error:
            ok = False
        if ok:
            out.extend(suffixes)
    return tuple(out)


def warning_kind(line: str) -> tuple[str, str] | None:
    """``(library, message with numbers as N)`` of a library warning line, or None when the
    line is not one (it is passed on to stderr)."""
    text = line.strip()
    if not text:
        return None
    cv = opencv_log(text)  # "[ WARN:0@0.031] global grfmt_tiff.cpp:123 TIFF_Warning ..." -> the message
    if cv is not None:
        text = cv[1]
    elif not re.match(r"^(libpng|Corrupt JPEG|Premature end of JPEG|Invalid SOS|Warning:|TIFF)", text):
        return None
    if text.startswith("TIFF_Warning") or text.startswith("TIFF"):
        lib = "libtiff"
        text = re.sub(r"^TIFF_Warning\s*", "", text)
    elif "JPEG" in text or "jpeg" in text:
        lib = "libjpeg"
    elif "png" in text.lower():
        lib = "libpng"
    else:
        lib = "OpenCV"
    return lib, _DIGITS.sub("N", _QUOTED.sub("'...'", text))


class ImageReader:
    """``cv2.imread`` of stills at their own depth, with the libraries' warnings counted.

    Not for concurrent use by two threads (one reader thread per source); other threads'
    output written while a read runs is passed on to stderr after it.

    Attributes
    ----------
    warnings : Counter
        ``(library, message kind)`` -> how many times it was printed.
    files_warned : Counter
        ``(library, message kind)`` -> in how many files.
    first_file : dict
        ``(library, message kind)`` -> the first file that printed it.
    quiet : bool
        The last read printed nothing (no warning, no other output).
    """

    def __init__(self, flags: int = cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH) -> None:
        self.flags = flags
        self.warnings: Counter = Counter()
        self.files_warned: Counter = Counter()
        self.first_file: dict[tuple[str, str], str] = {}
        self._spool = None
        self.quiet = True

    def read(self, path: str | Path) -> np.ndarray | None:
        """The image as stored (``uint8``, ``uint16`` or ``float32``; 1 or 3 channels, BGR), or
        None when OpenCV cannot decode it."""
        image, caught = self._captured(lambda: cv2.imread(str(path), self.flags))
        self.quiet = not caught
        kinds = set()
        passed = []
        for line in caught.splitlines(keepends=True):
            kind = warning_kind(line)
            if kind is None:
                passed.append(line)   # as it was written (a progress bar's "\r" included)
                continue
            self.warnings[kind] += 1
            kinds.add(kind)
            self.first_file.setdefault(kind, Path(path).name)
        for kind in kinds:
            self.files_warned[kind] += 1
        if passed:
            try:
                os.write(2, "".join(passed).encode("utf-8", errors="replace"))
            except OSError:
                pass
        return image

    def _captured(self, call):
        """Run ``call()`` with fd 2 pointed at a spool file; returns its result and the text."""
        try:
            sys.stderr.flush()
        except (OSError, ValueError, AttributeError):
            pass
        with _FD_LOCK:
            try:
                if self._spool is None:
                    self._spool = tempfile.TemporaryFile()
                saved = os.dup(2)
            except OSError:
                return call(), ""      # no fd 2 to redirect: read as it is
            try:
                self._spool.seek(0)
                self._spool.truncate()
                os.dup2(self._spool.fileno(), 2)
                try:
                    result = call()
                finally:
                    os.dup2(saved, 2)
            finally:
                os.close(saved)
            self._spool.seek(0)
            caught = self._spool.read().decode("utf-8", errors="replace")
        return result, caught

    def summary(self) -> list[str]:
        """One line per kind of warning: library, count, files, the first file, the message."""
        return [f"{lib} warned {n} time(s) in {self.files_warned[(lib, msg)]} file(s) (first "
                f"{self.first_file[(lib, msg)]}): {msg}" for (lib, msg), n in self.warnings.most_common()]

    def close(self) -> None:
        if self._spool is not None:
            self._spool.close()
            self._spool = None
