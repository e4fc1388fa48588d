"""MAVLink driver and replay tool: real logs, a synthetic log, loopback UDP/TCP, faults."""

from __future__ import annotations

import dataclasses
import logging
import math
import random
import socket
import struct
import sys
import threading
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from photomap.drivers.mavlink import (Link, TelemetryReader, load_tlog, mavlink, open_link,
                                      statustext_chunks)
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from photomap.config import load_config
from photomap.errors import ConfigError, InputError
from photomap.telemetry.samples import TelemetryBuffer
from tests.waiting import wait_until
from tools.mavlink_replay import main as replay_main
from tools.mavlink_replay import replay

from conftest import DATA_DIR as DATA
T0 = 1_700_000_000.0  # UNIX time of the synthetic log's first message


# ----------------------------------------------------------------------------- synthetic log
class _TlogWriter:
    """File-like for ``MAVLink.send``: each frame gets its 8-byte big-endian µs timestamp."""

    def __init__(self, f):
        self.f, self.t_us = f, 0

    def write(self, buf):
        self.f.write(struct.pack(">Q", self.t_us) + buf)


def true_yaw(t: float) -> float:
    """Known yaw [rad] at log time t: turns at 1 rad/s from 2.5 rad, so it crosses +-pi."""
    return math.remainder(2.5 + t, 2 * math.pi)


def true_lat(t: float) -> float:
    return 47.0 + 1e-4 * t


def true_rel_alt(t: float) -> float:
    return 20.0 + 2.0 * t


def write_log(path: Path, segments=((0.0, 2.0), (5.0, 6.0)), bad: dict | None = None) -> Counter:
    """Write a tlog of the known flight above during ``segments`` (log seconds, [a, b)).

    ATTITUDE at 10 Hz, GLOBAL_POSITION_INT and DISTANCE_SENSOR at 5 Hz, HEARTBEAT and
    SYSTEM_TIME at 1 Hz. ``bad`` maps a log time (one of the 10 Hz ticks) to a corruption:
    "nan_yaw", "no_fix", "absurd_alt". Returns the number of messages written per type.
    """
    bad = bad or {}
    counts: Counter = Counter()
    with open(path, "wb") as f:
        w = _TlogWriter(f)
        mav = mavlink2.MAVLink(w, srcSystem=1, srcComponent=1)

        def send(msg):
            mav.send(msg)
            counts[msg.get_type()] += 1

        for a, b in segments:
            for k in range(round(a * 10), round(b * 10)):
                t = k / 10
                w.t_us = round((T0 + t) * 1e6)
                boot_ms = 100_000 + k * 100
                fault = bad.get(round(t, 1))
                if k % 10 == 0:
                    send(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 4, mavlink.MAV_STATE_ACTIVE))
                    send(mav.system_time_encode(round((T0 + t) * 1e6), boot_ms))
                yaw = math.nan if fault == "nan_yaw" else true_yaw(t)
                send(mav.attitude_encode(boot_ms, 0.05, -0.02, yaw, 0.0, 0.0, 1.0))
                if k % 2 == 0:
                    lat = 0 if fault == "no_fix" else round(true_lat(t) * 1e7)
                    lon = 0 if fault == "no_fix" else round(8.0 * 1e7)
                    alt = 2_000_000_000 if fault == "absurd_alt" else round((400 + true_rel_alt(t)) * 1e3)
                    send(mav.global_position_int_encode(boot_ms, lat, lon, alt, round(true_rel_alt(t) * 1e3),
                                                        100, 0, 0, 9000))
                    send(mav.distance_sensor_encode(boot_ms, 20, 4000, round(true_rel_alt(t) * 100),
                                                    mavlink.MAV_DISTANCE_SENSOR_LASER, 0,
                                                    mavlink.MAV_SENSOR_ROTATION_PITCH_270, 0))
    return counts


@pytest.fixture
def synthetic(tmp_path) -> tuple[Path, Counter]:
    path = tmp_path / "synthetic.tlog"
    return path, write_log(path)


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ----------------------------------------------------------------------------- connection strings
@pytest.mark.parametrize("spec, words", [
    ("missing_flight.tlog", "not found"),
    ("udpin:14550", "udpin:HOST:PORT"),
    ("tcp:127.0.0.1:notaport", "tcp:HOST:PORT"),
    ("flight.bin", "DataFlash"),
    ("bogus", "unrecognised"),
    ("/dev/ttyNOPE_photomap,57600", "/dev/ttyNOPE_photomap"),
])
def test_bad_connection_strings_give_one_clear_error(spec, words):
    with pytest.raises(InputError, match=words):
        open_link(spec)


def test_missing_pyserial_is_explained(monkeypatch):
    monkeypatch.setitem(sys.modules, "serial", None)
    with pytest.raises(InputError, match=r"\[serial\]"):
        open_link("/dev/ttyUSB0,57600")


def test_refused_tcp_is_an_input_error():
    with pytest.raises(InputError, match="cannot open"):
        open_link(f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}")


def test_network_and_log_kinds(synthetic):
    port = free_port()
    for spec, kind in ((f"udpin:127.0.0.1:{port}", "udpin"), (f"udpout:127.0.0.1:{port}", "udpout"),
                       (str(synthetic[0]), "tlog")):
        link = open_link(spec)
        assert link.kind == kind and link.is_log == (kind == "tlog")
        link.close()


# ----------------------------------------------------------------------------- logs
def test_synthetic_log_interpolates_known_values(synthetic):
    path, written = synthetic
    buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.3, link_timeout=2.0)
    assert stats.messages == written
    assert stats.duplicates == 0 and not stats.rejected
    for t in (0.05, 0.55, 1.23, 1.75, 5.42):  # between samples
        s = buf.at(T0 + t)
        assert s.yaw == pytest.approx(true_yaw(t), abs=1e-6), t
        assert s.lat == pytest.approx(true_lat(t), abs=2e-7), t
        assert s.relative_alt == pytest.approx(true_rel_alt(t), abs=1e-3), t
        assert s.rangefinder == pytest.approx(true_rel_alt(t), abs=0.01), t
        assert s.height_source == "rangefinder"
        assert s.height_above_ground == pytest.approx(s.rangefinder * math.cos(0.05) * math.cos(0.02))
    assert buf.at(T0 + 1.05).yaw < 0 < buf.at(T0 + 0.5).yaw  # crossed +pi -> -pi
    # 2.0 .. 5.0 s: no data for 3 s > max_gap: unknown, and counted as a link gap
    assert buf.at(T0 + 3.5).yaw is None and buf.at(T0 + 3.5).lat is None
    assert stats.link_lost == stats.link_regained == stats.gaps == 1
    assert buf.latest("boot_to_unix")[1] == pytest.approx(T0 - 100.0)


def test_corrupt_values_are_rejected_and_logged_once(tmp_path, caplog):
    path = tmp_path / "bad.tlog"
    faults = {0.0: "no_fix", 0.2: "no_fix", 0.4: "absurd_alt", 0.8: "absurd_alt",
              1.0: "nan_yaw", 1.1: "nan_yaw"}
    written = write_log(path, segments=((0.0, 2.0),), bad=faults)
    with caplog.at_level(logging.INFO, logger="photomap.drivers.mavlink"):
        buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.05)
    assert stats.messages == written
    assert stats.rejected == {"GLOBAL_POSITION_INT: lat/lon no GPS fix (0/0)": 2,
                              "GLOBAL_POSITION_INT: alt out of range": 2,
                              "ATTITUDE: yaw not finite": 2}
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert sum("yaw not finite" in w for w in warnings) == 1
    assert sum("no GPS fix" in w for w in warnings) == 1
    assert any("valid ATTITUDE again" in r.getMessage() for r in caplog.records)
    assert buf.at(T0 + 0.2).lat is None                        # before the first fix
    assert buf.at(T0 + 0.5).lat == pytest.approx(true_lat(0.5), abs=2e-7)
    assert buf.at(T0 + 0.2).relative_alt == pytest.approx(true_rel_alt(0.2), abs=1e-3)
    assert buf.at(T0 + 1.05).yaw is None                       # between the rejected samples
    assert buf.at(T0 + 1.25).yaw == pytest.approx(true_yaw(1.25), abs=1e-6)


def test_truncated_log_ends_cleanly(synthetic, tmp_path):
    path, written = synthetic
    data = path.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 7])  # mid-record
    buf, stats = load_tlog(cut)
    assert 0 < stats.total < sum(written.values())
    first, last = buf.span
    assert first == pytest.approx(T0) and T0 < last < T0 + 6.0
    assert buf.at(last).yaw is not None
    # streaming the same file through the reader thread gives the same messages
    with TelemetryReader(str(cut)) as reader:
        assert reader.finished.wait(5.0)
    assert reader.stats.messages == stats.messages


def test_empty_or_random_file_gives_an_empty_buffer(tmp_path, caplog):
    empty, noise = tmp_path / "empty.tlog", tmp_path / "noise.tlog"
    empty.write_bytes(b"")
    noise.write_bytes(random.Random(3).randbytes(20000))
    for path in (empty, noise):
        buf, stats = load_tlog(path)
        assert buf.span is None and buf.at(T0).yaw is None
    assert stats.receive_errors > 0
    assert sum("no usable MAVLink telemetry" in r.getMessage() for r in caplog.records) == 2


def _check_real_log(name: str, expected: dict, alt_range, rel_range) -> None:
    path = DATA / "tlogs" / f"{name}.tlog"
    if not path.is_file():
        pytest.skip(f"real test data not found: {path} (shared/data is not beside the repo)")
    buf, stats = load_tlog(path)
    for mtype, n in expected.items():
        assert stats.messages[mtype] == n, mtype
    assert stats.out_of_order == 0
    assert not stats.rejected
    for f in ("yaw", "lat", "alt", "relative_alt"):
        t, v = buf.series(f)
        assert len(t) > 100 and (t[1:] >= t[:-1]).all(), f
    _, alt = buf.series("alt")
    _, rel = buf.series("relative_alt")
    assert alt_range[0] < np.nanmin(alt) and np.nanmax(alt) < alt_range[1]
    assert rel_range[0] < np.nanmin(rel) and np.nanmax(rel) < rel_range[1]
    t0, _ = buf.span
    for dt in range(0, 200, 7):  # interpolated yaw is always a wrapped angle
        y = buf.at(t0 + dt).yaw
        assert y is None or -math.pi <= y <= math.pi


def test_real_px4_log_rural():
    _check_real_log("rural", {"ATTITUDE": 4148, "GLOBAL_POSITION_INT": 1390, "VFR_HUD": 1106,
                              "DISTANCE_SENSOR": 138}, alt_range=(140, 185), rel_range=(-1, 31))


def test_real_ardupilot_log_vtol():
    _check_real_log("vtol", {"ATTITUDE": 888, "GLOBAL_POSITION_INT": 807, "VFR_HUD": 878,
                             "LOCAL_POSITION_NED": 807, "SYSTEM_TIME": 811},
                    alt_range=(580, 650), rel_range=(-3, 64))


# ----------------------------------------------------------------------------- loopback
def _replay_thread(path, out, **kw) -> tuple[threading.Thread, dict]:
    result: dict = {}
    th = threading.Thread(target=lambda: result.setdefault("sent", replay(path, out, **kw)))
    th.start()
    return th, result


def test_udp_replay_end_to_end_keeps_counts_and_timing(synthetic):
    path, written = synthetic
    port = free_port()
    with TelemetryReader(f"udpin:127.0.0.1:{port}", TelemetryBuffer(horizon=None)) as reader:  # bound before the replay
        th, result = _replay_thread(path, f"udpout:127.0.0.1:{port}", speed=10.0)
        th.join(10)
        assert wait_until(lambda: reader.stats.total >= result["sent"])
    assert result["sent"] == sum(written.values())
    assert reader.stats.messages == written
    t, _ = reader.buffer.series("yaw")
    # the log's ATTITUDE spans 5.9 s, with a 3.1 s silence; at speed 10 they take a tenth
    assert 0.59 * 0.7 < t[-1] - t[0] < 0.59 * 1.6
    silence = (t[1:] - t[:-1]).max()
    assert 0.31 * 0.7 < silence < 0.31 * 1.6
    assert reader.stats.link_lost == 0


def test_tcp_replay_end_to_end(synthetic):
    path, written = synthetic
    port = free_port(socket.SOCK_STREAM)
    with TelemetryReader(f"tcpin:127.0.0.1:{port}") as reader:
        th, result = _replay_thread(path, f"tcp:127.0.0.1:{port}", speed=50.0)
        th.join(10)
        assert wait_until(lambda: reader.stats.total >= result["sent"])
    assert reader.stats.messages == written


def test_garbage_on_the_link_loses_little_and_raises_nothing(synthetic):
    path, written = synthetic
    port = free_port()
    with TelemetryReader(f"udpin:127.0.0.1:{port}") as reader:
        th, result = _replay_thread(path, f"udpout:127.0.0.1:{port}", speed=20.0,
                                    garbage_rate=0.2, seed=7)
        th.join(10)
        wait_until(lambda: reader.stats.total >= result["sent"], timeout=1.0)
        assert reader.running
    assert reader.stats.receive_errors > 0             # garbage did arrive
    assert reader.stats.messages["ATTITUDE"] >= 0.7 * written["ATTITUDE"]
    assert not reader.stats.rejected


def test_replay_stopping_mid_flight_is_reported_as_link_lost(synthetic):
    path, _ = synthetic
    port = free_port()
    with TelemetryReader(f"udpin:127.0.0.1:{port}", link_timeout=0.3) as reader:
        th, result = _replay_thread(path, f"udpout:127.0.0.1:{port}", speed=10.0, stop_after=0.1)
        th.join(10)
        assert wait_until(lambda: reader.link_lost)
        assert 0 < result["sent"] and reader.stats.link_lost == 1 and reader.stats.gaps == 1
        with reader.lock:
            t_last, _ = reader.buffer.latest("yaw")
        assert reader.at(t_last).yaw is not None
        assert reader.at(t_last + 0.6).yaw is None    # past the gap: unknown
    assert reader.stats.link_regained == 0


def test_reader_heartbeat_and_statustext():
    port = free_port()
    with TelemetryReader(f"udpin:127.0.0.1:{port}", send_heartbeat=True) as reader:
        peer = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        try:
            peer.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
            hb = peer.recv_match(type="HEARTBEAT", blocking=True, timeout=3.0)
            assert hb is not None and hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
            assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
            reader.send_status("photomap: mapping started", mavlink.MAV_SEVERITY_NOTICE)
            st = peer.recv_match(type="STATUSTEXT", blocking=True, timeout=3.0)
            assert st is not None and st.text == "photomap: mapping started"
            assert st.severity == mavlink.MAV_SEVERITY_NOTICE
        finally:
            peer.close()
    assert reader.stats.messages["HEARTBEAT"] >= 1


# ----------------------------------------------------------------------------- replay tool
def _count_datagrams(port: int, stop: threading.Event, out: list) -> threading.Thread:
    """Collect the datagrams sent to ``port`` into ``out`` until ``stop`` is set."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.1)

    def run():
        with sock:
            while not stop.is_set():
                try:
                    out.append(sock.recv(65536))
                except socket.timeout:
                    pass
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_replay_start_offset_and_loop(synthetic):
    path, written = synthetic
    total = sum(written.values())
    port = free_port()
    stop, got = threading.Event(), []
    counter = _count_datagrams(port, stop, got)
    try:
        n_late = replay(path, f"udpout:127.0.0.1:{port}", speed=50.0, start=5.0)
        # the second segment (5.0 .. 6.0 s of log): 10 ATTITUDE, 5 GPI, 5 DISTANCE, 1+1 at 1 Hz
        assert n_late == 22
        n_loop = replay(path, f"udpout:127.0.0.1:{port}", speed=50.0, loop=True, stop_after=0.4)
        assert n_loop > total
        assert wait_until(lambda: len(got) == n_late + n_loop, timeout=2.0)
        mav = mavlink2.MAVLink(None)
        assert mav.parse_char(got[0]).get_type() in ("HEARTBEAT", "SYSTEM_TIME", "ATTITUDE")
    finally:
        stop.set()
        counter.join()


def test_replay_cli_errors(tmp_path, capsys):
    assert replay_main([str(tmp_path / "nope.tlog"), "--out", "udpout:127.0.0.1:9"]) == InputError.exit_code
    assert "not found" in capsys.readouterr().err
    path = tmp_path / "x.tlog"
    write_log(path, segments=((0.0, 0.2),))
    assert replay_main([str(path), "--out", "udpin:127.0.0.1:9"]) == InputError.exit_code
    assert "cannot replay to" in capsys.readouterr().err


def test_reader_from_config_streams_a_log_paced(synthetic):
    cfg = load_config(overrides=[f"telemetry.source={synthetic[0]}"]).telemetry
    reader = TelemetryReader.from_config(cfg)
    reader.speed = 50.0
    with reader:
        assert reader.finished.wait(5.0)
    loaded, _ = load_tlog(synthetic[0])
    assert reader.stats.messages == synthetic[1]
    np.testing.assert_array_equal(reader.buffer.series("yaw")[1], loaded.series("yaw")[1])  # NaN = gap
    with pytest.raises(InputError, match="telemetry.source"):
        TelemetryReader.from_config(dataclasses.replace(cfg, source=""))


def test_link_wraps_an_open_connection(synthetic):
    link = open_link(str(synthetic[0]))
    assert isinstance(link, Link)
    reader = TelemetryReader(link).start()
    assert reader.finished.wait(5.0)
    reader.stop()
    assert reader.stats.messages == synthetic[1]


# ----------------------------------------------------------------------------- one vehicle
OTHER_YAW = 0.5  # the second vehicle's constant yaw [rad]


def write_two_vehicles(path: Path, *, vehicle_heartbeat_at: float | None = 0.4,
                       other_heartbeat_at: float | None = 0.0) -> Counter:
    """A tlog where vehicle 1 flies the known flight (yaw :func:`true_yaw`) and vehicle 2 sends
    ATTITUDE with yaw OTHER_YAW at the same rate, interleaved; a ground station (255) sends its
    HEARTBEAT (autopilot INVALID) first. Vehicle 1's first HEARTBEAT comes at
    ``vehicle_heartbeat_at`` s (its ATTITUDE from 0 s; times on the 0.1 s grid), vehicle 2's at ``other_heartbeat_at``
    (None: never). Returns the messages written per system id."""
    counts: Counter = Counter()
    with open(path, "wb") as f:
        w = _TlogWriter(f)
        mavs = {s: mavlink2.MAVLink(w, srcSystem=s, srcComponent=1) for s in (1, 2, 255)}

        def send(sysid, msg):
            mavs[sysid].send(msg)
            counts[sysid] += 1

        for k in range(30):  # 3 s at 10 Hz
            t = k / 10
            w.t_us = round((T0 + t) * 1e6)
            boot_ms = 100_000 + k * 100
            if k % 10 == 0:
                send(255, mavs[255].heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                     0, 0, mavlink.MAV_STATE_ACTIVE))
            for sysid, first in ((2, other_heartbeat_at), (1, vehicle_heartbeat_at)):
                if first is not None and k >= round(first * 10) and (k - round(first * 10)) % 10 == 0:
                    send(sysid, mavs[sysid].heartbeat_encode(
                        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4,
                        mavlink.MAV_STATE_ACTIVE))
            send(2, mavs[2].attitude_encode(boot_ms + 7, 0.0, 0.0, OTHER_YAW, 0.0, 0.0, 0.0))
            send(1, mavs[1].attitude_encode(boot_ms, 0.05, -0.02, true_yaw(t), 0.0, 0.0, 1.0))
    return counts


def _yaws(buf: TelemetryBuffer) -> list[float | None]:
    return [buf.at(T0 + k / 10).yaw for k in range(30)]


def test_two_vehicles_are_never_mixed(tmp_path, caplog):
    """The bug: every system went into one buffer, so yaw jumped between two vehicles."""
    path = tmp_path / "two.tlog"
    counts = write_two_vehicles(path, vehicle_heartbeat_at=0.4, other_heartbeat_at=1.0)
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.mavlink"):
        buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.3)
    assert stats.system_id == 1  # its autopilot HEARTBEAT came first (the GCS's does not count)
    # vehicle 1's ATTITUDE from before its first HEARTBEAT (0 .. 0.3 s) is used too
    assert _yaws(buf) == pytest.approx([true_yaw(k / 10) for k in range(30)], abs=1e-6)
    assert stats.span == pytest.approx((T0, T0 + 2.9))
    assert stats.messages["ATTITUDE"] == 30 and stats.messages["HEARTBEAT"] == 3
    assert dict(stats.other_systems) == {2: counts[2], 255: counts[255]}
    warned = [r.getMessage() for r in caplog.records if "system 2" in r.getMessage()]
    assert len(warned) == 1 and "ignored" in warned[0]
    assert not [r for r in caplog.records if "system 255" in r.getMessage()]  # a GCS is normal


def test_a_configured_system_id_is_followed(tmp_path):
    path = tmp_path / "two.tlog"
    counts = write_two_vehicles(path, vehicle_heartbeat_at=0.0, other_heartbeat_at=None)
    buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.3, system_id=2)
    assert stats.system_id == 2
    assert _yaws(buf) == pytest.approx([OTHER_YAW] * 30)
    assert stats.other_systems[1] == counts[1]


def test_without_any_autopilot_heartbeat_the_busiest_system_is_followed(tmp_path, caplog):
    path = tmp_path / "none.tlog"
    with open(path, "wb") as f:
        w = _TlogWriter(f)
        mavs = {s: mavlink2.MAVLink(w, srcSystem=s, srcComponent=1) for s in (1, 2)}
        for k in range(50):  # 5 s: vehicle 1 at 10 Hz, vehicle 2 at 5 Hz, no HEARTBEAT at all
            w.t_us = round((T0 + k / 10) * 1e6)
            mavs[1].send(mavs[1].attitude_encode(1000 + k * 100, 0, 0, true_yaw(k / 10), 0, 0, 0))
            if k % 2:
                mavs[2].send(mavs[2].attitude_encode(1000 + k * 100, 0, 0, OTHER_YAW, 0, 0, 0))
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.mavlink"):
        buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.3)
    assert stats.system_id == 1 and stats.other_systems[2] == 25
    assert [buf.at(T0 + k / 10).yaw for k in range(50)] == pytest.approx(
        [true_yaw(k / 10) for k in range(50)], abs=1e-6)
    assert sum("no autopilot HEARTBEAT" in r.getMessage() for r in caplog.records) == 1
    short = tmp_path / "short.tlog"  # a log that ends before the wait is over: the same choice
    short.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 4])
    buf, stats = load_tlog(short)
    assert stats.system_id == 1 and buf.at(T0).yaw == pytest.approx(true_yaw(0.0))


def test_live_reader_follows_one_vehicle(tmp_path):
    path = tmp_path / "two.tlog"
    write_two_vehicles(path, vehicle_heartbeat_at=0.4, other_heartbeat_at=1.0)
    port = free_port()
    with TelemetryReader(f"udpin:127.0.0.1:{port}", TelemetryBuffer(horizon=None)) as reader:
        th, result = _replay_thread(path, f"udpout:127.0.0.1:{port}", speed=20.0)
        th.join(10)

        def last_yaw():
            with reader.lock:
                return reader.buffer.latest("yaw")[1]

        # the vehicle's last attitude arrives (on a busy machine, a little after the replay ends)
        assert wait_until(lambda: abs(last_yaw() - true_yaw(2.9)) < 1e-6), last_yaw()
    assert reader.stats.system_id == 1 and reader.stats.other_systems[2] > 0


def test_ids_outside_1_255_are_a_config_error_naming_the_key(tmp_path, capsys):
    """The bug: source_system=300 killed the reader thread or the worker (struct.error)."""
    port = free_port()
    with pytest.raises(ConfigError, match="telemetry.source_system"):
        open_link(f"udpin:127.0.0.1:{port}", source_system=300)
    with pytest.raises(ConfigError, match="telemetry.source_system"):
        TelemetryReader(f"udpin:127.0.0.1:{port}", source_system=0)
    with pytest.raises(ConfigError, match="telemetry.system_id"):
        TelemetryReader(f"udpin:127.0.0.1:{port}", system_id=256)
    with pytest.raises(ConfigError, match="telemetry.system_id"):
        load_tlog(tmp_path / "x.tlog", system_id=-1)
    from photomap.cli.main import main as cli
    code = cli(["replay", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "o"), "-q",
                "--mavlink", f"udpin:127.0.0.1:{port}", "--set", "telemetry.source_system=300"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code in (2, 3) and len(err) == 1 and "Traceback" not in err[0]


# ----------------------------------------------------------------------------- silence
def test_a_live_link_that_brings_nothing_is_reported_once_by_name(caplog):
    port = free_port()
    spec = f"udpin:127.0.0.1:{port}"
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.mavlink"):
        with TelemetryReader(spec, no_data_warning=0.3) as reader:
            assert wait_until(lambda: any("no telemetry" in r.getMessage() for r in caplog.records))
            reader._stop.wait(0.8)  # a while longer: still one warning
    warned = [r for r in caplog.records if "no telemetry" in r.getMessage()]
    assert len(warned) == 1 and warned[0].levelno == logging.WARNING
    assert spec in warned[0].getMessage() and "not a single MAVLink message" in warned[0].getMessage()


def test_only_a_ground_station_on_the_link_is_reported(caplog):
    port = free_port()
    spec = f"udpin:127.0.0.1:{port}"
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.mavlink"):
        with TelemetryReader(spec, no_data_warning=0.6) as reader:
            gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255)
            try:
                gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4)
                assert wait_until(lambda: any("no telemetry" in r.getMessage() for r in caplog.records))
            finally:
                gcs.close()
    message = next(r.getMessage() for r in caplog.records if "no telemetry" in r.getMessage())
    assert spec in message and "system 255: 1" in message
    assert reader.stats.system_id is None and reader.stats.total == 0


def test_a_link_going_silent_is_a_warning_naming_it(synthetic, caplog):
    path, _ = synthetic
    port = free_port()
    spec = f"udpin:127.0.0.1:{port}"
    with caplog.at_level(logging.WARNING, logger="photomap.drivers.mavlink"):
        with TelemetryReader(spec, link_timeout=0.3) as reader:
            th, _ = _replay_thread(path, f"udpout:127.0.0.1:{port}", speed=10.0, stop_after=0.1)
            th.join(10)
            assert wait_until(lambda: reader.link_lost)
    lost = [r.getMessage() for r in caplog.records if "link lost" in r.getMessage()]
    # once when the replay stops (and maybe once more mid-stream on a busy machine), by name
    assert lost and all(spec in m for m in lost)
    assert not [r for r in caplog.records if "no telemetry" in r.getMessage()]


# ----------------------------------------------------------------------------- STATUSTEXT
def test_statustext_chunks():
    assert statustext_chunks("") == [b""]
    assert statustext_chunks("x" * 50) == [b"x" * 50]                       # fits: one, id 0
    assert statustext_chunks("x" * 51) == [b"x" * 50, b"x"]
    assert statustext_chunks("x" * 100) == [b"x" * 50, b"x" * 50, b""]      # a NUL ends it
    text = "Kartierung läuft: Höhe über Grund unbekannt, Verbindung zur Karte verloren"
    chunks = statustext_chunks(text)
    assert all(len(c) == 50 for c in chunks[:-1]) and len(chunks[-1]) < 50
    assert b"".join(chunks).decode("utf-8") == text
    assert len(statustext_chunks("y" * 20000)) == 256                      # chunk_seq is a uint8


@pytest.mark.parametrize("text", ["photomap: link to map lost, new segment at frame 12345 (confidence 0.03)",
                                  "z" * 100, "ok"])
def test_long_statustext_arrives_whole(text):
    """The bug: STATUSTEXT was cut at 50 bytes. Chunks share a nonzero id, chunk_seq 0, 1, ..."""
    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
    link = open_link(f"udpout:127.0.0.1:{port}", source_system=1)
    try:
        link.send_status(text, mavlink.MAV_SEVERITY_WARNING)
        got = []
        while (msg := gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=3.0)) is not None:
            got.append(msg)
            if b"\x00" in msg._text_raw or (msg.id == 0):
                break
    finally:
        link.close()
        gcs.close()
    assert got and all(m.severity == mavlink.MAV_SEVERITY_WARNING for m in got)
    if len(text) <= 50:
        assert len(got) == 1 and got[0].id == 0 and got[0].text == text
        return
    assert len({m.id for m in got}) == 1 and got[0].id != 0
    assert [m.chunk_seq for m in got] == list(range(len(got)))
    assert b"".join(m._text_raw.rstrip(b"\x00") for m in got).decode() == text


def test_an_antenna_tracker_is_not_the_vehicle(tmp_path):
    """An ArduPilot antenna tracker has an autopilot too: its HEARTBEAT must not win the lock."""
    path = tmp_path / "tracker.tlog"
    with open(path, "wb") as f:
        w = _TlogWriter(f)
        tracker = mavlink2.MAVLink(w, srcSystem=2, srcComponent=1)
        vehicle = mavlink2.MAVLink(w, srcSystem=1, srcComponent=1)
        for k in range(20):
            w.t_us = round((T0 + k / 10) * 1e6)
            if k % 10 == 0:
                tracker.send(tracker.heartbeat_encode(mavlink.MAV_TYPE_ANTENNA_TRACKER,
                                                      mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4))
                tracker.send(tracker.attitude_encode(1000 + k * 100, 0, 0, OTHER_YAW, 0, 0, 0))
            if k % 10 == 1:
                vehicle.send(vehicle.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR,
                                                      mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4))
            vehicle.send(vehicle.attitude_encode(1000 + k * 100, 0, 0, true_yaw(k / 10), 0, 0, 0))
    buf, stats = load_tlog(path, max_gap=1.0, max_hold=0.3)
    assert stats.system_id == 1 and stats.other_systems[2] == 4
    assert [buf.at(T0 + k / 10).yaw for k in range(20)] == pytest.approx(
        [true_yaw(k / 10) for k in range(20)], abs=1e-6)
