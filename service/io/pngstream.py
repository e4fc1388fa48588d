"""A PNG written band by band: a large map never has to be in memory as one image.

``cv2.imwrite`` and Pillow need the whole image; a 8192 x 8192 BGRA mosaic is 268 MB, and the
render it comes from more. :class:`PngStream` takes rows in bands (top to bottom), filters each
row with PNG's *Up* filter (the difference to the row above: small numbers on photos, which
compress well) and deflates them as they come. The file appears atomically when complete.
"""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # grey, grey+alpha, RGB, RGBA
_UP = 2  # PNG filter type "Up"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


class PngStream:
    """Write an 8-bit PNG of ``width`` x ``height`` pixels with ``channels`` (1 grey, 2 grey +
    alpha, 3 BGR, 4 BGRA: OpenCV's order, stored as PNG's RGB(A)), a band of rows at a time.

    Use as a context manager; :meth:`write` the bands top to bottom. The file is written to a
    temporary name beside ``path`` and renamed when all ``height`` rows are in (an exception or
    missing rows leave no file).
    """

    def __init__(self, path: str | Path, width: int, height: int, channels: int, level: int = 1) -> None:
        if channels not in _COLOR_TYPE or width < 1 or height < 1:
            raise ValueError(f"PNG of {width}x{height} with {channels} channels")
        self.path = Path(path)
        self.width, self.height, self.channels = int(width), int(height), int(channels)
        self._rows = 0
        self._previous = np.zeros(self.width * self.channels, np.uint8)
        self._zlib = zlib.compressobj(level)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
        self._tmp = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        ihdr = struct.pack(">IIBBBBB", self.width, self.height, 8, _COLOR_TYPE[self.channels], 0, 0, 0)
        self._file.write(_SIGNATURE + _chunk(b"IHDR", ihdr))

    def write(self, band: np.ndarray) -> None:
        """Append rows: uint8 ``(n, width)`` for one channel, else ``(n, width, channels)``."""
        band = np.asarray(band, np.uint8)
        if band.ndim == 2:
            band = band[..., None]
        n = band.shape[0]
        if band.shape[1:] != (self.width, self.channels) or self._rows + n > self.height:
            raise ValueError(f"band {band.shape} does not fit a {self.width}x{self.height}x{self.channels} PNG "
                             f"at row {self._rows}")
        if self.channels >= 3:  # BGR(A) -> RGB(A)
            band = band[..., [2, 1, 0, 3][:self.channels]]
        rows = band.reshape(n, -1)
        data = np.empty((n, rows.shape[1] + 1), np.uint8)
        data[:, 0] = _UP
        data[0, 1:] = rows[0] - self._previous  # uint8 arithmetic wraps mod 256, as PNG wants
        data[1:, 1:] = rows[1:] - rows[:-1]
        self._previous = rows[-1].copy()
        deflated = self._zlib.compress(data.tobytes())
        if deflated:
            self._file.write(_chunk(b"IDAT", deflated))
        self._rows += n

    def close(self) -> None:
        """Finish the file (all rows written) and move it into place."""
        try:
            if self._rows != self.height:
                raise ValueError(f"PNG {self.path.name}: {self._rows} of {self.height} rows written")
            self._file.write(_chunk(b"IDAT", self._zlib.flush()) + _chunk(b"IEND", b""))
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp, self.path)
        finally:
            self.abort()

    def abort(self) -> None:
        """Drop the file being written (no-op once closed)."""
        if not self._file.closed:
            self._file.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> PngStream:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()
