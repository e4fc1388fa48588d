"""MAVLink telemetry: open a link, read it in a thread into a :class:`TelemetryBuffer`, load a tlog.

Connection strings are pymavlink's/MAVProxy's: ``udpin:0.0.0.0:14550``, ``udpout:HOST:PORT``,
``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``, a serial device
(``/dev/ttyUSB0``, ``/dev/ttyACM0,115200``, ``COM3,baud=57600``; needs the ``serial`` extra)
or a ``.tlog`` file (replay).

Time base: samples are stamped with host UNIX seconds. Live: the host clock at receipt, taken
as ``time.time()`` once at start plus ``time.monotonic()`` elapsed, so it never steps back.
From a tlog: the recorded receipt time of each message (``_timestamp``).

This module sets ``MAVLINK20=1`` before importing pymavlink, so that every connection in
the process speaks MAVLink 2 (pymavlink switches process-wide anyway on the first v2 frame).
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402  (needs MAVLINK20 set first)

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pymavlink was imported before us
    mavutil.set_dialect(mavutil.current_dialect)

from photomap.config import TelemetryConfig  # noqa: E402
from photomap.errors import InputError  # noqa: E402
from photomap.telemetry.samples import MESSAGE_TYPES, TelemetryBuffer, TelemetrySample  # noqa: E402

log = logging.getLogger(__name__)

mavlink = mavutil.mavlink
#: Types the reader asks pymavlink for; everything else (BAD_DATA, UNKNOWN_*, ...) is dropped.
RECV_TYPES = ["HEARTBEAT", *MESSAGE_TYPES]
_NET_PREFIXES = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")
_DATAFLASH_SUFFIXES = (".bin", ".log", ".px4log")
#: Seconds within which an identical frame of the same source is a duplicate.
DUPLICATE_WINDOW = 0.05
_SERIAL_RE = re.compile(r"^(?P<dev>/dev/\S+?|COM\d+)(?:,(?:baud=)?(?P<baud>\d+))?$", re.IGNORECASE)


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
        """Send a STATUSTEXT (``severity`` is a MAV_SEVERITY_*; text cut to MAVLink's 50 bytes)."""
        if self.is_log:
            return
        with self._send_lock:
            self.conn.mav.statustext_send(severity, text.encode("utf-8")[:50])

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
    a missing file or device, a refused TCP connection, or pyserial missing.
    """
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

    @property
    def total(self) -> int:
        return sum(self.messages.values())


def _autopilot_time(msg: Any) -> int | None:
    for name in ("time_boot_ms", "time_usec"):
        v = getattr(msg, name, None)
        if v is not None:
            return v
    return None


class _Ingest:
    """Feeds messages into a buffer: dedupes, counts, logs each kind of problem once."""

    def __init__(self, buffer: TelemetryBuffer, stats: LinkStats, link_timeout: float) -> None:
        self.buffer = buffer
        self.stats = stats
        self.link_timeout = link_timeout
        self.last_t: float | None = None
        self.lost = False
        self._previous: dict[tuple, tuple] = {}
        self._warned: set[str] = set()
        self._bad: set[str] = set()
        self._recovered: set[str] = set()

    def message(self, msg: Any, t: float) -> None:
        st = self.stats
        mtype = msg.get_type()
        st.messages[mtype] += 1
        if self.last_t is not None and not self.lost and t - self.last_t > self.link_timeout:
            self.lose(t, f"no message for {t - self.last_t:.1f} s")
        if self.lost:
            self.lost = False
            st.link_regained += 1
            log.info("MAVLink data again (%s)", mtype)
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
        log.warning("MAVLink link lost: %s", why)

    def _once(self, kind: str, consequence: str) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning("telemetry: %s; %s (logged once)", kind, consequence)


def load_tlog(path: str | Path, *, max_gap: float = 2.0, max_hold: float = 0.5,
              link_timeout: float = 2.0) -> tuple[TelemetryBuffer, LinkStats]:
    """Read a whole ``.tlog`` into a buffer with no horizon (for replay).

    Samples are stamped with the recorded receipt times (UNIX seconds). A silence longer
    than ``link_timeout`` in the log is marked as a gap. Returns the buffer and its stats.
    """
    link = open_link(str(path))
    if not link.is_log:
        link.close()
        raise InputError(f"not a telemetry log: {path}")
    buffer = TelemetryBuffer(max_gap=max_gap, max_hold=max_hold, horizon=None)
    stats = LinkStats()
    ingest = _Ingest(buffer, stats, link_timeout)
    try:
        while (msg := link.recv(RECV_TYPES, 0.0)) is not None:
            ingest.message(msg, msg._timestamp)
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
    open_kwargs
        Passed to :func:`open_link` (``baud``, ``source_system``).
    """

    recv_timeout = 0.5

    def __init__(self, link: str | Link, buffer: TelemetryBuffer | None = None, *,
                 link_timeout: float = 2.0, send_heartbeat: bool = False,
                 speed: float | None = None, **open_kwargs: Any) -> None:
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
        self._ingest = _Ingest(self.buffer, self.stats, self.link_timeout)

    @classmethod
    def from_config(cls, params: TelemetryConfig) -> TelemetryReader:
        """A reader (not started) for the ``telemetry`` settings; ``source`` must be set."""
        if not params.source:
            raise InputError("no telemetry source configured (telemetry.source)")
        buffer = TelemetryBuffer(max_gap=params.max_gap, max_hold=params.max_hold, horizon=params.horizon)
        return cls(params.source, buffer, link_timeout=params.link_timeout,
                   send_heartbeat=params.send_heartbeat, baud=params.baud,
                   source_system=params.source_system)

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
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if self.send_heartbeat and not link.is_log and now >= next_beat:
                    link.send_heartbeat()
                    next_beat = now + 1.0
                msg = link.recv(RECV_TYPES, self.recv_timeout)
                self.stats.receive_errors = link.receive_errors
                if msg is None:
                    if link.is_log:
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

    def _check_silence(self, t_now: float) -> None:
        ing = self._ingest
        if ing.last_t is not None and not ing.lost and t_now - ing.last_t > self.link_timeout:
            with self.lock:
                ing.lose(t_now, f"no message for {self.link_timeout:g} s")
