"""Survey stills carry their own telemetry: EXIF GPS/time/focal, DJI XMP, ODM geo.txt.

Fixtures are real-valued: the shared stills (stripped of their metadata when downscaled) get
their original EXIF and DJI XMP back from ``poses.csv``, written with Pillow, and are read back.
"""

from __future__ import annotations

import io
import math
import warnings

import cv2
import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from conftest import shared_data
from stills_fixtures import brighton_folder, dji_xmp, read_poses, seneca_folder

from photomap.config import load_config
from photomap.drivers.exif import (StillMetadata, camera_attitude, focal_length_px, parse_dji_xmp,
                                   parse_exif_datetime, read_still_metadata, still_sample)
from photomap.drivers.geotxt import parse_geo_txt, read_geo_txt
from photomap.drivers.images import ImageFolderSource, exif_time
from photomap.drivers.stills_telemetry import (StillsTelemetry, merge_geo, open_stills_telemetry,
                                               read_stills_telemetry, stills_telemetry_for)
from photomap.errors import InputError
from photomap.geo.georef import nadir_pixel, utm_epsg, utm_forward
from photomap.io.trajectory_files import read_trajectory_csv
from photomap.mapping.pipeline import MappingPipeline
from photomap.mapping.telemetry_join import TelemetryJoin
from photomap.telemetry.samples import TelemetrySample

FC300S_SENSOR_MM = 6.16     # OpenSfM sensor_data.json, "DJI FC300S"
ELPH300_SENSOR_MM = 6.16    # OpenSfM sensor_data.json, "Canon PowerShot ELPH 300 HS"


def wrapped(deg: float) -> float:
    return math.remainder(math.radians(deg), 2 * math.pi)


@pytest.fixture(scope="module")
def brighton(tmp_path_factory):
    return brighton_folder(shared_data("brighton_beach"), tmp_path_factory.mktemp("brighton"))


@pytest.fixture(scope="module")
def seneca(tmp_path_factory):
    return seneca_folder(shared_data("seneca_nir"), tmp_path_factory.mktemp("seneca"), count=6)


# --------------------------------------------------------------------------- real stills, read back

def test_brighton_exif_and_dji_xmp_read_back(brighton):
    folder, rows = brighton
    for row in rows:
        meta = read_still_metadata(folder / row["file"])
        assert meta.problems == ()
        assert meta.lat == pytest.approx(float(row["lat"]), abs=1e-6)
        assert meta.lon == pytest.approx(float(row["lon"]), abs=1e-6)
        assert meta.alt == pytest.approx(float(row["gps_alt"]), abs=1e-3)
        assert meta.relative_alt == pytest.approx(float(row["rel_alt"]))
        assert meta.time == parse_exif_datetime(row["datetime"])
        assert (meta.gimbal_yaw, meta.gimbal_pitch, meta.flight_yaw) == pytest.approx(
            (float(row["gimbal_yaw"]), float(row["gimbal_pitch"]), float(row["flight_yaw"])))
        # FocalLength 3.61 mm on the FC300S's 6.16 mm wide sensor, at the stills' 1000 px
        assert (meta.width, meta.height) == (1000, 562)
        assert meta.focal_source == "sensor_table"
        assert meta.focal_px == pytest.approx(3.61 / FC300S_SENSOR_MM * 1000)

        s = still_sample(meta)
        assert s.t == meta.time
        assert (s.lat, s.lon, s.alt) == (meta.lat, meta.lon, meta.alt)
        assert (s.height_above_ground, s.height_source) == (meta.relative_alt, "home")
        # the camera's heading is the gimbal's, not the airframe's; -89.9 deg is 0.1 deg of tilt
        assert s.yaw == pytest.approx(wrapped(float(row["gimbal_yaw"])), abs=1e-12)
        assert s.pitch == pytest.approx(math.radians(float(row["gimbal_pitch"]) + 90.0), abs=1e-12)
        assert s.roll == pytest.approx(math.radians(float(row["gimbal_roll"])), abs=1e-12)


def test_brighton_fixture_agrees_with_the_original_file(brighton):
    """DroneDB's binding tests read the original DJI_0023.JPG of this data set
    (DroneDB/test_data, test-datasets/drone_dataset_brighton_beach): capture time
    1466699554 s, cameraYaw 43.8, cameraPitch -89.9, FocalLengthIn35mmFilm 20, 4000 x 2250."""
    folder, _ = brighton
    s = still_sample(read_still_metadata(folder / "DJI_0023.JPG"))
    assert s.t == 1466699554.0
    assert math.degrees(s.yaw) == pytest.approx(43.8)
    assert math.degrees(s.pitch) == pytest.approx(-89.9 + 90.0)
    # the camera's own 35 mm equivalent (written for its 4:3 mode) underestimates the 16:9
    # stills' focal length by 10 %: the sensor width is preferred when it is known
    fx35, _ = focal_length_px(4000, 2250, focal_35mm=20.0)
    fx, source = focal_length_px(4000, 2250, focal_mm=3.61, focal_35mm=20.0, sensor_mm=FC300S_SENSOR_MM)
    assert source == "sensor_table" and fx == pytest.approx(2344.2, abs=0.1)
    assert fx35 / fx == pytest.approx(0.905, abs=0.005)


def test_seneca_gps_without_attitude_or_height(seneca):
    folder, rows = seneca
    for row in rows:
        meta = read_still_metadata(folder / row["file"])
        assert meta.lat == pytest.approx(float(row["lat"]), abs=1e-6)
        assert meta.lon == pytest.approx(float(row["lon"]), abs=1e-6)
        assert meta.alt == pytest.approx(float(row["gps_alt"]), abs=1e-3)
        assert meta.focal_px == pytest.approx(4.30 / ELPH300_SENSOR_MM * 900)
        s = still_sample(meta)
        assert s is not None and s.lat == meta.lat
        assert s.yaw is s.roll is s.pitch is s.height_above_ground is s.relative_alt is None


# --------------------------------------------------------------------------- the stills' telemetry

def test_stills_telemetry_answers_only_at_the_stills_times(brighton):
    folder, rows = brighton
    src = ImageFolderSource(folder)
    assert src.exif_times
    tel = stills_telemetry_for(src)
    assert tel.usable
    for t, row in zip(src.times, rows):
        s = tel.at(t)
        assert s.t == t and s.lat == pytest.approx(float(row["lat"]), abs=1e-6)
        assert tel.at(t + 0.0005) is s          # within the tolerance
        assert tel.at(t + 3.5) is None          # between stills: nothing, no interpolation
    assert tel.at(src.times[0] - 60.0) is None and tel.at(src.times[-1] + 60.0) is None
    summary = tel.summary()
    assert summary["source"] == "stills"
    for key in ("stills", "with_time", "with_gps", "with_altitude", "with_height", "with_attitude",
                "with_tilt", "with_focal"):
        assert summary[key] == 18, key
    assert summary["max_tilt_deg"] == pytest.approx(0.1, abs=1e-6)
    assert summary["focal_px"] == pytest.approx(3.61 / FC300S_SENSOR_MM * 1000)
    assert summary["duplicate_times"] == 0 and summary["problems"] == 0


def test_telemetry_join_uses_the_stills_telemetry_unchanged(brighton):
    folder, rows = brighton
    src = ImageFolderSource(folder)
    tel = stills_telemetry_for(src)
    cfg = load_config().updated({"camera": {"fx_px": tel.focal_px}})
    join = TelemetryJoin(tel.at, "log", cfg, video_start=0.0)
    frames = list(src)
    samples = [join.sample(f) for f in frames]
    assert join.stats.frames_with_telemetry == 18
    a, b = samples[6], samples[7]   # DJI_0024 -> DJI_0025: gimbal yaw -140 -> -132
    prior = join.prior(a, b)
    assert prior.angle_deg == pytest.approx(8.0)
    assert prior.scale == pytest.approx(float(rows[7]["rel_alt"]) / float(rows[6]["rel_alt"]))
    assert join.focal(1000) == pytest.approx(586.04, abs=0.01)
    # 0.1 deg of tilt is below the rectification threshold: the frame is left as it is
    assert join.rectify(frames[0].image, samples[0]) is frames[0].image


def test_pipeline_gets_metric_scale_from_the_stills(brighton, tmp_path):
    """No MAVLink, no camera config: the stills' relative altitude and focal length give the
    map's metres per pixel, and map distances agree with the GPS distances between stills."""
    folder, rows = brighton
    src = ImageFolderSource(folder)
    tel = stills_telemetry_for(src)
    cfg = load_config().updated({"camera": {"fx_px": tel.focal_px}})
    join = TelemetryJoin(tel.at, "stills", cfg, link_summary=tel.summary)
    summary = MappingPipeline(src, cfg, tmp_path, telemetry=join).run()
    mpp = summary["metres_per_pixel"]
    assert mpp == pytest.approx(40.0 / (3.61 / FC300S_SENSOR_MM * 1000), rel=0.01)
    assert summary["telemetry"]["link"]["source"] == "stills"
    assert summary["telemetry"]["frames_with_telemetry"] == 18
    traj = read_trajectory_csv(tmp_path / "trajectory.csv")
    ratios = []
    for p, q in zip(traj, traj[1:]):
        if not (p.glued and q.glued and p.segment == q.segment and q.status == "registered"):
            continue
        if p.frame < 6:  # DJI_0018-0023 fly over forest: the canopy stands well above the ground
            continue     # (parallax), so map distances there say little about the camera model
        ra, rb = rows[p.frame], rows[q.frame]
        lat0 = math.radians(float(ra["lat"]))
        north = (float(rb["lat"]) - float(ra["lat"])) * 111_320.0
        east = (float(rb["lon"]) - float(ra["lon"])) * 111_320.0 * math.cos(lat0)
        centre = np.array([499.5, 280.5, 1.0])
        d_px = np.linalg.norm(np.asarray(q.M) @ centre - np.asarray(p.M) @ centre)
        ratios.append(d_px * mpp / math.hypot(north, east))
    # consumer GPS over 13-14 m steps: single pairs within 20 %; the median within 5 % (the
    # height is above take-off, not above the beach: measured 1.02-1.035 depending on the pairs)
    assert len(ratios) >= 5
    assert np.median(ratios) == pytest.approx(1.0, abs=0.05)
    assert np.all(np.abs(np.array(ratios) - 1.0) < 0.2), ratios


def test_open_stills_telemetry_only_when_the_stills_say_where(tmp_path):
    plain = tmp_path / "plain"
    plain.mkdir()
    for i in range(3):
        (plain / f"f{i}.jpg").write_bytes(jpeg_bytes(Image.Exif()))
    src = ImageFolderSource(plain)
    assert open_stills_telemetry(src) is None                # nothing to join: vision alone
    geo = tmp_path / "geo.txt"
    geo.write_text("EPSG:4326\nf0.jpg 10 45 100\nf1.jpg 10.0001 45 100\n")
    tel = open_stills_telemetry(src, geo=geo)
    assert tel is not None and tel.summary()["with_gps"] == 2
    assert tel.at(src.times[2]) is None                       # f2 has no line: no sample

    class Video:   # any source without stills
        pass

    assert open_stills_telemetry(Video()) is None
    with pytest.raises(InputError, match="not a folder of stills"):
        open_stills_telemetry(Video(), geo=geo)


def test_duplicate_capture_times_keep_the_first_still():
    a, b = TelemetrySample(t=10.0, yaw=0.1), TelemetrySample(t=10.0, yaw=0.2)
    tel = StillsTelemetry([10.0, 10.0, 12.0], [a, b, None])
    assert tel.duplicate_times == 1 and tel.at(10.0) is a and tel.at(12.0) is None
    assert not tel.usable


# --------------------------------------------------------------------------- geo.txt

def geo_lines(rows: list[dict], fmt) -> str:
    return "\n".join(fmt(r) for r in rows)


def test_geo_txt_gives_the_stripped_shared_stills_their_gps(tmp_path):
    data = shared_data("brighton_beach")
    rows = read_poses(data)
    geo = tmp_path / "geo.txt"
    geo.write_text("EPSG:4326\n# name lon lat alt\n"
                   + geo_lines(rows, lambda r: f"{r['file']} {r['lon']} {r['lat']} {r['gps_alt']}") + "\n")
    src = ImageFolderSource(data / "images")   # lower-case .jpg, no EXIF: timed by index
    assert not src.exif_times
    tel = read_stills_telemetry(src.paths, src.times, geo=geo)
    assert tel.usable
    for t, row in zip(src.times, rows):
        s = tel.at(t)
        assert s.lat == pytest.approx(float(row["lat"]), abs=1e-6)
        assert s.lon == pytest.approx(float(row["lon"]), abs=1e-6)
        assert s.alt == pytest.approx(float(row["gps_alt"]))
        assert s.yaw is None and s.height_above_ground is None
    summary = tel.summary()
    assert summary["source"] == "stills+geo.txt" and summary["with_gps"] == 18
    assert summary["geo_txt"]["matched"] == 18 and summary["geo_txt"]["bad_lines"] == 0


@pytest.mark.parametrize("header", ["WGS84 UTM 15N", "EPSG:32615",
                                   "+proj=utm +zone=15 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"])
def test_geo_txt_in_utm(header):
    rows = read_poses(shared_data("brighton_beach"))
    lat = np.array([float(r["lat"]) for r in rows])
    lon = np.array([float(r["lon"]) for r in rows])
    assert utm_epsg(lat[0], lon[0]) == 32615
    e, n = utm_forward(lat, lon, 32615)
    text = header + "\n" + "\n".join(f"{r['file']} {x:.4f} {y:.4f} {r['gps_alt']}" for r, x, y in zip(rows, e, n))
    geo = parse_geo_txt(text)
    for r, la, lo in zip(rows, lat, lon):
        entry = geo.find(r["file"])
        assert entry.lat == pytest.approx(la, abs=1e-7) and entry.lon == pytest.approx(lo, abs=1e-7)


def test_geo_txt_the_opendronemap_docs_example():
    """The example of OpenDroneMap's docs (geo.rst) is two Brighton Beach stills."""
    geo = parse_geo_txt("EPSG:4326\n"
                        "DJI_0028.JPG -91.9942096111111 46.84252125 198.609\n"
                        "DJI_0032.JPG -91.9938293055556 46.8424584444444 198.609\n")
    rows = {r["file"]: r for r in read_poses(shared_data("brighton_beach"))}
    for name in ("DJI_0028.JPG", "DJI_0032.JPG"):
        entry, row = geo.find(name), rows[name]
        assert entry.lat == pytest.approx(float(row["lat"]), abs=1e-6)
        assert entry.lon == pytest.approx(float(row["lon"]), abs=1e-6)
        assert entry.alt == pytest.approx(float(row["gps_alt"]))
    assert geo.find("dji_0028.jpg") is geo.find("DJI_0028.png") is geo.entries["DJI_0028.JPG"]


def test_geo_txt_angles_accuracies_and_bad_lines():
    geo = parse_geo_txt("EPSG:4326\n"
                        "a.jpg 10.5 45.25 100 30 2 -1 0.02 0.05 label\n"
                        "b.jpg 10.5 45.25 100 0 0 0\n"
                        "c.jpg 10.5 45.25\n"
                        "d.jpg ten 45.25\n"
                        "e.jpg 10.5\n"
                        "f.jpg 10.5 95.0\n"
                        "\n# comment\n")
    a = geo.find("a.jpg")
    assert (a.lat, a.lon, a.alt, a.yaw, a.pitch, a.roll) == (45.25, 10.5, 100.0, 30.0, 2.0, -1.0)
    assert (a.horizontal_accuracy, a.vertical_accuracy) == (0.02, 0.05)
    assert geo.find("b.jpg").yaw is None           # 0 0 0: "not available" in OpenDroneMap
    assert geo.find("c.jpg").alt is None
    assert geo.bad_lines == [5, 6, 7]
    meta = StillMetadata(name="a.jpg", relative_alt=50.0, time=1.0)
    s = merge_geo(meta, still_sample(meta), a, 1.0)
    assert (s.lat, s.lon, s.alt, s.height_above_ground) == (45.25, 10.5, 100.0, 50.0)
    assert (s.yaw, s.pitch, s.roll) == pytest.approx((math.radians(30), math.radians(2), math.radians(-1)))


def test_geo_txt_errors_are_one_line(tmp_path):
    with pytest.raises(InputError, match="not supported"):
        parse_geo_txt("EPSG:3857\na.jpg 1 2\n")
    with pytest.raises(InputError, match="not supported"):
        parse_geo_txt("+proj=utm +zone=15 +ellps=GRS80\na.jpg 1 2\n")
    with pytest.raises(InputError, match="empty"):
        parse_geo_txt("\n# nothing\n")
    with pytest.raises(InputError, match="not readable"):
        read_geo_txt(tmp_path / "missing.txt")


# --------------------------------------------------------------------------- broken metadata

def jpeg_bytes(exif: Image.Exif | None = None, xmp: bytes | None = None, size=(64, 48)) -> bytes:
    buf = io.BytesIO()
    kwargs = {}
    if exif is not None:
        kwargs["exif"] = exif
    if xmp is not None:
        kwargs["xmp"] = xmp
    Image.new("RGB", size, (90, 120, 60)).save(buf, "JPEG", **kwargs)
    return buf.getvalue()


def gps_exif(lat_ref="N", lon_ref="E", lat=(46, 50, 33.38), lon=(91, 59, 40.41), alt=None) -> Image.Exif:
    exif = Image.Exif()
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    gps.update({1: lat_ref, 2: tuple(IFDRational(v) for v in lat), 3: lon_ref,
                4: tuple(IFDRational(v) for v in lon)})
    if alt is not None:
        gps.update({5: b"\x00", 6: IFDRational(alt)})
    exif.get_ifd(ExifTags.IFD.Exif)[0x9003] = "2020:01:02 03:04:05"
    return exif


def assert_nothing(meta: StillMetadata) -> None:
    for name in ("time", "lat", "lon", "alt", "relative_alt", "gimbal_yaw", "gimbal_pitch",
                 "flight_yaw", "focal_px"):
        assert getattr(meta, name) is None, name
    assert still_sample(meta, 0.0) is None


def test_broken_metadata_gives_none_not_an_error(tmp_path, recwarn):
    # truncated EXIF block (the TIFF header points past the end)
    truncated = tmp_path / "truncated.jpg"
    truncated.write_bytes(b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00II*\x00\xff\xff\xff\xff")
    meta = read_still_metadata(truncated)
    assert_nothing(meta)
    assert meta.problems
    # a real JPEG cut in the middle of its EXIF
    whole = jpeg_bytes(gps_exif(alt=120.0), dji_xmp(_ROW))
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(whole[:60])
    assert_nothing(read_still_metadata(cut))
    # a PNG without metadata; a text file named .jpg; a missing file
    png = tmp_path / "plain.png"
    cv2.imwrite(str(png), np.full((20, 30, 3), 128, np.uint8))
    assert_nothing(read_still_metadata(png))
    text = tmp_path / "notes.jpg"
    text.write_text("not an image")
    assert_nothing(read_still_metadata(text))
    assert_nothing(read_still_metadata(tmp_path / "missing.jpg"))
    assert exif_time(truncated) is None and exif_time(text) is None
    assert not [w for w in recwarn.list if "EXIF" in str(w.message)]   # Pillow's warnings are kept in


def test_nonsense_gps_fields(tmp_path):
    def read(exif: Image.Exif) -> StillMetadata:
        path = tmp_path / "g.jpg"
        path.write_bytes(jpeg_bytes(exif))
        return read_still_metadata(path)

    good = read(gps_exif(alt=120.5))
    assert good.lat == pytest.approx(46 + 50 / 60 + 33.38 / 3600, abs=1e-9)
    assert good.lon == pytest.approx(91 + 59 / 60 + 40.41 / 3600, abs=1e-9)
    assert good.alt == pytest.approx(120.5) and good.time is not None
    bad_ref = read(gps_exif(lat_ref="X", lon_ref="Q", alt=120.5))
    assert bad_ref.lat is None and bad_ref.lon is None and "refs" in " ".join(bad_ref.problems)
    assert bad_ref.alt == pytest.approx(120.5) and bad_ref.time == good.time   # the rest survives
    assert read(gps_exif(lat=(0, 0, 0), lon=(0, 0, 0))).lat is None            # no fix
    assert read(gps_exif(lat=(95, 0, 0))).lat is None                          # out of range
    assert read(gps_exif(lat=(46, 75, 0))).lat is None                         # 75 minutes
    zero_den = gps_exif()
    zero_den.get_ifd(ExifTags.IFD.GPSInfo)[2] = (IFDRational(46, 0), IFDRational(1), IFDRational(2))
    assert read(zero_den).lat is None
    missing_ref = gps_exif()
    del missing_ref.get_ifd(ExifTags.IFD.GPSInfo)[1]
    assert read(missing_ref).lat is None


_ROW = {"gps_alt": "+198.309", "rel_alt": "+39.80", "gimbal_roll": "+0.00", "gimbal_yaw": "+45.00",
        "gimbal_pitch": "-89.90", "flight_roll": "+3.00", "flight_yaw": "+46.00",
        "flight_pitch": "+1.80", "model": "FC300S"}


def test_xmp_without_dji_fields_and_malformed_xmp(tmp_path):
    plain = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
             b'<rdf:Description xmlns:tiff="http://ns.adobe.com/tiff/1.0/" tiff:Make="Canon"/></rdf:RDF></x:xmpmeta>')
    path = tmp_path / "x.jpg"
    path.write_bytes(jpeg_bytes(Image.Exif(), plain))
    meta = read_still_metadata(path)
    assert meta.gimbal_yaw is meta.relative_alt is meta.flight_yaw is None and meta.problems == ()
    assert still_sample(meta, 1.0) is None
    # undeclared prefix and trailing NULs: not XML, read by the fallback
    loose = b'<x:xmpmeta><rdf:Description drone-dji:RelativeAltitude="+52.10" drone-dji:GimbalYawDegree="-12.4"/></x:xmpmeta>\x00\x00'
    assert parse_dji_xmp(loose) == {"RelativeAltitude": "+52.10", "GimbalYawDegree": "-12.4"}
    # a DOCTYPE with entities is never handed to the XML parser
    bomb = (b'<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>'
            b'<x:xmpmeta><rdf:RDF><rdf:Description drone-dji:GimbalPitchDegree="&b;"/></rdf:RDF></x:xmpmeta>')
    assert parse_dji_xmp(bomb) == {"GimbalPitchDegree": "&b;"}
    # unreadable numbers are dropped with a reason
    path.write_bytes(jpeg_bytes(Image.Exif(), dji_xmp({**_ROW, "rel_alt": "n/a", "gimbal_yaw": "1e999"})))
    meta = read_still_metadata(path)
    assert meta.relative_alt is None and meta.gimbal_yaw is None and meta.gimbal_pitch == -89.9
    assert len(meta.problems) == 2
    assert parse_dji_xmp(b"") == {} and parse_dji_xmp(b"\xff\xfe garbage <x:xmpmeta") == {}


# Trimmed from a real DJI Mavic 3 Classic (Hasselblad L2D-20c) packet, as published in a public
# GitHub Kotlin sample that rewrites it with Ashampoo's Kim library (found through the code
# search index, which does not name the repository). Tab-indented namespace declarations,
# attribute form, www.dji.com namespace.
MAVIC3_XMP = """<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?>
<x:xmpmeta
\txmlns:x="adobe:ns:meta/">
\t<rdf:RDF
\t\txmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
\t\t<rdf:Description rdf:about="DJI Meta Data"
\t\t\txmlns:tiff="http://ns.adobe.com/tiff/1.0/"
\t\t\txmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"
   tiff:Make="Hasselblad"
   tiff:Model="L2D-20c"
   drone-dji:Version="1.2"
   drone-dji:GpsStatus="Normal"
   drone-dji:AltitudeType="GpsFusionAlt"
   drone-dji:GpsLatitude="+46.592612704"
   drone-dji:GpsLongitude="+7.525073398"
   drone-dji:AbsoluteAltitude="+1538.962"
   drone-dji:RelativeAltitude="+26.600"
   drone-dji:GimbalRollDegree="+0.00"
   drone-dji:GimbalYawDegree="-131.70"
   drone-dji:GimbalPitchDegree="-35.40"
   drone-dji:FlightRollDegree="+1.30"
   drone-dji:FlightYawDegree="-132.20"
   drone-dji:FlightPitchDegree="+4.30"
   drone-dji:ProductName="DJIMavic3Classic">
\t\t</rdf:Description>
\t</rdf:RDF>
</x:xmpmeta>
<?xpacket end="w"?>"""

# Trimmed from a real DJI Phantom 4 RTK (FC6310R) packet quoted in a public GitHub Python
# script (same index): note DJI's misspelt GpsLongtitude and the unsigned latitude.
P4RTK_XMP = """<x:xmpmeta xmlns:x="adobe:ns:meta/">
 <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
  <rdf:Description rdf:about="DJI Meta Data"
    xmlns:tiff="http://ns.adobe.com/tiff/1.0/"
    xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"
   tiff:Make="DJI"
   tiff:Model="FC6310R"
   drone-dji:AbsoluteAltitude="+514.64"
   drone-dji:RelativeAltitude="+100.09"
   drone-dji:GpsLatitude="34.03250565"
   drone-dji:GpsLongtitude="108.76779926"
   drone-dji:GimbalRollDegree="+0.00"
   drone-dji:GimbalYawDegree="+93.50"
   drone-dji:GimbalPitchDegree="-89.90"
   drone-dji:FlightRollDegree="+2.10"
   drone-dji:FlightYawDegree="+93.50"
   drone-dji:FlightPitchDegree="+1.00"
   drone-dji:CalibratedFocalLength="3666.666504"
   drone-dji:RtkFlag="50">
  </rdf:Description>
 </rdf:RDF>
</x:xmpmeta>"""


def test_real_dji_xmp_packets(tmp_path):
    props = parse_dji_xmp(MAVIC3_XMP)
    assert props["GimbalPitchDegree"] == "-35.40" and props["ProductName"] == "DJIMavic3Classic"
    assert "Make" not in props   # tiff:Make is not a drone-dji property
    path = tmp_path / "m3.jpg"
    path.write_bytes(jpeg_bytes(Image.Exif(), MAVIC3_XMP.encode()))
    meta = read_still_metadata(path)   # no EXIF GPS: the XMP position is used
    assert (meta.lat, meta.lon, meta.alt, meta.relative_alt) == (46.592612704, 7.525073398, 1538.962, 26.6)
    roll, pitch, yaw = camera_attitude(meta)
    assert math.degrees(yaw) == pytest.approx(-131.7)
    assert math.degrees(pitch) == pytest.approx(54.6)   # an oblique shot, 54.6 deg off nadir
    path.write_bytes(jpeg_bytes(Image.Exif(), P4RTK_XMP.encode()))
    meta = read_still_metadata(path)
    assert (meta.lat, meta.lon, meta.relative_alt) == (34.03250565, 108.76779926, 100.09)
    assert meta.gimbal_yaw == 93.5 and meta.flight_pitch == 1.0
    # DJI's newer namespace URI (Mavic 4 Pro) and the element form
    uav = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
           '<rdf:Description xmlns:drone-dji="http://www.uav.com/drone-dji/1.0/">'
           '<drone-dji:GimbalYawDegree>+125.00</drone-dji:GimbalYawDegree>'
           '</rdf:Description></rdf:RDF></x:xmpmeta>')
    assert parse_dji_xmp(uav) == {"GimbalYawDegree": "+125.00"}


def test_real_mavic2_exif_gps_and_focal(tmp_path):
    """The EXIF of a real DJI Mavic 2 Pro still as printed by Pillow in
    buildingsmart-norway/maskinlesbar_V441 (300_tester/dronefoto_metadata/README.md @ 199d53b):
    GPS ((61,1),(0,1),(502611,10000)) N, ((10,1),(45,1),(519669,10000)) E, altitude 494 m;
    FocalLength 10.26 mm, FocalLengthIn35mmFilm 28, 5472 x 3648, Hasselblad L1D-20c."""
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "Hasselblad", "L1D-20c"
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    sub.update({0x9003: "2020:05:22 15:04:51", 0x920A: IFDRational(10260, 1000), 0xA405: 28,
                0xA002: 5472, 0xA003: 3648})
    exif.get_ifd(ExifTags.IFD.GPSInfo).update({
        0: b"\x02\x03\x00\x00", 1: "N", 2: (IFDRational(61, 1), IFDRational(0, 1), IFDRational(502611, 10000)),
        3: "E", 4: (IFDRational(10, 1), IFDRational(45, 1), IFDRational(519669, 10000)), 5: b"\x00",
        6: IFDRational(494, 1)})
    path = tmp_path / "m2p.jpg"
    path.write_bytes(jpeg_bytes(exif, size=(684, 456)))   # the 5472 x 3648 still at 1/8 size
    meta = read_still_metadata(path)
    assert meta.lat == pytest.approx(61 + 50.2611 / 3600, abs=1e-9)
    assert meta.lon == pytest.approx(10 + 45 / 60 + 51.9669 / 3600, abs=1e-9)
    assert meta.alt == 494.0 and meta.time == parse_exif_datetime("2020:05:22 15:04:51")
    # 10.26 mm on the 13.2 mm wide 1" sensor, at 684 px; the 35 mm equivalent agrees to 0.1 %
    assert meta.focal_source == "sensor_table"
    assert meta.focal_px == pytest.approx(10.26 / 13.2 * 684)
    fx35, _ = focal_length_px(684, 456, focal_35mm=28.0)
    assert fx35 == pytest.approx(meta.focal_px, rel=2e-3)


def test_focal_plane_resolution_and_a_resized_still():
    # Canon ELPH 300 HS: 3600 px across 6.16 mm, written as pixels per inch
    xres = 3600 / (6.16 / 25.4)
    fx, source = focal_length_px(900, 675, focal_mm=4.3, plane_x_res=xres, plane_unit=2, exif_width=3600)
    assert source == "focal_plane" and fx == pytest.approx(4.3 / 6.16 * 900)
    assert focal_length_px(900, 675) == (None, None)
    assert focal_length_px(0, 675, focal_35mm=28.0) == (None, None)


# --------------------------------------------------------------------------- attitude conventions

def test_gimbal_tilt_matches_the_rectification_convention():
    """Gimbal pitch -80: the camera looks 10 deg forward of nadir, whatever the airframe does;
    the ground straight below then appears towards the bottom of the image (image up = forward)."""
    meta = StillMetadata(name="x", time=0.0, gimbal_yaw=30.0, gimbal_pitch=-80.0, gimbal_roll=0.0,
                         flight_pitch=-12.0, flight_roll=5.0, flight_yaw=33.0)
    roll, pitch, yaw = camera_attitude(meta)
    assert (math.degrees(roll), math.degrees(pitch), math.degrees(yaw)) == pytest.approx((0.0, 10.0, 30.0))
    fx, cx, cy = 500.0, 319.5, 239.5
    x, y = nadir_pixel(fx, cx, cy, roll, pitch)
    assert x == pytest.approx(cx) and y == pytest.approx(cy + fx * math.tan(math.radians(10.0)))
    # gimbal roll +5 (right side down): the ground below appears to the right
    x, _ = nadir_pixel(fx, cx, cy, *camera_attitude(StillMetadata(name="x", gimbal_pitch=-90.0, gimbal_roll=5.0))[:2])
    assert x == pytest.approx(cx + fx * math.tan(math.radians(5.0)))
    # no gimbal recorded: a camera fixed to the airframe
    fixed = StillMetadata(name="x", flight_yaw=33.0, flight_pitch=-2.0, flight_roll=1.5)
    assert [math.degrees(v) for v in camera_attitude(fixed)] == pytest.approx([1.5, -2.0, 33.0])


def test_exif_orientation_turns_the_heading_like_opencv_does(tmp_path):
    """OpenCV's imread rotates a still upright by its EXIF orientation: orientation 6 puts the
    stored image's top (the camera's forward) on the right, so image up is forward - 90 deg."""
    stored = np.zeros((48, 64, 3), np.uint8)
    stored[:4] = 255                       # mark the top rows: the camera's forward side
    exif = Image.Exif()
    exif[0x0112] = 6
    path = tmp_path / "o6.jpg"
    Image.fromarray(stored).save(path, exif=exif, xmp=dji_xmp({**_ROW, "gimbal_yaw": "+40.00"}))
    shown = cv2.imread(str(path), cv2.IMREAD_ANYCOLOR)
    assert shown.shape[:2] == (64, 48)
    assert shown[:, -4:].mean() > 200 and shown[:, :4].mean() < 50    # forward is on the right
    meta = read_still_metadata(path)
    assert meta.orientation == 6
    assert math.degrees(still_sample(meta, 0.0).yaw) == pytest.approx(40.0 - 90.0)
    # orientation 3 (upside down): heading + 180, and the tilt changes sign
    upside = StillMetadata(name="x", orientation=3, gimbal_yaw=40.0, gimbal_pitch=-85.0, gimbal_roll=2.0)
    roll, pitch, yaw = camera_attitude(upside)
    assert (math.degrees(roll), math.degrees(pitch)) == pytest.approx((-2.0, -5.0), abs=0.05)
    assert math.degrees(yaw) == pytest.approx(40.0 - 180.0, abs=0.05)
    # a mirrored still has no usable attitude
    assert camera_attitude(StillMetadata(name="x", orientation=2, gimbal_yaw=40.0)) == (None, None, None)


# --------------------------------------------------------------------------- capture times

def test_capture_time_from_a_png_exif_chunk(tmp_path):
    exif = Image.Exif()
    exif[0x010F] = "Test"   # Pillow writes no eXIf chunk for an empty IFD0
    exif.get_ifd(ExifTags.IFD.Exif).update({0x9003: "2021:03:04 05:06:07", 0x9291: "25"})
    path = tmp_path / "t.png"
    Image.new("RGB", (16, 16)).save(path, exif=exif)
    assert exif_time(path) == parse_exif_datetime("2021:03:04 05:06:07", "25")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_still_metadata(path).time == exif_time(path)


def lrf_xmp(status: str | None, distance: str, gimbal_pitch: str = "-90.00", gimbal_roll: str = "+0.00") -> bytes:
    """A DJI enterprise (M30T-style) XMP packet with its laser range finder's fields."""
    status_attr = "" if status is None else f' drone-dji:LRFStatus="{status}"'
    return ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
            '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"'
            ' drone-dji:RelativeAltitude="+120.20" drone-dji:GimbalYawDegree="+84.10"'
            f' drone-dji:GimbalPitchDegree="{gimbal_pitch}" drone-dji:GimbalRollDegree="{gimbal_roll}"'
            f'{status_attr} drone-dji:LRFTargetDistance="{distance}"/>'
            '</rdf:RDF></x:xmpmeta>').encode()


def test_laser_range_finder_gives_the_height_over_what_is_below(tmp_path):
    """DJI enterprise stills: the height over the canopy or roof under the drone is the laser
    range finder's distance (tilt-corrected like a MAVLink rangefinder), not the height over
    the take-off point; a reading whose status is not Normal, or 0 (no return), is not used."""
    path = tmp_path / "t.jpg"
    path.write_bytes(jpeg_bytes(Image.Exif(), lrf_xmp("Normal", "54.103")))
    meta = read_still_metadata(path)
    assert meta.lrf_distance == pytest.approx(54.103) and meta.relative_alt == pytest.approx(120.2)
    s = still_sample(meta, 0.0)
    assert s.height_source == "rangefinder" and s.rangefinder == pytest.approx(54.103)
    assert s.height_above_ground == pytest.approx(54.103, abs=1e-6) and s.relative_alt == pytest.approx(120.2)
    # 20 deg of gimbal tilt: the slant range times cos(tilt)
    path.write_bytes(jpeg_bytes(Image.Exif(), lrf_xmp("Normal", "60.000", gimbal_pitch="-70.00")))
    s = still_sample(read_still_metadata(path), 0.0)
    assert s.height_above_ground == pytest.approx(60.0 * math.cos(math.radians(20.0)), abs=1e-3)
    for status, distance in (("TooFar", "54.1"), ("Normal", "0.000"), ("Normal", "-3")):
        path.write_bytes(jpeg_bytes(Image.Exif(), lrf_xmp(status, distance)))
        meta = read_still_metadata(path)
        assert meta.lrf_distance is None and meta.problems == (), (status, distance)
        s = still_sample(meta, 0.0)
        assert s.height_source == "home" and s.height_above_ground == pytest.approx(120.2)
    path.write_bytes(jpeg_bytes(Image.Exif(), lrf_xmp(None, "n/a")))
    meta = read_still_metadata(path)
    assert meta.lrf_distance is None and any("LRFTargetDistance" in p for p in meta.problems)
