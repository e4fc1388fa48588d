"""Real-valued survey-still fixtures: shared stills with EXIF (and DJI XMP) written back from
``poses.csv`` with Pillow (the shared stills were stripped of their metadata when downscaled)."""

from __future__ import annotations

import csv
from pathlib import Path

from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

DJI_NS = "http://www.dji.com/drone-dji/1.0/"


def read_poses(folder: Path) -> list[dict[str, str]]:
    with open(folder / "poses.csv", newline="") as f:
        return list(csv.DictReader(f))


def dms(deg: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    """|deg| as EXIF degrees, minutes and seconds (micro-arcsecond rationals, like DJI's)."""
    a = abs(deg)
    d = int(a)
    m = int((a - d) * 60.0)
    s = (a - d - m / 60.0) * 3600.0
    return IFDRational(d, 1), IFDRational(m, 1), IFDRational(round(s * 1_000_000), 1_000_000)


def dji_xmp(row: dict[str, str]) -> bytes:
    """A DJI-style XMP packet (attributes of rdf:Description, as DJI writes them) from a row."""
    attrs = {
        "AbsoluteAltitude": row["gps_alt"], "RelativeAltitude": row["rel_alt"],
        "GimbalRollDegree": row["gimbal_roll"], "GimbalYawDegree": row["gimbal_yaw"],
        "GimbalPitchDegree": row["gimbal_pitch"], "FlightRollDegree": row["flight_roll"],
        "FlightYawDegree": row["flight_yaw"], "FlightPitchDegree": row["flight_pitch"],
    }
    body = "\n".join(f'   drone-dji:{k}="{v}"' for k, v in attrs.items() if v != "")
    return (f'<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            f'<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            f' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            f'  <rdf:Description rdf:about="DJI Meta Data"\n'
            f'    xmlns:tiff="http://ns.adobe.com/tiff/1.0/"\n'
            f'    xmlns:drone-dji="{DJI_NS}"\n'
            f'   tiff:Make="DJI"\n   tiff:Model="{row["model"]}"\n{body}>\n'
            f'  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>\n'
            f'<?xpacket end="w"?>').encode("utf-8")


def exif_from_row(row: dict[str, str], *, make: str) -> Image.Exif:
    exif = Image.Exif()
    exif[0x010F] = make
    exif[0x0110] = row["model"]
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    sub[0x9003] = row["datetime"]
    sub[0x920A] = IFDRational(round(float(row["focal_mm"]) * 100), 100)
    sub[0xA002] = int(row["width"])
    sub[0xA003] = int(row["height"])
    lat, lon = float(row["lat"]), float(row["lon"])
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    gps.update({0: b"\x02\x03\x00\x00", 1: "N" if lat >= 0 else "S", 2: dms(lat),
                3: "E" if lon >= 0 else "W", 4: dms(lon), 5: b"\x00",
                6: IFDRational(round(float(row["gps_alt"]) * 1000), 1000)})
    return exif


def write_still(src: Path, dst: Path, row: dict[str, str], *, make: str, xmp: bool) -> Path:
    """``src`` re-saved as a JPEG at ``dst`` carrying ``row``'s EXIF (and DJI XMP)."""
    with Image.open(src) as im:
        im.load()
        extra = {"xmp": dji_xmp(row)} if xmp else {}
        im.save(dst, "JPEG", quality=95, exif=exif_from_row(row, make=make), **extra)
    return dst


def brighton_folder(data: Path, out: Path, count: int | None = None) -> tuple[Path, list[dict]]:
    """Brighton Beach stills with DJI EXIF + XMP from poses.csv in ``out``; returns (out, rows)."""
    rows = read_poses(data)[:count]
    out.mkdir(parents=True, exist_ok=True)
    for row in rows:
        name = Path(row["file"]).stem
        write_still(data / "images" / f"{name}.jpg", out / f"{name}.JPG", row, make="DJI", xmp=True)
    return out, rows


def seneca_folder(data: Path, out: Path, count: int | None = None) -> tuple[Path, list[dict]]:
    """Seneca NIR stills with their Canon EXIF (GPS, no attitude) from poses.csv in ``out``."""
    rows = read_poses(data)[:count]
    out.mkdir(parents=True, exist_ok=True)
    for row in rows:
        src = data / "images" / row["file"]
        write_still(src, out / row["file"], row, make="Canon", xmp=False)
    return out, rows


def noisy_geo_txt(stills: Path, path: Path, sigma_m: float, seed: int = 0) -> Path:
    """An OpenDroneMap geo.txt for the JPEG stills in ``stills``: each still's EXIF GPS position
    moved by Gaussian noise of ``sigma_m`` metres east and north (a consumer GPS)."""
    import math

    import numpy as np

    from photomap.drivers.exif import read_still_metadata

    rng = np.random.default_rng(seed)
    lines = ["EPSG:4326\n"]
    for still in sorted(stills.glob("*.jpg")):
        m = read_still_metadata(still)
        de, dn = rng.normal(0.0, sigma_m, 2)
        lat = m.lat + math.degrees(dn / 6_378_137.0)
        lon = m.lon + math.degrees(de / (6_378_137.0 * math.cos(math.radians(m.lat))))
        lines.append(f"{still.name} {lon:.9f} {lat:.9f} {m.alt:.3f}\n")
    path.write_text("".join(lines))
    return path
