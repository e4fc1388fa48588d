"""Telemetry of a folder of stills, from the stills themselves (EXIF/XMP) and an optional geo.txt.

:class:`StillsTelemetry` answers ``at(t)`` like a
:class:`~photomap.telemetry.samples.TelemetryBuffer`, so ``TelemetryJoin(tel.at, "log", cfg,
video_start=0.0)`` joins it to the frames of an
:class:`~photomap.drivers.images.ImageFolderSource` unchanged: the samples are keyed by the very
frame times the source gives its stills (EXIF capture times, or ``index / rate``). ``at(t)``
returns the still's own sample at that still's time and nothing in between (stills are seconds
apart: no interpolation, no holding a sample across stills).
"""

from __future__ import annotations

import logging
import math
from bisect import bisect_left
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from photomap.errors import InputError
from photomap.drivers.exif import StillMetadata, median_focal_px, read_still_metadata, still_sample
from photomap.drivers.geotxt import GeoEntry, GeoFile, read_geo_txt
from photomap.telemetry.samples import TelemetrySample, wrap_angle

log = logging.getLogger(__name__)


class StillsTelemetry:
    """One telemetry sample per still, looked up by the still's frame time.

    Parameters
    ----------
    times : sequence of float
        Frame time of each still (``ImageFolderSource.times``), seconds.
    samples : sequence of TelemetrySample or None
        Each still's sample (None: the still tells nothing), in the same order.
    metadata : sequence of StillMetadata, optional
        What was read from each still (for :meth:`summary` and :attr:`focal_px`).
    geo : GeoFile, optional
        The geo.txt that was merged in (for :meth:`summary`).
    tolerance : float
        Seconds. ``at(t)`` answers for the still whose time is within this of ``t``.

    Attributes
    ----------
    focal_px : float or None
        Median focal length in pixels at the stills' resolution (EXIF), or None.
    """

    def __init__(self, times: Sequence[float], samples: Sequence[TelemetrySample | None], *,
                 metadata: Sequence[StillMetadata] = (), geo: GeoFile | None = None,
                 tolerance: float = 1e-3) -> None:
        if len(times) != len(samples):
            raise ValueError(f"{len(times)} times but {len(samples)} samples")
        if tolerance < 0:
            raise ValueError("tolerance must be >= 0")
        self.tolerance = float(tolerance)
        self.metadata = list(metadata)
        self.geo = geo
        self.focal_px = median_focal_px(self.metadata)
        order = sorted(range(len(times)), key=lambda i: float(times[i]))
        self._times: list[float] = []
        self._samples: list[TelemetrySample | None] = []
        self.duplicate_times = 0
        for i in order:
            t = float(times[i])
            if self._times and t - self._times[-1] <= self.tolerance:
                self.duplicate_times += 1   # the first still at a time keeps it
                continue
            self._times.append(t)
            self._samples.append(samples[i])
        self.samples = list(samples)
        if self.duplicate_times:
            log.info("%d still(s) share a capture time with another (capture times of one-second "
                     "resolution?): each still keeps its own telemetry (looked up by still)",
                     self.duplicate_times)

    def of_frame(self, frame) -> TelemetrySample | None:
        """The sample of the still a frame of the folder's source is (``frame.index``: its place
        in the folder), whatever its time: stills that share a capture time keep their own."""
        k = int(frame.index)
        return self.samples[k] if 0 <= k < len(self.samples) else None

    def at(self, t: float) -> TelemetrySample | None:
        """The sample of the still taken at ``t`` (within ``tolerance``; of stills sharing a time,
        the first), else None."""
        k = bisect_left(self._times, float(t) - self.tolerance)
        if k < len(self._times) and abs(self._times[k] - t) <= self.tolerance:
            return self._samples[k]
        return None

    @property
    def usable(self) -> bool:
        """True when any still has a GPS position or an altitude (AMSL or above take-off)."""
        return any(s is not None and (s.lat is not None or s.alt is not None
                                      or s.relative_alt is not None) for s in self.samples)

    def summary(self) -> dict:
        """What the stills carried: counts of stills with each kind of telemetry (run.json)."""
        got = [s for s in self.samples if s is not None]
        tilts = [math.degrees(math.acos(max(-1.0, min(1.0, math.cos(s.roll) * math.cos(s.pitch)))))
                 for s in got if s.roll is not None and s.pitch is not None]
        out = {
            "source": "stills" + ("+geo.txt" if self.geo is not None else ""),
            "stills": len(self.samples),
            "with_time": sum(m.time is not None for m in self.metadata),
            "with_gps": sum(s.lat is not None for s in got),
            "with_altitude": sum(s.alt is not None for s in got),
            "with_height": sum(s.height_above_ground is not None for s in got),
            "with_rangefinder": sum(s.height_source == "rangefinder" for s in got),
            "with_attitude": sum(s.yaw is not None for s in got),
            "with_tilt": len(tilts),
            "max_tilt_deg": round(max(tilts), 3) if tilts else None,
            "with_focal": sum(m.focal_px is not None for m in self.metadata),
            "focal_px": self.focal_px,
            "focal_source": _most_common([m.focal_source for m in self.metadata]),
            "duplicate_times": self.duplicate_times,
            "problems": sum(bool(m.problems) for m in self.metadata),
        }
        if self.geo is not None:
            matched = sum(self.geo.find(m.name) is not None for m in self.metadata)
            out["geo_txt"] = {"file": self.geo.path, "projection": self.geo.projection,
                              "entries": len(self.geo.entries), "matched": matched,
                              "bad_lines": len(self.geo.bad_lines)}
        return out


def _most_common(values: list[str | None]) -> str | None:
    present = [v for v in values if v]
    return max(set(present), key=present.count) if present else None


def merge_geo(meta: StillMetadata, sample: TelemetrySample | None, entry: GeoEntry | None,
              t: float) -> TelemetrySample | None:
    """A still's sample with its geo.txt line applied: the line's position (and altitude, and
    attitude when it gives one) replace the EXIF ones; the height above take-off stays."""
    if entry is None:
        return sample
    base = sample if sample is not None else TelemetrySample(t=float(t))
    fields = {"lat": entry.lat, "lon": entry.lon}
    if entry.alt is not None:
        fields["alt"] = entry.alt
    if entry.yaw is not None:   # OpenDroneMap: yaw of image up from north, pitch 0 = nadir
        fields.update(yaw=wrap_angle(math.radians(entry.yaw)),
                      pitch=wrap_angle(math.radians(entry.pitch)),
                      roll=wrap_angle(math.radians(entry.roll)))
    return replace(base, **fields)


def read_stills_telemetry(paths: Sequence[str | Path], times: Sequence[float], *,
                          geo: str | Path | GeoFile | None = None,
                          tolerance: float = 1e-3) -> StillsTelemetry:
    """Read every still's metadata and build its sample at its frame time.

    Parameters
    ----------
    paths, times
        The stills and their frame times, in the same order (``ImageFolderSource.paths`` and
        ``.times``).
    geo : path or GeoFile, optional
        An OpenDroneMap geo.txt whose positions override the stills' EXIF GPS.
    tolerance : float
        See :class:`StillsTelemetry`.

    Raises
    ------
    InputError
        ``geo`` cannot be read or names an unsupported projection.
    """
    if len(paths) != len(times):
        raise ValueError(f"{len(paths)} stills but {len(times)} times")
    geo_file = read_geo_txt(geo) if isinstance(geo, (str, Path)) else geo
    metas = [read_still_metadata(p) for p in paths]
    samples = []
    for meta, t in zip(metas, times):
        sample = still_sample(meta, t)
        entry = geo_file.find(meta.name) if geo_file is not None else None
        samples.append(merge_geo(meta, sample, entry, t))
    problems = [m for m in metas if m.problems]
    if problems:
        log.info("%d of %d stills have unreadable metadata fields (first: %s: %s)", len(problems),
                 len(metas), problems[0].name, "; ".join(problems[0].problems))
    if geo_file is not None:
        unmatched = [m.name for m in metas if geo_file.find(m.name) is None]
        if unmatched:
            log.warning("geo.txt %s: no line for %d of %d stills (first: %s)", geo_file.path,
                        len(unmatched), len(metas), unmatched[0])
    return StillsTelemetry(times, samples, metadata=metas, geo=geo_file, tolerance=tolerance)


def stills_telemetry_for(source, *, geo: str | Path | GeoFile | None = None) -> StillsTelemetry:
    """:func:`read_stills_telemetry` for an :class:`~photomap.drivers.images.ImageFolderSource`
    (its ``paths`` and ``times``)."""
    return read_stills_telemetry(source.paths, source.times, geo=geo)


def open_stills_telemetry(source, *, geo: str | Path | GeoFile | None = None) -> StillsTelemetry | None:
    """The stills' own telemetry for a replay without MAVLink, or None.

    None when ``source`` is not a folder of stills (it has no ``paths`` and ``times``), or when
    no still has a GPS position or an altitude (EXIF/XMP, or a line of ``geo``). Logs one line
    saying what the stills carry.

    Raises
    ------
    InputError
        ``geo`` is given for a source that is not a folder of stills, or cannot be read.
    """
    if not hasattr(source, "paths") or not hasattr(source, "times"):
        if geo is not None:
            raise InputError("a geo.txt gives positions to still images: the input is not a folder of stills")
        return None
    tel = stills_telemetry_for(source, geo=geo)
    s = tel.summary()
    if not tel.usable:
        log.info("the %d stills carry no GPS or altitude: mapping by vision alone", s["stills"])
        return None
    focal = f"{s['focal_px']:.1f} px ({s['focal_source']})" if s["focal_px"] else "unknown"
    ranged = f" ({s['with_rangefinder']} by laser range finder)" if s["with_rangefinder"] else " above take-off"
    log.info("telemetry from the stills (%s): %d of %d with GPS, %d with height%s, "
             "%d with attitude; focal length %s", s["source"], s["with_gps"], s["stills"],
             s["with_height"], ranged, s["with_attitude"], focal)
    return tel
