"""DJI video-subtitle telemetry (``DJI_0001.SRT`` beside ``DJI_0001.MP4``).

A DJI drone writes one subtitle cue per video frame (newer models) or per second (older ones)
with the aircraft's position and height. :func:`read_srt` parses every style in use into
:class:`SrtCue` objects and :meth:`SrtTrack.buffer` stores them in a
:class:`~photomap.telemetry.samples.TelemetryBuffer`, so the track is joined to the frames
exactly like a MAVLink log (``TelemetryJoin(buffer.at, "log", cfg, video_start=0.0)``).

Time base: a cue's time is its subtitle **start time** in seconds from the start of the video,
the very clock of ``Frame.t`` (a cue belongs to the frame shown from its start): the offset
between video and telemetry is known, zero (``telemetry.time_offset`` still adds to it). A
file without ``-->`` time lines (an early Mavic 2 style) is timed by its date lines instead,
from the first cue on.

Styles (a style is detected per cue, so joined files of two models parse too):

- ``bracket`` (Mini 2/3/4, Air 2/2S/3, Mavic 2/3, Mavic 3E/3T, M30): ``[latitude: ..]
  [longitude: ..]`` (Mavic 2: ``[latitude : ..] [longtitude : ..]``), heights ``[rel_alt: ..
  abs_alt: ..]`` or ``[altitude: ..]`` (AMSL), gimbal ``[gb_yaw: .. gb_pitch: .. gb_roll: ..]``.
- ``gps_lon_lat`` (Phantom 3/4, P4 RTK, Mavic Pro, Mavic Mini, Spark): ``GPS(lon, lat, n)``
  (``n`` is the satellite count), height above take-off ``H 85.8m``, ``BAROMETER:1.9`` or
  ``Hb:1.9`` (``HOME(..)``, the take-off point, is not needed), gimbal ``G.PRY (pitch, roll,
  yaw)`` (``F.PRY`` is the aircraft's and is not used: the camera hangs in the gimbal).
- ``gps_lat_lon`` (Matrice 200/300): ``GPS(lat, lon, 0.0M) BAROMETER:12.3M``.

Units and conventions of the samples (those of :mod:`photomap.telemetry.samples`): ``lat``,
``lon`` [deg WGS84], ``alt`` [m AMSL], ``relative_alt`` [m above take-off, the height used for
the metric scale over flat ground], ``roll``, ``pitch``, ``yaw`` [rad] of the camera as
:func:`photomap.drivers.exif.camera_attitude` gives them for DJI stills: yaw = gimbal yaw,
pitch = gimbal pitch + 90 deg (a gimbal at -90 deg looks straight down), roll = gimbal roll.
"""

from __future__ import annotations

import math
import re
import statistics
from collections import Counter
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

from photomap.errors import InputError
from photomap.telemetry.samples import TelemetryBuffer

#: File name endings of DJI subtitle telemetry.
SRT_SUFFIXES = (".srt",)

_NUM = r"[-+]?\d+(?:\.\d+)?"
_TIME = re.compile(r"(\d+):(\d{1,2}):(\d{1,2})[,.](\d{1,3})\s*-->\s*(\d+):(\d{1,2}):(\d{1,2})[,.](\d{1,3})")
_DATE = re.compile(r"(\d{4})[-./](\d{1,2})[-./](\d{1,2})\s+(\d{1,2}):(\d{2}):(\d{2})(?:[.,](\d{1,6}))?")
_TAG = re.compile(r"<[^>]*>")
_KEY_VALUE = re.compile(rf"([A-Za-z_]+)\s*:\s*({_NUM})")
#: Keys that make a cue of the bracket style (any one of them).
_BRACKET_KEYS = frozenset({"latitude", "longitude", "longtitude", "rel_alt", "abs_alt", "altitude",
                           "gb_yaw", "gb_pitch", "gb_roll"})
_GPS = re.compile(rf"\bGPS\s*\(\s*({_NUM})\s*,\s*({_NUM})\s*(?:,\s*([^)]*))?\)", re.I)
_HEIGHT = (re.compile(rf"(?:^|[\s,])H\s+({_NUM})\s*m\b"), re.compile(rf"\bBAROMETER\s*:\s*({_NUM})", re.I),
           re.compile(rf"\bHb\s*:\s*({_NUM})"))
_GPRY = re.compile(rf"\bG\.PRY\s*\(\s*({_NUM})\D*?,\s*({_NUM})\D*?,\s*({_NUM})", re.I)

_MAX_SPEED = 150.0          # m/s: a cue farther than this from both neighbours is a glitch
_REL_ALT_RANGE = (-2000.0, 12000.0)
_ALT_RANGE = (-500.0, 12000.0)
_EARTH_R = 6371008.8


@dataclass(frozen=True, slots=True)
class SrtCue:
    """One subtitle cue's telemetry. ``t``: seconds on the video's clock (subtitle start);
    ``lat``, ``lon`` [deg], ``rel_alt`` [m above take-off], ``abs_alt`` [m AMSL], gimbal
    angles [deg, DJI's: pitch -90 = nadir]; None where the cue does not say."""

    index: int
    t: float
    style: str
    lat: float | None = None
    lon: float | None = None
    rel_alt: float | None = None
    abs_alt: float | None = None
    gimbal_yaw: float | None = None
    gimbal_pitch: float | None = None
    gimbal_roll: float | None = None
    decimals: int | None = None   # digits after the point of the position
    focal_35mm: float | None = None   # 35 mm equivalent focal length [mm] (``focal_len``)


@dataclass
class SrtTrack:
    """The cues of one file, in time order, and what was left out of them."""

    path: str
    cues: list[SrtCue]
    blocks: int = 0
    styles: Counter = field(default_factory=Counter)
    without_gps: int = 0
    unparsed: int = 0             # blocks without a time, or without any known field
    out_of_order: int = 0
    glitches: int = 0
    timed_by_date: bool = False

    @property
    def with_gps(self) -> int:
        return sum(c.lat is not None for c in self.cues)

    @property
    def period(self) -> float | None:
        """Median seconds between cues (None with fewer than two)."""
        dt = [b.t - a.t for a, b in zip(self.cues, self.cues[1:]) if b.t > a.t]
        return float(statistics.median(dt)) if dt else None

    @property
    def decimals(self) -> int | None:
        """Fewest digits after the point of any position (4 digits: ~11 m steps)."""
        d = [c.decimals for c in self.cues if c.decimals is not None]
        return min(d) if d else None

    @property
    def focal_35mm(self) -> float | None:
        """Median 35 mm equivalent focal length of the cues (mm), or None."""
        f = [c.focal_35mm for c in self.cues if c.focal_35mm is not None]
        return float(statistics.median(f)) if f else None

    def buffer(self, max_gap: float = 2.0, max_hold: float = 0.5) -> TelemetryBuffer:
        """The cues as a whole-file :class:`TelemetryBuffer` (see the module doc for fields).

        ``max_gap``/``max_hold`` are raised to 1.5x/1x the cue period, so 1 Hz cues
        interpolate and the last one holds until its next would have come.
        """
        period = self.period or 0.0
        buf = TelemetryBuffer(max_gap=max(max_gap, 1.5 * period), max_hold=max(max_hold, period),
                              horizon=None)
        for c in self.cues:
            values: dict[str, float] = {}
            if c.lat is not None and c.lon is not None:
                values.update(lat=c.lat, lon=c.lon)
            if c.abs_alt is not None:
                values["alt"] = c.abs_alt
            if c.rel_alt is not None:
                values["relative_alt"] = c.rel_alt
            if c.gimbal_yaw is not None:
                values["yaw"] = math.radians(c.gimbal_yaw)
            if c.gimbal_pitch is not None and c.gimbal_roll is not None:
                values["pitch"] = math.radians(c.gimbal_pitch + 90.0)
                values["roll"] = math.radians(c.gimbal_roll)
            if values:
                buf.add(c.t, values)
        return buf

    def describe(self) -> str:
        """One line: the file, its cues and what they carry (and a coarse position's warning)."""
        s = self.summary()
        period = f"every {s['period_s']:.3g} s" if s["period_s"] else "one cue"
        text = (f"{Path(self.path).name}: {s['cues']} DJI subtitle cues {period} "
                f"({', '.join(sorted(self.styles))}), {s['with_gps']} with GPS, {s['with_height']} with "
                f"height above take-off, {s['with_gimbal']} with gimbal attitude")
        dropped = self.unparsed + self.out_of_order
        if dropped:
            text += (f"; {dropped} block(s) left out (unreadable {self.unparsed}, time going back "
                     f"{self.out_of_order})")
        if self.glitches:
            text += f"; {self.glitches} position jump(s) removed"
        if self.decimals is not None and self.decimals <= 4:
            step = 111_320 * 10 ** -self.decimals
            text += f"; positions have {self.decimals} decimals (steps of ~{step:.0f} m)"
        return text

    def summary(self) -> dict:
        """What the file held (``run.json`` ``telemetry.link``)."""
        return {"source": self.path, "format": "dji_srt", "blocks": self.blocks, "cues": len(self.cues),
                "styles": dict(self.styles), "with_gps": self.with_gps,
                "with_height": sum(c.rel_alt is not None for c in self.cues),
                "with_gimbal": sum(c.gimbal_pitch is not None for c in self.cues),
                "without_gps": self.without_gps, "unparsed": self.unparsed,
                "out_of_order": self.out_of_order, "glitches": self.glitches,
                "period_s": self.period, "position_decimals": self.decimals, "focal_35mm": self.focal_35mm,
                "timed_by_date": self.timed_by_date,
                "span": [self.cues[0].t, self.cues[-1].t] if self.cues else None}


# ------------------------------------------------------------------------------ parsing
def _decimals(text: str) -> int:
    return len(text.split(".")[1]) if "." in text else 0


def _position(lat: float | None, lon: float | None) -> tuple[float | None, float | None]:
    """A plausible fix, else (None, None): out of range, or 0/0 (no fix yet)."""
    if lat is None or lon is None or not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return None, None
    if abs(lat) < 1e-9 and abs(lon) < 1e-9:
        return None, None
    return lat, lon


def _in(v: float | None, lo_hi: tuple[float, float]) -> float | None:
    return v if v is not None and lo_hi[0] <= v <= lo_hi[1] else None


def _float(text: str | None) -> float | None:
    if text is None:
        return None
    v = float(text)
    return v if math.isfinite(v) else None


def _f(m: re.Match | None, group: int = 1) -> float | None:
    return None if m is None else _float(m.group(group))


def parse_cue_text(text: str, index: int, t: float) -> SrtCue | None:
    """The telemetry of one cue's text (tags removed, lines joined), or None when it names no
    field of any known style (position, height or gimbal)."""
    kv = {k.lower(): v for k, v in _KEY_VALUE.findall(text)}   # "[latitude : 1.5]" -> latitude: "1.5"
    fields: dict = {}
    if _BRACKET_KEYS.intersection(kv):
        style = "bracket"
        lat_s, lon_s = kv.get("latitude"), kv.get("longitude", kv.get("longtitude"))
        fields["lat"], fields["lon"] = _position(_float(lat_s), _float(lon_s))
        if fields["lat"] is not None:
            fields["decimals"] = min(_decimals(lat_s), _decimals(lon_s))
        fields["rel_alt"] = _in(_float(kv.get("rel_alt")), _REL_ALT_RANGE)
        fields["abs_alt"] = _in(_float(kv.get("abs_alt", kv.get("altitude"))), _ALT_RANGE)
        if fields["lat"] is None and fields["abs_alt"] == 0.0:
            fields["abs_alt"] = None   # "[latitude: 0.000000] .. [altitude: 0.000000]": no fix yet
        focal = _float(kv.get("focal_len"))
        if focal is not None and focal > 0:   # Mavic 2 / Air 2S write tenths of a mm: 240 = 24 mm
            fields["focal_35mm"] = focal / 10.0 if focal >= 100.0 else focal
        pitch, roll, yaw = (_float(kv.get(k)) for k in ("gb_pitch", "gb_roll", "gb_yaw"))
        if pitch is not None and -180.0 <= pitch <= 180.0:
            fields.update(gimbal_pitch=pitch, gimbal_roll=roll if roll is not None else 0.0)
        if yaw is not None and -360.0 <= yaw <= 360.0:
            fields["gimbal_yaw"] = yaw
    elif (gps := _GPS.search(text)) is not None:
        third = (gps.group(3) or "").strip()
        a, b = float(gps.group(1)), float(gps.group(2))
        # Matrice: GPS(lat, lon, 0.0M); the others lon first. A first value beyond 90 deg is a
        # longitude, a second one beyond 90 deg is too.
        lat_first = (third.upper().endswith("M") or abs(b) > 90.0) and abs(a) <= 90.0
        lat, lon = (a, b) if lat_first else (b, a)
        style = "gps_lat_lon" if lat_first else "gps_lon_lat"
        fields["lat"], fields["lon"] = _position(lat, lon)
        if fields["lat"] is not None:
            fields["decimals"] = min(_decimals(gps.group(1)), _decimals(gps.group(2)))
        for pattern in _HEIGHT:
            h = _in(_f(pattern.search(text)), _REL_ALT_RANGE)
            if h is not None:
                fields["rel_alt"] = h
                break
        gpry = _GPRY.search(text)
        if gpry:
            fields.update(gimbal_pitch=float(gpry.group(1)), gimbal_roll=float(gpry.group(2)),
                          gimbal_yaw=float(gpry.group(3)))
    else:
        return None
    return SrtCue(index=index, t=float(t), style=style, **fields)


def _blocks(text: str) -> list[list[str]]:
    """Blank-line separated blocks of non-empty, stripped lines."""
    out: list[list[str]] = []
    cur: list[str] = []
    for line in text.splitlines():
        s = line.strip()
        if s:
            cur.append(s)
        elif cur:
            out.append(cur)
            cur = []
    if cur:
        out.append(cur)
    return out


def _date(m: re.Match) -> float | None:
    y, mo, d, hh, mm, ss, frac = m.groups()
    try:
        base = datetime(int(y), int(mo), int(d), int(hh), int(mm), int(ss), tzinfo=timezone.utc).timestamp()
    except ValueError:
        return None
    return base + (int(frac[:3].ljust(3, "0")) / 1000.0 if frac else 0.0)


def parse_srt_text(text: str, name: str = "<srt>") -> SrtTrack:
    """Parse the text of a DJI subtitle file (see the module doc). Never raises on bad content:
    blocks it cannot read are counted (``unparsed``, ``without_gps``), cues whose time goes
    backwards are dropped (``out_of_order``), and an isolated position jump faster than
    150 m/s from both neighbours is removed (``glitches``)."""
    blocks = _blocks(text.replace("\x00", ""))
    track = SrtTrack(path=name, cues=[], blocks=len(blocks))
    raw: list[tuple[float | None, float | None, str, int]] = []   # (cue time, date time, text, index)
    for k, lines in enumerate(blocks):
        start = date = None
        body = []
        for line in lines:
            m = _TIME.search(line) if start is None and "-->" in line else None
            if m:
                h, mi, sec, ms = m.groups()[:4]
                start = int(h) * 3600 + int(mi) * 60 + int(sec) + int(ms.ljust(3, "0")) / 1000.0
                continue
            d = _DATE.search(line) if date is None and line[:1].isdigit() else None
            if d:
                date = _date(d)
            body.append(line)
        raw.append((start, date, _TAG.sub(" ", " ".join(body)), k + 1))
    timed = sum(r[0] is not None for r in raw)
    if timed == 0 and any(r[1] is not None for r in raw):
        t0 = next(r[1] for r in raw if r[1] is not None)
        raw = [(None if d is None else d - t0, d, body, k) for _, d, body, k in raw]
        track.timed_by_date = True
    cues: list[SrtCue] = []
    for t, _, body, k in raw:
        cue = parse_cue_text(body, k, t) if t is not None else None
        if cue is None:
            track.unparsed += 1
            continue
        if cues and cue.t <= cues[-1].t:
            track.out_of_order += 1
            continue
        track.styles[cue.style] += 1
        if cue.lat is None:
            track.without_gps += 1
        cues.append(cue)
    track.cues = _drop_glitches(cues, track)
    return track


def _metres(a: SrtCue, b: SrtCue) -> float:
    dy = math.radians(b.lat - a.lat) * _EARTH_R
    dx = math.radians(b.lon - a.lon) * _EARTH_R * math.cos(math.radians((a.lat + b.lat) / 2))
    return math.hypot(dx, dy)


def _drop_glitches(cues: list[SrtCue], track: SrtTrack) -> list[SrtCue]:
    """Remove the position of a cue that is too far (faster than 150 m/s, plus 50 m) from both
    its neighbours with a fix, while those two agree with each other."""
    fixed = [i for i, c in enumerate(cues) if c.lat is not None]
    bad = set()
    for j in range(len(fixed)):
        i = fixed[j]
        nbrs = [fixed[j + d] for d in (-1, 1) if 0 <= j + d < len(fixed)]
        if not nbrs:
            continue
        far = [_metres(cues[i], cues[n]) > _MAX_SPEED * abs(cues[n].t - cues[i].t) + 50.0 for n in nbrs]
        if all(far) and (len(nbrs) == 1 or _metres(cues[nbrs[0]], cues[nbrs[1]])
                         <= _MAX_SPEED * abs(cues[nbrs[1]].t - cues[nbrs[0]].t) + 50.0):
            bad.add(i)
    track.glitches = len(bad)
    if not bad:
        return cues
    return [replace(c, lat=None, lon=None, decimals=None) if i in bad else c for i, c in enumerate(cues)]


def read_srt(path: str | Path) -> SrtTrack:
    """Read and parse a DJI ``.SRT`` file (UTF-8 with or without BOM; other bytes replaced).

    Raises
    ------
    InputError
        The file cannot be read, or holds no cue of a known style (one clear line naming
        what it holds instead).
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read subtitle telemetry {p}: {exc.strerror or exc}") from None
    text = data.decode("utf-8-sig", errors="replace")
    track = parse_srt_text(text, str(p))
    if not track.cues:
        what = (f"{track.blocks} subtitle block(s)" if track.blocks else "no subtitle blocks")
        raise InputError(f"{p.name}: not DJI telemetry of a known style ({what}, none with a time and a "
                         "position, height or gimbal field)")
    return track


def srt_beside(video: str | Path) -> Path | None:
    """The subtitle file with the video's name beside it (``DJI_0001.SRT`` or ``.srt`` for
    ``DJI_0001.MP4``), or None."""
    v = Path(video)
    if not v.is_file():
        return None
    for suffix in (".SRT", ".srt", ".Srt"):
        cand = v.with_suffix(suffix)
        if cand.is_file():
            return cand
    try:   # any other case of the suffix
        for cand in v.parent.iterdir():
            if cand.stem == v.stem and cand.suffix.lower() == ".srt" and cand.is_file():
                return cand
    except OSError:
        return None
    return None


def is_srt(spec: str | Path) -> bool:
    """True when ``spec`` names a subtitle file by its ending."""
    return str(spec).lower().endswith(SRT_SUFFIXES)
