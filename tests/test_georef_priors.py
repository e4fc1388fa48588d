"""Survey stills whose priors are wrong keep the georeference of their good GPS.

A simulated survey (``photomap simulate --mode stills``: JPEG stills with EXIF GPS and DJI XMP)
whose XMP is then rewritten as some real drones record it: ``RelativeAltitude`` over the take-off
point (0.75 of the height over the ground below) and ``GimbalYawDegree`` 55 degrees off. Truth:
the photos' own GPS (the camera's position, straight above the frame centre of these nadir
stills) and the simulator's metres per pixel.
"""

from __future__ import annotations

import logging
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from stills_fixtures import noisy_geo_txt

from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.exif import read_still_metadata
from photomap.geo.georef import enu_from_latlon
from photomap.io.trajectory_files import read_trajectory_csv
from photomap.sim.simulate import simulate_flight

SIZE = (480, 384)
XMP_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"


def survey(out: Path, strips: int, per_strip: int, seed: int = 1) -> Path:
    simulate_flight(out, terrain="texture", terrain_size=(3400, 2400), mode="stills", strips=strips,
                    stills_per_strip=per_strip, size=SIZE, altitude=(60.0, 60.0), seed=seed)
    return out


def rewrite_xmp(path: Path, edit) -> None:
    """Replace the XMP packet of a JPEG (its APP1 segment) by ``edit(text)``; the image data and
    EXIF stay byte for byte."""
    data = path.read_bytes()
    at = data.index(XMP_HEADER) - 4          # FF E1, then the segment length (big-endian)
    assert data[at:at + 2] == b"\xff\xe1"
    (length,) = struct.unpack(">H", data[at + 2:at + 4])
    start, end = at + 4 + len(XMP_HEADER), at + 2 + length
    packet = edit(data[start:end].decode("utf-8")).encode("utf-8")
    segment = b"\xff\xe1" + struct.pack(">H", 2 + len(XMP_HEADER) + len(packet)) + XMP_HEADER + packet
    path.write_bytes(data[:at] + segment + data[end:])


def wrong_priors(folder: Path, height_factor: float = 0.75, yaw_off_deg: float = 55.0) -> None:
    def edit(text: str) -> str:
        text = re.sub(r'RelativeAltitude="([^"]+)"',
                      lambda m: f'RelativeAltitude="{float(m.group(1)) * height_factor:+.3f}"', text)
        return re.sub(r'GimbalYawDegree="([^"]+)"',
                      lambda m: f'GimbalYawDegree="{math.remainder(float(m.group(1)) + yaw_off_deg, 360.0):+.2f}"',
                      text)

    for still in sorted(folder.glob("*.jpg")):
        rewrite_xmp(still, edit)


def centre_errors_m(run: Path, stills: Path) -> np.ndarray:
    """Distance (m) of each placed frame centre (trajectory lat/lon) from its photo's GPS."""
    rows = [r for r in read_trajectory_csv(run / "trajectory.csv") if r.glued]
    files = sorted(stills.glob("*.jpg"))
    errors = []
    for r in rows:
        meta = read_still_metadata(files[r.frame])
        e, n = enu_from_latlon(np.array([r.extra["lat"]]), np.array([r.extra["lon"]]), meta.lat, meta.lon)
        errors.append(math.hypot(float(e[0]), float(n[0])))
    return np.array(errors)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return survey(tmp_path_factory.mktemp("survey"), strips=3, per_strip=8)


@pytest.fixture(scope="module")
def wrong(flight, tmp_path_factory):
    """The survey with its relative altitude over the take-off point and its gimbal yaw 55 deg off."""
    folder = tmp_path_factory.mktemp("wrong") / "stills"
    folder.mkdir()
    for still in sorted((flight / "stills").glob("*.jpg")):
        (folder / still.name).write_bytes(still.read_bytes())
    wrong_priors(folder)
    return folder


def test_the_rewritten_priors_read_back(flight, wrong):
    a = read_still_metadata(flight / "stills" / "000003.jpg")
    b = read_still_metadata(wrong / "000003.jpg")
    assert b.relative_alt == pytest.approx(0.75 * a.relative_alt, abs=1e-3)
    assert math.remainder(b.gimbal_yaw - a.gimbal_yaw, 360.0) == pytest.approx(55.0, abs=0.01)
    assert (b.lat, b.lon, b.focal_px) == (a.lat, a.lon, a.focal_px)


def test_wrong_height_and_gimbal_yaw_are_dropped_and_the_gps_georeferences(flight, wrong, tmp_path, caplog):
    """... with a consumer GPS: the positions 1.5 m (sigma) off (a geo.txt); judged against the
    photos' true positions."""
    caplog.set_level(logging.INFO)
    geo = noisy_geo_txt(wrong, tmp_path / "geo.txt", sigma_m=1.5, seed=4)
    summary = replay(str(wrong), tmp_path / "run", load_config(), geo=str(geo))
    tel = summary["telemetry"]
    assert summary["segments"] == 1 and summary["registered"] == 24
    assert tel["status"] == "ok"
    assert [p.split(":")[0] for p in tel["problems"]] == ["camera_scale", "compass"], tel["problems"]
    assert "x1.33" in tel["problems"][0] and "turned 55 deg" in tel["problems"][1]
    dropped = [r.getMessage() for r in caplog.records if "telemetry prior dropped" in r.getMessage()]
    assert len(dropped) == 2
    assert not [r for r in caplog.records if "telemetry refused" in r.getMessage()]
    geo = summary["georeference"]
    assert geo is not None and geo["crs"].startswith("EPSG:326") and geo["scale_source"] == "gps"
    assert 0.5 < geo["gps_rms_m"] < 3.0   # the GPS noise
    assert (tmp_path / "run" / "mosaic.pgw").is_file()
    # the map's scale is the GPS's: the simulator's ground metres per map pixel
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    map_scale = summary["map_scale"] or 1.0
    truth_mpp = 60.0 / meta["camera"]["fx"] / map_scale
    assert summary["metres_per_pixel"] == pytest.approx(truth_mpp, rel=0.03)
    errors = centre_errors_m(tmp_path / "run", wrong)
    assert len(errors) == 24 and float(np.median(errors)) < 3.0, errors


def test_the_same_survey_with_right_priors_has_no_problem(flight, tmp_path):
    summary = replay(str(flight / "stills"), tmp_path / "run", load_config())
    assert summary["telemetry"]["status"] == "ok" and summary["telemetry"]["problems"] == []
    assert summary["georeference"] is not None
    assert float(np.median(centre_errors_m(tmp_path / "run", flight / "stills"))) < 3.0


def test_another_flights_gps_is_still_refused(flight, wrong, tmp_path, caplog):
    """A geo.txt from another survey of the same area (4 strips of 6, not 3 of 8): same count,
    another shape; wrong priors or not, the GPS is refused."""
    other = survey(tmp_path / "other", strips=4, per_strip=6, seed=2)
    lines = ["EPSG:4326\n"]
    for mine, theirs in zip(sorted(wrong.glob("*.jpg")), sorted((other / "stills").glob("*.jpg"))):
        m = read_still_metadata(theirs)
        lines.append(f"{mine.name} {m.lon:.9f} {m.lat:.9f} {m.alt:.3f}\n")
    (tmp_path / "geo.txt").write_text("".join(lines))
    caplog.set_level(logging.INFO)
    summary = replay(str(wrong), tmp_path / "run", load_config(), geo=str(tmp_path / "geo.txt"))
    tel = summary["telemetry"]
    assert tel["status"] == "gps_mismatch", tel["problems"]
    assert "GPS fixes fit the vision track" in tel["problems"][0]  # its shape, not the priors
    assert summary["georeference"] is None and not (tmp_path / "run" / "mosaic.pgw").exists()
    assert len([r for r in caplog.records if "telemetry refused" in r.getMessage()]) == 1


def test_stills_sharing_one_second_capture_times_keep_their_own_gps(tmp_path, caplog):
    """EXIF times of one-second resolution (no SubSecTimeOriginal) with two stills a second:
    each still keeps its own GPS (looked up by still, not by time), the map is georeferenced,
    and trajectory.tum says once how many frames it leaves out."""
    out = tmp_path / "fast"
    simulate_flight(out, terrain="texture", terrain_size=(3400, 2400), mode="stills", strips=2, stills_per_strip=6,
                    size=SIZE, altitude=(60.0, 60.0), seed=1, speed=40.0, t0_unix=1_700_000_000.25)
    for still in sorted((out / "stills").glob("*.jpg")):
        data = still.read_bytes()
        with Image.open(still) as im:  # re-saved: the metadata kept but the sub-seconds
            im.load()
            exif, xmp = im.getexif(), im.info.get("xmp")
            exif.get_ifd(0x8769).pop(0x9291, None)
            im.save(still, "JPEG", quality=92, exif=exif, xmp=xmp)
        assert still.read_bytes() != data
    times = [read_still_metadata(p).time for p in sorted((out / "stills").glob("*.jpg"))]
    assert len(set(times)) < len(times)   # stills share capture times
    caplog.set_level(logging.INFO)
    summary = replay(str(out / "stills"), tmp_path / "run", load_config())
    assert summary["telemetry"]["status"] == "ok" and summary["georeference"] is not None
    assert float(np.median(centre_errors_m(tmp_path / "run", out / "stills"))) < 1.0
    tum = [r.getMessage() for r in caplog.records if r.getMessage().startswith("TUM:")]
    skipped = len(times) - len(set(times))
    assert len(tum) == 1 and tum[0].startswith(f"TUM: {skipped} frame(s) skipped (frames "), tum
    assert tum[0].endswith("their times do not increase (e.g. capture times of one-second resolution)")


def test_a_laser_range_finder_gives_the_camera_scale_that_the_height_over_take_off_does_not(tmp_path):
    """A DJI enterprise survey taken off 20 m below the ground it maps (RelativeAltitude reads 80 m
    over ground 60 m below): with the laser range finder in the XMP the camera's scale agrees
    with the GPS (no prior dropped); the same stills without it drop the camera scale."""
    out = tmp_path / "lrf"
    simulate_flight(out, terrain="texture", terrain_size=(3400, 2400), mode="stills", strips=2, stills_per_strip=8,
                    size=SIZE, altitude=(60.0, 60.0), seed=3, home_below_m=20.0, lrf=True)
    meta = read_still_metadata(out / "stills" / "000004.jpg")
    assert meta.relative_alt == pytest.approx(80.0, abs=0.01) and meta.lrf_distance == pytest.approx(60.0, rel=0.01)
    summary = replay(str(out / "stills"), tmp_path / "with", load_config())
    tel = summary["telemetry"]
    assert summary["segments"] == 1 and tel["status"] == "ok" and tel["problems"] == [], tel["problems"]
    assert summary["georeference"] is not None
    cam = yaml.safe_load((out / "meta.yaml").read_text())["camera"]
    assert summary["metres_per_pixel"] == pytest.approx(60.0 / cam["fx"] / (summary["map_scale"] or 1.0), rel=0.03)

    without = tmp_path / "without"
    without.mkdir()
    for still in sorted((out / "stills").glob("*.jpg")):
        (without / still.name).write_bytes(still.read_bytes())
        rewrite_xmp(without / still.name, lambda text: re.sub(r'\s*drone-dji:LRF\w+="[^"]*"', "", text))
    assert read_still_metadata(without / "000004.jpg").lrf_distance is None
    tel = replay(str(without), tmp_path / "run_without", load_config())["telemetry"]
    assert [p.split(":")[0] for p in tel["problems"]] == ["camera_scale"], tel["problems"]
    assert "x0.75" in tel["problems"][0]
