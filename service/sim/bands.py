"""Multi-band captures of the simulated survey: a MicaSense-like 5-lens camera.

Each band is its own lens: band ``b``'s image is the simulated frame (the camera of the ground
truth, ``groundtruth.csv``) seen through a slightly different lens position, the known
homography :func:`lens_homography` (a few pixels of shift and under a degree of rotation about
the image centre), and its pixel values are a spectral mix of the terrain's blue, green and red
channels (:data:`BANDS`), written as 16-bit TIFF ``IMG_NNNN_B.tif`` (``B`` from 1) with the
still's EXIF (time, GPS, focal length) and MicaSense-style XMP (``MicaSense:CaptureId``,
``Camera:BandName``, ``Camera:CentralWavelength``, ``Camera:RigCameraIndex``).

Conventions: ``G_b = lens_homography(b, size)`` maps band ``b``'s pixels to the truth camera's
pixels (OpenCV pixel centres): ``band_b(u) = mix_b(frame(G_b u))``. So the homography from band
``b``'s pixels to band ``r``'s is ``inv(G_r) @ G_b``, and band ``b``'s pose on the terrain is
``H @ G_b``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import cv2
import numpy as np

from photomap.errors import PhotomapError

#: (name, central wavelength nm, weights of the frame's (blue, green, red) in 0..1, offset): the
#: bands in the camera's order (MicaSense RedEdge: band 4 is NIR, band 5 red edge).
BANDS = (("Blue", 475, (0.80, 0.15, 0.05), 0.02),
         ("Green", 560, (0.10, 0.80, 0.10), 0.02),
         ("Red", 668, (0.05, 0.15, 0.80), 0.01),
         ("NIR", 840, (0.10, 1.10, -0.45), 0.25),
         ("Red edge", 717, (0.05, 0.65, 0.25), 0.08))
#: Lens offsets of the bands: (dx, dy) pixels and rotation degrees at a 640-pixel-wide frame
#: (scaled with the width).
_LENS = ((0.0, 0.0, 0.0), (3.2, -2.1, 0.35), (-2.6, 3.4, -0.55), (4.1, 1.6, 0.25), (-1.9, -3.1, 0.7))
#: 16-bit values: ``DARK + GAIN * mix`` (a dark level and a sensor gain, as a real camera's DNs).
DARK, GAIN = 3000.0, 40000.0


def lens_homography(band: int, size: tuple[int, int]) -> np.ndarray:
    """``G_b``: band ``band``'s pixels (0-based band) -> the truth camera's pixels, for a
    ``size = (w, h)`` frame: a rotation about the centre and a shift (see :data:`_LENS`)."""
    w, h = size
    dx, dy, deg = _LENS[band % len(_LENS)]
    k = w / 640.0
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    R = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0.0, 0.0, 1.0]])
    T = np.array([[1.0, 0.0, dx * k], [0.0, 1.0, dy * k], [0.0, 0.0, 1.0]])
    return T @ R


def band_image(frame_bgr: np.ndarray, band: int, rng: np.random.Generator | None = None,
               noise: float = 20.0) -> np.ndarray:
    """Band ``band`` (0-based) of a simulated BGR frame: through its lens, spectrally mixed,
    uint16 (``DARK + GAIN * mix`` plus Gaussian noise of ``noise`` DN)."""
    h, w = frame_bgr.shape[:2]
    G = lens_homography(band, (w, h))
    seen = cv2.warpPerspective(frame_bgr, G, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT)
    _, _, weights, offset = BANDS[band]
    mix = seen.astype(np.float32) @ (np.asarray(weights, np.float32) / 255.0) + offset
    value = DARK + GAIN * np.clip(mix, 0.0, 1.2)
    if rng is not None and noise > 0:
        value = value + rng.normal(0.0, noise, value.shape)
    return np.clip(np.rint(value), 0, 65535).astype(np.uint16)


def micasense_xmp(*, capture_id: str, band: int, dji: Mapping[str, str] | None = None) -> bytes:
    """An XMP packet with the MicaSense fields a capture's band file carries and, given ``dji``
    (:func:`photomap.sim.stills.dji_attributes`), DJI's attitude and height as a P4 Multispectral
    writes them beside its band fields."""
    name, wavelength, _, _ = BANDS[band]
    extra = ""
    if dji:
        body = "\n".join(f'   drone-dji:{k}="{v}"' for k, v in dji.items())
        extra = ('  <rdf:Description rdf:about="DJI Meta Data" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"\n'
                 f'{body}/>\n')
    text = ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '  <rdf:Description rdf:about="" xmlns:MicaSense="http://micasense.com/MicaSense/1.0/">\n'
            f'   <MicaSense:CaptureId>{capture_id}</MicaSense:CaptureId>\n'
            '  </rdf:Description>\n'
            '  <rdf:Description rdf:about="" xmlns:Camera="http://pix4d.com/1.0">\n'
            f'   <Camera:BandName>{name}</Camera:BandName>\n'
            f'   <Camera:CentralWavelength>{wavelength}</Camera:CentralWavelength>\n'
            f'   <Camera:RigCameraIndex>{band}</Camera:RigCameraIndex>\n'
            '  </rdf:Description>\n'
            f'{extra}'
            ' </rdf:RDF>\n'
            '</x:xmpmeta>\n'
            '<?xpacket end="w"?>')
    return text.encode("utf-8")


def write_band_still(path: str | Path, image: np.ndarray, exif, xmp: bytes) -> None:
    """Write a uint16 (or uint8) band image as an uncompressed 16-bit (8-bit) TIFF with ``exif`` (Pillow
    ``Image.Exif``) and the XMP packet (TIFF tag 700)."""
    from PIL import Image
    from PIL.TiffImagePlugin import ImageFileDirectory_v2
    info = ImageFileDirectory_v2()
    for tag, value in exif.items():
        info[tag] = value
    for tag in (0x8769, 0x8825):  # the Exif and GPS sub-IFDs, written nested
        info[tag] = dict(exif.get_ifd(tag))
    info[700] = xmp  # XMLPacket in IFD0, as the cameras write it
    info.tagtype[700] = 1
    try:
        depth = np.uint8 if np.asarray(image).dtype == np.uint8 else np.uint16
        Image.fromarray(np.ascontiguousarray(image, dtype=depth)).save(str(path), "TIFF", tiffinfo=info)
    except OSError as exc:
        raise PhotomapError(f"cannot write band still {path}: {exc}") from None
