"""DJI subtitle telemetry (drivers/srt.py): each real style parsed to the values its text holds,
bad files refused in one line, and a simulated DJI video georeferenced from its .SRT alone.

The real files in tests/data/srt are the first cues of JuanIrache/DJI_SRT_Parser's samples
(MIT, LICENSE-DJI_SRT_Parser.txt beside them); the whole files in ../shared/data/dji_srt are
read when present.
"""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import DATA_DIR, shared_data
from photomap.cli.main import main
from photomap.cli.replay import replay
from photomap.config import load_config
from photomap.drivers.srt import parse_srt_text, read_srt, srt_beside
from photomap.errors import InputError
from photomap.io.trajectory_files import read_groundtruth, read_trajectory_csv
from photomap.sim.flight import pixel_to_latlon
from photomap.sim.simulate import simulate_flight
from photomap.sim.srt_writer import write_srt

SRT = Path(__file__).parent / "data" / "srt"
W, H = 320, 240
EARTH_M_PER_DEG = 111_320.0


def cues_in(path: Path) -> int:
    return len(re.findall(r"-->", path.read_text(encoding="utf-8-sig", errors="replace")))


# ------------------------------------------------------------------ each real style, value by value

def test_mavic3_bracket_style_with_rel_and_abs_alt():
    track = read_srt(SRT / "mavic3.srt")   # [latitude: 3.41531] [longitude: -3.37440] [rel_alt: -2.400 abs_alt: 0.401]
    assert len(track.cues) == cues_in(SRT / "mavic3.srt") == 20 and dict(track.styles) == {"bracket": 20}
    c = track.cues[0]
    assert (c.t, c.lat, c.lon, c.rel_alt, c.abs_alt) == (0.0, 3.41531, -3.37440, -2.4, 0.401)
    assert c.focal_35mm == 24.0 and c.gimbal_pitch is None
    assert [k.t for k in track.cues[:4]] == pytest.approx([0.0, 0.02, 0.04, 0.06])   # subtitle start times
    assert track.period == pytest.approx(0.02)


def test_mavic2_longtitude_and_air2s_altitude():
    m2 = read_srt(SRT / "m2zoom.SRT")   # [latitude : 31.452012] [longtitude : 74.398751] [altitude: 213.983002]
    c = m2.cues[0]
    assert (c.lat, c.lon, c.abs_alt, c.rel_alt) == (31.452012, 74.398751, 213.983002, None)
    assert c.focal_35mm == 24.0            # [focal_len : 240]: tenths of a mm
    assert m2.cues[1].t == pytest.approx(0.016)
    air = read_srt(SRT / "air2s.srt")    # [latitude: 41.424724] [longitude: 2.234156] [altitude: 117.000000]
    assert len(air.cues) == 17
    assert (air.cues[0].lat, air.cues[0].lon, air.cues[0].abs_alt) == (41.424724, 2.234156, 117.0)
    assert (air.cues[-1].lat, air.cues[-1].lon, air.cues[-1].t) == (41.42473, 2.234102, 0.533)


def test_phantom4_rtk_gps_lon_lat_height_and_gimbal():
    track = read_srt(SRT / "p4_rtk.SRT")
    # GPS (-58.851745, -34.237922, 15), H 85.80m, G.PRY (-24.4°, 0.0°, 110.4°)
    c = track.cues[0]
    assert (c.lat, c.lon, c.rel_alt) == (-34.237922, -58.851745, 85.8)
    assert (c.gimbal_pitch, c.gimbal_roll, c.gimbal_yaw) == (-24.4, 0.0, 110.4)
    last = track.cues[-1]   # 00:00:19,000: GPS (-58.850948, -34.236195, 15), H 85.56m, G.PRY (.., .., 111.9°)
    assert (last.t, last.lat, last.lon, last.rel_alt, last.gimbal_yaw) == (19.0, -34.236195, -58.850948, 85.56, 111.9)
    assert dict(track.styles) == {"gps_lon_lat": 20}
    # the camera attitude of the samples: gimbal pitch -24.4 = 65.6 deg forward of nadir
    s = track.buffer().at(0.0)
    assert math.degrees(s.pitch) == pytest.approx(65.6) and math.degrees(s.yaw) == pytest.approx(110.4)
    assert s.height_above_ground == pytest.approx(85.8) and s.height_source == "home"


@pytest.mark.parametrize("name, t0, lat, lon, height", [
    ("mavic_pro.SRT", 1.0, -20.2533, 149.0251, 1.9),      # HOME(..) GPS(149.0251,-20.2533,16) BAROMETER:1.9
    ("old_format.SRT", 1.0, -20.2533, 149.0251, 1.9),     # HOME(..) GPS(149.0251,-20.2533,16) Hb:1.9 Hs:1.9
    ("mavic_mini.SRT", 0.0, 48.0771, -121.7458, 200.7),   # GPS (-121.7458, 48.0771, 17), D 221.21m, H 200.70m
    ("matrice_300.srt", 0.0, 36.6146, -6.1120, 0.3),      # GPS(36.6146,-6.1120,0.0M) BAROMETER:0.3M (lat first)
])
def test_gps_bracket_styles(name, t0, lat, lon, height):
    track = read_srt(SRT / name)
    c = track.cues[0]
    assert (c.t, c.lat, c.lon, c.rel_alt) == (t0, lat, lon, height)
    assert len(track.cues) == cues_in(SRT / name) == 20
    assert track.decimals == 4 and "steps of ~11 m" in track.describe()


def test_matrice_order_and_crlf():
    track = read_srt(SRT / "matrice_300.srt")
    assert b"\r\n" in (SRT / "matrice_300.srt").read_bytes()
    assert dict(track.styles) == {"gps_lat_lon": 20}
    assert [c.rel_alt for c in track.cues[:5]] == [0.3, 0.3, 0.8, 1.3, 4.1]   # BAROMETER:..M


def test_mavic2_style_without_time_lines_is_timed_by_its_dates():
    track = read_srt(SRT / "mavic_2_style.SRT")   # "2017.08.05 14:11:51,393,525" then 14:11:52 ...
    assert track.timed_by_date
    assert [c.t for c in track.cues[:3]] == pytest.approx([0.0, 1.0, 2.0])
    assert (track.cues[0].lat, track.cues[0].lon) == (-20.2533, 149.0251)


def test_two_styles_in_one_file_with_bom():
    track = read_srt(SRT / "mix_p4rtk_mavic2pro.srt")
    assert (SRT / "mix_p4rtk_mavic2pro.srt").read_bytes().startswith(b"\xef\xbb\xbf")
    assert dict(track.styles) == {"gps_lon_lat": 6, "bracket": 6}
    assert track.cues[0].t == pytest.approx(904.904)   # 00:15:04,904
    assert (track.cues[0].lat, track.cues[0].lon) == (-34.6502, -59.409424)
    assert (track.cues[-1].lat, track.cues[-1].lon, track.cues[-1].abs_alt) == (-34.65118, -59.409483, 120.140999)
    assert all(b.t > a.t for a, b in zip(track.cues, track.cues[1:]))


def test_truncated_file_keeps_what_it_has():
    track = read_srt(SRT / "broken_incomplete2.SRT")   # cue 3 cut at "[latit", cue 6 at "[lo"
    assert [c.index for c in track.cues] == [1, 2, 4, 5, 6]
    assert [c.lat is not None for c in track.cues] == [True, True, True, True, False]
    assert (track.cues[3].lat, track.cues[3].lon) == (-34.869945, -57.823383)
    assert track.without_gps == 1 and track.unparsed == 1
    assert "1 block(s) left out" in track.describe()


@pytest.mark.parametrize("name", sorted(p.name for p in DATA_DIR.glob("dji_srt/*.[sS][rR][tT]"))
                         or ["(none)"])
def test_every_real_file_is_a_plausible_track_or_one_clear_error(name):
    path = shared_data("dji_srt") / name
    try:
        track = read_srt(path)
    except InputError as exc:
        assert name == "mavic_air.SRT" and "\n" not in str(exc)
        return
    t = np.array([c.t for c in track.cues])
    assert len(t) >= 5 and np.all(np.diff(t) > 0)
    fixes = [c for c in track.cues if c.lat is not None]
    assert len(fixes) >= 0.6 * len(track.cues)
    for a, b in zip(fixes, fixes[1:]):
        if a.style != b.style:
            continue   # the mix_ file joins two recordings
        d = math.hypot((b.lat - a.lat) * EARTH_M_PER_DEG,
                       (b.lon - a.lon) * EARTH_M_PER_DEG * math.cos(math.radians(a.lat)))
        assert d <= 60.0 * (b.t - a.t) + 25.0, (a, b)   # a drone's speed, plus a 4-decimal step
    heights = [c.rel_alt for c in track.cues if c.rel_alt is not None]
    assert all(-50 < h < 1000 for h in heights)


# ------------------------------------------------------------------ bad input: one line

def test_no_gps_unknown_and_garbage_are_one_clear_line(tmp_path):
    with pytest.raises(InputError, match=r"mavic_air.SRT: not DJI telemetry of a known style \(2 subtitle"):
        read_srt(SRT / "mavic_air.SRT")   # exposure only
    (tmp_path / "film.srt").write_text("1\n00:00:01,000 --> 00:00:02,000\nHello there\n\n2\n"
                                       "00:00:02,000 --> 00:00:03,000\nGeneral Kenobi\n")
    with pytest.raises(InputError, match="film.srt: not DJI telemetry"):
        read_srt(tmp_path / "film.srt")
    rng = np.random.default_rng(1)
    (tmp_path / "noise.SRT").write_bytes(rng.integers(0, 256, 20000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="noise.SRT: not DJI telemetry"):
        read_srt(tmp_path / "noise.SRT")
    (tmp_path / "empty.srt").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty.srt: not DJI telemetry of a known style \(no subtitle blocks"):
        read_srt(tmp_path / "empty.srt")
    with pytest.raises(InputError, match="cannot read subtitle telemetry"):
        read_srt(tmp_path / "missing.srt")


def test_a_position_jump_and_time_going_back_are_left_out():
    def cue(k, t, lat, lon):
        return (f"{k}\n00:00:{t:02d},000 --> 00:00:{t + 1:02d},000\n"
                f"GPS({lon:.6f},{lat:.6f},15) BAROMETER:50.0\n\n")
    text = (cue(1, 0, 47.0, 8.0) + cue(2, 1, 47.00001, 8.0) + cue(3, 2, 48.5, 8.0)   # 160 km away
            + cue(4, 3, 47.00003, 8.0) + cue(5, 2, 47.00004, 8.0) + cue(6, 4, 47.00004, 8.0)
            + cue(7, 5, 0.0, 0.0))                                                      # no fix yet
    track = parse_srt_text(text)
    assert [c.index for c in track.cues] == [1, 2, 3, 4, 6, 7]
    assert [c.lat for c in track.cues] == [47.0, 47.00001, None, 47.00003, 47.00004, None]
    assert track.glitches == 1 and track.out_of_order == 1 and track.without_gps == 1


def test_gps_order_follows_the_values_when_the_style_does_not_say():
    cue = "1\n00:00:00,000 --> 00:00:01,000\nGPS({}, {}, 17) H 50.0m\n"
    lon_first = parse_srt_text(cue.format("149.0251", "-20.2533")).cues[0]
    lat_first = parse_srt_text(cue.format("-20.2533", "149.0251")).cues[0]
    assert (lon_first.lat, lon_first.lon) == (lat_first.lat, lat_first.lon) == (-20.2533, 149.0251)
    assert (lon_first.style, lat_first.style) == ("gps_lon_lat", "gps_lat_lon")


def test_no_fix_yet_in_the_bracket_style():
    text = ("1\n00:00:00,000 --> 00:00:00,016\n<font size=\"36\">SrtCnt : 1, DiffTime : 16ms\n"
            "[iso : 3200] [focal_len : 240] [latitude: 0.000000] [longitude: 0.000000] "
            "[altitude: 0.000000] </font>\n")
    cue = parse_srt_text(text).cues[0]
    assert (cue.lat, cue.lon, cue.abs_alt, cue.focal_35mm) == (None, None, None, 24.0)


def test_srt_beside_a_video_in_any_case(tmp_path):
    video = tmp_path / "DJI_0001.MP4"
    video.write_bytes(b"x")
    assert srt_beside(video) is None
    (tmp_path / "DJI_0001.srt").write_text("")
    assert srt_beside(video) == tmp_path / "DJI_0001.srt"
    (tmp_path / "DJI_0001.srt").rename(tmp_path / "DJI_0001.sRt")
    assert srt_beside(video) == tmp_path / "DJI_0001.sRt"


def test_buffer_interpolates_cues_and_gimbal_nadir_is_level():
    text = "".join(f"{k + 1}\n00:00:0{k},000 --> 00:00:0{k + 1},000\n[latitude: {47 + k * 1e-5:.6f}] "
                   f"[longitude: 8.000000] [rel_alt: {50 + k:.3f} abs_alt: {450 + k:.3f}] "
                   f"[gb_yaw: {170 + 10 * k:.1f} gb_pitch: -90.0 gb_roll: 0.0]\n\n" for k in range(3))
    buf = parse_srt_text(text).buffer()
    s = buf.at(1.5)
    assert s.lat == pytest.approx(47.000015) and s.relative_alt == pytest.approx(51.5)
    assert s.alt == pytest.approx(451.5) and s.height_above_ground == pytest.approx(51.5)
    assert abs(s.pitch) < 1e-12 and abs(s.roll) < 1e-12
    assert math.degrees(s.yaw) == pytest.approx(-175.0)   # 185 deg across +-180, wrapped
    assert buf.at(2.9).lat is not None   # the last cue holds for its own second


# ------------------------------------------------------------------ a DJI video, end to end

@pytest.fixture(scope="module")
def dji(tmp_path_factory):
    """A simulated flight written as DJI_0001.MP4 + DJI_0001.SRT, alone in a folder."""
    root = tmp_path_factory.mktemp("dji")
    flight = simulate_flight(root / "sim", terrain="aukerman", n_frames=150, size=(W, H), fps=15.0, seed=3,
                             yaw_rate=20.0, srt=True)
    folder = root / "card"
    folder.mkdir()
    shutil.copy(flight / "video.mp4", folder / "DJI_0001.MP4")
    shutil.copy(flight / "video.srt", folder / "DJI_0001.SRT")
    return flight, folder


def truth_centres(flight: Path) -> tuple[np.ndarray, np.ndarray]:
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    gt = read_groundtruth(flight / "groundtruth.csv")
    xy = np.array([hk @ [(W - 1) / 2, (H - 1) / 2, 1.0] for hk in gt.H])
    lat, lon = pixel_to_latlon(xy[:, 0] / xy[:, 2], xy[:, 1] / xy[:, 2], meta["gsd"],
                               meta["origin"]["lat"], meta["origin"]["lon"])
    return np.asarray(lat), np.asarray(lon)


def test_simulated_srt_reads_back_the_truth(dji):
    flight, _ = dji
    meta = yaml.safe_load((flight / "meta.yaml").read_text())
    gt = read_groundtruth(flight / "groundtruth.csv")
    track = read_srt(flight / "video.srt")
    assert meta["files"]["srt"] == "video.srt" and len(track.cues) == 150 == meta["frames"]
    assert [c.t for c in track.cues] == pytest.approx(list(gt.t), abs=5e-4)
    assert [c.rel_alt for c in track.cues] == pytest.approx(list(gt.columns["alt_m"]), abs=5e-4)
    assert [c.abs_alt - c.rel_alt for c in track.cues] == pytest.approx([meta["origin"]["amsl_m"]] * 150, abs=1e-3)
    assert track.focal_35mm * math.hypot(W, H) / 43.2666 == pytest.approx(meta["camera"]["fx"], rel=2e-3)


def test_dji_video_is_georeferenced_from_its_srt_alone(dji, tmp_path, caplog):
    """`photomap replay DJI_0001.MP4`: the SRT beside it is the only telemetry."""
    flight, folder = dji
    caplog.set_level(logging.INFO)
    assert main(["replay", str(folder / "DJI_0001.MP4"), "--out", str(tmp_path), "--no-progress"]) == 0
    found = [r.getMessage() for r in caplog.records if "found beside the video" in r.getMessage()]
    assert len(found) == 1 and found[0].startswith("telemetry from DJI_0001.SRT: 150 DJI subtitle cues")
    summary = json.loads((tmp_path / "run.json").read_text())
    tel = summary["telemetry"]
    assert tel["status"] == "ok" and tel["problems"] == [] and tel["frames_with_telemetry"] == 150
    assert tel["link"]["format"] == "dji_srt" and tel["link"]["with_gps"] == 150
    assert tel["time_offset_check"]["refused"] is None and abs(tel["time_offset_check"]["residual_offset_s"]) < 0.05
    assert summary["georeference"] is not None and (tmp_path / "mosaic.pgw").is_file()
    err = centre_errors_m(tmp_path, flight)
    assert len(err) == 150
    assert float(np.median(err)) < 1.5, np.median(err)
    assert max(err) < 1.5, max(err)


def centre_errors_m(run: Path, flight: Path) -> list[float]:
    lat, lon = truth_centres(flight)
    rows = [r for r in read_trajectory_csv(run / "trajectory.csv") if r.glued]
    return [math.hypot((r.extra["lat"] - lat[r.frame]) * EARTH_M_PER_DEG,
                       (r.extra["lon"] - lon[r.frame]) * EARTH_M_PER_DEG * math.cos(math.radians(lat[r.frame])))
            for r in rows]


def test_phantom_style_cues_once_a_second_are_interpolated(dji, tmp_path):
    """The same flight as 1 Hz Phantom 4 cues (GPS(lon, lat, n), H above take-off, no gimbal,
    no focal length: the camera model is configured): positions between cues are interpolated."""
    flight, folder = dji
    lines = []
    for k, c in enumerate(read_srt(folder / "DJI_0001.SRT").cues[::15]):   # 15 fps: one a second
        start = f"00:00:{int(c.t):02d},{round(c.t % 1 * 1000):03d}"
        end = f"00:00:{int(c.t) + 1:02d},{round(c.t % 1 * 1000):03d}"
        lines += [str(k + 1), f"{start} --> {end}", f"F/2.8, SS 200, ISO 100, EV 0, GPS ({c.lon:.6f}, "
                  f"{c.lat:.6f}, 17), D 10.00m, H {c.rel_alt:.2f}m, H.S 1.00m/s, V.S 0.00m/s", ""]
    (tmp_path / "p4.SRT").write_text("\n".join(lines))
    fx = yaml.safe_load((flight / "meta.yaml").read_text())["camera"]["fx"]
    summary = replay(str(folder / "DJI_0001.MP4"), tmp_path / "run", load_config().updated({"camera": {"fx_px": fx}}),
                     mavlink=str(tmp_path / "p4.SRT"))
    assert summary["telemetry"]["status"] == "ok" and summary["telemetry"]["frames_with_telemetry"] == 150
    assert summary["telemetry"]["link"]["styles"] == {"gps_lon_lat": 10}
    assert summary["georeference"] is not None
    err = centre_errors_m(tmp_path / "run", flight)
    assert len(err) == 150 and float(np.median(err)) < 1.5, np.median(err)


def test_telemetry_flag_takes_an_srt_and_its_gps_is_still_checked(dji, tmp_path, caplog):
    """--telemetry FILE.SRT names the file; an SRT whose GPS track runs backwards (another
    shape, same place) is refused by the same checks as a .tlog's."""
    flight, folder = dji
    track = read_srt(folder / "DJI_0001.SRT")
    c = track.cues
    write_srt(tmp_path / "reversed.SRT", np.array([k.t for k in c]), np.array([k.lat for k in c])[::-1],
              np.array([k.lon for k in c])[::-1], np.array([k.rel_alt for k in c]),
              np.array([k.gimbal_roll for k in c]), np.array([k.gimbal_pitch + 90.0 for k in c]),
              np.array([k.gimbal_yaw for k in c]), t0_unix=0.0)
    caplog.set_level(logging.INFO)
    summary = replay(str(folder / "DJI_0001.MP4"), tmp_path / "run", load_config(),
                     mavlink=str(tmp_path / "reversed.SRT"))
    assert summary["telemetry"]["status"] == "gps_mismatch", summary["telemetry"]["problems"]
    assert summary["georeference"] is None
    assert not [r for r in caplog.records if "found beside the video" in r.getMessage()]


def test_a_real_srt_of_another_flight_is_refused(dji, tmp_path):
    _, folder = dji
    summary = replay(str(folder / "DJI_0001.MP4"), tmp_path, load_config(), mavlink=str(SRT / "p4_rtk.SRT"))
    tel = summary["telemetry"]
    assert tel["frames_with_telemetry"] > 0 and tel["status"] != "ok", tel
    assert tel["problems"] and summary["georeference"] is None


def test_batch_takes_the_srt_as_the_videos_sidecar(dji):
    _, folder = dji
    from photomap.cli.batch import sidecar_telemetry
    assert sidecar_telemetry(folder / "DJI_0001.MP4") == str(folder / "DJI_0001.SRT")


def test_simulate_srt_flag(tmp_path):
    assert main(["simulate", "--out", str(tmp_path / "s"), "--frames", "6", "--size", "160x120", "--srt",
                 "-q"]) == 0
    track = read_srt(tmp_path / "s" / "video.srt")
    assert len(track.cues) == 6 and track.with_gps == 6 and dict(track.styles) == {"bracket": 6}


def test_cli_telemetry_srt_without_gps_is_one_line(dji, tmp_path, capsys):
    _, folder = dji
    code = main(["replay", str(folder / "DJI_0001.MP4"), "--out", str(tmp_path / "run"), "--no-progress",
                 "--telemetry", str(SRT / "mavic_air.SRT")])
    err = capsys.readouterr().err
    assert code == InputError.exit_code
    assert "mavic_air.SRT: not DJI telemetry of a known style" in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.strip()]) == 1, err
