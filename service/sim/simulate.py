"""The simulated flight, our ground truth: a pinhole camera flown over a terrain image.

:func:`simulate_flight` writes into a folder: the video (or, in stills mode, JPEG stills with EXIF
GPS/time/focal length and DJI XMP), ``groundtruth.csv`` (the exact frame->terrain matrix of every
frame), ``telemetry.tlog`` (MAVLink 2) and ``meta.yaml`` (camera, terrain, georeference,
parameters). The command is :mod:`photomap.cli.simulate`.
"""
from __future__ import annotations

import csv
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import yaml

from photomap.sim.srt_writer import write_srt
from photomap.sim.tlog_writer import RATES_HZ, write_tlog

from photomap.errors import InputError, PhotomapError
from photomap.sim.flight import PATTERNS, YAW_MODES, Camera, build_pyramid, iter_frames, pixel_to_latlon, plan_flight, split_params
from photomap.sim.hotspots import HOTSPOT_STYLES, paint_hotspots, place_hotspots, thermal_terrain, write_hotspots_csv
from photomap.geo.lens import LensModel
from photomap.sim.lens import OVERLAY_BGR, DistortedRender, Overlay
from photomap.sim.objects import ObjectScene, random_objects
from photomap.sim.bands import BANDS, DARK, GAIN, band_image, lens_homography, micasense_xmp, write_band_still
from photomap.sim.stills import (SENSOR_WIDTH_MM, SURVEY_YAW_MODES, dji_attributes, focal_35mm, plan_survey, still_exif, subset,
                                 write_still)
from photomap.sim.terrain import DEFAULT_GSD, PERIODIC, PROCEDURAL, TERRAIN_GSD, TERRAIN_ZOOM, load_terrain, valid_mask
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


MODES = ("video", "stills")


def simulate_flight(out_dir: str | Path, *, terrain: str = "aukerman", n_frames: int = 300,
                    size: tuple[int, int] = (640, 480), fps: float = 30.0, seed: int = 0,
                    hfov_deg: float = 60.0, gsd: float = 0.0, terrain_zoom: float = 0.0,
                    terrain_size: tuple[int, int] = (4096, 4096), save_frames: bool = False,
                    frames_format: str = "png", origin_lat: float = 41.1, origin_lon: float = -81.7,
                    origin_amsl: float = 300.0, t0_unix: float = 0.0, boot_offset_s: float = 60.0,
                    video_codec: str = "mp4v", terrain_period: int = 80, terrain_variation: float = 0.1,
                    terrain_stain: float = 0.3, objects: float = 0.0, object_height: float = 5.0,
                    object_size: tuple[float, float] = (4.0, 12.0), object_walls: bool = True,
                    mode: str = "video", strips: int = 4, stills_per_strip: int = 10,
                    forward_overlap: float = 0.65, stills_yaw: str = "flip", stills_quality: int = 92,
                    stills_xmp: bool = True, stills_bands: int = 1, hotspots: int = 0, hotspot_style: str = "thermal",
                    srt: bool = False, distortion: tuple[float, ...] = (), osd: bool = False,
                    home_below_m: float = 0.0, lrf: bool = False, **params) -> Path:
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
    terrain_period, terrain_variation, terrain_stain : period (terrain px), per-tile/row
        variation and stain of the ``tiles`` and ``rows`` terrains (:mod:`photomap.sim.periodic`).
    objects : fraction of the ground under objects standing ``object_height`` metres above it
        (box roofs and tree crowns, sides ``object_size`` = (min, max) metres; walls on the
        boxes if ``object_walls``): parallax (:mod:`photomap.sim.objects`). 0 = none. The
        truth stays the ground plane.
    mode : ``video``, or ``stills``: a lawn-mower survey of ``strips`` x ``stills_per_strip``
        stills with ``forward_overlap`` (:mod:`photomap.sim.stills`), written as
        ``stills/NNNNNN.jpg`` (JPEG ``stills_quality``, EXIF, DJI XMP if ``stills_xmp``) instead
        of a video; ``n_frames``, ``fps``, pattern and yaw settings then do not apply.
        ``stills_yaw``: ``flip`` (the picture turns 180 degrees between strips) or ``hold`` (a
        gimbal holds the camera's heading; the telemetry's yaw still flips).
        ``stills_bands`` > 1: each still is a multi-band capture instead, ``stills/IMG_NNNN_B.tif``
        (16-bit, one lens per band, :mod:`photomap.sim.bands`; ``meta.yaml`` ``bands`` gives
        each band's lens homography).
    hotspots : number of hot spots planted into the terrain along the flight
        (:mod:`photomap.sim.hotspots`), their truth in ``hotspots.csv``; ``hotspot_style``
        ``thermal`` (grey thermal-looking terrain, hot grey spots) or ``visible`` (colour
        terrain, fire-orange spots).
    srt : also write ``video.srt`` beside the video, the DJI Mini-style subtitle telemetry of
        every frame (:mod:`photomap.sim.srt_writer`; video mode only).
    distortion : the camera's Brown-Conrady ``(k1, k2, p1, p2, k3)`` about the frame centre
        (:mod:`photomap.sim.lens`; () or zeros = an ideal pinhole camera). The ground truth is
        the ideal pinhole view: undistorting a frame with this model gives the truth's frame.
    osd : burn an overlay (text, crosshair, box) into every frame; ``mask.png`` marks it.
    home_below_m : stills mode: the take-off point lies this many metres below the ground under
        the flight (a canopy, a hillside): the stills' ``RelativeAltitude`` (height over take-off,
        as DJI stores it) reads that much more than the height over the ground.
    lrf : stills mode: the DJI XMP also carries a laser range finder's reading (DJI enterprise
        cameras): ``LRFTargetDistance`` = the true distance along the optical axis to the
        (flat) ground, height / (cos roll cos pitch).
    **params : :class:`photomap.sim.flight.Motion` and :class:`photomap.sim.flight.Effects` fields.

    Returns the output folder.
    """
    motion, effects = split_params(params)
    out = Path(out_dir)
    if frames_format not in ("png", "jpg"):
        raise InputError(f"frames format must be png or jpg, got {frames_format!r}")
    if mode not in MODES:
        raise InputError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    stills = mode == "stills"
    if stills_bands > len(BANDS) or stills_bands < 1:
        raise InputError(f"bands per capture must be 1..{len(BANDS)}, got {stills_bands}")
    if stills_bands > 1 and not stills:
        raise InputError("multi-band captures are stills: use --mode stills with --bands")
    if not stills and video_codec not in VIDEO_CODECS:
        raise InputError(f"video codec must be one of {', '.join(VIDEO_CODECS)}, got {video_codec!r}")
    name = str(terrain)
    procedural = name in PROCEDURAL
    zoom = 1.0 if procedural else (terrain_zoom or TERRAIN_ZOOM.get(name, 1.0))
    gsd_eff = (gsd or TERRAIN_GSD.get(name, DEFAULT_GSD)) / zoom
    t_start = time.perf_counter()
    periodic = ({"period": terrain_period, "variation": terrain_variation, "stain": terrain_stain}
                if name in PERIODIC else {})
    img = load_terrain(name, zoom=zoom, size=(terrain_size[1], terrain_size[0]), seed=seed, **periodic)
    valid = valid_mask(img)
    camera = Camera.from_hfov(size[0], size[1], hfov_deg)
    dist = tuple(float(v) for v in distortion)
    lens = (LensModel("brown", camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                      (dist + (0.0,) * 5)[:5]) if any(dist) else None)
    if lens is not None and objects > 0:
        raise InputError("simulated lens distortion and objects (parallax) cannot be combined")
    distorted = DistortedRender(lens) if lens is not None else None
    if stills:
        truth, shots, flight_yaw = plan_survey(valid, camera, gsd_eff, motion, strips=strips,
                                               per_strip=stills_per_strip, forward_overlap=forward_overlap,
                                               yaw_mode=stills_yaw, seed=seed)
        frames_truth = subset(truth, shots)
    else:
        truth = plan_flight(valid, n_frames, camera, fps, gsd_eff, motion, seed)
        frames_truth = truth
        flight_yaw = truth.yaw_deg
    if t0_unix <= 0:
        t0_unix = round(time.time(), 3)
    spots = []
    if hotspots > 0:
        if hotspot_style not in HOTSPOT_STYLES:
            raise InputError(f"hot spot style must be one of {', '.join(HOTSPOT_STYLES)}, got {hotspot_style!r}")
        spots = place_hotspots(frames_truth.x, frames_truth.y, hotspots, gsd_eff, shape=img.shape[:2], seed=seed)
        img = paint_hotspots(thermal_terrain(img) if hotspot_style == "thermal" else img, spots, gsd_eff,
                             hotspot_style)
    overlay = None
    scene_objects = []
    if objects > 0:
        scene_objects = random_objects(img.shape[:2], gsd_eff, cover=objects, size_m=tuple(object_size), seed=seed)
        if object_height >= float(truth.alt_m.min()):
            raise InputError(f"object height {object_height} m must be below the camera ({truth.alt_m.min():.1f} m)")
        scene = ObjectScene(scene_objects, object_height, gsd_eff, shape=img.shape[:2], walls=object_walls,
                            max_scale=float(frames_truth.scale.max()), seed=seed)
        overlay = scene.overlay(frames_truth)

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PhotomapError(f"cannot create output folder {out}: {exc.strerror}") from None
    frames_dir = out / "frames"
    if save_frames:
        frames_dir.mkdir(exist_ok=True)
    lat, lon = pixel_to_latlon(truth.cam_x, truth.cam_y, gsd_eff, origin_lat, origin_lon)
    pyramid = build_pyramid(img, float(frames_truth.scale.max()) * 1.2)
    osd_layer = Overlay(camera.width, camera.height) if osd else None
    frames = iter_frames(img, frames_truth, camera, effects, seed, motion.period_s, pyramid, overlay=overlay,
                         lens=distorted, osd=osd_layer)
    if osd_layer is not None and not cv2.imwrite(str(out / "mask.png"), osd_layer.mask()):
        raise PhotomapError(f"cannot write {out / 'mask.png'}")
    def lrf_range(i: int) -> float | None:
        """The laser range finder's distance along the optical axis to the flat ground (m)."""
        if not lrf:
            return None
        tilt = math.cos(math.radians(float(truth.roll_deg[i]))) * math.cos(math.radians(float(truth.pitch_deg[i])))
        return float(truth.alt_m[i]) / tilt

    if stills and stills_bands > 1:
        media = out / "stills"
        media.mkdir(exist_ok=True)
        noise_rng = np.random.default_rng([seed, 33])
        for k, frame in enumerate(frames):
            i = int(shots[k])
            exif = still_exif(t_unix=t0_unix + float(truth.t[i]), lat=float(lat[i]), lon=float(lon[i]),
                              amsl_m=origin_amsl + float(truth.alt_m[i]), camera=camera)
            dji = dji_attributes(rel_alt_m=float(truth.alt_m[i]) + home_below_m,
                                 amsl_m=origin_amsl + float(truth.alt_m[i]),
                                 lat=float(lat[i]), lon=float(lon[i]), roll=float(truth.roll_deg[i]),
                                 pitch=float(truth.pitch_deg[i]), yaw=float(truth.yaw_deg[i]), camera=camera,
                                 flight_yaw=float(flight_yaw[i]), lrf_m=lrf_range(i)) if stills_xmp else None
            for b in range(stills_bands):
                write_band_still(media / f"IMG_{k:04d}_{b + 1}.tif", band_image(frame, b, noise_rng), exif,
                                 micasense_xmp(capture_id=f"sim{seed}-{k:06d}", band=b, dji=dji))
            if save_frames:
                cv2.imwrite(str(frames_dir / f"{k:06d}.{frames_format}"), frame)
    elif stills:
        media = out / "stills"
        media.mkdir(exist_ok=True)
        for k, frame in enumerate(frames):
            i = int(shots[k])
            write_still(media / f"{k:06d}.jpg", frame, t_unix=t0_unix + float(truth.t[i]), lat=float(lat[i]),
                        lon=float(lon[i]), amsl_m=origin_amsl + float(truth.alt_m[i]),
                        rel_alt_m=float(truth.alt_m[i]) + home_below_m, camera=camera,
                        roll=float(truth.roll_deg[i]), pitch=float(truth.pitch_deg[i]), yaw=float(truth.yaw_deg[i]),
                        flight_yaw=float(flight_yaw[i]), quality=stills_quality, xmp=stills_xmp, lrf_m=lrf_range(i))
            if save_frames:
                cv2.imwrite(str(frames_dir / f"{k:06d}.{frames_format}"), frame)
    else:
        name_, fourcc = VIDEO_CODECS[video_codec]
        media = out / name_
        writer = cv2.VideoWriter(str(media), cv2.VideoWriter_fourcc(*fourcc), fps, (camera.width, camera.height))
        if not writer.isOpened():
            raise PhotomapError(f"cannot write {media} ({fourcc} encoder unavailable or folder not writable)")
        try:
            for k, frame in enumerate(frames):
                writer.write(frame)
                if save_frames:
                    cv2.imwrite(str(frames_dir / f"{k:06d}.{frames_format}"), frame)
        finally:
            writer.release()

    write_groundtruth(out / "groundtruth.csv", frames_truth)
    if spots:
        write_hotspots_csv(out / "hotspots.csv", spots,
                           *pixel_to_latlon(np.array([s.x for s in spots]), np.array([s.y for s in spots]),
                                            gsd_eff, origin_lat, origin_lon))
    srt_file = None
    if srt and not stills:
        srt_file = media.with_suffix(".srt")
        write_srt(srt_file, truth.t, lat, lon, truth.alt_m, truth.roll_deg, truth.pitch_deg, truth.yaw_deg,
                  t0_unix=t0_unix, home_amsl_m=origin_amsl, focal_35mm=focal_35mm(camera))
    write_tlog(out / "telemetry.tlog", truth.t, lat, lon, truth.alt_m, truth.roll_deg, truth.pitch_deg,
               flight_yaw, t0_unix=t0_unix, boot_offset_s=boot_offset_s, home_amsl_m=origin_amsl,
               fixed_wing=motion.max_bank > 0)
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
        "files": {"video": media.name, "groundtruth": "groundtruth.csv", "telemetry": "telemetry.tlog",
                  "frames": f"frames/%06d.{frames_format}" if save_frames else None},
        "conventions": "H maps frame pixels to terrain pixels (OpenCV pixel centres); yaw_deg = MAVLink "
                       "heading of the image's up direction = angle of H; scale = terrain px per frame px "
                       "at nadir; tlog position = camera nadir point, groundtruth x, y = frame centre",
    }
    if srt_file is not None:
        meta["files"]["srt"] = srt_file.name
    if lens is not None:
        meta["camera"].update({"model": "brown", "distortion": dict(zip(("k1", "k2", "p1", "p2", "k3"), lens.dist)),
                               "note": "frames seen through OpenCV's Brown-Conrady model (fx, fy, cx, cy, these "
                                       "coefficients); groundtruth H maps the undistorted (pinhole) frame"})
    if stills and (home_below_m or lrf):
        meta["stills_height"] = {"home_below_m": float(home_below_m), "lrf": bool(lrf),
                                 "note": "XMP RelativeAltitude = height over the ground + home_below_m; "
                                         "LRFTargetDistance = height / (cos roll cos pitch)"}
    if osd_layer is not None:
        meta["overlay"] = {"mask": "mask.png", "colour_bgr": list(OVERLAY_BGR),
                           "note": "text, crosshair and box burned into every frame; mask.png black there"}
    if periodic:
        meta["terrain"].update(periodic)
    if objects > 0:
        meta["objects"] = {"cover": float(objects), "height_m": float(object_height),
                           "size_m": [float(v) for v in object_size], "walls": bool(object_walls),
                           "count": len(scene_objects),
                           "note": "object tops on a plane height_m above the ground; truth = ground plane"}
    if spots:
        meta["hotspots"] = {"count": len(spots), "style": hotspot_style, "file": "hotspots.csv",
                            "note": "discs painted into the terrain; x_px, y_px = terrain px of the centre"}
    if stills and stills_bands > 1:
        meta["bands"] = [{"name": BANDS[b][0], "file": f"stills/IMG_%04d_{b + 1}.tif",
                          "central_wavelength_nm": BANDS[b][1], "mix_bgr": list(BANDS[b][2]),
                          "lens_H": lens_homography(b, (camera.width, camera.height)).tolist()}
                         for b in range(stills_bands)]
        meta["bands_note"] = ("lens_H maps the band's pixels to the truth camera's (groundtruth.csv H); the band's "
                              "16-bit value = %g + %g * (mix . frame BGR / 255 + offset) + noise" % (DARK, GAIN))
    if stills:
        meta["frames"] = len(shots)
        meta["fps"] = None
        meta["files"].update({"video": None, "stills": "stills/%06d.jpg" if stills_bands <= 1 else "stills/IMG_%04d_B.tif"})
        meta["stills"] = {"strips": int(strips), "per_strip": int(stills_per_strip),
                          "forward_overlap": float(forward_overlap), "side_overlap": float(motion.side_overlap),
                          "yaw": stills_yaw,
                          "altitude_m": float(truth.alt_m[0]), "quality": int(stills_quality), "xmp": bool(stills_xmp),
                          "focal_length_mm": camera.fx * SENSOR_WIDTH_MM / camera.width,
                          "focal_35mm": focal_35mm(camera), "sensor_width_mm": SENSOR_WIDTH_MM,
                          "note": "t = 0 at the first still; EXIF times are t0_unix + t (UTC); EXIF GPS = "
                                  "camera nadir point; FocalLengthIn35mmFilm by the diagonal rule (43.27 mm); "
                                  "tlog ATTITUDE yaw and XMP FlightYawDegree = the aircraft's heading, "
                                  "groundtruth yaw and XMP GimbalYawDegree = the camera's"}
    (out / "meta.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
    log.info("simulated %d %s in %.1f s", len(frames_truth), "stills" if stills else "frames",
             time.perf_counter() - t_start)
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
