"""Fly a virtual down-looking camera over a terrain image and write the flight with its truth.

Writes into --out DIR: video.mp4 (mp4v; or --codec mjpg/ffv1), groundtruth.csv (the exact frame->terrain matrix of
every frame), telemetry.tlog (MAVLink 2: HEARTBEAT, SYSTEM_TIME, ATTITUDE, GLOBAL_POSITION_INT,
VFR_HUD, ALTITUDE, DISTANCE_SENSOR), meta.yaml (camera, terrain, georeference, parameters) and,
with --save-frames, frames/NNNNNN.png. Defaults come from the `simulate:` config section.

examples:
  photomap simulate --out sim
  photomap simulate --out sim --terrain grass --pattern lawnmower --frames 600 --noise 3
  photomap simulate --out sim --size 320x240 --altitude 30:45 --tilt 2 --yaw-rate 30
"""

from __future__ import annotations

import argparse
import dataclasses
import csv
import logging
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import yaml

from photomap.sim.tlog_writer import RATES_HZ, write_tlog

from photomap.errors import InputError, PhotomapError
from photomap.sim.flight import PATTERNS, YAW_MODES, Camera, build_pyramid, iter_frames, pixel_to_latlon, plan_flight, split_params
from photomap.sim.terrain import DEFAULT_GSD, PROCEDURAL, TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask
from photomap.io.trajectory_files import GROUNDTRUTH_COLUMNS

log = logging.getLogger(__name__)

def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(w, h)``."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"size must look like 640x480, got {text!r}") from None
    if w < 16 or h < 16:
        raise InputError(f"size must be at least 16x16, got {text!r}")
    return w, h


def parse_range(text: str) -> tuple[float, float]:
    """``"MIN:MAX"`` (or a single value) -> ``(min, max)``."""
    try:
        parts = [float(v) for v in str(text).split(":")]
    except ValueError:
        raise InputError(f"altitude must look like 50:70 (metres), got {text!r}") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2:
        raise InputError(f"altitude must look like 50:70 (metres), got {text!r}")
    return parts[0], parts[1]


# codec -> (file name, fourcc); OpenCV's FFmpeg wheel has no H.264 encoder
VIDEO_CODECS = {"mp4v": ("video.mp4", "mp4v"), "mjpg": ("video.avi", "MJPG"), "ffv1": ("video.mkv", "FFV1")}


def simulate_flight(out_dir: str | Path, *, terrain: str = "aukerman", n_frames: int = 300,
                    size: tuple[int, int] = (640, 480), fps: float = 30.0, seed: int = 0,
                    hfov_deg: float = 60.0, gsd: float = 0.0, terrain_zoom: float = 0.0,
                    terrain_size: tuple[int, int] = (4096, 4096), save_frames: bool = False,
                    frames_format: str = "png", origin_lat: float = 41.1, origin_lon: float = -81.7,
                    origin_amsl: float = 300.0, t0_unix: float = 0.0, boot_offset_s: float = 60.0,
                    video_codec: str = "mp4v", **params) -> Path:
    """Simulate a flight and write video, ground truth, telemetry and metadata into ``out_dir``.

    Parameters
    ----------
    terrain : terrain name or image path (see :func:`photomap.sim.terrain.load_terrain`).
    size, terrain_size : ``(w, h)`` of the frames and of a procedural terrain.
    gsd : metres per pixel of the stored terrain image (0 = the terrain's default); the terrain
        pixels of the ground truth are those after ``terrain_zoom`` (0 = the terrain's default),
        so the effective gsd written to meta.yaml is ``gsd / zoom``.
    origin_lat, origin_lon, origin_amsl : georeference of terrain pixel (0, 0).
    t0_unix : Unix time of frame 0 (0 = now). boot_offset_s : autopilot uptime at frame 0.
    video_codec : ``mp4v`` (``video.mp4``: MPEG-4 part 2 at the wheel's fixed, low bitrate, a
        strong compression that wipes low-contrast texture), ``mjpg`` (``video.avi``) or ``ffv1``
        (``video.mkv``, lossless, like a camera recording at a high bitrate).
    **params : :class:`photomap.sim.flight.Motion` and :class:`photomap.sim.flight.Effects` fields.

    Returns the output folder.
    """
    motion, effects = split_params(params)
    out = Path(out_dir)
    if frames_format not in ("png", "jpg"):
        raise InputError(f"frames format must be png or jpg, got {frames_format!r}")
    name = str(terrain)
    procedural = name in PROCEDURAL
    zoom = 1.0 if procedural else (terrain_zoom or TERRAIN_ZOOM.get(name, 1.0))
    gsd_eff = (gsd or TERRAIN_GSD.get(name, DEFAULT_GSD)) / zoom
    t_start = time.perf_counter()
    img = load_terrain(name, zoom=zoom, size=(terrain_size[1], terrain_size[0]), seed=seed)
    valid = valid_mask(img)
    camera = Camera.from_hfov(size[0], size[1], hfov_deg)
    truth = plan_flight(valid, n_frames, camera, fps, gsd_eff, motion, seed)
    if t0_unix <= 0:
        t0_unix = round(time.time(), 3)

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PhotomapError(f"cannot create output folder {out}: {exc.strerror}") from None
    frames_dir = out / "frames"
    if save_frames:
        frames_dir.mkdir(exist_ok=True)
    if video_codec not in VIDEO_CODECS:
        raise InputError(f"video codec must be one of {', '.join(VIDEO_CODECS)}, got {video_codec!r}")
    name_, fourcc = VIDEO_CODECS[video_codec]
    video_path = out / name_
    writer = cv2.VideoWriter(str(video_path), cv2.VideoWriter_fourcc(*fourcc), fps, (camera.width, camera.height))
    if not writer.isOpened():
        raise PhotomapError(f"cannot write {video_path} ({fourcc} encoder unavailable or folder not writable)")
    try:
        pyramid = build_pyramid(img, float(truth.scale.max()) * 1.2)
        for k, frame in enumerate(iter_frames(img, truth, camera, effects, seed, motion.period_s, pyramid)):
            writer.write(frame)
            if save_frames:
                cv2.imwrite(str(frames_dir / f"{k:06d}.{frames_format}"), frame)
    finally:
        writer.release()

    write_groundtruth(out / "groundtruth.csv", truth)
    lat, lon = pixel_to_latlon(truth.cam_x, truth.cam_y, gsd_eff, origin_lat, origin_lon)
    write_tlog(out / "telemetry.tlog", truth.t, lat, lon, truth.alt_m, truth.roll_deg, truth.pitch_deg,
               truth.yaw_deg, t0_unix=t0_unix, boot_offset_s=boot_offset_s, home_amsl_m=origin_amsl)
    meta = {
        "camera": {"model": "pinhole", "width": camera.width, "height": camera.height, "fx": camera.fx,
                   "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "hfov_deg": camera.hfov_deg},
        "fps": float(fps),
        "frames": int(n_frames),
        "terrain": {"name": name, "width": int(img.shape[1]), "height": int(img.shape[0]),
                    "zoom": float(zoom), "procedural": procedural},
        "gsd": float(gsd_eff),
        "origin": {"lat": float(origin_lat), "lon": float(origin_lon), "amsl_m": float(origin_amsl),
                   "note": "terrain pixel (0, 0); east = +x, north = -y, metres = pixels * gsd"},
        "t0_unix": float(t0_unix),
        "boot_offset_s": float(boot_offset_s),
        "seed": int(seed),
        "motion": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(motion).items()},
        "effects": asdict(effects),
        "telemetry_rates_hz": dict(RATES_HZ),
        "files": {"video": video_path.name, "groundtruth": "groundtruth.csv", "telemetry": "telemetry.tlog",
                  "frames": f"frames/%06d.{frames_format}" if save_frames else None},
        "conventions": "H maps frame pixels to terrain pixels (OpenCV pixel centres); yaw_deg = MAVLink "
                       "heading of the image's up direction = angle of H; scale = terrain px per frame px "
                       "at nadir; tlog position = camera nadir point, groundtruth x, y = frame centre",
    }
    (out / "meta.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
    log.info("simulated %d frames in %.1f s", n_frames, time.perf_counter() - t_start)
    return out


def write_groundtruth(path: str | Path, truth) -> None:
    """Write ``groundtruth.csv``: one row per frame, columns :data:`GROUNDTRUTH_COLUMNS`."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(GROUNDTRUTH_COLUMNS)
        for k in range(len(truth)):
            row = [truth.t[k], truth.x[k], truth.y[k], truth.yaw_deg[k], truth.scale[k], truth.roll_deg[k],
                   truth.pitch_deg[k], truth.alt_m[k], *truth.H[k].ravel()]
            w.writerow([k, *(f"{v:.12g}" for v in row)])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``photomap simulate``; unset ones fall back to the ``simulate:`` config."""
    a = parser.add_argument
    a("--out", required=True, metavar="DIR", help="output folder (created)")
    a("--terrain", metavar="NAME|PATH", help="aukerman, grass, sand, texture or an image file")
    a("--zoom", type=float, metavar="F", help="upsampling of an image terrain (0 = automatic)")
    a("--gsd", type=float, metavar="M", help="metres per stored terrain pixel (0 = automatic)")
    a("--frames", type=int, metavar="N", help="number of frames")
    a("--size", metavar="WxH", help="frame size, e.g. 640x480")
    a("--fps", type=float, help="frames per second")
    a("--seed", type=int, help="random seed")
    a("--hfov", type=float, metavar="DEG", help="horizontal field of view")
    a("--pattern", choices=PATTERNS, help="flight pattern")
    a("--speed", type=float, metavar="M/S", help="ground speed")
    a("--yaw-mode", choices=YAW_MODES, help="how the yaw moves")
    a("--yaw-rate", type=float, metavar="DEG/S", help="peak yaw rate")
    a("--altitude", metavar="MIN:MAX", help="altitude range above ground, metres")
    a("--scale-rate", type=float, metavar="1/S", help="peak relative altitude change per second")
    a("--tilt", type=float, metavar="DEG", help="roll/pitch amplitude")
    a("--noise", type=float, metavar="SIGMA", help="Gaussian noise, grey levels")
    a("--blur", type=float, metavar="SIGMA", help="Gaussian blur, pixels")
    a("--gain-drift", type=float, metavar="F", help="peak slow brightness gain change (fraction)")
    a("--jpeg", type=int, metavar="Q", help="JPEG round trip quality (0 = off)")
    a("--save-frames", action="store_true", default=None, help="also write frames/ as images")
    a("--codec", choices=sorted(VIDEO_CODECS), help="video codec: mp4v (video.mp4, strong compression), "
      "mjpg (video.avi) or ffv1 (video.mkv, lossless)")


def main(args: argparse.Namespace, cfg: dict) -> int:
    """``photomap simulate``: merge flags over the config, simulate, print where the files are."""
    c = dataclasses.asdict(cfg.simulate)
    flags = {"terrain": "terrain", "zoom": "terrain_zoom", "gsd": "gsd", "frames": "frames", "size": "size",
             "fps": "fps", "seed": "seed", "hfov": "hfov_deg", "pattern": "pattern", "speed": "speed",
             "yaw_mode": "yaw_mode", "yaw_rate": "yaw_rate", "altitude": "altitude", "scale_rate": "scale_rate",
             "tilt": "tilt", "noise": "noise", "blur": "blur", "gain_drift": "gain_drift",
             "jpeg": "jpeg_quality", "save_frames": "save_frames", "codec": "video_codec"}
    for flag, key in flags.items():
        value = getattr(args, flag, None)
        if value is not None:
            c[key] = value
    altitude = c["altitude"]
    altitude = parse_range(altitude) if isinstance(altitude, str) else tuple(float(v) for v in altitude)
    ts = parse_size(c["terrain_size"])
    out = simulate_flight(
        args.out, terrain=c["terrain"], n_frames=int(c["frames"]), size=parse_size(c["size"]), fps=c["fps"],
        seed=c["seed"], hfov_deg=c["hfov_deg"], gsd=c["gsd"], terrain_zoom=c["terrain_zoom"], terrain_size=ts,
        save_frames=c["save_frames"], frames_format=c["frames_format"], origin_lat=c["origin_lat"],
        origin_lon=c["origin_lon"], origin_amsl=c["origin_amsl"], t0_unix=c["t0_unix"],
        boot_offset_s=c["boot_offset_s"], pattern=c["pattern"], speed=c["speed"], yaw_mode=c["yaw_mode"],
        yaw_rate=c["yaw_rate"], yaw0=c["yaw0"], altitude=altitude, scale_rate=c["scale_rate"], tilt=c["tilt"],
        period_s=c["period_s"], side_overlap=c["side_overlap"], gain_drift=c["gain_drift"], blur=c["blur"],
        noise=c["noise"], jpeg_quality=int(c["jpeg_quality"]), video_codec=c["video_codec"])
    video = VIDEO_CODECS[c["video_codec"]][0]
    print(f"simulated {c['frames']} frames into {out}/: {video}, groundtruth.csv, telemetry.tlog, meta.yaml"
          + (", frames/" if c["save_frames"] else ""))
    return 0
