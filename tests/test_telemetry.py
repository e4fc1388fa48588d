"""TelemetryBuffer and message decoding (pure): interpolation, wrap, gaps, validation."""

from __future__ import annotations

import math

import pytest

from photomap.telemetry.samples import TelemetryBuffer, decode_message, wrap_angle


def attitude(roll=0.0, pitch=0.0, yaw=0.0, rates=(0.0, 0.0, 0.0)) -> dict:
    return dict(time_boot_ms=0, roll=roll, pitch=pitch, yaw=yaw,
                rollspeed=rates[0], pitchspeed=rates[1], yawspeed=rates[2])


def gpi(lat=47.0, lon=8.0, alt=500.0, rel=30.0, v=(0.0, 0.0, 0.0), hdg=9000) -> dict:
    return dict(time_boot_ms=0, lat=round(lat * 1e7), lon=round(lon * 1e7), alt=round(alt * 1e3),
                relative_alt=round(rel * 1e3), vx=round(v[0] * 100), vy=round(v[1] * 100),
                vz=round(v[2] * 100), hdg=hdg)


def distance(cm, orientation=25, lo=20, hi=4000) -> dict:
    return dict(time_boot_ms=0, min_distance=lo, max_distance=hi, current_distance=cm, type=0,
                id=0, orientation=orientation, covariance=0, signal_quality=0)


def test_wrap_angle():
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle(-0.1) == pytest.approx(-0.1)


def test_linear_interpolation_and_yaw_across_pi():
    buf = TelemetryBuffer(max_gap=2.0, max_hold=0.5)
    buf.add_message(10.0, "ATTITUDE", attitude(roll=0.1, pitch=-0.2, yaw=3.0))
    buf.add_message(11.0, "ATTITUDE", attitude(roll=0.3, pitch=0.2, yaw=-2.9))
    step = 2 * math.pi - 5.9  # the short way from 3.0 to -2.9 rad
    s = buf.at(10.25)
    assert s.roll == pytest.approx(0.15)
    assert s.pitch == pytest.approx(-0.1)
    assert s.yaw == pytest.approx(3.0 + 0.25 * step)
    assert buf.at(10.75).yaw == pytest.approx(wrap_angle(3.0 + 0.75 * step))
    assert -math.pi < buf.at(10.75).yaw < 0
    assert buf.at(10.0).yaw == pytest.approx(3.0)  # exact at a sample


def test_heading_and_velocity_units():
    buf = TelemetryBuffer()
    buf.add_message(0.0, "GLOBAL_POSITION_INT", gpi(hdg=35900, v=(1.0, -2.0, 0.5)))
    buf.add_message(1.0, "GLOBAL_POSITION_INT", gpi(hdg=100, v=(3.0, -2.0, 0.5)))
    s = buf.at(0.5)
    assert math.degrees(s.heading) == pytest.approx(0.0, abs=1e-9)  # 359 -> 1 deg passes north
    assert (s.vn, s.ve, s.vd) == pytest.approx((2.0, -2.0, 0.5))
    assert s.lat == pytest.approx(47.0) and s.alt == pytest.approx(500.0)


def test_gap_longer_than_max_gap_is_unknown_and_ends_hold_briefly():
    buf = TelemetryBuffer(max_gap=2.0, max_hold=0.5)
    buf.add_message(0.0, "ATTITUDE", attitude(yaw=0.0))
    buf.add_message(3.0, "ATTITUDE", attitude(yaw=0.3))
    assert buf.at(1.5).yaw is None
    assert buf.at(0.4).yaw == pytest.approx(0.0)     # held: 0.4 s after a sample
    assert buf.at(2.7).yaw == pytest.approx(0.3)     # held: 0.3 s before a sample
    assert buf.at(3.4).yaw == pytest.approx(0.3)     # past the end, within max_hold
    assert buf.at(3.6).yaw is None                   # past the end: unknown, not stale
    assert buf.at(-0.6).yaw is None
    assert buf.at(1.0).lat is None                   # never seen


def test_rejected_sample_marks_a_gap():
    buf = TelemetryBuffer(max_gap=5.0, max_hold=0.5)
    buf.add_message(0.0, "ATTITUDE", attitude(yaw=0.0))
    dec, stored = buf.add_message(1.0, "ATTITUDE", attitude(yaw=math.nan))
    assert stored and dec.problems == {"yaw": "not finite"}
    buf.add_message(2.0, "ATTITUDE", attitude(yaw=0.2))
    assert buf.at(1.0).yaw is None       # without the mark this would interpolate to 0.1
    assert buf.at(0.3).yaw == pytest.approx(0.0)
    assert buf.at(1.8).yaw == pytest.approx(0.2)
    assert buf.count("yaw") == 2


def test_mark_gap_and_backwards_time():
    buf = TelemetryBuffer(max_gap=5.0, max_hold=0.5)
    buf.add_message(0.0, "ATTITUDE", attitude(yaw=0.1))
    buf.mark_gap(0.5)
    buf.add_message(2.0, "ATTITUDE", attitude(yaw=0.2))
    assert buf.at(0.2).yaw == pytest.approx(0.1)
    assert buf.at(1.0).yaw is None
    _, stored = buf.add_message(1.9, "ATTITUDE", attitude(yaw=0.3))
    assert not stored
    assert buf.count("yaw") == 2


def test_horizon_bounds_memory():
    buf = TelemetryBuffer(horizon=10.0)
    for i in range(1001):
        buf.add_message(i * 0.1, "ATTITUDE", attitude(yaw=0.0))
    first, last = buf.span
    assert last == pytest.approx(100.0) and first >= 90.0 - 1e-9
    assert buf.count("yaw") == 101
    assert TelemetryBuffer(horizon=None).horizon is None


@pytest.mark.parametrize("fields, problem", [
    (attitude(yaw=math.nan), {"yaw": "not finite"}),
    (attitude(yaw=4.0), {"yaw": "out of range"}),
    (attitude(pitch=2.0), {"pitch": "out of range"}),
    (attitude(rates=(0.0, 0.0, 1e6)), {"yawspeed": "out of range"}),
])
def test_bad_attitude_rejects_the_whole_message(fields, problem):
    dec = decode_message("ATTITUDE", fields)
    assert dec.problems == problem
    assert dec.values == {}
    assert sorted(dec.rejected) == sorted(["roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed"])


def test_gps_without_fix_keeps_the_barometric_altitude():
    dec = decode_message("GLOBAL_POSITION_INT", gpi(lat=0.0, lon=0.0, alt=0.0, rel=12.5))
    assert dec.problems == {"lat/lon": "no GPS fix (0/0)"}
    assert "lat" not in dec.values and dec.values["relative_alt"] == pytest.approx(12.5)


def test_absurd_altitude_and_unknown_heading():
    fields = gpi(hdg=65535)
    fields["alt"] = 2_000_000_000  # 2000 km AMSL
    dec = decode_message("GLOBAL_POSITION_INT", fields)
    assert dec.problems == {"alt": "out of range"}
    assert dec.unknown == ["heading"]
    assert dec.values["lat"] == pytest.approx(47.0)


def test_altitude_nan_is_unknown_not_rejected():
    dec = decode_message("ALTITUDE", dict(time_usec=0, altitude_monotonic=100.0, altitude_amsl=500.0,
                                          altitude_local=1.0, altitude_relative=20.0,
                                          altitude_terrain=math.nan, bottom_clearance=-1.0))
    assert dec.values == {"altitude_amsl": 500.0, "altitude_relative": 20.0}
    assert dec.unknown == ["altitude_terrain"]
    assert dec.problems == {"bottom_clearance": "out of range"}


def test_rangefinder_validity():
    assert decode_message("DISTANCE_SENSOR", distance(1234)).values == {"rangefinder": 12.34}
    assert decode_message("DISTANCE_SENSOR", distance(0, lo=0, hi=400)).unknown == ["rangefinder"]
    assert decode_message("DISTANCE_SENSOR", distance(5000)).unknown == ["rangefinder"]
    forward = decode_message("DISTANCE_SENSOR", distance(1234, orientation=0))
    assert forward.values == {} and forward.unknown == []


def test_system_time_from_a_gcs_is_ignored():
    assert decode_message("SYSTEM_TIME", dict(time_unix_usec=1_700_000_000_000_000, time_boot_ms=0)).unknown
    dec = decode_message("SYSTEM_TIME", dict(time_unix_usec=1_700_000_100_000_000, time_boot_ms=100_000))
    assert dec.values["boot_to_unix"] == pytest.approx(1_700_000_000.0)


def test_height_above_ground_prefers_the_tilt_corrected_rangefinder():
    buf = TelemetryBuffer()
    for t in (0.0, 1.0):
        buf.add_message(t, "ATTITUDE", attitude(roll=0.2, pitch=0.1))
        buf.add_message(t, "GLOBAL_POSITION_INT", gpi(rel=30.0))
    buf.add_message(0.0, "DISTANCE_SENSOR", distance(2000))
    buf.add_message(1.0, "DISTANCE_SENSOR", distance(2200))
    s = buf.at(0.5)
    assert s.rangefinder == pytest.approx(21.0)
    assert s.height_above_ground == pytest.approx(21.0 * math.cos(0.2) * math.cos(0.1))
    assert s.height_source == "rangefinder"
    buf.add_message(2.0, "DISTANCE_SENSOR", distance(0))  # no reading any more
    buf.add_message(2.0, "GLOBAL_POSITION_INT", gpi(rel=30.0))
    s = buf.at(2.0)
    assert s.rangefinder is None
    assert (s.height_above_ground, s.height_source) == (pytest.approx(30.0), "home")
    assert buf.latest("relative_alt") == (2.0, pytest.approx(30.0))
