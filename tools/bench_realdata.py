"""Real imagery that nobody on the team produced: does it map into one piece? (issue 10)

For each shared real set (``$PHOTOMAP_DATA`` or ``../shared/data``: Brighton Beach DJI stills,
Seneca near-infrared fixed-wing stills), ``photomap replay`` maps the stills by vision alone and
with their GPS (a ``geo.txt`` written from the set's ``poses.csv``, with the gimbal yaw where the
set has one), and the tool reports:

- segments, the stills in the largest map, consecutive pairs that truly overlap (by GPS distance)
  and how many of them were linked, and by which method (``trajectory.csv`` ``method``);
- the GPS fit: the RMS (metres) of the frame centres of the largest map against the stills' GPS
  after the best similarity (scale, rotation, shift), i.e. how well the map's geometry agrees;
- a thumbnail of each map in ``docs/realdata/``.

    python -m tools.bench_realdata [--out docs/benchmarks.md] [--sets brighton seneca]

Prints a markdown table; with --out, replaces the section between the realdata markers.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import math
import os
import platform
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.geo.georef import enu_from_latlon
from photomap.geometry import similarity_fit
from photomap.io.trajectory_files import read_trajectory_csv
from tools.report import replace_section

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("PHOTOMAP_DATA") or REPO.parent / "shared" / "data")
THUMBS = REPO / "docs" / "realdata"


@dataclass(frozen=True)
class RealSet:
    name: str
    folder: str
    overlap_m: float  # consecutive stills closer than this (GPS) share ground
    note: str


SETS = {
    "brighton": RealSet("brighton", "brighton_beach", 27.0,
                        "18 DJI stills, 40 m, three lawn-mower strips (one over forest), ~65 % forward overlap"),
    "seneca": RealSet("seneca", "seneca_nir", 45.0,
                      "17 NIR fixed-wing stills, bare fields, 5-20 deg rotation, two strips and a turn"),
}


def read_poses(folder: Path) -> list[dict]:
    with open(folder / "poses.csv", newline="") as f:
        return list(csv.DictReader(f))


def write_geo_txt(path: Path, poses: list[dict]) -> None:
    """OpenDroneMap's geo.txt (EPSG:4326) from poses.csv: lon lat alt [yaw pitch roll]."""
    lines = ["EPSG:4326"]
    for p in poses:
        name = Path(p["file"]).stem + ".jpg"
        line = f"{name} {float(p['lon']):.8f} {float(p['lat']):.8f} {float(p['gps_alt']):.3f}"
        if p.get("gimbal_yaw"):
            # ODM angles: yaw 0 = image top north; pitch 0 = nadir (DJI gimbal pitch -90)
            line += f" {float(p['gimbal_yaw']):.2f} {float(p['gimbal_pitch']) + 90.0:.2f} {float(p['gimbal_roll']):.2f}"
        lines.append(line)
    path.write_text("\n".join(lines) + "\n")


def gps_fit_rms(rows, poses: list[dict], segment: int) -> tuple[float | None, int]:
    """RMS (m) of the segment's frame centres against GPS after the best similarity; and the count."""
    pts = [(r.xy, poses[r.frame]) for r in rows if r.glued and r.segment == segment and r.xy is not None]
    if len(pts) < 3:
        return None, len(pts)
    lat = np.array([float(p["lat"]) for _, p in pts])
    lon = np.array([float(p["lon"]) for _, p in pts])
    east, north = enu_from_latlon(lat, lon, float(lat[0]), float(lon[0]))
    src = np.array([xy for xy, _ in pts], float)
    dst = np.c_[east, -north]  # map px have y down: fit to (east, south) to keep a proper similarity
    m = similarity_fit(src, dst)
    res = src @ m[:, :2].T + m[:, 2] - dst
    return float(np.sqrt((res ** 2).sum(axis=1).mean())), len(pts)


def thumbnail(png: Path, out: Path, px: int = 480) -> None:
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    if image is None:
        return
    f = px / max(image.shape[:2])
    small = cv2.resize(image, None, fx=f, fy=f, interpolation=cv2.INTER_AREA) if f < 1 else image
    if small.shape[2] == 4:  # on white, so that the page shows the map's outline
        a = small[..., 3:4].astype(np.float32) / 255.0
        small = (small[..., :3] * a + 255 * (1 - a)).astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), small)


def run_set(spec: RealSet, mode: str, work: Path) -> dict:
    folder = DATA / spec.folder
    poses = read_poses(folder)
    geo = None
    if mode == "gps":
        geo = work / "geo.txt"
        write_geo_txt(geo, poses)
    out = work / f"{spec.name}-{mode}"
    summary = replay(str(folder / "images"), out, load_config(), geo=str(geo) if geo else None)
    rows = read_trajectory_csv(out / "trajectory.csv")
    counts: dict[int, int] = {}
    for r in rows:
        if r.glued:
            counts[r.segment] = counts.get(r.segment, 0) + 1
    main = max(counts, key=counts.get) if counts else 0
    overlapping = linked = 0
    methods: dict[str, int] = {}
    for a, b in zip(rows, rows[1:]):
        pa, pb = poses[a.frame], poses[b.frame]
        lat0 = math.radians(float(pa["lat"]))
        d = math.hypot((float(pb["lat"]) - float(pa["lat"])) * 111_320.0,
                       (float(pb["lon"]) - float(pa["lon"])) * 111_320.0 * math.cos(lat0))
        if d >= spec.overlap_m:
            continue
        overlapping += 1
        if a.glued and b.glued and a.segment == b.segment:
            linked += 1
            method = b.extra.get("method") or "ifmi"
            methods[method] = methods.get(method, 0) + 1
    rms, n_fit = gps_fit_rms(rows, poses, main)
    geo_rms = (summary.get("georeference") or {}).get("gps_rms_m")
    thumb = THUMBS / f"{spec.name}_{mode}.png"
    mosaics = summary.get("mosaics") or []
    if mosaics:
        thumbnail(out / mosaics[0]["file"], thumb)
    return {"set": spec.name, "mode": mode, "stills": len(rows), "registered": summary["registered"],
            "segments": summary["segments"], "largest": counts.get(main, 0),
            "pairs": f"{linked}/{overlapping}", "methods": ", ".join(f"{k} {v}" for k, v in sorted(methods.items())),
            "gps_fit_rms_m": rms, "georeference_rms_m": geo_rms,
            "telemetry": (summary.get("telemetry") or {}).get("status"),
            "thumbnail": thumb.relative_to(REPO).as_posix() if thumb.exists() else None}


def table(results: list[dict]) -> str:
    def f(v, spec=".2f"):
        return "-" if v is None else format(v, spec)
    lines = ["| set | telemetry | stills | segments | largest map | overlapping pairs linked | by | "
             "GPS fit RMS of the largest map (m) | georeference RMS (m) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['set']} | {r['mode']} | {r['stills']} | {r['segments']} | {r['largest']} | "
                     f"{r['pairs']} | {r['methods'] or '-'} | {f(r['gps_fit_rms_m'])} | {f(r['georeference_rms_m'])} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    parser.add_argument("--out", type=Path, help="markdown report to update (section 'realdata')")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-realdata-") as tmp:
        for name in args.sets:
            if not (DATA / SETS[name].folder).is_dir():
                print(f"skipping {name}: {DATA / SETS[name].folder} not found (set PHOTOMAP_DATA)")
                continue
            for mode in ("vision", "gps"):
                work = Path(tmp) / f"{name}-{mode}"
                work.mkdir()
                results.append(run_set(SETS[name], mode, work))
    body = table(results)
    print(body)
    if args.out:
        sets = "\n".join(f"- **{s.name}** (`{s.folder}`): {s.note}." for s in SETS.values() if s.name in args.sets)
        thumbs = "\n".join(f"![{r['set']} {r['mode']}]({Path(r['thumbnail']).relative_to('docs').as_posix()})"
                           for r in results if r["thumbnail"])
        text = (f"## Real data\n\nWritten by `python -m tools.bench_realdata --out docs/benchmarks.md` "
                f"({datetime.date.today().isoformat()}, {platform.machine()}, default config). "
                f"*vision*: no telemetry; *gps*: the stills' positions (and DJI gimbal yaw) as a geo.txt "
                f"(`--geo`). Overlapping pairs: consecutive stills closer than the set's threshold by "
                f"GPS. GPS fit RMS: frame centres of the largest map against GPS after the best similarity.\n\n"
                f"{sets}\n\n{body}\n\n{thumbs}\n")
        replace_section(args.out, "realdata", text)


if __name__ == "__main__":
    main()
