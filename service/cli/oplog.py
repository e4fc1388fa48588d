"""What an operator (or journald) reads while a run goes on: JSON log lines and a periodic status line.

``--log-format json`` gives one JSON object per line on stderr (:class:`JsonFormatter`); the
status line (:class:`StatusReporter`) says every few seconds what the mapping does, for a
service that otherwise prints nothing between its start and its stop.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from datetime import datetime, timezone
from typing import Any, Callable

from photomap.drivers import native_log
from photomap.mapping.events import FrameEvent

STATUS_LOGGER = "photomap.status"
LOG_FORMATS = ("text", "json")

# attributes every LogRecord has; anything else on a record came from ``extra=``
_RECORD_FIELDS = frozenset(logging.LogRecord("", 0, "", 0, "", (), None).__dict__) | {"message", "asctime"}


class JsonFormatter(logging.Formatter):
    """One JSON object per record: ``time`` (UTC, ISO 8601, ms), ``level``, ``logger``,
    ``message``, then the record's ``extra=`` fields, and ``exception`` (the formatted traceback)
    when there is one. Values JSON cannot hold are written as their ``str``; non-finite floats
    as ``null``."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in record.__dict__.items():
            if key not in _RECORD_FIELDS and not key.startswith("_") and key not in out:
                out[key] = _jsonable(value)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exception"] = record.exc_text
        return json.dumps(out, default=str, allow_nan=False)


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def setup_logging(level: int, log_format: str = "text") -> None:
    """Log records of ``level`` and above to stderr, as text (``HH:MM:SS LEVEL logger: message``)
    or JSON lines (:class:`JsonFormatter`; Python warnings are routed into the log too).

    The records go to stderr past the decoder-message tap (:func:`photomap.drivers.native_log.python_stderr`),
    so that a native line written in pieces never swallows one. Like :func:`logging.basicConfig`,
    it leaves a root logger that already has handlers alone (e.g. under pytest).
    """
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {LOG_FORMATS}, got {log_format!r}")
    if logging.getLogger().handlers:
        return
    handler = logging.StreamHandler(native_log.python_stderr())
    if log_format == "json":
        handler.setFormatter(JsonFormatter())
        logging.basicConfig(level=level, handlers=[handler])
        logging.captureWarnings(True)
    else:
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                            datefmt="%H:%M:%S", handlers=[handler])


class StatusReporter:
    """A status line at INFO every ``interval`` seconds while mapping.

    :meth:`on_frame` is a pipeline sink: it only updates counters under a lock (a few µs, never
    raises). A daemon thread logs the line, so a stalled camera shows up as "no frames for N s"
    and a slow log writer never holds up the worker. The line (logger ``photomap.status``) gives
    frames in total and per second over the interval, the share registered, frames dropped by
    the capture, map segments, capture-to-mapped latency (live sources; else the worker's ms per
    frame), camera reconnects and the telemetry link state (``none`` without telemetry, ``ok``,
    ``lost``, ``no sample``). The same values are the record's ``extra`` fields (JSON lines).

    Parameters
    ----------
    interval : float
        Seconds between lines (> 0).
    telemetry : bool
        Whether telemetry is joined (else the link state is ``none``).
    clock : callable
        Monotonic seconds; must be the clock of live ``FrameEvent.t`` (``time.monotonic``).
    logger : logging.Logger
        Where the lines go.
    """

    def __init__(self, interval: float, *, telemetry: bool = False,
                 clock: Callable[[], float] = time.monotonic, logger: logging.Logger | None = None) -> None:
        if not interval > 0:
            raise ValueError(f"status interval must be > 0 s, got {interval}")
        self.interval = float(interval)
        self.telemetry = telemetry
        self.clock = clock
        self.log = logger or logging.getLogger(STATUS_LOGGER)
        self.lines = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        t = clock()
        self._t_start = self._t_last_report = self._t_last_frame = t
        self._frames = self._registered = self._dropped = self._reconnects = 0
        self._segments = 0
        self._link = "none"
        self._live = False
        # over the current interval
        self._n = self._n_registered = 0
        self._frame_ms = 0.0
        self._latency_ms: list[float] = []

    # ------------------------------------------------------------------ worker side
    def on_frame(self, event: FrameEvent) -> None:
        """The pipeline sink: count the frame. Never raises."""
        try:
            now = self.clock()
            registered = event.status in ("reference", "registered")
            if not self.telemetry:
                link = "none"
            elif event.link_lost > event.link_regained:
                link = "lost"
            else:
                link = "ok" if event.telemetry is not None else "no sample"
            with self._lock:
                self._frames += 1
                self._n += 1
                self._registered += registered
                self._n_registered += registered
                self._dropped = event.dropped_frames
                self._reconnects = event.reconnects
                self._segments = max(self._segments, event.segment + 1)
                self._link = link
                self._frame_ms += event.frame_ms
                self._live = event.live
                if event.live and len(self._latency_ms) < 100_000:
                    self._latency_ms.append(1000.0 * (now - event.t))
                self._t_last_frame = now
        except Exception:  # a status line must never cost a frame
            pass

    # ------------------------------------------------------------------ reporting
    def start(self) -> StatusReporter:
        """Start the thread that logs every ``interval`` seconds."""
        self._thread = threading.Thread(target=self._run, name="photomap-status", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.report()
            except Exception:
                pass

    def report(self) -> dict:
        """Log the status line now (and start a new interval); returns its fields."""
        now = self.clock()
        with self._lock:
            span = max(now - self._t_last_report, 1e-9)
            n, n_reg, frame_ms, lat = self._n, self._n_registered, self._frame_ms, self._latency_ms
            fields: dict[str, Any] = {
                "frames": self._frames, "fps": round(n / span, 2), "dropped": self._dropped,
                "segments": self._segments, "reconnects": self._reconnects, "telemetry": self._link,
                "registered_pct": round(100.0 * n_reg / n, 1) if n else None,
                "worker_ms": round(frame_ms / n, 2) if n else None,
                "idle_s": round(now - self._t_last_frame, 1),
            }
            self._n = self._n_registered = 0
            self._frame_ms, self._latency_ms = 0.0, []
            self._t_last_report = now
        if lat:
            lat.sort()
            fields["latency_ms"] = round(lat[len(lat) // 2], 1)
            fields["latency_max_ms"] = round(lat[-1], 1)
        self.log.info(self._line(fields, n, span), extra=fields)
        self.lines += 1
        return fields

    @staticmethod
    def _line(f: dict, n: int, span: float) -> str:
        if n == 0:
            head = (f"status: no frames for {f['idle_s']:.0f} s ({f['frames']} in total)" if f["frames"]
                    else f"status: waiting for the first frame ({f['idle_s']:.0f} s)")
        else:
            head = (f"status: {f['frames']} frames, {f['fps']:.1f} fps, "
                    f"{f['registered_pct']:.0f}% registered")
        if n and f["idle_s"] >= 1.0 and f["idle_s"] >= span / 2:
            head += f", last frame {f['idle_s']:.0f} s ago"
        parts = [head, f"{f['dropped']} dropped", f"{f['segments']} segment{'s' if f['segments'] != 1 else ''}"]
        if "latency_ms" in f:
            parts.append(f"latency {f['latency_ms']:.0f} ms (max {f['latency_max_ms']:.0f})")
        elif f["worker_ms"] is not None:
            parts.append(f"{f['worker_ms']:.1f} ms/frame")
        if f["reconnects"]:
            parts.append(f"{f['reconnects']} camera reconnects")
        parts.append(f"telemetry {f['telemetry']}")
        return ", ".join(parts)

    def close(self) -> None:
        """Stop the thread (no final line: the run's summary follows). Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
