"""Decoder messages of native code (FFmpeg's ``av_log``, OpenCV's videoio log) counted, not printed.

FFmpeg inside OpenCV writes its messages straight to file descriptor 2 ("[h264 @ 0x...] non-existing
PPS 0 referenced" once per packet while a decoder waits for a key frame), OpenCV its own
("[ WARN:0@5.0] global cap_ffmpeg_impl.hpp:453 ... Stream timeout triggered"). Python's logging
cannot see or filter them. While a :class:`StderrTap` is held, fd 2 is a pipe read by a thread: a
line in one of those two forms is counted by its text (numbers folded) and dropped; every other line
(Python's own log, any other library) goes on, unchanged and in order, to the real stderr. Releasing
the last hold restores fd 2.

The tap is one per process (fd 2 is): :func:`acquire` and :func:`release` count the holders.

Native writers may split a line over several writes (av_log writes its "[h264 @ 0x...] " prefix
and its message apart), so a line another thread writes to fd 2 between them would be read as part
of a decoder line. Python's own log therefore does not go through fd 2: :func:`python_stderr` is a
stream to the real stderr that no tap is in (photomap's log handler writes to it).
"""

from __future__ import annotations

import atexit
import os
import re
import sys
import threading
from collections import Counter
from typing import TextIO

# "[h264 @ 0x55813e5c9880] non-existing PPS 0 referenced"
_AV_LOG = re.compile(r"^\[([\w:.\-]+) @ (?:0x)?[0-9a-fA-F]+\] ?(.*)$")
# OpenCV's own log: "[ WARN:0@5.010] global cap_ffmpeg_impl.hpp:453 _opencv_ffmpeg_interrupt_callback
# Stream timeout ...", "[ WARN:0@0.031] global grfmt_tiff.cpp:123 TIFF_Warning TIFFReadDirectory: ..."
_CV_LOG = re.compile(r"^\[\s*(?:WARN|ERROR|INFO|DEBUG)[^\]]*\]\s*(?:global\s+)?(?:(\S+?\.[ch]pp)(?::\d+)?\s+)?(.*)$")
_FUNCTION = re.compile(r"^\w+ ")  # videoio's lines name the function first
# av_log's own repeat suppression: "    Last message repeated 5 times"
_REPEATED = re.compile(r"^\s*Last message repeated (\d+) times?\s*$")
# Numbers that change from message to message (times, sizes, addresses), not parts of an address.
_NUMBER = re.compile(r"(?<![.\d:])(?:0x[0-9a-fA-F]+|\d+\.\d+|\d{3,})(?![.\d:])")

CLOSE_WAIT_S = 2.0  # seconds StderrTap.close waits for the pump to forward what is in the pipe


def python_stderr() -> TextIO:
    """A line-buffered text stream to the process's stderr that bypasses any tap (a duplicate
    of fd 2 taken now, before a tap replaces fd 2; ``sys.stderr`` where fd 2 cannot be duplicated).
    Call it before the first :func:`acquire`; the stream stays open for the process's life."""
    try:
        fd = os.dup(2)
    except OSError:  # no stderr at all
        return sys.stderr
    return open(fd, "w", buffering=1, encoding=getattr(sys.stderr, "encoding", None) or "utf-8",
                errors="backslashreplace")


def opencv_log(line: str) -> tuple[str, str] | None:
    """``(source file, message)`` of a line of OpenCV's own log (``[ WARN:0@t] global
    file.cpp:line message``; the source ``""`` when the line names none), or None when the line
    is not one. Shared by the decoder tap (videoio's ``cap*`` sources) and the still reader
    (:mod:`photomap.drivers.imread`: imgcodecs' warnings during a read)."""
    m = _CV_LOG.match(line.strip())
    return None if m is None else (m.group(1) or "", m.group(2).strip())


def decoder_message(line: str) -> str | None:
    """The counting key of a native decoder log line ("h264: non-existing PPS N referenced"),
    or None when the line is something else."""
    m = _AV_LOG.match(line)
    if m:
        return f"{m.group(1)}: {_NUMBER.sub('N', m.group(2).strip())}"
    cv = opencv_log(line)
    if cv is not None and cv[0].startswith("cap"):  # videoio: cap.cpp, cap_ffmpeg_impl.hpp, cap_gstreamer.cpp ...
        return f"opencv: {_NUMBER.sub('N', _FUNCTION.sub('', cv[1], count=1))}"
    return None


def summarise(counts: Counter, most: int = 3) -> str:
    """One line for ``counts`` (key -> number): "23 decoder messages (15x h264: ..., ...)"."""
    total = sum(counts.values())
    if not total:
        return "no decoder messages"
    top = ", ".join(f"{n}x {key!r}" for key, n in counts.most_common(most))
    more = "" if len(counts) <= most else f", {len(counts) - most} other kinds"
    return f"{total} decoder message{'s' if total != 1 else ''} ({top}{more})"


class StderrTap:
    """fd 2 through a pipe: native decoder lines counted, everything else passed on.

    ``take()`` returns and resets the counts. Use :func:`acquire`/:func:`release`, not the
    class, so that one process has one tap.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter = Counter()
        self._last_key: str | None = None
        try:
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):
            pass
        self._saved = os.dup(2)
        read_end, write_end = os.pipe()
        os.dup2(write_end, 2)
        os.close(write_end)
        self._read_end = read_end
        self._thread = threading.Thread(target=self._pump, name="photomap-stderr-tap", daemon=True)
        self._thread.start()

    def take(self) -> Counter:
        """The decoder messages counted since the last ``take()`` (and reset them)."""
        with self._lock:
            counts, self._counts = self._counts, Counter()
        return counts

    def _pump(self) -> None:
        pending = b""
        try:
            while chunk := os.read(self._read_end, 65536):  # to the pipe's end: every writer gone
                pending += chunk
                *lines, pending = pending.split(b"\n")
                passed = [line + b"\n" for line in lines if not self._counted(line)]
                if passed:
                    self._write(b"".join(passed))
            if pending and not self._counted(pending):
                self._write(pending)
        finally:  # the pump's own: nothing reads or writes them after this
            os.close(self._read_end)
            os.close(self._saved)

    def _counted(self, raw: bytes) -> bool:
        line = raw.decode("utf-8", "replace").rstrip("\r")
        key = decoder_message(line)
        repeated = _REPEATED.match(line)
        with self._lock:
            if key is not None:
                self._counts[key] += 1
                self._last_key = key
                return True
            if repeated and self._last_key is not None:
                self._counts[self._last_key] += int(repeated.group(1))
                return True
            self._last_key = None
        return False

    def _write(self, data: bytes) -> None:
        while data:
            try:
                data = data[os.write(self._saved, data):]
            except OSError:
                return  # the real stderr is gone: nothing to tell

    def close(self) -> None:
        """Restore fd 2 and wait (at most :data:`CLOSE_WAIT_S`) for the pump to pass on what is
        still in the pipe. The pump owns the pipe's read end and the saved stderr and closes both
        at the pipe's end, so what it forwards is never cut off: a writer that still holds the
        pipe (a child process that inherited fd 2) keeps it forwarding after the wait."""
        try:
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):
            pass
        os.dup2(self._saved, 2)  # closes the pipe's write end held by fd 2: the pump sees its end
        self._thread.join(CLOSE_WAIT_S)


_tap: StderrTap | None = None
_holders = 0
_tap_lock = threading.Lock()


def acquire() -> StderrTap:
    """Hold the process's tap (installing it on the first hold)."""
    global _tap, _holders
    with _tap_lock:
        if _tap is None:
            _tap = StderrTap()
            atexit.register(_restore_at_exit)
        _holders += 1
        return _tap


def _restore_at_exit() -> None:
    """At exit with a hold left (a capture thread stuck in the driver): fd 2 back, the pipe drained."""
    global _tap, _holders
    with _tap_lock:
        tap, _tap, _holders = _tap, None, 0
    if tap is not None:
        tap.close()


def release() -> Counter:
    """Drop a hold; the last one restores fd 2. Returns the counts not taken yet."""
    global _tap, _holders
    with _tap_lock:
        if _tap is None:
            return Counter()
        _holders -= 1
        if _holders > 0:
            return Counter()
        tap, _tap = _tap, None
    tap.close()
    return tap.take()


def current() -> StderrTap | None:
    """The installed tap, if any hold is active."""
    with _tap_lock:
        return _tap
