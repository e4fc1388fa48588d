"""Typed configuration: one frozen dataclass per section of ``config/default.yaml``.

The dataclasses below are the one source of defaults; ``config/default.yaml`` documents every
key with the same values (a test keeps the two equal). A YAML file (``--config``) and
``section.key=value`` items (``--set``) override them. Every value is checked when the config is
built, by type and by value (range or allowed choices): a wrong key or value is a
:class:`~photomap.errors.ConfigError` naming the key and what it accepts, before any frame is
read. Components take their section (e.g. :class:`RegistrationConfig`), never a dict.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import yaml

from photomap.errors import ConfigError

__all__ = ["Config", "RegistrationConfig", "MappingConfig", "OutputConfig", "CaptureConfig",
           "TelemetryConfig", "MosaicConfig", "SimulateConfig", "ViewerConfig", "MapServerConfig", "CameraConfig",
           "GeorefConfig", "PosegraphConfig", "HazardsConfig", "load_config", "parse_set", "default_config_path"]


def _num(default: float | int | None, lo: float | None = None, hi: float | None = None, *,
         lo_open: bool = False, hi_open: bool = False) -> Any:
    """A numeric field with an allowed range (``lo_open``/``hi_open``: the bound is excluded)."""
    return field(default=default, metadata={"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open})


def _choice(default: Any, *choices: Any) -> Any:
    """A field that takes one of ``choices``."""
    return field(default=default, metadata={"choices": choices})


class _Section:
    """Validation shared by the section dataclasses (types from the annotations, ranges and
    choices from the field metadata); ``_name`` is the section's key in the YAML."""

    _name = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            key = f"{self._name}.{f.name}"
            value = _coerce(key, hints[f.name], getattr(self, f.name))
            object.__setattr__(self, f.name, value)
            _check_value(key, value, f.metadata)
        self._check()

    def _check(self) -> None:
        """Checks across keys (override)."""

    def _fail(self, key: str, message: str) -> None:
        raise ConfigError(f"config key '{self._name}.{key}' {message}")


def _type_name(tp: Any) -> str:
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


def _coerce(key: str, tp: Any, value: Any) -> Any:
    """``value`` as type ``tp`` (an int is accepted for a float; lists for tuples), or ConfigError."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(key, args[0], value)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"config key '{key}' must be a list of {len(args)} numbers, got {value!r}")
        return tuple(_coerce(key, a, v) for a, v in zip(args, value))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}' must be true or false, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"config key '{key}' must be a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' must be an integer, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' must be a string, got {value!r}")
        return value
    raise TypeError(f"config key '{key}': unsupported type {tp!r}")  # a programming error


def _check_value(key: str, value: Any, meta: typing.Mapping[str, Any]) -> None:
    if value is None:
        return
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        allowed = ", ".join(str(c) for c in choices)
        raise ConfigError(f"config key '{key}' must be one of {allowed}; got {value!r}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is None and hi is None:
        return
    for v in value if isinstance(value, tuple) else (value,):
        low_bad = lo is not None and (v <= lo if meta.get("lo_open") else v < lo)
        high_bad = hi is not None and (v >= hi if meta.get("hi_open") else v > hi)
        if low_bad or high_bad:
            left = "(" if meta.get("lo_open") else "["
            right = ")" if meta.get("hi_open") else "]"
            span = f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"
            raise ConfigError(f"config key '{key}' must be in {span}; got {value!r}")


# ---------------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class RegistrationConfig(_Section):
    """iFMI registration (:class:`photomap.core.ifmi.Registrar`); ``working_size`` is the
    pipeline's downscaling before registration."""

    _name = "registration"
    working_size: int = _num(320, 0, 16384)
    window: str = _choice("tukey", "tukey", "hann", "circular")
    window_taper: float = _num(0.5, 0.0, 1.0)
    angle_bins: int = _num(0, 0, 8192)
    radius_bins: int = _num(0, 0, 8192)
    band_low: float = _num(0.02, 0.0, 0.5, lo_open=True, hi_open=True)
    band_high: float = _num(0.45, 0.0, 0.5, lo_open=True)
    snr_weighting: bool = True
    peak_sigma: float = _num(0.18, 0.0, 10.0, lo_open=True)
    candidate_ratio: float = _num(0.6, 0.0, 1.0, lo_open=True)
    max_candidates: int = _num(3, 1, 32)
    refine_iterations: int = _num(20, 0, 1000)

    def _check(self) -> None:
        if 0 < self.working_size < 16:
            self._fail("working_size", f"must be 0 (full resolution) or at least 16; got {self.working_size}")
        if self.band_low >= self.band_high:
            self._fail("band_low", f"must be below registration.band_high ({self.band_high}); got {self.band_low}")


@dataclass(frozen=True)
class MappingConfig(_Section):
    """Poses, keyframes, segments, loop closure (:mod:`photomap.core.tracking`,
    :mod:`photomap.mapping.loopclosure`)."""

    _name = "mapping"
    min_confidence: float = _num(0.12, 0.0, 1.0)
    trust_confidence: float = _num(0.3, 0.0, 1.0)
    verify_placements: bool = True
    second_opinion: str = _choice("sift", "sift", "orb", "none")
    second_opinion_px: int = _num(640, 64, 16384)
    max_lost_frames: int = _num(10, 0, 100000)
    keyframes: bool = True
    keyframe_confidence: float = _num(0.5, 0.0, 1.0)
    keyframe_max_shift: float = _num(0.5, 0.0, 10.0, lo_open=True)
    motion_prior: bool = True
    prior_angle_tol_deg: float = _num(20.0, 0.0, 180.0, lo_open=True)
    prior_scale_tol: float = _num(0.15, 0.0, 10.0, lo_open=True)
    map_scale: float = _num(1.0, 0.0, 16.0, lo_open=True)
    map_px: int = _num(2048, 0, 1 << 16)
    paint: str = _choice("new_ground", "new_ground", "every")
    opencv_threads: int = _num(2, 0, 256)
    map_relative: bool = False
    loop_closure: bool = True
    loop_min_gap: int = _num(8, 1, 100000)
    loop_radius: float = _num(0.35, 0.0, 100.0, lo_open=True)
    loop_min_confidence: float = _num(0.25, 0.0, 1.0)
    loop_candidates: int = _num(2, 1, 1000)
    loop_appearance: bool = True
    loop_appearance_candidates: int = _num(2, 1, 1000)
    loop_appearance_min_score: float = _num(0.0, -1.0, 1.0)
    optimize_in_background: bool = True


@dataclass(frozen=True)
class OutputConfig(_Section):
    """What a run writes and how often (:mod:`photomap.mapping.run_outputs`)."""

    _name = "output"
    checkpoint_interval: float = _num(10.0, 0.0, None)
    max_mosaic_px: int = _num(8192, 64, 1 << 20)
    preview_px: int = _num(1024, 16, 1 << 16)
    data_dir: str = "~/photomap-flights"
    geotiff: bool = True
    footprints: str = _choice("spaced", "all", "keyframes", "spaced", "none")
    checkpoint_map: bool = True
    min_free_mb: float = _num(50.0, 0.0, None)
    composite: str = ""

    def _check(self) -> None:
        names = [n.strip() for n in self.composite.split(",")] if self.composite.strip() else []
        if names and (len(names) != 3 or not all(names)):
            self._fail("composite", f"must name 3 bands (red, green, blue of the picture), e.g. nir,red,green, "
                                    f"or be empty; got {self.composite!r}")


@dataclass(frozen=True)
class CaptureConfig(_Section):
    """Frame sources (:mod:`photomap.drivers`)."""

    _name = "capture"
    device: str = ""
    width: int = _num(0, 0, 16384)
    height: int = _num(0, 0, 16384)
    fps: float = _num(0.0, 0.0, 1000.0)
    fourcc: str = ""
    queue_size: int = _num(4, 1, 1000)
    read_failures: int = _num(5, 1, 100000)
    reconnect_initial: float = _num(0.5, 0.0, 3600.0, lo_open=True)
    reconnect_max: float = _num(8.0, 0.0, 3600.0, lo_open=True)
    open_timeout: float = _num(5.0, 0.0, 3600.0, lo_open=True)
    stream_timeout: float = _num(2.0, 0.0, 3600.0, lo_open=True)
    rtsp_transport: str = _choice("udp", "udp", "tcp")
    decoder_threads: int = _num(1, 0, 64)
    image_rate: float = _num(1.0, 0.0, 1000.0, lo_open=True)
    mask: str = ""
    band: str = ""

    def _check(self) -> None:
        if len(self.fourcc.strip()) > 4 or (self.fourcc and not self.fourcc.strip()):
            self._fail("fourcc", f"must be a code of up to 4 characters such as MJPG, YUYV, GREY or Y16, "
                                 f"or empty; got {self.fourcc!r}")
        if self.reconnect_max < self.reconnect_initial:
            self._fail("reconnect_max", f"must be at least capture.reconnect_initial ({self.reconnect_initial})")


@dataclass(frozen=True)
class TelemetryConfig(_Section):
    """MAVLink telemetry and how the map uses it (:mod:`photomap.drivers.mavlink`,
    :mod:`photomap.mapping.telemetry_join`)."""

    _name = "telemetry"
    source: str = ""
    baud: int = _num(57600, 1, 10_000_000)
    max_gap: float = _num(2.0, 0.0, 3600.0, lo_open=True)
    max_hold: float = _num(0.5, 0.0, 3600.0)
    horizon: float = _num(120.0, 0.0, 1e6, lo_open=True)
    link_timeout: float = _num(2.0, 0.0, 3600.0, lo_open=True)
    send_heartbeat: bool = False
    send_statustext: bool = False
    source_system: int = _num(1, 1, 255)
    system_id: int = _num(0, 0, 255)
    use_priors: bool = True
    prior_angle_tol_deg: float = _num(5.0, 0.0, 180.0, lo_open=True)
    prior_scale_tol: float = _num(0.05, 0.0, 10.0, lo_open=True)
    rectify_tilt: bool = True
    time_offset: float = 0.0
    max_disagreements_in_a_row: int = _num(10, 0, None)


@dataclass(frozen=True)
class MosaicConfig(_Section):
    """The tiled map (:class:`photomap.core.mosaic.TiledMosaic`)."""

    _name = "mosaic"
    tile_size: int = _num(256, 16, 8192)
    channels: int = _choice(3, 1, 3)
    blend: str = _choice("overwrite", "overwrite", "feather")
    exposure: str = _choice("none", "none", "gain", "channel_gain")
    border: int = _num(1, 0, 1000)
    max_tiles_in_memory: int | None = _num(None, 1, None)
    cache_dir: str | None = None
    max_footprint_px: int = _num(16777216, 1, None)


@dataclass(frozen=True)
class SimulateConfig(_Section):
    """The simulated flight (:mod:`photomap.sim`)."""

    _name = "simulate"
    terrain: str = "aukerman"
    terrain_zoom: float = _num(0.0, 0.0, 64.0)
    terrain_size: str = "4096x4096"
    gsd: float = _num(0.0, 0.0, 1000.0)
    frames: int = _num(300, 1, 10_000_000)
    size: str = "640x480"
    fps: float = _num(30.0, 0.0, 1000.0, lo_open=True)
    seed: int = 0
    hfov_deg: float = _num(60.0, 0.0, 179.0, lo_open=True)
    pattern: str = _choice("random", "random", "lawnmower", "figure8", "circle")
    speed: float = _num(8.0, 0.0, 1000.0)
    yaw_mode: str = _choice("random", "random", "constant", "heading", "fixed")
    yaw_rate: float = _num(15.0, 0.0, 3600.0)
    yaw0: float | None = None
    altitude: tuple[float, float] = _num((50.0, 70.0), 0.0, 100000.0, lo_open=True)
    scale_rate: float = _num(0.05, 0.0, 10.0)
    tilt: float = _num(0.0, 0.0, 80.0)
    period_s: float = _num(10.0, 0.0, 1e6, lo_open=True)
    side_overlap: float = _num(0.3, 0.0, 1.0, hi_open=True)
    gain_drift: float = _num(0.0, 0.0, 1.0)
    blur: float = _num(0.0, 0.0, 100.0)
    noise: float = _num(0.0, 0.0, 255.0)
    jpeg_quality: int = _num(0, 0, 100)
    save_frames: bool = False
    frames_format: str = _choice("png", "png", "jpg")
    origin_lat: float = _num(41.1, -90.0, 90.0)
    origin_lon: float = _num(-81.7, -180.0, 180.0)
    origin_amsl: float = 300.0
    t0_unix: float = _num(0.0, 0.0, None)
    boot_offset_s: float = _num(60.0, 0.0, None)
    video_codec: str = _choice("mp4v", "mp4v", "mjpg", "ffv1")
    terrain_period: int = _num(80, 8, 4096)
    terrain_variation: float = _num(0.1, 0.0, 1.0)
    terrain_stain: float = _num(0.3, 0.0, 1.0)
    objects: float = _num(0.0, 0.0, 0.9)
    object_height: float = _num(5.0, 0.0, 10000.0)
    object_size: tuple[float, float] = _num((4.0, 12.0), 0.0, 10000.0, lo_open=True)
    object_walls: bool = True
    max_bank: float = _num(0.0, 0.0, 80.0)
    pitch_offset: float = _num(0.0, -80.0, 80.0)
    mode: str = _choice("video", "video", "stills")
    strips: int = _num(4, 1, 1000)
    stills_per_strip: int = _num(10, 2, 100000)
    forward_overlap: float = _num(0.65, 0.0, 1.0, hi_open=True)
    stills_yaw: str = _choice("flip", "flip", "hold")
    stills_quality: int = _num(92, 1, 100)
    stills_xmp: bool = True
    hotspots: int = _num(0, 0, 1000)
    hotspot_style: str = _choice("thermal", "thermal", "visible")
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    overlay: bool = False
    stills_bands: int = _num(1, 1, 5)
    stills_home_below_m: float = _num(0.0, -1000.0, 1000.0)
    stills_lrf: bool = False

    def _check(self) -> None:
        if self.object_size[0] > self.object_size[1]:
            self._fail("object_size", f"must be [min, max] with min <= max; got {list(self.object_size)}")
        if self.altitude[0] > self.altitude[1]:
            self._fail("altitude", f"must be [min, max] with min <= max; got {list(self.altitude)}")
        for key in ("terrain_size", "size"):
            w, _, h = getattr(self, key).lower().partition("x")
            if not (w.isdigit() and h.isdigit() and int(w) >= 16 and int(h) >= 16):
                self._fail(key, f"must be WxH in pixels (each at least 16), e.g. 640x480; got {getattr(self, key)!r}")


@dataclass(frozen=True)
class ViewerConfig(_Section):
    """The live rerun view (:mod:`photomap.live.viewer`)."""

    _name = "viewer"
    mode: str = "none"
    port: int = _num(9876, 1, 65535)
    server_memory_limit: str = "256MB"
    queue_size: int = _num(32, 1, 100000)
    tile_hz: float = _num(2.0, 0.0, 1000.0, lo_open=True)
    max_tiles: int = _num(64, 1, 100000)
    camera_hz: float = _num(5.0, 0.0, 1000.0, lo_open=True)
    camera_px: int = _num(480, 16, 16384)
    jpeg_quality: int = _num(75, 1, 100)
    trajectory_every: int = _num(30, 1, 1_000_000)
    trajectory_max_points: int = _num(2000, 2, 10_000_000)
    color_by: str = _choice("confidence", "confidence", "segment")


@dataclass(frozen=True)
class MapServerConfig(_Section):
    """The live map over HTTP: XYZ tiles, status, GeoJSON and a page (:mod:`photomap.live.mapserver`)."""

    _name = "map_server"
    listen: str = ""
    port: int = _num(8765, 1, 65535)
    threads: int = _num(4, 1, 64)
    max_connections: int = _num(32, 1, 10000)
    timeout_s: float = _num(5.0, 0.0, 600.0, lo_open=True)
    keepalive_s: float = _num(15.0, 0.0, 3600.0)
    tile_hz: float = _num(2.0, 0.0, 1000.0, lo_open=True)
    max_raw_tiles: int = _num(256, 0, 10_000_000)
    cache_tiles: int = _num(256, 1, 1_000_000)
    min_render_interval_s: float = _num(2.0, 0.0, 3600.0)
    jpeg_quality: int = _num(0, 0, 100)
    cpu_share: float = _num(0.1, 0.0, 64.0)
    write_xyz: bool = True


@dataclass(frozen=True)
class CameraConfig(_Section):
    """The camera model of the input frames (metric scale, tilt rectification)."""

    _name = "camera"
    fx_px: float = _num(0.0, 0.0, None)
    hfov_deg: float = _num(0.0, 0.0, 180.0, hi_open=True)
    # lens model (photomap.geo.lens): from a calibration file, or the keys below at the input size
    calibration: str = ""
    model: str = _choice("brown", "brown", "fisheye")
    fy_px: float = _num(0.0, 0.0, None)
    cx_px: float = _num(0.0, 0.0, None)
    cy_px: float = _num(0.0, 0.0, None)
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    def _check(self) -> None:
        if self.calibration:
            for key in ("fx_px", "hfov_deg", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3", "k4"):
                if getattr(self, key):
                    self._fail(key, f"conflicts with camera.calibration ({self.calibration}), which gives the "
                                    f"camera model: leave it at 0")
        if self.model == "fisheye" and any((self.p1, self.p2)):
            self._fail("p1" if self.p1 else "p2", "is a Brown-Conrady coefficient: a fisheye lens takes k1..k4")
        if self.model == "brown" and self.k4:
            self._fail("k4", "is a fisheye coefficient: set camera.model=fisheye (a Brown-Conrady lens takes "
                             "k1 k2 p1 p2 k3)")


@dataclass(frozen=True)
class GeorefConfig(_Section):
    """Georeference from GPS and the time offset check (:mod:`photomap.geo.georef`,
    :mod:`photomap.telemetry.timesync`)."""

    _name = "georef"
    gps_inlier_m: float = _num(10.0, 0.0, None, lo_open=True)
    min_extent_m: float = _num(20.0, 0.0, None)
    min_fixes: int = _num(5, 2, None)
    timesync_window_s: float = _num(10.0, 0.0, 3600.0)
    timesync_min_correlation: float = _num(0.9, 0.0, 1.0)
    timesync_min_yaw_rate: float = _num(2.0, 0.0, 3600.0)
    min_inlier_fraction: float = _num(0.7, 0.0, 1.0)
    max_scale_ratio: float = _num(1.3, 1.0, None, lo_open=True)
    max_heading_error_deg: float = _num(20.0, 0.0, 180.0)
    alone_min_inlier_fraction: float = _num(0.9, 0.0, 1.0)
    alone_max_rms_fraction: float = _num(0.1, 0.0, None)


@dataclass(frozen=True)
class PosegraphConfig(_Section):
    """Drift correction of keyframe poses (:mod:`photomap.core.posegraph`)."""

    _name = "posegraph"
    sigma_px: float = _num(1.0, 0.0, None, lo_open=True)
    min_confidence: float = _num(0.05, 0.0, 1.0, lo_open=True)
    robust: str = _choice("cauchy", "cauchy", "soft_l1", "huber", "linear")
    f_scale: float = _num(3.0, 0.0, None, lo_open=True)
    outlier_sigma: float = _num(4.0, 0.0, None, lo_open=True)
    solver: str = _choice("lm", "lm", "trf")
    max_nfev: int = _num(100, 1, 1_000_000)
    max_solve_nodes: int | None = _num(1000, 2, None)
    heading_sigma_deg: float = _num(5.0, 0.0, 180.0, lo_open=True)
    altitude_sigma: float = _num(0.02, 0.0, 10.0, lo_open=True)
    gps_sigma_m: float = _num(3.0, 0.0, None, lo_open=True)


@dataclass(frozen=True)
class HazardsConfig(_Section):
    """Hazard spots: hot spots or colour anomalies tracked on the map (:mod:`photomap.mapping.hazards`)."""

    _name = "hazards"
    enabled: bool = False
    mode: str = _choice("hot", "hot", "colour")
    k: float = _num(8.0, 0.0, None)
    min_excess: float = _num(60.0, 0.0, None)
    window_frames: float = _num(300.0, 1.0, None)
    min_area_px: float = _num(6.0, 1.0, None)
    max_area_px: float = _num(4000.0, 1.0, None)
    detect_px: int = _num(320, 0, 100000)
    hue_deg: float = _num(25.0, 0.0, 360.0)
    hue_tol_deg: float = _num(15.0, 0.0, 180.0)
    min_saturation: float = _num(150.0, 0.0, 255.0)
    min_value: float = _num(150.0, 0.0, 255.0)
    match_m: float = _num(3.0, 0.0, None, lo_open=True)
    match_px: float = _num(30.0, 0.0, None, lo_open=True)
    min_frames: int = _num(3, 1, 100000)
    forget_frames: int = _num(30, 1, None)
    statustext: bool = True

    def _check(self) -> None:
        if self.min_area_px > self.max_area_px:
            self._fail("min_area_px", f"must not exceed max_area_px ({self.max_area_px}); got {self.min_area_px}")


@dataclass(frozen=True)
class Config:
    """The whole configuration: one typed section per YAML section."""

    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    mosaic: MosaicConfig = field(default_factory=MosaicConfig)
    simulate: SimulateConfig = field(default_factory=SimulateConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)
    map_server: MapServerConfig = field(default_factory=MapServerConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    georef: GeorefConfig = field(default_factory=GeorefConfig)
    posegraph: PosegraphConfig = field(default_factory=PosegraphConfig)
    hazards: HazardsConfig = field(default_factory=HazardsConfig)

    def to_dict(self) -> dict:
        """Plain nested mapping (YAML/JSON-able; tuples become lists)."""
        return {f.name: {k: list(v) if isinstance(v, tuple) else v
                         for k, v in vars(getattr(self, f.name)).items()}
                for f in dataclasses.fields(self)}

    def updated(self, changes: typing.Mapping[str, Any] | str | Iterable[str]) -> Config:
        """A copy with ``changes`` applied: a nested mapping (``{"mapping": {"keyframes": False}}``)
        or ``section.key=value`` items; checked like a config file."""
        if isinstance(changes, str):
            changes = [changes]
        if not isinstance(changes, typing.Mapping):
            merged: dict = {}
            for item in changes:
                _deep_update(merged, parse_set(item))
            changes = merged
        data = _merged(self.to_dict(), changes, "")
        return Config(**{f.name: type(getattr(self, f.name))(**data[f.name]) for f in dataclasses.fields(self)})


def _deep_update(base: dict, extra: dict) -> None:
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _deep_update(base[k], v)
        else:
            base[k] = v


def _merged(base: dict, override: typing.Mapping, prefix: str) -> dict:
    """``base`` with ``override`` applied; unknown keys and sections given a scalar are errors."""
    out = dict(base)
    for key, value in override.items():
        name = f"{prefix}{key}"
        if key not in base:
            known = ", ".join(sorted(base))
            raise ConfigError(f"unknown config key '{name}' (known here: {known})")
        if isinstance(base[key], dict):
            if not isinstance(value, typing.Mapping):
                raise ConfigError(f"config key '{name}' is a section and needs a mapping")
            out[key] = _merged(base[key], value, f"{name}.")
        else:
            if isinstance(value, typing.Mapping):
                raise ConfigError(f"config key '{name}' is not a section; got a mapping")
            out[key] = value
    return out


def _build(data: dict) -> Config:
    sections = {f.name: f.default_factory for f in dataclasses.fields(Config)}  # type: ignore[misc]
    return Config(**{name: cls(**data[name]) for name, cls in sections.items()})


def default_config_path() -> Path:
    """Path of ``config/default.yaml`` in a source checkout (the documented defaults)."""
    return Path(__file__).resolve().parents[1] / "config" / "default.yaml"


def read_yaml(path: str | Path) -> dict:
    """A config file as a nested mapping; unreadable or malformed files are a ConfigError."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"config file {path} is not UTF-8 text") from None
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {' '.join(str(exc).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of sections")
    return data


def parse_set(item: str) -> dict:
    """Turn ``section.key=value`` (value in YAML syntax) into a nested mapping."""
    if "=" not in item:
        raise ConfigError(f"--set needs key=value, got {item!r}")
    key, _, raw = item.partition("=")
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set needs key=value, got {item!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    out: dict = {parts[-1]: value}
    for part in reversed(parts[:-1]):
        out = {part: out}
    return out


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """The defaults, then the YAML file at ``path``, then each ``section.key=value`` of ``overrides``."""
    data = Config().to_dict()
    if path is not None:
        data = _merged(data, read_yaml(path), "")
    for item in overrides:
        data = _merged(data, parse_set(item), "")
    return _build(data)
