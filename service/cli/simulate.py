"""Fly a virtual down-looking camera over a terrain image and write the flight with its truth.

Writes into --out DIR: video.mp4 (mp4v; or --codec mjpg/ffv1), groundtruth.csv (the exact frame->terrain matrix of
every frame), telemetry.tlog (MAVLink 2: HEARTBEAT, SYSTEM_TIME, ATTITUDE, GLOBAL_POSITION_INT,
VFR_HUD, ALTITUDE, DISTANCE_SENSOR), meta.yaml (camera, terrain, georeference, parameters) and,
with --save-frames, frames/NNNNNN.png. Defaults come from the `simulate:` config section;
every flag overrides its key.

examples:
  photomap simulate --out sim
  photomap simulate --out sim --terrain grass --pattern lawnmower --frames 600 --noise 3
  photomap simulate --out sim --size 320x240 --altitude 30:45 --tilt 2 --yaw-rate 30
"""


from __future__ import annotations

import argparse

import yaml

from photomap.config import Config
from photomap.sim.flight import PATTERNS, YAW_MODES
from photomap.sim.simulate import MODES, VIDEO_CODECS, parse_range, parse_size, simulate_flight
from photomap.sim.stills import SURVEY_YAW_MODES

# flag (argparse dest) -> key of the simulate section
FLAGS = {"terrain": "terrain", "zoom": "terrain_zoom", "gsd": "gsd", "frames": "frames", "size": "size",
         "fps": "fps", "seed": "seed", "hfov": "hfov_deg", "pattern": "pattern", "speed": "speed",
         "yaw_mode": "yaw_mode", "yaw_rate": "yaw_rate", "altitude": "altitude", "scale_rate": "scale_rate",
         "tilt": "tilt", "noise": "noise", "blur": "blur", "gain_drift": "gain_drift",
         "jpeg": "jpeg_quality", "save_frames": "save_frames", "codec": "video_codec",
         "side_overlap": "side_overlap", "terrain_period": "terrain_period",
         "terrain_variation": "terrain_variation", "terrain_stain": "terrain_stain", "objects": "objects",
         "object_height": "object_height", "object_size": "object_size", "max_bank": "max_bank",
         "pitch_offset": "pitch_offset", "mode": "mode", "strips": "strips",
         "stills_per_strip": "stills_per_strip", "forward_overlap": "forward_overlap",
         "stills_yaw": "stills_yaw", "hotspots": "hotspots", "hotspot_style": "hotspot_style",
         "k1": "k1", "k2": "k2", "p1": "p1", "p2": "p2", "k3": "k3", "overlay": "overlay",
         "bands": "stills_bands", "home_below": "stills_home_below_m", "lrf": "stills_lrf"}


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
    a("--side-overlap", type=float, metavar="F", help="lawn-mower strip spacing as footprint overlap (0..1)")
    a("--srt", action="store_true", help="also write video.srt, DJI Mini-style subtitle telemetry (one cue per "
      "frame), which `photomap replay video.mp4` joins by itself")
    g = parser.add_argument_group("hard cases of real flights")
    a = g.add_argument
    a("--terrain-period", type=int, metavar="PX", help="period of the tiles/rows terrains, terrain pixels")
    a("--terrain-variation", type=float, metavar="F", help="tile/row variation, 0 = identical")
    a("--terrain-stain", type=float, metavar="F", help="non-periodic stain layer over tiles/rows, 0 = none")
    a("--objects", type=float, metavar="F", help="fraction of the ground under raised objects (parallax), 0 = none")
    a("--object-height", type=float, metavar="M", help="height of the objects' tops above the ground")
    a("--object-size", metavar="MIN:MAX", help="object side lengths, metres")
    a("--max-bank", type=float, metavar="DEG", help="coordinated-turn bank limit of a fixed-wing "
      "(camera fixed to the airframe), 0 = off")
    a("--pitch-offset", type=float, metavar="DEG", help="constant pitch added to every frame")
    a("--mode", choices=MODES, help="video, or stills: a lawn-mower survey of JPEG stills with EXIF/XMP")
    a("--strips", type=int, metavar="N", help="stills mode: number of strips")
    a("--stills-per-strip", type=int, metavar="N", help="stills mode: stills per strip")
    a("--forward-overlap", type=float, metavar="F", help="stills mode: overlap of consecutive stills (0..1)")
    a("--stills-yaw", choices=SURVEY_YAW_MODES, help="stills mode: flip (the picture turns 180 deg between "
      "strips) or hold (a gimbal holds the camera heading; the telemetry yaw flips)")
    a("--hotspots", type=int, metavar="N", help="plant N hot spots along the flight (truth in hotspots.csv)")
    a("--hotspot-style", choices=("thermal", "visible"), help="thermal (grey terrain, hot spots) or visible "
      "(colour terrain, fire-orange spots)")
    a("--bands", type=int, metavar="N", help="stills mode: bands per capture (2-5: IMG_NNNN_B.tif, 16-bit, "
      "one lens per band)")
    a("--home-below", type=float, metavar="M", help="stills mode: the take-off point M metres below the ground "
      "under the flight (XMP RelativeAltitude reads M more than the height over the ground)")
    a("--lrf", action="store_true", default=None, help="stills mode: a laser range finder's distance in the XMP "
      "(LRFTargetDistance, as DJI enterprise cameras store it)")
    g = parser.add_argument_group("the camera's lens and overlay")
    a = g.add_argument
    for name in ("k1", "k2", "p1", "p2", "k3"):
        a(f"--{name}", type=float, metavar="C", help=f"Brown-Conrady distortion coefficient {name} (OpenCV)")
    a("--overlay", action="store_true", default=None, help="burn OSD text, a crosshair and a box into every "
      "frame; also writes mask.png (for replay --mask)")


def main(args: argparse.Namespace, cfg: Config) -> int:
    """``photomap simulate``: flags over the config (checked like it), simulate, print where the files are."""
    changes = {}
    for flag, key in FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None:
            changes[key] = list(parse_range(value)) if key in ("altitude", "object_size") else value
    s = cfg.updated({"simulate": changes}).simulate
    out = simulate_flight(
        args.out, terrain=s.terrain, n_frames=s.frames, size=parse_size(s.size), fps=s.fps,
        seed=s.seed, hfov_deg=s.hfov_deg, gsd=s.gsd, terrain_zoom=s.terrain_zoom,
        terrain_size=parse_size(s.terrain_size), save_frames=s.save_frames, frames_format=s.frames_format,
        origin_lat=s.origin_lat, origin_lon=s.origin_lon, origin_amsl=s.origin_amsl, t0_unix=s.t0_unix,
        boot_offset_s=s.boot_offset_s, pattern=s.pattern, speed=s.speed, yaw_mode=s.yaw_mode,
        yaw_rate=s.yaw_rate, yaw0=s.yaw0, altitude=s.altitude, scale_rate=s.scale_rate, tilt=s.tilt,
        period_s=s.period_s, side_overlap=s.side_overlap, gain_drift=s.gain_drift, blur=s.blur,
        noise=s.noise, jpeg_quality=s.jpeg_quality, video_codec=s.video_codec, max_bank=s.max_bank,
        pitch_offset=s.pitch_offset, terrain_period=s.terrain_period, terrain_variation=s.terrain_variation,
        terrain_stain=s.terrain_stain, objects=s.objects, object_height=s.object_height,
        object_size=s.object_size, object_walls=s.object_walls, mode=s.mode, strips=s.strips,
        stills_per_strip=s.stills_per_strip, forward_overlap=s.forward_overlap, stills_yaw=s.stills_yaw,
        stills_quality=s.stills_quality, stills_xmp=s.stills_xmp, stills_bands=s.stills_bands, hotspots=s.hotspots,
        hotspot_style=s.hotspot_style, home_below_m=s.stills_home_below_m, lrf=s.stills_lrf,
        srt=bool(getattr(args, "srt", False)),
        distortion=(s.k1, s.k2, s.p1, s.p2, s.k3), osd=s.overlay)
    if s.mode == "stills":
        n = yaml.safe_load((out / "meta.yaml").read_text(encoding="utf-8"))["frames"]
        print(f"simulated {n} stills into {out}/: stills/, groundtruth.csv, telemetry.tlog, meta.yaml"
              + (", frames/" if s.save_frames else ""))
        return 0
    video = VIDEO_CODECS[s.video_codec][0]
    print(f"simulated {s.frames} frames into {out}/: {video}, groundtruth.csv, telemetry.tlog, meta.yaml"
          + (", video.srt" if getattr(args, "srt", False) else "") + (", frames/" if s.save_frames else ""))
    return 0
