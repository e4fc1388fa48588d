"""`photomap calibrate`: a checkerboard seen through a known lens gives that lens back."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from photomap.cli import main as cli
from photomap.geo.lens import LensModel
from photomap.io.camera_files import read_calibration
from photomap.sim.lens import DistortedRender

BOARD = (9, 6)  # inner corners
SQUARE_PX = 40  # texture pixels per square
MARGIN = 2 * SQUARE_PX  # texture pixels from the texture's edge to the first inner corner
SQUARE_M = 0.025


def _board_texture() -> np.ndarray:
    cols, rows = BOARD[0] + 1, BOARD[1] + 1
    tex = np.full((rows * SQUARE_PX + 2 * SQUARE_PX, cols * SQUARE_PX + 2 * SQUARE_PX), 235, np.uint8)
    for j in range(rows):
        for i in range(cols):
            if (i + j) % 2 == 0:
                y, x = SQUARE_PX + j * SQUARE_PX, SQUARE_PX + i * SQUARE_PX
                tex[y:y + SQUARE_PX, x:x + SQUARE_PX] = 25
    return tex


def render_views(lens: LensModel, n: int, seed: int = 0, spread: float = 0.2,
                 depth_m: tuple[float, float] = (0.28, 0.45)) -> list[np.ndarray]:
    """``n`` views of the board through ``lens`` from random poses (tilted up to 35 deg), its
    centre within ``spread`` of the frame's (a fraction of the size), ``depth_m`` away."""
    rng = np.random.default_rng(seed)
    tex = _board_texture()
    render = DistortedRender(lens)
    x0, y0 = render.offset
    s = SQUARE_M / SQUARE_PX
    tex_to_plane = np.array([[s, 0, -MARGIN * s], [0, s, -MARGIN * s], [0, 0, 1.0]])
    to_canvas = np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]])
    centre = np.array([(BOARD[0] - 1) * SQUARE_M / 2, (BOARD[1] - 1) * SQUARE_M / 2, 0.0])
    views = []
    while len(views) < n:
        rvec = np.radians(rng.uniform([-35, -35, -180], [35, 35, 180]))
        rot, _ = cv2.Rodrigues(rvec)
        depth = rng.uniform(*depth_m)
        # the board's centre somewhere in the frame, away from the very edge
        u, v = rng.uniform(0.5 - spread, 0.5 + spread, 2) * (lens.width, lens.height)
        ray = np.array([(u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy, 1.0]) * depth
        t = ray - rot @ centre
        h_ideal = lens.ideal_matrix() @ np.column_stack([rot[:, 0], rot[:, 1], t]) @ tex_to_plane
        canvas = cv2.warpPerspective(tex, to_canvas @ h_ideal, render.canvas, flags=cv2.INTER_AREA,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=128)
        img = render.distort(canvas.astype(np.float32))
        img = img + rng.normal(0, 2.0, img.shape)
        views.append(np.clip(img, 0, 255).astype(np.uint8))
    return views


def test_calibrate_recovers_a_known_lens(tmp_path, capsys):
    fx = 320 / math.tan(math.radians(38))
    lens = LensModel("brown", 640, 480, fx, fx, 319.5, 239.5, (-0.25, 0.07, 0.0, 0.0, 0.0))
    folder = tmp_path / "shots"
    folder.mkdir()
    for k, img in enumerate(render_views(lens, 14)):
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    out = tmp_path / "camera.yaml"
    assert cli.main(["calibrate", str(folder), "--board", "9x6", "--square", str(SQUARE_M), "--out", str(out),
                     "-q"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("calibrated brown lens from ") and "RMS reprojection error" in line
    got = read_calibration(out)  # the file reads back through the project's reader
    assert (got.model, got.width, got.height) == ("brown", 640, 480)
    assert got.fx == pytest.approx(fx, rel=0.01) and got.fy == pytest.approx(fx, rel=0.01)
    assert got.dist[0] == pytest.approx(-0.25, abs=0.02)
    assert abs(got.cx - 319.5) < 3 and abs(got.cy - 239.5) < 3
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert 0 < fs.getNode("avg_reprojection_error").real() < 0.5
    fs.release()
    # the same views as a video (each held for 3 frames: held frames count once)
    video = tmp_path / "board.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    for img in render_views(lens, 14):
        for _ in range(3):
            writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    assert cli.main(["calibrate", str(video), "--board", "9x6", "--square", str(SQUARE_M),
                     "--out", str(tmp_path / "video.yaml"), "-q"]) == 0
    assert "from 14 views" in capsys.readouterr().out
    assert read_calibration(tmp_path / "video.yaml").dist[0] == pytest.approx(-0.25, abs=0.02)


def test_no_board_is_one_clear_error(tmp_path, capsys):
    folder = tmp_path / "shots"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for k in range(3):
        cv2.imwrite(str(folder / f"{k:03d}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    assert cli.main(["calibrate", str(folder), "--board", "9x6", "--square", "0.02",
                     "--out", str(tmp_path / "c.yaml"), "-q"]) != 0
    err = capsys.readouterr().err
    assert "board was found in 0 distinct view(s)" in err and "Traceback" not in err
    assert not (tmp_path / "c.yaml").exists()
    assert cli.main(["calibrate", str(folder), "--board", "9", "--square", "0.02", "--out", "x.yaml", "-q"]) != 0
    assert "COLSxROWS" in capsys.readouterr().err


def test_calibrate_a_fisheye_lens(tmp_path, capsys):
    lens = LensModel("fisheye", 640, 480, 280.0, 280.0, 319.5, 239.5, (0.05, -0.02, 0.004, -0.001))
    folder = tmp_path / "shots"
    folder.mkdir()
    for k, img in enumerate(render_views(lens, 20, spread=0.3, depth_m=(0.17, 0.28))):
        cv2.imwrite(str(folder / f"{k:03d}.png"), img)
    out = tmp_path / "fisheye.yaml"
    assert cli.main(["calibrate", str(folder), "--board", "9x6", "--square", str(SQUARE_M), "--fisheye",
                     "--out", str(out), "-q"]) == 0
    assert capsys.readouterr().out.startswith("calibrated fisheye lens from ")
    got = read_calibration(out)
    assert got.model == "fisheye" and got.fx == pytest.approx(280.0, rel=0.02)
    # the fitted lens bends rays like the true one over the middle of the frame
    xx, yy = np.meshgrid(np.linspace(96, 544, 15), np.linspace(72, 408, 11))
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    assert np.abs(got.undistort_points(pts) - lens.undistort_points(pts)).max() < 2.0
