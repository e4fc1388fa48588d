"""MAVLink telemetry: open a link, read it in a thread into a :class:`TelemetryBuffer`, load a tlog.

Connection strings are pymavlink's/MAVProxy's: ``udpin:0.0.0.0:14550``, ``udpout:HOST:PORT``,
``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``, a serial device
(``/dev/ttyUSB0``, ``/dev/ttyACM0,115200``, ``COM3,baud=57600``; needs the ``serial`` extra)
or a ``.tlog`` file (replay).

Time base: samples are stamped with host UNIX seconds. Live: the host clock at receipt, taken
as ``time.time()`` once at start plus ``time.monotonic()`` elapsed, so it never steps back.
From a tlog: the recorded receipt time of each message (``_timestamp``).

One vehicle: the reader follows one MAVLink system, the configured ``system_id`` or (0, auto)
the sender of the first autopilot HEARTBEAT (``autopilot != MAV_AUTOPILOT_INVALID``; a ground
station's, an antenna tracker's or a peripheral's heartbeat does not count). Messages of other systems are counted per system id and
ignored, so a second vehicle (or a GCS) on the link never mixes into the telemetry. Messages
that arrive before the first autopilot HEARTBEAT wait (up to ``LOCK_WAIT`` s of data) and are
used once their system is known; without any autopilot HEARTBEAT the system sending most is
followed, with a warning.

This module sets ``MAVLINK20=1`` before importing pymavlink, so that every connection in
the process speaks MAVLink 2 (pymavlink switches process-wide anyway on the first v2 frame).
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402  (needs MAVLINK20 set first)

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pymavlink was imported before us
    mavutil.set_dialect(mavutil.current_dialect)

from photomap.config import TelemetryConfig  # noqa: E402
from photomap.errors import ConfigError, InputError  # noqa: E402
from photomap.telemetry.samples import MESSAGE_TYPES, TelemetryBuffer, TelemetrySample  # noqa: E402

log = logging.getLogger(__name__)

mavlink = mavutil.mavlink
#: Types the reader asks pymavlink for; everything else (BAD_DATA, UNKNOWN_*, ...) is dropped.
RECV_TYPES = ["HEARTBEAT", *MESSAGE_TYPES]
_NET_PREFIXES = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")
_DATAFLASH_SUFFIXES = (".bin", ".log", ".px4log")
#: Seconds within which an identical frame of the same source is a duplicate.
DUPLICATE_WINDOW = 0.05
#: Seconds of data (message time) that wait for an autopilot HEARTBEAT before the system
#: sending most is followed anyway.
LOCK_WAIT = 3.0
#: Messages held while waiting for the autopilot HEARTBEAT (beyond: the fallback decides).
_PENDING_MAX = 5000
#: Bytes of text in one STATUSTEXT.
STATUSTEXT_BYTES = 50
#: HEARTBEAT types that are never the vehicle, even with an autopilot (an ArduPilot antenna
#: tracker, a ground station, peripherals with their own system id).
_NOT_VEHICLES = frozenset(getattr(mavlink, f"MAV_TYPE_{n}") for n in (
    "GCS", "ANTENNA_TRACKER", "ONBOARD_CONTROLLER", "CAMERA", "GIMBAL", "ADSB", "OSD", "LOG",
    "ODID", "FLARM", "BATTERY", "SERVO", "GPS", "IMU", "WINCH", "GRIPPER", "PARACHUTE",
    "ILLUMINATOR", "CHARGING_STATION") if hasattr(mavlink, f"MAV_TYPE_{n}"))
_SERIAL_RE = re.compile(r"^(?P<dev>/dev/\S+?|COM\d+)(?:,(?:baud=)?(?P<baud>\d+))?$", re.IGNORECASE)


def check_id(value: Any, key: str, *, auto: bool = False) -> int:
    """``value`` as a MAVLink system/component id (1..255; 0 too when ``auto``).

    Raises
    ------
    ConfigError
        Naming ``key`` (the config key or parameter the value came from).
    """
    low = 0 if auto else 1
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= 255:
        allowed = "0 (auto) or 1..255" if auto else "1..255"
        raise ConfigError(f"{key} must be a MAVLink id, {allowed}; got {value!r}")
    return value


def is_vehicle_heartbeat(msg: Any) -> bool:
    """True for the HEARTBEAT of a vehicle's autopilot: ``autopilot != MAV_AUTOPILOT_INVALID``
    and not a ground station, antenna tracker or peripheral type."""
    return (msg.get_type() == "HEARTBEAT"
            and getattr(msg, "autopilot", mavlink.MAV_AUTOPILOT_INVALID) != mavlink.MAV_AUTOPILOT_INVALID
            and getattr(msg, "type", mavlink.MAV_TYPE_GCS) not in _NOT_VEHICLES)


def statustext_chunks(text: str, size: int = STATUSTEXT_BYTES) -> list[bytes]:
    """UTF-8 ``text`` cut into STATUSTEXT payloads of at most ``size`` bytes (MAVLink 2 chunking).

    Every chunk but the last is exactly ``size`` bytes (a NUL in a chunk marks the last one, and
    MAVLink pads a shorter text with NULs); when the text fills its last chunk exactly, an
    empty chunk ends the sequence. At most 256 chunks (``chunk_seq`` is a uint8): longer text
    is cut. A text that fits one message is one chunk.
    """
    data = text.encode("utf-8")
    if len(data) <= size:
        return [data]
    chunks = [data[i:i + size] for i in range(0, len(data), size)]
    if len(chunks[-1]) == size:
        chunks.append(b"")
    if len(chunks) > 256:
        chunks = chunks[:255] + [b""]
    return chunks


class Link:
    """An open MAVLink connection (network, serial or tlog) and what we send on it.

    Sending is serialised by a lock, so ``send_status`` may be called from any thread while
    the reader thread receives.
    """

    def __init__(self, conn: Any, spec: str, kind: str) -> None:
        self.conn = conn
        self.spec = spec
        #: "udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin", "serial" or "tlog".
        self.kind = kind
        self._send_lock = threading.Lock()
        self._status_id = 0  # id of the last chunked STATUSTEXT (1..65535)

    @property
    def is_log(self) -> bool:
        """True for a ``.tlog`` file: messages carry recorded times, the end is final."""
        return self.kind == "tlog"

    @property
    def receive_errors(self) -> int:
        """Frames pymavlink's parser failed on (bad CRC, garbage) so far."""
        return int(getattr(self.conn.mav, "total_receive_errors", 0))

    def recv(self, types: list[str], timeout: float) -> Any:
        """Next message of one of ``types``, or None after ``timeout`` seconds (at once at a log's end)."""
        if self.is_log:
            return self.conn.recv_match(type=types, blocking=False)
        return self.conn.recv_match(type=types, blocking=True, timeout=timeout)

    def write(self, data: bytes) -> None:
        """Send raw bytes (e.g. a recorded frame) on the link."""
        with self._send_lock:
            self.conn.write(data)

    def send_heartbeat(self) -> None:
        """Announce ourselves: MAV_TYPE_ONBOARD_CONTROLLER, no autopilot, active."""
        if self.is_log:
            return
        with self._send_lock:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                         mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)

    def send_status(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (``severity`` is a MAV_SEVERITY_*).

        Text longer than 50 bytes goes as a MAVLink 2 chunk sequence (same nonzero ``id``,
        ``chunk_seq`` 0, 1, ...; see :func:`statustext_chunks`), which QGroundControl, MAVSDK
        and Mission Planner reassemble. A send error (network down) is logged, never raised.
        """
        if self.is_log:
            return
        chunks = statustext_chunks(text)
        try:
            with self._send_lock:
                if len(chunks) == 1:
                    self.conn.mav.statustext_send(severity, chunks[0])
                    return
                self._status_id = self._status_id % 65535 + 1
                for seq, chunk in enumerate(chunks):
                    self.conn.mav.statustext_send(severity, chunk, id=self._status_id, chunk_seq=seq)
        except OSError as exc:
            log.warning("MAVLink %s: STATUSTEXT not sent: %s", self.spec, exc)

    def close(self) -> None:
        """Close the connection (idempotent)."""
        try:
            self.conn.close()
        except OSError:
            pass


def _check_host_port(spec: str, prefix: str) -> None:
    rest = spec[len(prefix) + 1:]
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"bad MAVLink connection string {spec!r}: expected {prefix}:HOST:PORT")


def open_link(spec: str, *, baud: int = 57600, source_system: int = 1,
              source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER) -> Link:
    """Open a MAVLink connection from a MAVProxy/QGC-style string (see the module doc).

    ``baud`` is used for a serial device whose string names none. ``source_system`` and
    ``source_component`` identify what *we* send. Raises :class:`InputError` on a bad string,
    a missing file or device, a refused TCP connection, or pyserial missing;
    :class:`ConfigError` on an id outside 1..255 (``telemetry.source_system``).
    """
    check_id(source_system, "telemetry.source_system")
    check_id(source_component, "MAVLink source_component")
    spec = str(spec).strip()
    if not spec:
        raise InputError("empty MAVLink connection string")
    ids = dict(source_system=source_system, source_component=source_component)
    prefix = spec.split(":", 1)[0].lower()
    if prefix in _NET_PREFIXES and ":" in spec:
        _check_host_port(spec, prefix)
        try:
            if prefix == "tcp":
                conn = mavutil.mavlink_connection(spec, autoreconnect=True, retries=1,
                                                  reconnect_delay=0.5, **ids)
            else:
                conn = mavutil.mavlink_connection(spec, **ids)
        except OSError as exc:
            raise InputError(f"cannot open MAVLink link {spec!r}: {exc.strerror or exc}") from None
        return Link(conn, spec, prefix)

    m = _SERIAL_RE.match(spec)
    if m:
        try:
            import serial  # noqa: F401  (pymavlink needs it but does not declare it)
        except ImportError:
            raise InputError(f"{spec!r} is a serial port, which needs pyserial: "
                             "pip install 'ifmi-photomap[serial]'") from None
        dev = m["dev"]
        try:
            conn = mavutil.mavlink_connection(dev, baud=int(m["baud"] or baud), **ids)
        except (OSError, serial.SerialException) as exc:
            raise InputError(f"cannot open serial port {dev}: {exc}") from None
        return Link(conn, spec, "serial")

    path = Path(spec).expanduser()
    if path.suffix.lower() in _DATAFLASH_SUFFIXES:
        raise InputError(f"{spec}: DataFlash logs are not supported, give the telemetry log (.tlog)")
    if path.suffix.lower() == ".tlog" or path.exists():
        if not path.is_file():
            raise InputError(f"telemetry log not found (or not a file): {spec}")
        try:
            conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read telemetry log {spec}: {exc}") from None
        return Link(conn, spec, "tlog")
    raise InputError(f"unrecognised MAVLink connection string {spec!r}: expected udpin:HOST:PORT, "
                     "udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, /dev/ttyXXX[,BAUD] or FILE.tlog")


@dataclass
class LinkStats:
    """What a reader saw. ``messages``: by type, as received (duplicates included)."""

    messages: Counter = field(default_factory=Counter)
    #: Rejected samples by kind, e.g. ``"ATTITUDE: yaw out of range"``.
    rejected: Counter = field(default_factory=Counter)
    #: Fields the sender flagged unknown, by kind, e.g. ``"DISTANCE_SENSOR: rangefinder"``.
    unknown: Counter = field(default_factory=Counter)
    #: Messages repeating the previous one of their type and source (same autopilot time,
    #: or the same bytes within DUPLICATE_WINDOW): dropped.
    duplicates: int = 0
    #: Messages dropped because their time went backwards.
    out_of_order: int = 0
    #: Gaps marked in the buffer (link lost live, or a silence in a log).
    gaps: int = 0
    link_lost: int = 0
    link_regained: int = 0
    #: Frames the MAVLink parser failed on (garbage, bad CRC).
    receive_errors: int = 0
    #: The MAVLink system followed (None until known); ``messages`` counts only its messages.
    system_id: int | None = None
    #: Messages of other systems (ignored), by system id.
    other_systems: Counter = field(default_factory=Counter)
    #: Time (s, the samples' time base) of the first and the last message of the followed system.
    first_t: float | None = None
    last_t: float | None = None

    @property
    def total(self) -> int:
        return sum(self.messages.values())

    @property
    def span(self) -> tuple[float, float] | None:
        """``(first_t, last_t)`` of the followed system's messages, or None before any."""
        if self.first_t is None or self.last_t is None:
            return None
        return self.first_t, self.last_t


def _autopilot_time(msg: Any) -> int | None:
    for name in ("time_boot_ms", "time_usec"):
        v = getattr(msg, name, None)
        if v is not None:
            return v
    return None


class _Ingest:
    """Feeds one system's messages into a buffer: dedupes, counts, logs each kind of problem once.

    ``system_id`` 0 follows the first autopilot HEARTBEAT's system (see the module doc).
    """

    def __init__(self, buffer: TelemetryBuffer, stats: LinkStats, link_timeout: float, *,
                 system_id: int = 0, name: str = "") -> None:
        self.buffer = buffer
        self.stats = stats
        self.link_timeout = link_timeout
        self.name = name
        self.last_t: float | None = None
        self.lost = False
        stats.system_id = system_id or None
        self._pending: deque[tuple[Any, float]] = deque()  # before the system is known
        self._previous: dict[tuple, tuple] = {}
        self._warned: set[str] = set()
        self._bad: set[str] = set()
        self._recovered: set[str] = set()

    @property
    def waiting(self) -> int:
        """Messages held until the system to follow is known."""
        return len(self._pending)

    def message(self, msg: Any, t: float) -> None:
        """Take one received message (``t``: its time in the buffer's time base)."""
        st = self.stats
        src = msg.get_srcSystem()
        if st.system_id is None:
            if msg.get_type() == "HEARTBEAT":
                if is_vehicle_heartbeat(msg):
                    self._follow(src, "its autopilot HEARTBEAT came first")
                    self.message(msg, t)
                else:
                    st.other_systems[src] += 1  # a ground station or a peripheral: never followed
                return
            self._pending.append((msg, t))
            if t - self._pending[0][1] > LOCK_WAIT or len(self._pending) >= _PENDING_MAX:
                self.settle()
            return
        if src != st.system_id:
            st.other_systems[src] += 1
            if msg.get_type() != "HEARTBEAT" or is_vehicle_heartbeat(msg):
                # telemetry or an autopilot: a second vehicle (a ground station's heartbeat is normal)
                self._once(f"system {src} also sends telemetry, ignored",
                           f"following system {st.system_id} only (telemetry.system_id)")
            return
        self._take(msg, t)

    def settle(self) -> None:
        """No autopilot HEARTBEAT so far: follow the system that sent most of the waiting messages."""
        if self.stats.system_id is not None or not self._pending:
            return
        counts = Counter(m.get_srcSystem() for m, _ in self._pending)
        src = counts.most_common(1)[0][0]
        log.warning("MAVLink %s: no autopilot HEARTBEAT in %d messages: following system %d, the "
                    "one sending most (set telemetry.system_id to choose)", self.name,
                    len(self._pending), src)
        self._follow(src, "it sent most")

    def _follow(self, src: int, why: str) -> None:
        """Lock to system ``src``; the waiting messages are taken (or ignored) in order."""
        self.stats.system_id = src
        log.info("MAVLink %s: following system %d (%s)", self.name, src, why)
        pending, self._pending = self._pending, deque()
        for msg, t in pending:
            self.message(msg, t)

    def _take(self, msg: Any, t: float) -> None:
        st = self.stats
        mtype = msg.get_type()
        st.messages[mtype] += 1
        if st.first_t is None:
            st.first_t = t
        st.last_t = t if st.last_t is None else max(st.last_t, t)
        if self.last_t is not None and not self.lost and t - self.last_t > self.link_timeout:
            self.lose(t, f"no message for {t - self.last_t:.1f} s")
        if self.lost:
            self.lost = False
            st.link_regained += 1
            log.info("MAVLink %s: data again (%s)", self.name, mtype)
        self.last_t = t
        if mtype == "HEARTBEAT":
            return
        if self._duplicate(msg, t):
            st.duplicates += 1
            return
        dec, stored = self.buffer.add_message(t, mtype, msg.to_dict())
        if not stored:
            st.out_of_order += 1
            self._once(f"{mtype}: time went backwards", "dropped")
            return
        for what, reason in dec.problems.items():
            kind = f"{mtype}: {what} {reason}"
            st.rejected[kind] += 1
            self._bad.add(mtype)
            self._once(kind, "sample rejected, field unknown until valid data returns")
        for name in dec.unknown:
            st.unknown[f"{mtype}: {name}"] += 1
        if mtype in self._bad and not dec.problems and dec.values:
            self._bad.discard(mtype)
            if mtype not in self._recovered:  # once per type, like the warnings
                self._recovered.add(mtype)
                log.info("valid %s again, used from now on", mtype)

    def _duplicate(self, msg: Any, t: float) -> bool:
        """Same source and type as the previous one, and the same autopilot time, or the
        same payload within ``DUPLICATE_WINDOW`` s (a frame forwarded twice)."""
        key = (msg.get_type(), msg.get_srcSystem(), msg.get_srcComponent(), getattr(msg, "id", None))
        stamp, payload = _autopilot_time(msg), msg.get_payload()
        prev = self._previous.get(key)
        self._previous[key] = (stamp, payload, t)
        if prev is None:
            return False
        return (stamp is not None and stamp == prev[0]) or (
            payload == prev[1] and t - prev[2] <= DUPLICATE_WINDOW)

    def lose(self, t_now: float, why: str) -> None:
        """The link has been silent since ``last_t`` (now ``t_now``): mark the gap, count, log.

        The gap starts ``max_hold`` after the last message, so that a query just after it
        gets the same held value before and after the loss is noticed.
        """
        self.lost = True
        self.buffer.mark_gap(min(self.last_t + self.buffer.max_hold, t_now))
        self.stats.gaps += 1
        self.stats.link_lost += 1
        log.warning("MAVLink %s: link lost: %s", self.name, why)

    def _once(self, kind: str, consequence: str) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning("telemetry: %s; %s (logged once)", kind, consequence)


def load_tlog(path: str | Path, *, max_gap: float = 2.0, max_hold: float = 0.5,
              link_timeout: float = 2.0, system_id: int = 0) -> tuple[TelemetryBuffer, LinkStats]:
    """Read a whole ``.tlog`` into a buffer with no horizon (for replay).

    Samples are stamped with the recorded receipt times (UNIX seconds). A silence longer
    than ``link_timeout`` in the log is marked as a gap. Only one system is read:
    ``system_id`` (``telemetry.system_id``), or 0 for the first autopilot HEARTBEAT's.
    Returns the buffer and its stats (``stats.span``: the followed system's first and last
    message time, e.g. to see that a log ends before the video).
    """
    check_id(system_id, "telemetry.system_id", auto=True)
    link = open_link(str(path))
    if not link.is_log:
        link.close()
        raise InputError(f"not a telemetry log: {path}")
    buffer = TelemetryBuffer(max_gap=max_gap, max_hold=max_hold, horizon=None)
    stats = LinkStats()
    ingest = _Ingest(buffer, stats, link_timeout, system_id=system_id, name=Path(path).name)
    try:
        while (msg := link.recv(RECV_TYPES, 0.0)) is not None:
            ingest.message(msg, msg._timestamp)
        ingest.settle()  # a log without any autopilot HEARTBEAT
    finally:
        stats.receive_errors = link.receive_errors
        link.close()
    if buffer.span is None:
        log.warning("no usable MAVLink telemetry in %s (%d parse errors)", path, stats.receive_errors)
    else:
        log.info("loaded %s: %d messages", path, stats.total)
    return buffer, stats


class TelemetryReader:
    """A thread reading a MAVLink link into a :class:`TelemetryBuffer`.

    The reader owns the buffer's lock: read the buffer (and :attr:`stats`) through :meth:`at`
    or while holding :attr:`lock`. Link loss (no message for ``link_timeout`` s) marks a gap
    in the buffer and is logged; so is the data's return. A ``.tlog`` source is streamed to
    its end (paced by ``speed`` x its recorded timing, or as fast as possible when ``speed``
    is None), then :attr:`finished` is set.

    Parameters
    ----------
    link : str or Link
        A connection string for :func:`open_link`, or an open link (which the reader closes).
    buffer : TelemetryBuffer, optional
        Where samples go (a new one with default settings if None).
    link_timeout : float
        Seconds without any message that count as link lost.
    send_heartbeat : bool
        Send our HEARTBEAT at 1 Hz (live links only).
    speed : float or None
        Pacing of a tlog source (1 = recorded timing).
    system_id : int
        The MAVLink system to follow; 0 = the first autopilot HEARTBEAT's (see the module doc).
    no_data_warning : float
        A live link that delivered nothing from the vehicle this many seconds after the start
        gets one WARNING naming the connection (going silent later is a "link lost" WARNING).
    open_kwargs
        Passed to :func:`open_link` (``baud``, ``source_system``).

    Raises
    ------
    ConfigError
        ``system_id`` (or, at :meth:`start`, ``source_system``) is not a MAVLink id.
    """

    recv_timeout = 0.5

    def __init__(self, link: str | Link, buffer: TelemetryBuffer | None = None, *,
                 link_timeout: float = 2.0, send_heartbeat: bool = False,
                 speed: float | None = None, system_id: int = 0, no_data_warning: float = 5.0,
                 **open_kwargs: Any) -> None:
        check_id(system_id, "telemetry.system_id", auto=True)
        if "source_system" in open_kwargs:
            check_id(open_kwargs["source_system"], "telemetry.source_system")
        self._spec = link
        self._open_kwargs = open_kwargs
        self.buffer = buffer if buffer is not None else TelemetryBuffer()
        self.lock = threading.Lock()
        self.stats = LinkStats()
        self.link: Link | None = None
        self.link_timeout = float(link_timeout)
        self.send_heartbeat = send_heartbeat
        self.speed = speed
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.no_data_warning = float(no_data_warning)
        name = link.spec if isinstance(link, Link) else str(link)
        self._ingest = _Ingest(self.buffer, self.stats, self.link_timeout, system_id=system_id,
                               name=name)

    @classmethod
    def from_config(cls, params: TelemetryConfig) -> TelemetryReader:
        """A reader (not started) for the ``telemetry`` settings; ``source`` must be set."""
        if not params.source:
            raise InputError("no telemetry source configured (telemetry.source)")
        buffer = TelemetryBuffer(max_gap=params.max_gap, max_hold=params.max_hold, horizon=params.horizon)
        return cls(params.source, buffer, link_timeout=params.link_timeout,
                   send_heartbeat=params.send_heartbeat, baud=params.baud,
                   source_system=params.source_system, system_id=params.system_id)

    def start(self) -> TelemetryReader:
        """Open the link (errors raise here, in the caller's thread) and start reading."""
        if self._thread is not None:
            raise RuntimeError("TelemetryReader already started")
        self.link = self._spec if isinstance(self._spec, Link) else open_link(self._spec, **self._open_kwargs)
        self._thread = threading.Thread(target=self._run, name="mavlink-reader", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close the link."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> TelemetryReader:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def link_lost(self) -> bool:
        """True while the link is silent (after ``link_timeout``)."""
        return self._ingest.lost

    def at(self, t: float) -> TelemetrySample:
        """The buffer's :meth:`TelemetryBuffer.at`, under the lock."""
        with self.lock:
            return self.buffer.at(t)

    def send_status(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT on the link (no-op before start or on a log)."""
        if self.link is not None:
            self.link.send_status(text, severity)

    def _run(self) -> None:
        link = self.link
        assert link is not None
        unix0, mono0 = time.time(), time.monotonic()
        next_beat = time.monotonic()
        pace0: tuple[float, float] | None = None
        quiet_start = not link.is_log  # warn once if a live link brings nothing at first
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if self.send_heartbeat and not link.is_log and now >= next_beat:
                    link.send_heartbeat()
                    next_beat = now + 1.0
                if quiet_start and now - mono0 >= self.no_data_warning:
                    quiet_start = False
                    if self._ingest.last_t is None:
                        self._warn_no_data(now - mono0)
                msg = link.recv(RECV_TYPES, self.recv_timeout)
                self.stats.receive_errors = link.receive_errors
                if msg is None:
                    if link.is_log:
                        with self.lock:
                            self._ingest.settle()
                        log.info("end of telemetry log %s after %d messages", link.spec, self.stats.total)
                        break
                    self._check_silence(unix0 + (time.monotonic() - mono0))
                    continue
                if link.is_log:
                    t = msg._timestamp
                    if self.speed:
                        pace0 = pace0 or (t, time.monotonic())
                        delay = (t - pace0[0]) / self.speed - (time.monotonic() - pace0[1])
                        if delay > 0 and self._stop.wait(delay):
                            break
                else:
                    t = unix0 + (time.monotonic() - mono0)
                with self.lock:
                    self._ingest.message(msg, t)
        except Exception:  # a reader must not die silently
            log.exception("MAVLink reader on %s failed", link.spec)
        finally:
            self.stats.receive_errors = link.receive_errors
            link.close()
            self.finished.set()

    def _warn_no_data(self, elapsed: float) -> None:
        st, spec = self.stats, self.link.spec if self.link else self._spec
        if st.other_systems:
            seen = ", ".join(f"system {k}: {v}" for k, v in sorted(st.other_systems.items()))
            why = f"only messages of systems not followed ({seen})"
        elif self._ingest.waiting:
            why = f"{self._ingest.waiting} messages but no autopilot HEARTBEAT yet"
        elif self.stats.receive_errors:
            why = f"{self.stats.receive_errors} unreadable frames (wrong baud rate or protocol?)"
        else:
            why = ("not a single MAVLink message: check the connection string, the port or baud "
                   "rate, and that the vehicle or router sends to this address")
        log.warning("MAVLink %s: no telemetry from the vehicle %.0f s after the start (%s); mapping "
                    "continues without it until it arrives", spec, elapsed, why)

    def _check_silence(self, t_now: float) -> None:
        ing = self._ingest
        if ing.last_t is not None and not ing.lost and t_now - ing.last_t > self.link_timeout:
            with self.lock:
                ing.lose(t_now, f"no message for {self.link_timeout:g} s")
