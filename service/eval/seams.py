"""Brightness steps at frame edges in a map (pure: arrays in, numbers out).

Which frame shows at each map pixel of an ``overwrite`` map is known from the poses
(:func:`frame_labels`: the last frame painted there). A seam is where two neighbouring map pixels
show different frames. :func:`seam_steps` compares the map's luminance ``gap`` pixels on either side
of each seam pixel (so that bilinear edges do not count) and reports

- ``pixel_step``: the mean absolute luminance difference across seams (texture included);
- ``texture``: the same difference between pixels as far apart that show one frame (what the
  texture alone gives; a seamless map has ``pixel_step`` close to it);
- ``level_step``: per pair of frames meeting at a seam, the mean *signed* difference across their
  seam (the texture averages out, an exposure step does not), absolute, averaged over the pairs
  weighted by seam length. This is the brightness step at frame edges, grey levels.
- ``colour_step``: ``level_step`` of each colour channel, averaged over the channels (a white
  balance change between frames shows here, not in the luminance).

Conventions: poses are 2x3, frame pixels -> map pixels, as :class:`photomap.core.mosaic.TiledMosaic`
takes them; map rectangles are ``(x, y, w, h)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

__all__ = ["SeamSteps", "frame_labels", "seam_steps"]


@dataclass(frozen=True)
class SeamSteps:
    """See the module docstring. Grey levels (0..255) of luminance, the mean of the channels."""

    pixel_step: float
    texture: float
    level_step: float
    colour_step: float
    seam_pixels: int
    frame_pairs: int


def frame_labels(poses: Sequence[np.ndarray], frame_size: tuple[int, int], bounds: tuple[int, int, int, int],
                 border: int = 1) -> np.ndarray:
    """Index of the frame an ``overwrite`` map shows at each pixel of ``bounds``.

    Parameters
    ----------
    poses : sequence of 2x3 poses, in painting order (None: not painted)
    frame_size : (width, height) of the frames
    bounds : (x, y, w, h) map rectangle
    border : frame pixels kept out of the map (``mosaic.border``)

    Returns
    -------
    int32 array (h, w): the index in ``poses`` of the last frame covering each pixel (a frame covers
    a map pixel when all four bilinear sources lie ``border`` pixels inside it), -1 where none.
    """
    fw, fh = frame_size
    x, y, w, h = bounds
    labels = np.full((h, w), -1, np.int32)
    valid = np.zeros((fh, fw), np.uint8)
    valid[border:fh - border, border:fw - border] = 255
    corners = np.array([[-1.0, -1.0], [fw, -1.0], [-1.0, fh], [fw, fh]])
    for k, M in enumerate(poses):
        if M is None:
            continue
        M = np.asarray(M, np.float64)[:2]
        mapped = corners @ M[:, :2].T + M[:, 2]
        x0, y0 = np.floor(mapped.min(axis=0)).astype(int)
        x1, y1 = np.ceil(mapped.max(axis=0)).astype(int) + 1
        x0, y0, x1, y1 = max(x0, x), max(y0, y), min(x1, x + w), min(y1, y + h)
        if x0 >= x1 or y0 >= y1:
            continue
        A = M.copy()
        A[:, 2] -= (x0, y0)
        cover = cv2.warpAffine(valid, A, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0) == 255
        labels[y0 - y:y1 - y, x0 - x:x1 - x][cover] = k
    return labels


def seam_steps(image: np.ndarray, labels: np.ndarray, gap: int = 2) -> SeamSteps:
    """Brightness steps across the seams of ``labels`` in ``image`` (see the module docstring).

    Parameters
    ----------
    image : uint8 (h, w) or (h, w, C): the map (rendered at scale 1 over the labels' rectangle)
    labels : int32 (h, w) from :func:`frame_labels` (-1: empty)
    gap : pixels between each seam pixel and the sample on its side (the samples are
        ``2 * gap + 1`` pixels apart); both samples must show the frame of their side of the seam.
    """
    img = np.asarray(image, np.float32)
    if img.ndim == 2:
        img = img[..., None]
    # luminance first, then the channels
    planes = np.concatenate([img.mean(axis=2, keepdims=True), img], axis=2) if img.shape[2] > 1 else img
    labels = np.asarray(labels)
    if planes.shape[:2] != labels.shape:
        raise ValueError(f"image {planes.shape[:2]} and labels {labels.shape} differ in size")
    sep = 2 * gap + 1
    diffs, pairs_a, pairs_b, texture = [], [], [], []
    for L, Y in ((labels, planes), (labels.T, planes.transpose(1, 0, 2))):  # seams between columns, then rows
        if L.shape[1] <= sep:
            continue
        a, b = L[:, :-sep], L[:, sep:]  # labels of the two samples
        # the seam lies between columns gap and gap+1 of the span: the span holds a's label up to
        # it and b's label after it
        left, right = L[:, gap:-sep + gap], L[:, gap + 1:L.shape[1] - sep + gap + 1]
        seam = (a >= 0) & (b >= 0) & (a != b) & (left == a) & (right == b)
        same = (a >= 0) & (a == b) & (left == a) & (right == a)
        d = Y[:, sep:] - Y[:, :-sep]  # (rows, cols, planes)
        texture.append(np.abs(d[same][:, 0]))
        lo, hi = np.minimum(a[seam], b[seam]), np.maximum(a[seam], b[seam])
        diffs.append(np.where((b[seam] == hi)[:, None], d[seam], -d[seam]))  # signed: later minus earlier
        pairs_a.append(lo)
        pairs_b.append(hi)
    d = np.concatenate(diffs) if diffs else np.zeros((0, planes.shape[2]))
    tex = np.concatenate(texture) if texture else np.zeros(0)
    tex_mean = float(tex.mean()) if tex.size else 0.0
    if d.shape[0] == 0:
        return SeamSteps(0.0, tex_mean, 0.0, 0.0, 0, 0)
    lo, hi = np.concatenate(pairs_a).astype(np.int64), np.concatenate(pairs_b).astype(np.int64)
    _, pair, counts = np.unique(lo * (int(hi.max()) + 1) + hi, return_inverse=True, return_counts=True)
    levels = [float(np.sum(np.abs(np.bincount(pair, weights=d[:, c]) / counts) * counts) / counts.sum())
              for c in range(d.shape[1])]
    colour = float(np.mean(levels[1:])) if len(levels) > 1 else levels[0]
    return SeamSteps(float(np.abs(d[:, 0]).mean()), tex_mean, levels[0], colour, int(d.shape[0]),
                     int(counts.size))


def overlap_steps(frames: Sequence[np.ndarray], poses: Sequence[np.ndarray | None],
                  gains: Sequence[np.ndarray | float | None], labels: np.ndarray, origin: tuple[int, int],
                  border: int = 1, band: int = 8, min_index_gap: int = 1) -> tuple[float, float, int]:
    """The exposure step at the seams of an ``overwrite`` map, free of texture.

    For each pair of frames ``a < b`` meeting at a seam of ``labels`` (:func:`frame_labels`), both
    frames (times their gains, clipped to 0..255) are compared on the same ground: the map pixels
    within ``band`` pixels of their seam that both cover. The step of the pair is the mean
    difference ``b - a`` there; texture and small misregistration cancel in that mean.

    Parameters
    ----------
    frames : uint8 BGR or gray frames; poses : 2x3 frame -> map (None: not painted)
    gains : per frame, the gain (scalar or per channel) the map applied; None = 1
    labels : int32 (h, w) map of frame indices whose top-left pixel is map pixel ``origin``
    border : frame pixels kept out of the map
    min_index_gap : only pairs of frames at least this many indices apart (e.g. the seams between
        the strips of a survey, not between consecutive video frames)

    Returns
    -------
    (luminance step, colour step, number of frame pairs): mean absolute steps, grey levels, over
    the pairs weighted by their seam length; ``colour`` averages the steps of each channel.
    """
    h, w = labels.shape
    ox, oy = origin
    pair_px: dict[tuple[int, int], list[np.ndarray]] = {}
    for dy, dx in ((0, 1), (1, 0)):
        a = labels[:h - dy, :w - dx]
        b = labels[dy:, dx:]
        seam = (a >= 0) & (b >= 0) & (a != b)
        ys, xs = np.nonzero(seam)
        lo, hi = np.minimum(a[seam], b[seam]), np.maximum(a[seam], b[seam])
        for key in set(zip(lo.tolist(), hi.tolist())):
            if key[1] - key[0] < min_index_gap:
                continue
            sel = (lo == key[0]) & (hi == key[1])
            pair_px.setdefault(key, []).append(np.stack([xs[sel], ys[sel]], axis=1))
    steps, weights = [], []
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    for (ia, ib), pts in sorted(pair_px.items()):
        pts = np.concatenate(pts)
        x0, y0 = np.maximum(pts.min(axis=0) - band, 0)
        x1, y1 = np.minimum(pts.max(axis=0) + band + 2, (w, h))
        near = np.zeros((y1 - y0, x1 - x0), np.uint8)
        near[pts[:, 1] - y0, pts[:, 0] - x0] = 1
        near = cv2.dilate(near, kernel) > 0
        values = []
        for k in (ia, ib):
            f = np.asarray(frames[k])
            f = f[..., None] if f.ndim == 2 else f
            fh, fw = f.shape[:2]
            valid = np.zeros((fh, fw), np.uint8)
            valid[border:fh - border, border:fw - border] = 255
            A = np.asarray(poses[k], np.float64)[:2].copy()
            A[:, 2] -= (ox + x0, oy + y0)
            img = cv2.warpAffine(f.astype(np.float32), A, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)
            img = img.reshape(y1 - y0, x1 - x0, -1)
            cov = cv2.warpAffine(valid, A, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR) == 255
            g = 1.0 if gains[k] is None else np.asarray(gains[k], np.float32)
            values.append((np.clip(img * g, 0, 255), cov))
        both = near & values[0][1] & values[1][1]
        if not both.any():
            continue
        d = values[1][0][both].mean(axis=0) - values[0][0][both].mean(axis=0)  # per channel
        steps.append(np.concatenate([[d.mean()], d]))
        weights.append(len(pts))
    if not steps:
        return 0.0, 0.0, 0
    s, wts = np.abs(np.array(steps)), np.array(weights, float)
    level = s.T @ wts / wts.sum()
    return float(level[0]), float(level[1:].mean() if len(level) > 2 else level[0]), len(steps)
