"""``report.html``: a self-contained flight report of a run folder.

One HTML file with no network access needed (the map thumbnail is an inline base64 WebP image, plots
are inline SVG): the map with the track, footprints, a north arrow and a scale bar; area
covered, ground resolution, frames registered/skipped/dropped, segments, georeference accuracy,
the telemetry time-sync verdict, timing, events; and the files of the run. Everything comes from
``run.json``, ``trajectory.csv`` and the mosaic PNG, so it works on any finished run (and, with
less in it, on a checkpoint).
"""

from __future__ import annotations

import base64
import html
import logging
import math
import time
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from photomap.errors import InputError
from photomap.core.area import AreaRows, premultiplied_planes
from photomap.core.records import PoseRow
from photomap.geo.georef import png_to_map
from photomap.io.runfiles import RunFiles
from photomap.io.trackfiles import coverage, frame_outline, select_footprints
from photomap.io.trajectory_files import atomic_write_text

log = logging.getLogger(__name__)

THUMB_PX = 960
SYNC_TOLERANCE_S = 0.2  # the pipeline warns beyond this residual offset
_STATUS_COLOURS = {"low_confidence": "#e08a00", "dropped": "#d62728", "corrupt": "#9467bd"}

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:24px auto;max-width:1040px;color:#222}
h1{font-size:1.5em;margin-bottom:0} h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ddd}
.sub{color:#666;margin-top:2px} table{border-collapse:collapse} td,th{padding:3px 12px 3px 0;text-align:left;vertical-align:top}
th{font-weight:600;color:#444} .ok{color:#1a7f37;font-weight:600} .warn{color:#b35900;font-weight:600}
.map{position:relative;display:inline-block;background:#eee} .map img,.map svg{display:block}
.map svg{position:absolute;left:0;top:0} code{background:#f3f3f3;padding:1px 4px}
.grid{display:grid;grid-template-columns:1fr 1fr;gap:8px 32px} .muted{color:#777}
"""


def _fmt(v, spec: str = ".3g", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{format(v, spec)}{unit}"


def _table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _thumbnail(png: Path, max_px: int = THUMB_PX) -> tuple[str, float, tuple[int, int]] | None:
    """(data URI, thumbnail px per PNG px, (w, h)) of a map PNG, or None if unreadable. Reads
    the whole PNG (see :func:`report_html`'s ``map_image`` to avoid it)."""
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    return _encode_thumbnail(image, image.shape[1], max_px)


def _encode_thumbnail(image: np.ndarray, png_width: int, max_px: int = THUMB_PX
                      ) -> tuple[str, float, tuple[int, int]] | None:
    """:func:`_thumbnail` of a map image whose PNG is ``png_width`` px wide (the image may
    already be smaller: downscaled further to ``max_px`` when larger)."""
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA)
    elif image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    h, w = image.shape[:2]
    f = min(1.0, max_px / max(w, h))
    if f < 1.0:
        # alpha-weighted area downscale (no dark fringe at the map's edge)
        size = (max(1, round(w * f)), max(1, round(h * f)))
        pre = _area_premultiplied(image, size)
        cov = pre[..., 3:]
        rgb = np.where(cov > 1e-6, pre[..., :3] / np.maximum(cov, 1e-6), 0)
        image = np.dstack([np.clip(np.rint(rgb), 0, 255), np.clip(np.rint(cov * 255), 0, 255)]).astype(np.uint8)
    # WebP keeps the alpha at a tenth of a PNG's size (every current browser shows it)
    ok, buf = cv2.imencode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, 85])
    kind = "webp"
    if not ok:
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        kind = "png"
    if not ok:
        return None
    return (f"data:image/{kind};base64," + base64.b64encode(buf.tobytes()).decode("ascii"),
            image.shape[1] / png_width, (image.shape[1], image.shape[0]))


def _area_premultiplied(bgra: np.ndarray, size: tuple[int, int], band: int = 256) -> np.ndarray:
    """float32 (h', w', 4): the ``INTER_AREA`` downscale to ``size`` = (w', h') of (colour * alpha,
    alpha), alpha in [0, 1], computed a band of rows at a time (:class:`~photomap.core.area.AreaRows`):
    an 8192 px map needs tens of MB here, not the 2 GB of float copies of the whole map."""
    h, w = bgra.shape[:2]
    ow, oh = size
    rows = AreaRows(h, w, oh, ow, 4)
    blocks = []
    for y0 in range(0, h, band):
        part = bgra[y0:y0 + band]
        blocks += rows.add(y0, premultiplied_planes(part[..., :3], part[..., 3]))
    return np.concatenate(blocks + rows.close())


def _nice(v: float) -> float:
    """1, 2 or 5 times a power of ten, at most ``v``."""
    p = 10 ** math.floor(math.log10(v))
    return max(m * p for m in (1, 2, 5) if m * p <= v)


def _map_svg(entry: dict, rows: Sequence[PoseRow], frame_size: tuple[int, int] | None, f: float,
             size: tuple[int, int], mpp: float | None, map_to_crs: np.ndarray | None) -> str:
    """SVG over the thumbnail: footprints, track, start/end, north arrow, scale bar."""
    W, H = size
    to_png = cv2.invertAffineTransform(png_to_map(entry["origin_xy"], entry.get("pixel_scale") or entry["scale"]))

    def thumb(xy: np.ndarray) -> np.ndarray:
        p = np.asarray(xy, float) @ to_png[:, :2].T + to_png[:, 2]
        return (p + 0.5) * f  # PNG pixel centre -> thumbnail coordinates (SVG: corner origin)

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}">']
    seg = entry.get("segment", 0)
    seg_rows = [r for r in rows if r.glued and r.segment == seg]
    if seg_rows and frame_size is not None:
        w, h = frame_size
        outline = np.c_[frame_outline((w, h)), np.ones(4)]
        for r in select_footprints(seg_rows, (w, h), "spaced"):
            q = thumb((np.asarray(r.M, float).reshape(-1, 3)[:2] @ outline.T).T)
            parts.append('<polygon fill="rgba(0,120,255,0.06)" stroke="#0a84ff" stroke-width="1" points="'
                         + " ".join(f"{x:.1f},{y:.1f}" for x, y in q) + '"/>')
        centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        c = thumb(np.array([np.asarray(r.M, float).reshape(-1, 3)[:2] @ centre for r in seg_rows]))
        parts.append('<polyline fill="none" stroke="#ffd60a" stroke-width="2.5" stroke-linejoin="round" points="'
                     + " ".join(f"{x:.1f},{y:.1f}" for x, y in c) + '"/>')
        parts.append(f'<circle cx="{c[0, 0]:.1f}" cy="{c[0, 1]:.1f}" r="5" fill="#30d158" stroke="#000"/>')
        parts.append(f'<circle cx="{c[-1, 0]:.1f}" cy="{c[-1, 1]:.1f}" r="5" fill="#ff453a" stroke="#000"/>')
    if map_to_crs is not None:
        north = np.linalg.solve(np.asarray(map_to_crs, float)[:, :2], [0.0, 1.0])
        d = north / np.linalg.norm(north) * 28  # map and thumbnail have the same axes (positive scale)
        x0, y0 = W - 48, 52
        tip, base, n = (x0 + d[0] * 0.85, y0 + d[1] * 0.85), (x0 + d[0] * 0.35, y0 + d[1] * 0.35), d / 28 * 8
        parts.append(f'<circle cx="{x0}" cy="{y0}" r="42" fill="rgba(255,255,255,0.75)"/>'
                     f'<line x1="{x0 - d[0] * 0.7:.1f}" y1="{y0 - d[1] * 0.7:.1f}" x2="{base[0]:.1f}" '
                     f'y2="{base[1]:.1f}" stroke="#000" stroke-width="3"/>'
                     f'<polygon fill="#000" points="{tip[0]:.1f},{tip[1]:.1f} {base[0] - n[1]:.1f},{base[1] + n[0]:.1f} '
                     f'{base[0] + n[1]:.1f},{base[1] - n[0]:.1f}"/>'
                     f'<text x="{x0 + d[0] * 1.22:.1f}" y="{y0 + d[1] * 1.22 + 5:.1f}" font-size="14" '
                     f'font-weight="bold" text-anchor="middle">N</text>')
    if mpp:
        png_scale = max(entry.get("pixel_scale") or [entry["scale"]])  # PNG px per map px
        m_per_thumb = mpp / png_scale / f
        length_m = _nice(W * 0.25 * m_per_thumb)
        px = length_m / m_per_thumb
        parts.append(f'<rect x="10" y="{H - 34}" width="{px + 16:.1f}" height="26" fill="rgba(255,255,255,0.75)"/>'
                     f'<line x1="18" y1="{H - 14}" x2="{18 + px:.1f}" y2="{H - 14}" stroke="#000" stroke-width="3"/>'
                     f'<text x="{18 + px / 2:.1f}" y="{H - 19}" font-size="12" text-anchor="middle">'
                     f'{length_m:g} m</text>')
    parts.append("</svg>")
    return "".join(parts)


def _plot_svg(x: np.ndarray, y: np.ndarray, *, title: str, xlabel: str, ylim: tuple[float, float] | None = None,
              marks: Sequence[tuple[float, str]] = (), width: int = 500, height: int = 180) -> str:
    """A small line plot as inline SVG (``marks``: vertical ticks ``(x, colour)`` at the bottom)."""
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return f'<p class="muted">{html.escape(title)}: no data</p>'
    x, y = x[ok], y[ok]
    L, R, T, B = 44, 10, 22, 30
    x0, x1 = float(x.min()), float(x.max())
    y0, y1 = ylim if ylim else (float(y.min()), float(y.max()))
    if x1 <= x0:
        x1 = x0 + 1
    if y1 <= y0:
        y0, y1 = y0 - 0.5, y1 + 0.5
    sx = lambda v: L + (v - x0) / (x1 - x0) * (width - L - R)  # noqa: E731
    sy = lambda v: height - B - (v - y0) / (y1 - y0) * (height - T - B)  # noqa: E731
    pts = " ".join(f"{sx(a):.1f},{sy(b):.1f}" for a, b in zip(x, y))
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-size="11">',
           f'<text x="{L}" y="14" font-weight="600">{html.escape(title)}</text>',
           f'<rect x="{L}" y="{T}" width="{width - L - R}" height="{height - T - B}" fill="none" stroke="#bbb"/>']
    for v in (y0, (y0 + y1) / 2, y1):
        out.append(f'<text x="{L - 4}" y="{sy(v) + 4:.1f}" text-anchor="end">{v:.3g}</text>')
    for v in (x0, (x0 + x1) / 2, x1):
        out.append(f'<text x="{sx(v):.1f}" y="{height - B + 14}" text-anchor="middle">{v:.4g}</text>')
    out.append(f'<text x="{(L + width - R) / 2:.0f}" y="{height - 3}" text-anchor="middle" fill="#666">'
               f'{html.escape(xlabel)}</text>')
    for mx, colour in marks:
        out.append(f'<line x1="{sx(mx):.1f}" y1="{height - B}" x2="{sx(mx):.1f}" y2="{height - B - 8}" '
                   f'stroke="{colour}" stroke-width="1.5"/>')
    out.append(f'<polyline fill="none" stroke="#0a84ff" stroke-width="1.5" points="{pts}"/></svg>')
    return "".join(out)


def time_sync_verdict(summary: dict) -> tuple[str, bool | None]:
    """(text, ok) of the telemetry/video time check in ``run.json`` (ok None: not checked)."""
    tel = summary.get("telemetry")
    if not tel:
        return "no telemetry joined", None
    check = tel.get("time_offset_check")
    offset = tel.get("time_offset_s") or 0.0
    if not check:
        return (f"not checked (too little yaw motion, or too few frames); offset used {offset:+.2f} s", None)
    if check.get("refused"):
        best = check.get("best_correlation")
        return ("refused: the yaw rates of video and telemetry do not match (" + str(check["refused"])
                + (f", best correlation {best:.2f}" if best is not None else "") + ")", False)
    res, corr = float(check["residual_offset_s"]), float(check.get("correlation") or float("nan"))
    if abs(res) <= SYNC_TOLERANCE_S:
        return (f"in sync: residual {res:+.3f} s (yaw-rate correlation {corr:.2f}); offset used {offset:+.2f} s", True)
    return (f"telemetry seems {res:+.2f} s off the video (correlation {corr:.2f}): rerun with "
            f"--time-offset {offset + res:.2f}", False)


def _files(run_dir: Path) -> list[tuple[str, str]]:
    out = []
    for p in sorted(run_dir.iterdir()):
        if p.name.startswith(".") or p.name == "report.html":
            continue
        if p.is_dir():
            n = sum(1 for _ in p.rglob("*") if _.is_file())
            out.append((p.name + "/", f"{n} files"))
        else:
            out.append((p.name, f"{p.stat().st_size / 1024:.0f} KiB"))
    return out


def report_html(run_dir: str | Path, map_image: np.ndarray | None = None) -> str:
    """The text of ``report.html`` for a run folder (see the module docstring).

    ``map_image``: the main map (the run's first mosaic) already downscaled, BGRA over the same
    extent as its PNG (e.g. rendered from the map's tiles in bands); None: the PNG is read,
    whole (hundreds of MB for an 8192 px map).
    """
    run = RunFiles(run_dir)
    s = run.summary
    try:
        rows = run.rows
    except InputError as exc:
        log.warning("report without the trajectory: %s", exc)
        rows = []
    frame_size = tuple(s["frame_size"]) if len(s.get("frame_size") or []) == 2 else None
    maps = run.mosaics
    entry = maps[0] if maps else None
    geo = (entry or {}).get("georeference") or s.get("georeference") or {}
    m2c = None
    if geo.get("map_to_crs"):
        try:
            m2c, _ = run.georeference(entry) if entry else run.georeference()
        except InputError:
            m2c = None
    mpp = geo.get("metres_per_pixel") or s.get("metres_per_pixel")

    # map
    map_html = '<p class="muted">no map image</p>'
    png = run.dir / entry["file"] if entry else run.dir / "preview.png"
    if map_image is not None and entry and len(entry.get("size") or []) == 2:
        thumb = _encode_thumbnail(map_image, int(entry["size"][0]))
    else:
        thumb = _thumbnail(png) if png.is_file() else None
    if thumb is not None:
        uri, f, size = thumb
        svg = _map_svg(entry, rows, frame_size, f, size, mpp, m2c) if entry else ""
        legend = ("; yellow: track (green start, red end); blue: frame footprints (spaced)"
                  if "polyline" in svg else "")
        map_html = (f'<div class="map"><img src="{uri}" width="{size[0]}" height="{size[1]}" alt="map">{svg}</div>'
                    f'<p class="muted">{html.escape(png.name)}{legend}</p>')

    # numbers
    area = None
    glued = [r for r in rows if r.glued]
    if glued and frame_size and mpp:
        scale = np.array([[mpp, 0.0, 0.0], [0.0, mpp, 0.0]])
        area = sum(coverage([r for r in glued if r.segment == seg], frame_size,
                            m2c if (m2c is not None and entry and seg == entry.get("segment", 0)) else scale).area_m2
                   for seg in sorted({r.segment for r in glued}))
    statuses = {}
    for r in rows:
        statuses[r.status] = statuses.get(r.status, 0) + 1
    duration = (rows[-1].t - rows[0].t) if len(rows) > 1 and math.isfinite(rows[-1].t) else None
    flight = [
        ("frames in", _fmt(s.get("frames_in"), "d")),
        ("registered", f"{_fmt(s.get('registered'), 'd')} "
                       f"({_fmt(100.0 * s['registered'] / s['frames_in'] if s.get('frames_in') else None, '.1f', ' %')})"),
        ("skipped (low confidence / corrupt / errors)",
         f"{_fmt(s.get('skipped'), 'd')} ({_fmt(s.get('low_confidence'), 'd')} / {_fmt(s.get('corrupt'), 'd')} / "
         f"{_fmt(s.get('errors'), 'd')})"),
        ("dropped (not processed)", _fmt(s.get("dropped"), "d")),
        ("map segments", _fmt(s.get("segments"), "d")),
        ("mean confidence", _fmt(s.get("mean_confidence"), ".3f")),
        ("video duration", _fmt(duration, ".1f", " s")),
        ("area covered", f"{_fmt(area / 1e6 if area is not None else None, '.4f', ' km²')} "
                         f"({_fmt(area, '.0f', ' m²')})" if area is not None else "n/a (no metric scale)"),
        ("ground resolution of the map", _fmt(mpp * 100 if mpp else None, ".2f", " cm/pixel")),
    ]
    lc = s.get("loop_closure")
    if lc:
        flight.append(("keyframes / loop closures", f"{lc.get('keyframes')} / {lc.get('loop_edges')} "
                                                     f"({lc.get('corrections')} corrections)"))
    georef = [("CRS", html.escape(str(geo.get("crs", "none"))))]
    if geo.get("crs"):
        georef += [("GPS fit RMS", _fmt(geo.get("gps_rms_m"), ".3f", " m")),
                   ("scale from", html.escape(str(geo.get("scale_source", "n/a")))),
                   ("origin (first fix)", f"{_fmt(geo.get('origin_lat'), '.7f')}, {_fmt(geo.get('origin_lon'), '.7f')}")]
    verdict, ok = time_sync_verdict(s)
    css = "ok" if ok else "warn" if ok is False else ""
    georef.append(("time sync", f'<span class="{css}">{html.escape(verdict)}</span>'))
    tel = s.get("telemetry") or {}
    if tel:
        georef.append(("frames with telemetry", f"{_fmt(tel.get('frames_with_telemetry'), 'd')} of "
                                                f"{_fmt(s.get('frames_in'), 'd')}; priors used "
                                                f"{_fmt(tel.get('priors_used'), 'd')}, rectified "
                                                f"{_fmt(tel.get('rectified'), 'd')}"))
        status = tel.get("status")
        if status:
            css = "ok" if status == "ok" else "warn"
            text = status if status == "ok" else f"refused: {'; '.join(tel.get('problems') or [status])}"
            georef.append(("telemetry", f'<span class="{css}">{html.escape(text)}</span>'))
    ms, reg = s.get("ms_per_frame"), s.get("ms_register_per_frame")
    timing = [("per frame (worker)", _fmt(ms, ".1f", " ms")),
              ("  registration", _fmt(reg, ".1f", " ms")),
              ("  map update and the rest", _fmt(ms - reg if ms is not None and reg is not None else None, ".1f", " ms")),
              ("wall time", _fmt(s.get("wall_time_s"), ".1f", " s")),
              ("throughput", _fmt(s.get("fps"), ".1f", " frames/s"))]

    # plots
    plots = []
    if rows:
        fr = np.array([r.frame for r in rows], float)
        conf = np.array([r.confidence if r.glued or r.status == "low_confidence" else np.nan for r in rows], float)
        marks = [(float(r.frame), _STATUS_COLOURS[r.status]) for r in rows if r.status in _STATUS_COLOURS]
        plots.append(_plot_svg(fr, conf, title="registration confidence", xlabel="frame", ylim=(0.0, 1.0),
                               marks=marks))
        alt = np.array([r.extra.get("alt_m") if isinstance(r.extra.get("alt_m"), float) else np.nan for r in rows])
        if np.isfinite(alt).any():
            t = np.array([r.t for r in rows], float)
            plots.append(_plot_svg(t, alt, title="height above ground (m)", xlabel="time (s)"))
    legend = " ".join(f'<span style="color:{c}">▮ {k.replace("_", " ")}</span>' for k, c in _STATUS_COLOURS.items())

    events = s.get("events") or []
    title = f"photomap flight report: {html.escape(run.dir.resolve().name)}"
    state = "complete" if run.complete else "checkpoint of an unfinished run"
    when = ""
    if run.video_start_unix:
        when = " · " + time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(run.video_start_unix))
    out = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{title}</title>"
           f"<style>{_CSS}</style></head><body>",
           f"<h1>{title}</h1><p class=\"sub\">{html.escape(str(s.get('input', '')))} · {state}{when}</p>",
           "<h2>Map</h2>", map_html,
           '<div class="grid"><div><h2>Flight</h2>', _table(flight), "</div>",
           "<div><h2>Georeference and telemetry</h2>", _table(georef), "<h2>Timing</h2>", _table(timing), "</div></div>",
           "<h2>Per frame</h2>", "".join(plots) or '<p class="muted">no trajectory</p>',
           f'<p class="muted">ticks: {legend}</p>' if plots else ""]
    if events:
        out.append("<h2>Events</h2><ul>" + "".join(f"<li>{html.escape(str(e))}</li>" for e in events[-30:]) + "</ul>")
    out.append("<h2>Files</h2>" + _table([(n, html.escape(v)) for n, v in _files(run.dir)]))
    out.append(f'<p class="muted">written by photomap export at '
               f'{time.strftime("%Y-%m-%d %H:%M:%S", time.localtime())}</p></body></html>')
    return "\n".join(out) + "\n"


def write_report(run_dir: str | Path, path: str | Path | None = None, *, map_image: np.ndarray | None = None) -> Path:
    """Write ``report.html`` (default: in the run folder) atomically; returns its path.
    ``map_image``: see :func:`report_html`."""
    target = Path(path) if path is not None else Path(run_dir) / "report.html"
    atomic_write_text(target, report_html(run_dir, map_image))
    return target
