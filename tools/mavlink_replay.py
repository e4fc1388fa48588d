"""Play a MAVLink ``.tlog`` to a link with its recorded timing (a headless, SITL-style source).

Sends the original frames byte for byte (seq, system id and CRC preserved), paced by the
recorded receipt times divided by ``--speed``. Fault injection for tests: ``--garbage-rate``
sends a burst of random bytes (1-32) before a message with that probability;
``--stop-after`` goes silent after that many wall-clock seconds, like a lost link.

    python tools/mavlink_replay.py flight.tlog --out udpout:127.0.0.1:14550 --speed 2 --loop

``mavplayback.py`` from pymavlink does the same with a Tk GUI, which needs a display.
"""

from __future__ import annotations

import argparse
import logging
import random
import sys
import threading
import time
from pathlib import Path

from photomap.drivers.mavlink import open_link
from photomap.errors import InputError

log = logging.getLogger("mavlink_replay")

_SEND_KINDS = ("udpout", "udpbcast", "tcp", "tcpin", "serial")


def replay(tlog: str | Path, out: str = "udpout:127.0.0.1:14550", speed: float = 1.0,
           loop: bool = False, start: float = 0.0, stop_event: threading.Event | None = None,
           *, garbage_rate: float = 0.0, stop_after: float | None = None,
           seed: int | None = None) -> int:
    """Send the frames of ``tlog`` to ``out`` with their recorded timing; return how many were sent.

    Parameters
    ----------
    tlog : path
        The telemetry log.
    out : str
        Where to send: ``udpout:HOST:PORT``, ``udpbcast:...``, ``tcp:HOST:PORT``,
        ``tcpin:HOST:PORT`` or a serial device.
    speed : float
        Playback speed factor (2 = twice as fast as recorded).
    loop : bool
        Start again at the end of the log (until stopped).
    start : float
        Seconds into the log (from its first message) at which to begin.
    stop_event : threading.Event, optional
        Set it to stop the replay.
    garbage_rate : float
        Probability (0..1) of sending 1-32 random bytes before each message.
    stop_after : float, optional
        Stop after this many wall-clock seconds.
    seed : int, optional
        Seed for the garbage generator.
    """
    if speed <= 0:
        raise InputError(f"speed must be > 0, got {speed}")
    if not 0.0 <= garbage_rate <= 1.0:
        raise InputError(f"garbage rate must be within 0..1, got {garbage_rate}")
    src = open_link(str(tlog))
    if not src.is_log:
        src.close()
        raise InputError(f"not a telemetry log: {tlog}")
    dst = open_link(out)
    if dst.kind not in _SEND_KINDS:
        src.close()
        dst.close()
        raise InputError(f"cannot replay to {out!r}: use udpout:HOST:PORT, tcp:HOST:PORT, tcpin:... or a serial port")
    rng = random.Random(seed)
    stop = stop_event or threading.Event()
    wall_start = time.monotonic()
    sent = 0
    try:
        while True:
            n = _play_once(src, dst, speed, start, stop, wall_start, stop_after, garbage_rate, rng)
            sent += n
            if not loop or n == 0 or stop.is_set() or _expired(wall_start, stop_after):
                break
            src.conn.rewind()
    finally:
        src.close()
        dst.close()
    log.info("sent %d messages in %.2f s", sent, time.monotonic() - wall_start)
    return sent


def _expired(wall_start: float, stop_after: float | None) -> bool:
    return stop_after is not None and time.monotonic() - wall_start >= stop_after


def _play_once(src, dst, speed, start, stop, wall_start, stop_after, garbage_rate, rng) -> int:
    t_first = t_log0 = t_wall0 = None
    sent = 0
    while not stop.is_set():
        msg = src.conn.recv_match()
        if msg is None:  # end of log
            break
        if msg.get_type() == "BAD_DATA":
            continue
        t = msg._timestamp
        t_first = t if t_first is None else t_first
        if t - t_first < start:
            continue
        if t_log0 is None:
            t_log0, t_wall0 = t, time.monotonic()
        delay = (t - t_log0) / speed - (time.monotonic() - t_wall0)
        if stop_after is not None:
            delay = min(delay, stop_after - (time.monotonic() - wall_start))
        if delay > 0 and stop.wait(delay):
            break
        if _expired(wall_start, stop_after):
            break
        if garbage_rate and rng.random() < garbage_rate:
            dst.write(rng.randbytes(rng.randint(1, 32)))
        dst.write(msg.get_msgbuf())
        sent += 1
    return sent


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="mavlink_replay", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tlog", help="telemetry log (.tlog) to play")
    p.add_argument("--out", default="udpout:127.0.0.1:14550",
                   help="destination link (default udpout:127.0.0.1:14550)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end of the log")
    p.add_argument("--start", type=float, default=0.0, metavar="SECONDS",
                   help="begin this many seconds into the log")
    p.add_argument("--garbage-rate", type=float, default=0.0, metavar="P",
                   help="probability of random bytes before each message (fault injection)")
    p.add_argument("--stop-after", type=float, default=None, metavar="SECONDS",
                   help="go silent after this many seconds (fault injection)")
    p.add_argument("--seed", type=int, default=None, help="seed for the garbage bytes")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        replay(args.tlog, args.out, speed=args.speed, loop=args.loop, start=args.start,
               garbage_rate=args.garbage_rate, stop_after=args.stop_after, seed=args.seed)
    except InputError as exc:
        print(f"mavlink_replay: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
