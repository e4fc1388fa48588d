"""Calibrate a camera's lens from a video or a folder of images of a checkerboard.

Finds the board (its inner corners, COLSxROWS as cv2.findChessboardCorners counts them) in
frames spread over the input, keeps the views where it moved, fits OpenCV's Brown-Conrady
model (or, with --fisheye, its fisheye model) and writes a cv2.FileStorage YAML file with the
RMS reprojection error, for `camera.calibration` (docs/camera.md).

examples:
  photomap calibrate board.mp4 --board 9x6 --square 0.025 --out camera.yaml
  photomap calibrate shots/ --board 7x5 --square 0.03 --fisheye --out fisheye.yaml
"""

from __future__ import annotations

import argparse
import logging

from photomap.cli.wiring import open_capture
from photomap.config import Config
from photomap.errors import InputError
from photomap.geo.lens_calibration import calibrate, distinct, find_corners, parse_board
from photomap.io.camera_files import write_calibration

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="video file, folder of images, or a glob such as 'dir/*.png'")
    parser.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners of the board, e.g. 9x6")
    parser.add_argument("--square", required=True, type=float, metavar="M", help="side of a square, metres")
    parser.add_argument("--out", required=True, metavar="FILE", help="calibration file to write (.yaml or .json)")
    parser.add_argument("--fisheye", action="store_true", help="fit OpenCV's fisheye model (k1..k4)")
    parser.add_argument("--frames", type=int, default=150, metavar="N",
                        help="look for the board in about N frames spread over a video (default 150)")
    parser.add_argument("--views", type=int, default=40, metavar="N",
                        help="fit on at most N distinct views, spread over those found (default 40)")


def main(args: argparse.Namespace, cfg: Config) -> int:
    board = parse_board(args.board)
    if not args.square > 0:
        raise InputError(f"--square must be > 0 metres, got {args.square}")
    source = open_capture(str(args.input), cfg.capture)
    total = getattr(source, "frame_count", None) or len(getattr(source, "paths", ()) or ()) or 0
    step = max(1, total // max(1, args.frames)) if total else 1
    views, size, looked = [], None, 0
    try:
        for frame in source:
            if frame.index % step:
                continue
            h, w = frame.image.shape[:2]
            if size is None:
                size = (w, h)
            elif size != (w, h):
                log.warning("frame %d: %dx%d differs from the first frame's %dx%d; skipped", frame.index, w, h, *size)
                continue
            looked += 1
            corners = find_corners(frame.image, board)
            if corners is not None:
                views.append(corners)
    finally:
        source.close()
    if size is None:
        raise InputError(f"no frames could be read from {args.input}")
    kept = distinct(views, min_move=0.01 * max(size))
    if len(kept) > args.views > 0:  # spread over the input
        kept = [kept[round(i * (len(kept) - 1) / (args.views - 1))] for i in range(args.views)]
    result = calibrate([views[i] for i in kept], board, args.square, size,
                       model="fisheye" if args.fisheye else "brown")
    lens = result.lens
    write_calibration(args.out, lens, rms_px=result.rms_px, views=result.views, board=args.board,
                      square_m=args.square)
    coeffs = " ".join(f"{n} {v:+.4f}" for n, v in zip(("k1", "k2", "k3", "k4") if args.fisheye else
                                                       ("k1", "k2", "p1", "p2", "k3"), lens.dist))
    print(f"calibrated {lens.model} lens from {result.views} views ({len(views)} of {looked} frames showed "
          f"the board): {lens.width}x{lens.height}, fx {lens.fx:.1f} fy {lens.fy:.1f} cx {lens.cx:.1f} "
          f"cy {lens.cy:.1f} px, {coeffs}; RMS reprojection error {result.rms_px:.3f} px -> {args.out}")
    return 0
