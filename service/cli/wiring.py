"""What the mapping commands share: telemetry links, the pipeline with its sinks, signals, summary.

``replay``, ``run`` and ``demo`` are thin: they open a frame source, call :func:`open_telemetry`
and :func:`map_source`, and print :func:`print_summary`.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import yaml
from tqdm import tqdm

from photomap.cli.oplog import StatusReporter
from photomap.config import CaptureConfig, Config
from photomap.drivers.capture import open_source
from photomap.drivers.exif import focal_length_px
from photomap.drivers.frames import FrameSource
from photomap.drivers.mavlink import TelemetryReader, load_tlog
from photomap.drivers.srt import is_srt, read_srt, srt_beside
from photomap.drivers.stills_telemetry import open_stills_telemetry as stills_telemetry
from photomap.errors import InputError
from photomap.io.preflight import check_output_dir
from photomap.live.mapserver import MapServer, write_run_tiles
from photomap.live.viewer import Viewer
from photomap.mapping.events import FrameEvent, FrameSink
from photomap.mapping.hazards import HazardTracker
from photomap.mapping.pipeline import MappingPipeline
from photomap.mapping.telemetry_join import TelemetryJoin

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------- arguments
def add_telemetry_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mavlink", "--telemetry", dest="mavlink", metavar="CONNECTION",
                        help="telemetry: a .tlog file, a DJI .SRT (replay; found beside DJI_0001.MP4 "
                             "by itself), udpin:0.0.0.0:14550, tcp:HOST:PORT, /dev/ttyUSB0,57600 ... "
                             "(default: telemetry.source; none = vision only)")
    parser.add_argument("--time-offset", type=float, metavar="SECONDS",
                        help="seconds added to frame times to get telemetry times")


def add_viewer_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--viewer", metavar="MODE",
                        help="live view in rerun (needs the viewer extra): none, spawn, serve[=PORT] "
                             "(on 127.0.0.1: an operator tunnels in with `ssh -L PORT:127.0.0.1:PORT` "
                             "and runs `rerun --connect rerun+http://127.0.0.1:PORT/proxy`), serve=ADDR:PORT "
                             "(e.g. 0.0.0.0:9876: open to the network, without authentication, and "
                             "clients can also write into the view), connect=URL, save=FILE.rrd "
                             "(default: viewer.mode)")


def add_hazards_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hazards", action="store_true",
                        help="detect hazard spots (hot spots or colour anomalies: the hazards config "
                             "section) and write hazards.geojson/.kml/.csv (default: hazards.enabled)")


def hazards_config(args: argparse.Namespace, cfg: Config) -> Config:
    """``cfg`` with ``hazards.enabled`` set when ``--hazards`` was given."""
    return cfg.updated({"hazards": {"enabled": True}}) if getattr(args, "hazards", False) else cfg


def add_mask_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mask", metavar="PNG",
                        help="frame mask image: black pixels (burned-in text, a crosshair, the drone in "
                             "view) are never registered or painted; scaled to the frame size "
                             "(default: capture.mask)")


def with_mask_argument(args: argparse.Namespace, cfg: Config) -> Config:
    """``cfg`` with ``--mask`` as ``capture.mask`` when it was given."""
    mask = getattr(args, "mask", None)
    return cfg.updated({"capture": {"mask": str(mask)}}) if mask else cfg


def add_map_server_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--map-server", metavar="[ADDR:]PORT", nargs="?", const="127.0.0.1",
                        help="serve the live map over HTTP (web tiles for QGroundControl, Mission Planner, "
                             "QGIS, a browser page; docs/live-map.md) on 127.0.0.1:PORT, or ADDR:PORT (e.g. "
                             "0.0.0.0:8765: open to the network, no authentication); alone: "
                             "127.0.0.1:map_server.port (default: map_server.listen)")


# ---------------------------------------------------------------------------------- frames
def open_capture(spec: str, c: CaptureConfig) -> FrameSource:
    """The frame source ``spec`` names (camera, folder/glob of stills, video), set up from ``capture``."""
    return open_source(spec, width=c.width, height=c.height, fps=c.fps, fourcc=c.fourcc,
                       open_timeout=c.open_timeout, stream_timeout=c.stream_timeout,
                       rtsp_transport=c.rtsp_transport, decoder_threads=c.decoder_threads,
                       queue_size=c.queue_size, read_failures=c.read_failures,
                       reconnect_initial=c.reconnect_initial, reconnect_max=c.reconnect_max,
                       image_rate=c.image_rate, band=c.band)


# ---------------------------------------------------------------------------------- telemetry
def video_metadata(input_spec: str) -> dict:
    """The simulator's meta.yaml beside a video (camera model, UNIX time of frame 0), if any."""
    meta = Path(input_spec).parent / "meta.yaml"
    if not Path(input_spec).is_file() or not meta.is_file():
        return {}
    try:
        data = yaml.safe_load(meta.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError):
        return {}
    return data if isinstance(data, dict) else {}


def _link_summary(spec: str, stats) -> dict:
    return {"source": spec, "messages": stats.total, "gaps": stats.gaps,
            "link_lost": stats.link_lost, "link_regained": stats.link_regained,
            "rejected_samples": sum(stats.rejected.values()), "parse_errors": stats.receive_errors,
            "system_id": stats.system_id,
            "other_systems": {str(k): v for k, v in sorted(stats.other_systems.items())},
            "span": list(stats.span) if stats.span else None}


def open_telemetry(spec: str, cfg: Config, *, source: FrameSource | None = None, input_spec: str = "",
                   video_start: float | None = None, realtime: bool = False, live: bool = False
                   ) -> tuple[TelemetryJoin, TelemetryReader | None, Config]:
    """A telemetry join for ``spec`` (a .tlog or a live link), the reader to stop (or None), and
    the config completed with the video's own camera model when it has one."""
    tcfg = cfg.telemetry
    meta = video_metadata(input_spec) if input_spec else {}
    camera = meta.get("camera") or {}
    if not cfg.camera.fx_px and not cfg.camera.hfov_deg and not cfg.camera.calibration and camera.get("fx"):
        cfg = cfg.updated({"camera": {"fx_px": float(camera["fx"])}})  # the video's own camera model
    if is_srt(spec):
        if live:
            raise InputError(f"{spec}: a DJI subtitle file is the telemetry of a recorded video, "
                             "not of a live camera")
        beside = bool(input_spec) and Path(spec).with_suffix("") == Path(input_spec).with_suffix("")
        join, cfg = open_srt_telemetry(spec, cfg, source=source, beside=beside)
        return join, None, cfg
    if spec.lower().endswith(".tlog") and not live:
        if not Path(spec).is_file():
            raise InputError(f"telemetry log not found: {spec}")
        buffer, stats = load_tlog(spec, max_gap=tcfg.max_gap, max_hold=tcfg.max_hold,
                                  link_timeout=tcfg.link_timeout, system_id=tcfg.system_id)
        if video_start is None:
            video_start = meta.get("t0_unix") or getattr(source, "creation_time", None)
        if video_start is None and getattr(source, "exif_times", None):
            video_start = 0.0  # stills carry UNIX times already
        if video_start is None:
            span = buffer.span
            video_start = span[0] if span else 0.0
            log.warning("video start time unknown: assuming it starts with the telemetry log "
                        "(use --video-start or --time-offset)")
        join = TelemetryJoin(buffer.at, "log", cfg, video_start=float(video_start), offset=tcfg.time_offset,
                             link_summary=lambda: _link_summary(spec, stats), field_at=buffer.value_at)
        return join, None, cfg
    link_cfg = cfg.updated({"telemetry": {"source": spec, "send_heartbeat": tcfg.send_heartbeat and live}})
    reader = TelemetryReader.from_config(link_cfg.telemetry).start()
    if not live and not realtime:
        log.warning("a live telemetry link with a replay as fast as possible cannot be joined in "
                    "time: use --realtime")
    join = TelemetryJoin(reader.at, "live" if live else "link", cfg, offset=tcfg.time_offset,
                         link_summary=lambda: _link_summary(spec, reader.stats))
    return join, reader, cfg


def open_srt_telemetry(path: str | Path, cfg: Config, *, source: FrameSource | None = None,
                       beside: bool = False) -> tuple[TelemetryJoin, Config]:
    """A join for a DJI subtitle file (:mod:`photomap.drivers.srt`): its cues are on the video's
    clock (video start 0, offset ``telemetry.time_offset``), joined like a .tlog. The config
    gets the cues' 35 mm equivalent focal length (at the frames' size, as for stills) when the
    camera model is not configured. Logs one line (``beside``: the file was found beside the
    video, and the line says so)."""
    tcfg = cfg.telemetry
    if not Path(path).is_file():
        raise InputError(f"telemetry file not found: {path}")
    track = read_srt(path)
    log.info("telemetry from %s%s", track.describe(), " (found beside the video)" if beside else "")
    size = getattr(source, "size", None)
    if not cfg.camera.fx_px and not cfg.camera.hfov_deg and track.focal_35mm and size:
        fx, _ = focal_length_px(*size, focal_35mm=track.focal_35mm)
        if fx:
            cfg = cfg.updated({"camera": {"fx_px": float(fx)}})
    buffer = track.buffer(max_gap=tcfg.max_gap, max_hold=tcfg.max_hold)
    join = TelemetryJoin(buffer.at, "log", cfg, video_start=0.0, offset=tcfg.time_offset,
                         link_summary=track.summary, field_at=buffer.value_at)
    return join, cfg


def telemetry_beside(input_spec: str) -> str | None:
    """The DJI subtitle file beside a video (``DJI_0001.SRT`` for ``DJI_0001.MP4``), or None."""
    found = srt_beside(input_spec)
    return None if found is None else str(found)


def open_stills_telemetry(source: FrameSource, cfg: Config, geo: str | None = None
                          ) -> tuple[TelemetryJoin | None, Config]:
    """The telemetry that survey stills carry (EXIF GPS, DJI XMP, or a ``geo.txt``), joined like
    MAVLink samples; None for a video or stills without any. The config gets the stills' focal
    length when the camera model is not configured."""
    tel = stills_telemetry(source, geo=geo)
    if tel is None:
        return None, cfg
    if not cfg.camera.fx_px and not cfg.camera.hfov_deg and not cfg.camera.calibration and tel.focal_px:
        cfg = cfg.updated({"camera": {"fx_px": float(tel.focal_px)}})
    return TelemetryJoin(tel.at, "stills", cfg, link_summary=tel.summary, sample_of=tel.of_frame), cfg


# ---------------------------------------------------------------------------------- sinks
def stderr_is_terminal() -> bool:
    """True when stderr is a terminal (not a file, a pipe or journald)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def progress_sink(total: int | None, enabled: bool) -> tuple[FrameSink, Callable[[], None]]:
    """A progress bar on stderr (one tick per frame) and its close function.

    Only on a terminal: redirected to a file or journald, its ``\r`` redraws would make one
    endless line, so it is off there (the status line of :func:`map_source` says the same).
    """
    bar = tqdm(total=total, unit="frame", disable=not (enabled and stderr_is_terminal()), file=sys.stderr,
               dynamic_ncols=True)
    return (lambda event: bar.update(1)), bar.close


def pacing_sink() -> FrameSink:
    """Sleeps so that frame times advance no faster than wall time (``--realtime``)."""
    t0: list[float] = []

    def pace(event: FrameEvent) -> None:
        if not t0:
            t0.extend((event.t, time.monotonic()))
            return
        delay = (event.t - t0[0]) - (time.monotonic() - t0[1])
        if delay > 0:
            time.sleep(delay)
    return pace


def statustext_sink(send: Callable[[str], None]) -> FrameSink:
    """Mapping events to the autopilot/GCS as STATUSTEXT: mapping started, link to the map lost."""
    def notify(event: FrameEvent) -> None:
        if event.new_segment:
            send("photomap: mapping started" if event.segment == 0 else
                 f"photomap: link to map lost, new segment at frame {event.index}")
    return notify


def hazard_tracker(cfg: Config, out_dir: str | Path, reader: TelemetryReader | None,
                   live: bool) -> HazardTracker | None:
    """The run's hazard tracker when ``hazards.enabled`` (its ``on_frame`` is a sink, its
    ``hazards`` the live FeatureCollection); one STATUSTEXT per new hazard on a live link with
    ``telemetry.send_statustext`` and ``hazards.statustext``."""
    if not cfg.hazards.enabled:
        return None
    send = (reader.send_status if cfg.hazards.statustext and cfg.telemetry.send_statustext and reader is not None
            and live else None)
    return HazardTracker(cfg.hazards, out_dir, send_status=send)


# ---------------------------------------------------------------------------------- mapping
def map_source(source: FrameSource, cfg: Config, out_dir: str | Path, *, input_name: str = "",
               progress: bool = False, total: int | None = None, realtime: bool = False,
               telemetry: TelemetryJoin | None = None, reader: TelemetryReader | None = None,
               viewer: str | None = None, status_interval: float = 0.0, map_server: str | None = None) -> dict:
    """Run the mapping pipeline over ``source`` and write the outputs; returns the run summary.

    SIGINT/SIGTERM (when called from the main thread) stop capture, drain the queue and write
    the outputs. ``viewer`` is a ``--viewer`` mode string (default: the ``viewer.mode`` config);
    ``reader`` is the live telemetry link (STATUSTEXT goes out on it when configured).
    ``progress``: a progress bar, on a terminal only. ``status_interval`` > 0: a status line at
    INFO every that many seconds (:class:`~photomap.cli.oplog.StatusReporter`), unless the
    progress bar is shown. At the end the run's counts are logged at INFO (as fields in JSON lines).
    ``map_server``: ``--map-server``'s ``[ADDR:]PORT`` (default ``map_server.listen``; see
    :class:`~photomap.live.mapserver.MapServer`); it serves until the outputs (and its ``xyz/``
    tiles) are written.
    """
    check_output_dir(out_dir, expected_frames=total, min_free_mb=cfg.output.min_free_mb)  # before any frame
    view = Viewer.from_config(cfg.viewer, viewer)
    if view.url:
        hint = f" ({view.connect_hint})" if view.connect_hint else ""
        print(f"viewer: connect with `rerun --connect {view.url}`{hint}")
    server = MapServer.from_config(cfg.map_server, map_server)
    if server is not None:
        print(f"map server: {server.url} (tiles {server.url}tiles/{{z}}/{{x}}/{{y}}.png)")
    bar_shown = progress and stderr_is_terminal()
    tick, close_bar = progress_sink(total, progress)
    sinks = [tick]
    status = None
    if status_interval and status_interval > 0 and not bar_shown:
        status = StatusReporter(status_interval, telemetry=telemetry is not None)
        sinks.append(status.on_frame)
    hazards = hazard_tracker(cfg, out_dir, reader, source.live)
    if hazards is not None:
        sinks.append(hazards.on_frame)
        view.show_hazards(hazards.hazards)
    if view.enabled:
        sinks.append(view.on_frame)
    if cfg.telemetry.send_statustext and reader is not None and source.live:
        sinks.append(statustext_sink(reader.send_status))
    if server is not None:
        sinks.append(server.on_frame)
        if hazards is not None:
            server.hazards = hazards.hazards  # /hazards.geojson and the page's markers
    if realtime:
        sinks.append(pacing_sink())
    pipeline = MappingPipeline(source, cfg, out_dir, sinks=sinks, input_name=input_name, telemetry=telemetry,
                               final_outputs={"hazards": hazards.finish} if hazards is not None else None)
    if server is not None:
        pipeline.on_georeference = server.on_georeference
        server.gate = pipeline.worker_first
    previous = {}
    if status is not None:
        status.start()
    if threading.current_thread() is threading.main_thread():
        def handler(signum, _frame):
            log.warning("%s: stopping, writing the map", signal.Signals(signum).name)
            pipeline.stop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        summary = pipeline.run()
        if server is not None and cfg.map_server.write_xyz and summary.get("georeference"):
            write_run_tiles(out_dir)
    finally:
        if status is not None:
            status.close()
        close_bar()
        view.close()
        if server is not None:
            server.close()
        for sig, old in previous.items():
            signal.signal(sig, old)
    _log_summary(summary, out_dir)
    return summary


def _log_summary(summary: dict, out_dir: str | Path) -> None:
    """The run's counts at INFO, one line (and fields, for JSON log lines)."""
    keys = ("frames_in", "registered", "skipped", "dropped", "segments", "ms_per_frame", "fps")
    fields = {k: summary.get(k) for k in keys}
    fields["out"] = str(out_dir)
    log.info("run finished: %s frames in, %s registered, %s skipped, %s dropped, %s segment(s); "
             "outputs in %s", *(fields[k] for k in keys[:5]), out_dir, extra=fields)


def print_summary(summary: dict, out_dir: str | Path) -> None:
    out = Path(out_dir)
    mosaics = summary.get("mosaics") or []
    print(f"frames: {summary['frames_in']} in, {summary['registered']} registered, "
          f"{summary['skipped']} skipped, {summary['dropped']} dropped; "
          f"{summary['segments']} segment(s); "
          f"{summary['ms_per_frame'] or 0:.1f} ms/frame ({summary['fps'] or 0:.1f} fps)")
    if mosaics:
        print(f"map: {out / mosaics[0]['file']}")
    elif summary.get("map_unwritten") and not summary.get("map_kept_in"):
        print(f"map: could not be written ({', '.join(summary['map_unwritten'])})")
    else:
        print("map: nothing was mapped")
    if summary.get("map_kept_in"):
        print(f"map: not all written ({'; '.join(f'{k}: {v}' for k, v in summary['write_errors'].items())}); "
              f"kept in {out / summary['map_kept_in']}: free space, then `photomap recover {out}`")
    elif summary.get("write_errors"):
        print(f"not written: {'; '.join(f'{k}: {v}' for k, v in summary['write_errors'].items())}")
    geo = summary.get("georeference")
    if geo:
        print(f"georeferenced: {geo['crs']}, {summary['metres_per_pixel']:.3f} m per map pixel "
              f"(world file {out / geo['world_file']}; opens in place in QGIS)")
    elif summary.get("metres_per_pixel"):
        print(f"scale: {summary['metres_per_pixel']:.3f} m per map pixel")
    haz = summary.get("hazards")
    if haz and haz.get("geojson"):
        print(f"hazards: {haz['count']} ({out / haz['geojson']}, {haz['kml']}, {haz['csv']}; "
              f"{haz['ms_per_frame'] or 0:.1f} ms/frame)")
    print(f"trajectory: {out / 'trajectory.csv'}")
