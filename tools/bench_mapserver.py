"""Map server benchmark: what a ground station's client costs the mapping.

A simulated 640x480 flight with its telemetry (``simulate_flight``, aukerman, MJPG video) is
mapped by ``photomap replay`` (:func:`photomap.cli.replay.replay`, as fast as possible) in four
conditions:

- *no server*;
- *server, no client*: ``--map-server`` on loopback, nobody asking;
- *server + client*: a client process that, five times a second, fetches ``/status.json`` and
  the 3 x 3 tiles around the vehicle's position at ``max_zoom`` (``tiles_url`` of the status:
  pixel-frame tiles before the georeference, web-mercator ones after), as a map view following
  the flight does, asking for each tile it holds with its ``ETag`` (``If-None-Match``), as a
  browser's or Qt's HTTP cache does;
- *server + client, no cache*: the same client fetching every tile whole.

Every pass with a server runs between two passes without (:func:`pass_order`), and its effect is
its fps against the geometric mean of those two (:func:`sandwich_effects`): the machine's speed
drifts by several per cent over minutes, which this cancels to first order. Reported per
condition: the pipeline's own fps (``run.json`` ``fps``), the mean fps ratio with a bootstrap 95 %
interval, raw and in units of the machine's speed in the pass (fps times the frame reader's CPU
per frame, :data:`REFERENCE`: the same decoding in every pass, so the speed of a virtual
machine's cores, which swings from pass to pass, cancels); this process's CPU milliseconds per
frame (mapping and server: the client is another process), and its ratio in units of the same
reference; the
server's own CPU by its threads' clocks (:func:`_server_clocks`: answering, and its copy of the
map in the worker); the client's requests (and failures, by reason; 304s), their latencies, its
own CPU, and the server's renders and cache hits. Target: no measurable slowdown, 3 %
(:func:`flat_out_verdict`): the 95 % interval of the client's speed-relative fps ratio above
0.97, or, where it straddles 0.97, that of the CPU ratio below 1.03.

    python -m tools.bench_mapserver [--frames 1500] [--passes 10] [--live-frames 300] [--live-passes 3]
                                    [--hz 5] [--greedy-passes 3] [--no-live] [--out FILE] [--json FILE]

Then a greedy client (:class:`GreedyClient`: 4 connections asking without pause for tiles no view
needs), with the server's CPU budget (``map_server.cpu_share``) and without, ``--greedy-passes``
passes each between passes without a server: the mapping's fps against those. Then (unless
``--no-live``) the live case: a flight of ``--live-frames`` frames (the same
simulation) fed at its frame rate like a camera (``tools.bench_pipeline.PacedVideoSource``),
without a server and with the server and the client: frames mapped and dropped, the worker's ms
per frame.

Replaces the section between ``<!-- mapserver:start -->`` and ``<!-- mapserver:end -->`` of
``docs/benchmarks.md`` (``--out -``: print only). The 1-minute load average before and after is
reported: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import logging
import math
import os
import platform
import random
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Iterator
from unittest import mock

from photomap.cli.replay import replay
from photomap.cli.wiring import map_source
from photomap.config import load_config
from photomap.geo import webmercator as wm
from photomap.live.livemap import LiveMap
from photomap.live.mapserver import MapServer, _Server
from photomap.sim.simulate import simulate_flight
from tools.bench_pipeline import PacedVideoSource
from tools.report import replace_section

REPO = Path(__file__).resolve().parents[1]
SIZE = (640, 480)
FPS = 30.0  # of the simulated flight; the live passes feed it at this rate
NO_SERVER, IDLE, CLIENT, NO_CACHE = "no server", "server, no client", "server + client", "server + client, no cache"
CONDITIONS = (NO_SERVER, IDLE, CLIENT, NO_CACHE)
CLIENTS = {CLIENT: True, NO_CACHE: False}  # the client conditions: whether the client revalidates
GREEDY, GREEDY_FREE = "greedy client", "greedy client, no CPU budget"  # (map_server.cpu_share 0)
GREEDIES = (GREEDY, GREEDY_FREE)
GREEDY_CONNECTIONS = 4
REFERENCE = "photomap-decode"  # the pipeline's frame reader: the same work in every pass
log = logging.getLogger("bench_mapserver")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


class Client(threading.Thread):
    """Fetches the status and the 3 x 3 tiles around the vehicle ``hz`` times a second.

    HTTP/1.1 GETs over one kept-alive plain socket, as a browser or Qt client reuses its
    connections (a new one when the server closes it): the client shares the cores with the
    mapping here, as a ground station on another computer does not, so it spends as little CPU
    as it can, and its CPU is reported beside the server's. It is
    stopped before the server closes at the end of the run (:func:`one_pass`): any error once
    the server has answered, or an answer but 200, is a failure of the server, counted by reason."""

    def __init__(self, base: str, hz: float, revalidate: bool = True) -> None:
        super().__init__(name="bench-client", daemon=True)
        host, port = base.split("//", 1)[1].rstrip("/").rsplit(":", 1)
        self.address, self.period = (host, int(port)), 1.0 / hz
        # the ETag of each tile it has (revalidate: asked with If-None-Match, as a browser's or Qt's
        # cache asks for a no-cache answer it holds); None: no cache, every tile fetched whole
        self.etags: dict[str, str] | None = {} if revalidate else None
        self.not_modified = 0
        self.stop = threading.Event()
        self.latencies: list[float] = []
        self.failed = 0
        self.reasons: dict[str, int] = {}
        self.tiles = 0
        self.last_status: dict | None = None
        self.sock: socket.socket | None = None
        self.buffer = b""

    def _fail(self, reason: str) -> None:
        self.failed += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1

    def _get(self, path: str) -> bytes | None:
        t0 = time.perf_counter()
        try:
            try:
                code, body = self._ask(path)
            except (ConnectionError, EOFError):  # closed by the server between requests: once more
                self._close()
                code, body = self._ask(path)
        except (OSError, EOFError) as exc:
            self._close()
            if self.latencies:  # not before the server is up
                self._fail(type(exc).__name__)
            return None
        if code == "304":
            self.not_modified += 1
        elif code != "200":
            self._fail(f"HTTP {code}")
            return None
        self.latencies.append(time.perf_counter() - t0)
        return body

    def _ask(self, path: str) -> tuple[str, bytes]:
        """One GET on the kept connection (opened when there is none): its status code and body."""
        if self.sock is None:
            self.sock = socket.create_connection(self.address, timeout=5.0)
            self.buffer = b""
        tag = None if self.etags is None else self.etags.get(path)
        ask = "" if tag is None else f"If-None-Match: {tag}\r\n"
        self.sock.sendall(f"GET /{path} HTTP/1.1\r\nHost: {self.address[0]}\r\n{ask}\r\n".encode())
        while b"\r\n\r\n" not in self.buffer:
            self.buffer += self._recv()
        head, _, rest = self.buffer.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        fields = {k.lower(): v for k, _, v in (line.partition(": ") for line in lines[1:])}
        size = int(fields.get("content-length", "0"))
        while len(rest) < size:
            rest += self._recv()
        self.buffer = rest[size:]
        if fields.get("connection", "").lower() == "close":
            self._close()
        if self.etags is not None and "etag" in fields:
            self.etags[path] = fields["etag"]
        words = lines[0].split(" ", 2)
        return (words[1] if len(words) >= 2 else "no answer"), rest[:size]

    def _recv(self) -> bytes:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise EOFError
        return chunk

    def _close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        self.sock, self.buffer = None, b""

    def _tick(self) -> None:
        body = self._get("status.json")
        if body is None:
            return
        st = json.loads(body)
        self.last_status = st
        pos, z = st.get("position"), st["max_zoom"]
        if not pos:
            return
        if "lat" in pos:
            cx, cy = wm.tile_of(pos["lat"], pos["lon"], z)
        else:
            cx, cy = math.floor(pos["x"] / 256), math.floor(pos["y"] / 256)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                url = st["tiles_url"].lstrip("/").format(z=z, x=cx + dx, y=cy + dy)
                if self._get(url) is not None:
                    self.tiles += 1

    def run(self) -> None:
        due = time.monotonic()
        while not self.stop.is_set():
            self._tick()
            due += self.period
            self.stop.wait(max(0.0, due - time.monotonic()))


class GreedyClient(Client):
    """A client asking without pause, as an overeager or hostile one does: after each status, 30
    tiles of the 9 x 9 around the vehicle at the three zooms beyond ``max_zoom`` (upsampled:
    tiles no view of the flight needs), each fetched whole. ``offset`` staggers the tiles of the
    :data:`GREEDY_CONNECTIONS` clients that ask at once, each on its connection."""

    def __init__(self, base: str, offset: int) -> None:
        super().__init__(base, 1.0, revalidate=False)
        self.offset = offset

    def _tick(self) -> None:
        body = self._get("status.json")
        st = None if body is None else json.loads(body)
        pos = None if st is None else st.get("position")
        if not pos or "lat" not in pos:  # not yet georeferenced (its tiles are pixel-frame ones)
            self.stop.wait(0.05)
            return
        self.last_status = st
        for k in range(30):
            z = st["max_zoom"] + 1 + (k + self.offset) % 3
            cx, cy = wm.tile_of(pos["lat"], pos["lon"], z)
            i = 7 * k + self.offset
            if self._get(st["tiles_url"].lstrip("/").format(z=z, x=cx + i % 9 - 4, y=cy + i // 9 % 9 - 4)) is not None:
                self.tiles += 1

    def run(self) -> None:
        while not self.stop.is_set():
            self._tick()


def client_main(base: str, hz: float, revalidate: bool, greedy: bool = False) -> int:
    """The client process (``greedy``: :data:`GREEDY_CONNECTIONS` greedy clients): fetches until
    its stdin closes, then prints what it saw (JSON)."""
    clients = ([GreedyClient(base, k) for k in range(GREEDY_CONNECTIONS)] if greedy
               else [Client(base, hz, revalidate)])
    print("ready", flush=True)  # imported: the pass starts now (the imports' CPU is not its)
    cpu0 = _cpu_s()
    for client in clients:
        client.start()
    sys.stdin.read()
    for client in clients:
        client.stop.set()
    for client in clients:
        client.join()
        client._close()
    lat = sorted(x for c in clients for x in c.latencies)
    reasons: dict[str, int] = {}
    for c in clients:
        for k, v in c.reasons.items():
            reasons[k] = reasons.get(k, 0) + v
    st = clients[0].last_status or {}
    server = st.get("server") or {}
    print(json.dumps({"requests": len(lat), "failed": sum(c.failed for c in clients), "reasons": reasons,
                      "tiles": sum(c.tiles for c in clients), "not_modified": sum(c.not_modified for c in clients),
                      "client_cpu_s": _cpu_s() - cpu0,
                      "median_ms": 1000 * statistics.median(lat) if lat else float("nan"),
                      "max_ms": 1000 * lat[-1] if lat else float("nan"),
                      "renders": st.get("tile_renders"), "hits": st.get("tile_hits"),
                      "budget_waits": server.get("budget_waits"),
                      "server_errors": {k: v for k, v in server.items() if k != "requests" and v}}))
    return 0


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


@contextlib.contextmanager
def _server_clocks() -> Iterator[dict[str, float]]:
    """The server's CPU seconds by its threads' own clocks (``time.thread_time``): ``answers``
    (accepting and answering requests), ``sink`` (its copy of the map in the mapping worker),
    ``packing``; work OpenCV hands to its own threads is not counted. On a shared machine these
    hold where the difference of two runs' process CPU drowns in the others' load."""
    own = {"answers": 0.0, "sink": 0.0, "packing": 0.0}
    lock = threading.Lock()

    def clocked(name: str, fn):
        def run(*args, **kwargs):
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                with lock:
                    own[name] += time.thread_time() - t0
        return run

    with mock.patch.object(_Server, "process_request", clocked("answers", _Server.process_request)), \
            mock.patch.object(_Server, "_work", clocked("answers", _Server._work)), \
            mock.patch.object(MapServer, "on_frame", clocked("sink", MapServer.on_frame)), \
            mock.patch.object(LiveMap, "pack", clocked("packing", LiveMap.pack)):
        yield own


@contextlib.contextmanager
def _thread_clocks() -> Iterator[dict[str, float]]:
    """CPU seconds by thread name of the threads that run a target (``threading.Thread(target=)``)
    and end inside the block, each by its own clock at its end."""
    spent: dict[str, float] = {}
    lock = threading.Lock()
    real_run = threading.Thread.run

    def run(self: threading.Thread) -> None:
        try:
            real_run(self)
        finally:
            with lock:
                spent[self.name] = spent.get(self.name, 0.0) + time.thread_time()

    with mock.patch.object(threading.Thread, "run", run):
        yield spent


def one_pass(flight: Path, out: Path, condition: str, hz: float, live: bool = False) -> dict:
    """One replay in ``condition``: the pipeline's fps and this process's CPU seconds per frame
    (mapping and server; the client is another process). ``live``: the video fed at its frame
    rate through a drop-oldest queue, as a camera is (``tools.bench_pipeline.PacedVideoSource``),
    without telemetry (the server shows the map's pixel frame)."""
    # no xyz/ at the end: an output after the mapping, not what a client costs it
    served = {"write_xyz": False} | ({"cpu_share": 0.0} if condition == GREEDY_FREE else {})
    cfg = load_config().updated({"output": {"checkpoint_interval": 2.0}, "map_server": served})
    port = _free_port()
    server = None if condition == NO_SERVER else str(port)
    client = None
    if condition in CLIENTS or condition in GREEDIES:
        kind = (["--greedy"] if condition in GREEDIES
                else [] if CLIENTS[condition] else ["--no-revalidate"])
        client = subprocess.Popen([sys.executable, "-m", "tools.bench_mapserver", "--client",
                                   f"http://127.0.0.1:{port}/", "--hz", str(hz)] + kind, cwd=REPO,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        client.stdout.readline()
    seen: list[str] = []

    def stop_client() -> None:  # closes its stdin; it prints what it saw
        if client is not None and not seen:
            seen.append(client.communicate("", timeout=60)[0])

    real_close = MapServer.close

    def close(self: MapServer) -> None:  # the client stops before the server closes at the run's end
        stop_client()
        real_close(self)

    cpu0 = _cpu_s()
    try:
        with mock.patch.object(MapServer, "close", close), _server_clocks() as own, _thread_clocks() as threads:
            if live:
                source = PacedVideoSource(flight / "video.avi", FPS, cfg.capture.queue_size)
                s = map_source(source, cfg, out, input_name="video.avi", map_server=server)
            else:
                s = replay(str(flight / "video.avi"), out, cfg, mavlink=str(flight / "telemetry.tlog"),
                           map_server=server)
    finally:
        cpu = _cpu_s() - cpu0
        stop_client()
    per_frame = 1000 / max(1, s["frames_in"])
    row = {"fps": float(s["fps"]), "frames": s["frames_in"], "registered": s["registered"],
           "cpu_ms": cpu * per_frame, "dropped": int(s.get("dropped") or 0),
           "worker_ms": float(s.get("ms_per_frame") or 0.0),
           "own_ms": {k: v * per_frame for k, v in own.items()},
           "threads_ms": {k: v * per_frame for k, v in threads.items()}}
    # the frame reader's CPU per frame (decoding the same frames, preparing them): the speed of
    # the machine in this pass, by which the process's CPU per frame is divided (REFERENCE)
    row["relative_cpu"] = row["cpu_ms"] / row["threads_ms"].get(REFERENCE, float("nan"))
    # fps in units of the same speed: the frames a second the machine of this pass would map at
    # the reference's speed (a pass on cores running 10 % slower maps 10 % fewer frames a second)
    row["relative_fps"] = row["fps"] * row["threads_ms"].get(REFERENCE, float("nan"))
    if seen and seen[0]:
        row.update(json.loads(seen[0].strip().splitlines()[-1]))
        row["client_cpu_ms"] = 1000 * row["client_cpu_s"] / max(1, s["frames_in"])
    return row


def mean_interval(values: list[float], level: float = 0.95, rounds: int = 4000) -> tuple[float, float]:
    """A bootstrap interval of the mean of ``values`` (seeded: the same passes, the same interval)."""
    rng = random.Random(0)
    means = sorted(statistics.fmean(rng.choices(values, k=len(values))) for _ in range(rounds))
    return means[int((1 - level) / 2 * rounds)], means[int((1 + level) / 2 * rounds) - 1]


def pass_order(rounds: int) -> list[str]:
    """The passes: every other one without a server, so that each pass with one lies between two
    without (``no server, X, no server, Y, no server, Z, no server, ...``, the others' order
    turning from round to round)."""
    others = CONDITIONS[1:]
    order = [NO_SERVER]
    for k in range(rounds):
        for cond in others[k % len(others):] + others[:k % len(others)]:
            order += [cond, NO_SERVER]
    return order


def sandwich_effects(order: list[str], values: list[float]) -> dict[str, list[float]]:
    """Per condition, the log ratio of each of its passes' ``values`` (fps, CPU per frame) to the
    geometric mean of the two passes without a server around it: a drift of the machine's speed
    over the minutes of the passes cancels (to first order), which a comparison with passes
    further away does not."""
    out: dict[str, list[float]] = {c: [] for c in order}
    for i, cond in enumerate(order):
        if cond != NO_SERVER and 0 < i < len(order) - 1 and order[i - 1] == order[i + 1] == NO_SERVER:
            out[cond].append(math.log(values[i]) - 0.5 * (math.log(values[i - 1]) + math.log(values[i + 1])))
    return out


def paired_effects(effects: dict[str, list[float]], cond: str, against: str) -> list[float]:
    """Per round, the log ratio of ``cond``'s pass to ``against``'s (each already relative to the
    passes without a server around it, :func:`sandwich_effects`): ``cond`` against another
    condition of the same round (every round holds one pass of each)."""
    return [a - b for a, b in zip(effects[cond], effects[against])]


def flat_out_verdict(fps: tuple[float, float], cpu: tuple[float, float], cpu_share: float,
                     limit: float = 0.03) -> str:
    """The flat-out target, from the 95 % interval of the fps ratio in units of the machine's
    speed (with the client / without a server), else that of the CPU per frame ratio. A shared
    virtual machine's cores swing in speed by 10-20 % from pass to pass, and its raw fps with
    them: the raw ratio of a server that does nothing lies a few per cent below 1 (measured), so
    the fps decides in units of a fixed work's CPU in the same pass (:data:`REFERENCE`), where
    such a server's ratio is 1. It decides where its interval lies above ``1 - limit`` (met) or
    below it (not met). The process's CPU per frame in the same units decides next (met below
    ``1 + limit``, not met above), though it misses what the server costs the mapping's critical
    path in waits (the worker waiting for the interpreter lock), which the fps sees. Where both
    straddle, the target is not decided: the server's own threads' CPU (``cpu_share`` of the
    mapping's) is a lower bound of the cost and decides only above ``limit`` (not met)."""
    (lo, hi), (cpu_lo, cpu_hi) = fps, cpu
    if lo >= 1 - limit:
        return f"met (the speed-relative fps ratio's 95 % interval lies above {1 - limit:.2f})"
    if hi < 1 - limit:
        return f"NOT met (the speed-relative fps ratio's 95 % interval lies below {1 - limit:.2f})"
    by_fps = f"not decidable by fps on this machine (its speed-relative ratio's 95 % interval, {lo:.3f} .. {hi:.3f}, straddles {1 - limit:.2f})"
    if cpu_hi <= 1 + limit:
        return f"met by CPU per frame ({by_fps}; the CPU ratio's, {cpu_lo:.3f} .. {cpu_hi:.3f}, lies below {1 + limit:.2f})"
    if cpu_lo > 1 + limit:
        return f"NOT met by CPU per frame ({by_fps}; the CPU ratio's, {cpu_lo:.3f} .. {cpu_hi:.3f}, lies above {1 + limit:.2f})"
    if cpu_share > limit:
        return f"NOT met (the server's own threads alone take {100 * cpu_share:.1f} % of the mapping's CPU)"
    return (f"not shown: {by_fps}, nor by CPU per frame ({cpu_lo:.3f} .. {cpu_hi:.3f}, straddling "
            f"{1 + limit:.2f}); the server's own threads take {100 * cpu_share:.1f} % of the mapping's CPU, "
            f"a lower bound of the cost")


def _own_total(row: dict) -> float:
    return sum(row["own_ms"].values())


def _own(rs: list[dict]) -> str:
    """The server's own CPU ms per frame of the passes (median): answers + in the worker."""
    if not any(_own_total(r) for r in rs):
        return "-"
    answers = statistics.median(r["own_ms"]["answers"] + r["own_ms"]["packing"] for r in rs)
    return (f"{statistics.median(_own_total(r) for r in rs):.2f}: {answers:.2f} + "
            f"{statistics.median(r['own_ms']['sink'] for r in rs):.2f}")


def _requests(rs: list[dict]) -> tuple[str, str, str]:
    """The client's requests (tiles; not modified), latencies and the server's renders / hits."""
    req = (f"{statistics.median(r['requests'] for r in rs):.0f} ({statistics.median(r['tiles'] for r in rs):.0f}; "
           f"{statistics.median(r['not_modified'] for r in rs):.0f})")
    if any(r["failed"] for r in rs):
        reasons: dict[str, int] = {}
        for r in rs:
            for k, v in r.get("reasons", {}).items():
                reasons[k] = reasons.get(k, 0) + v
        req += f", {sum(r['failed'] for r in rs)} failed ({', '.join(f'{k} {v}' for k, v in reasons.items())})"
    latency = f"{statistics.median(r['median_ms'] for r in rs):.1f} / {max(r['max_ms'] for r in rs):.0f}"
    cache = (f"{statistics.median(r['renders'] or 0 for r in rs):.0f} / "
             f"{statistics.median(r['hits'] or 0 for r in rs):.0f}")
    return req, latency, cache


def _ratio(effects: list[float]) -> tuple[float, float, float]:
    lo, hi = mean_interval(effects)
    return math.exp(statistics.fmean(effects)), math.exp(lo), math.exp(hi)


def _shown(ratio: tuple[float, float, float]) -> str:
    """A :func:`_ratio` as a table cell: mean (95 % interval)."""
    return "{:.3f} ({:.3f} .. {:.3f})".format(*ratio)


def render(args, order: list[str], passes: list[dict], took: float, loads: tuple[float, float],
           live: dict | None, greedy: tuple[list[str], list[dict]] = ([], [])) -> str:
    rows = {c: [r for o, r in zip(order, passes) if o == c] for c in CONDITIONS}
    raw_effects = sandwich_effects(order, [r["fps"] for r in passes])
    effects = sandwich_effects(order, [r["relative_fps"] for r in passes])
    cpu_effects = sandwich_effects(order, [r["relative_cpu"] for r in passes])
    lines = ["## Map server", "",
             f"Written by `python -m tools.bench_mapserver --frames {args.frames} --live-frames {args.live_frames} "
             f"--passes {args.passes} --live-passes {args.live_passes} --hz {args.hz:g} "
             f"--greedy-passes {args.greedy_passes}` on "
             f"{datetime.date.today().isoformat()}, {platform.machine()}, {os.cpu_count()} cores, Python "
             f"{platform.python_version()}; {args.frames} frames of {SIZE[0]}x{SIZE[1]} (simulated, with "
             f"telemetry) mapped by `photomap replay` as fast as possible, {args.passes} passes per condition "
             f"with a server, every one of them between two passes without (`{pass_order(1)[0]}, "
             f"{', '.join(pass_order(1)[1:])}, ...`, the order turning by round; {len(order)} passes); 1-minute load "
             f"{loads[0]:.1f} before, {loads[1]:.1f} after; {took / 60:.1f} min.", "",
             "| condition | median fps (range) | fps / the two no-server passes around it: mean (95 % interval) "
             "| fps in units of the machine's speed (fps x frame-reader CPU per frame) / that of the two around it "
             "(95 % interval) | CPU ms per frame (median) | CPU per frame in frame-reader units / that of the two around it "
             "(95 % interval) "
             "| the server's own CPU ms per frame: answers + in the worker "
             "(median) | client requests (tiles; not modified) | latency median / max ms "
             "| tile renders / hits |", "|---|---|---|---|---|---|---|---|---|---|"]
    base_cpu = statistics.median(r["cpu_ms"] for r in rows[NO_SERVER])
    raw_ratios = {c: _ratio(raw_effects[c]) for c in CONDITIONS[1:]}
    ratios = {c: _ratio(effects[c]) for c in CONDITIONS[1:]}
    cpu_ratios = {c: _ratio(cpu_effects[c]) for c in CONDITIONS[1:]}
    for cond in CONDITIONS:
        rs = rows[cond]
        fps = [r["fps"] for r in rs]
        cpu = statistics.median(r["cpu_ms"] for r in rs)
        req, latency, cache = _requests(rs) if cond in CLIENTS else ("-", "-", "-")
        raw, ratio, cpu_ratio = ("-", "-", "-") if cond == NO_SERVER else (
            _shown(raw_ratios[cond]), _shown(ratios[cond]), _shown(cpu_ratios[cond]))
        lines.append(f"| {cond} | {statistics.median(fps):.1f} ({min(fps):.1f} .. {max(fps):.1f}) | {raw} | {ratio} "
                     f"| {cpu:.2f} | {cpu_ratio} | {_own(rs)} | {req} | {latency} | {cache} |")
    verdicts = {}
    for cond in CLIENTS:
        own = statistics.median(_own_total(r) for r in rows[cond])
        verdicts[cond] = (own, flat_out_verdict(ratios[cond][1:], cpu_ratios[cond][1:], own / base_cpu))
    # the client's own cost: against the server without a client in the same round (the row's "without")
    client_fps = _ratio(paired_effects(effects, CLIENT, IDLE))
    client_cpu = _ratio(paired_effects(cpu_effects, CLIENT, IDLE))
    answers = statistics.median(r["own_ms"]["answers"] for r in rows[CLIENT])
    client_verdict = flat_out_verdict(client_fps[1:], client_cpu[1:], answers / base_cpu)
    per_request = statistics.median(r["own_ms"]["answers"] * r["frames"] / max(1, r["requests"]) for r in rows[CLIENT])
    own, verdict = verdicts[CLIENT]
    lines += ["", f"The client (another process on the same cores, as a ground station is not) asks for the status "
              f"and the 3 x 3 tiles around the vehicle at `max_zoom` {args.hz:g} times a second (up to "
              f"{10 * args.hz:g} requests/s), each tile it holds with its `ETag` in `If-None-Match`, as a browser's "
              f"or QGIS's (Qt's) cache asks again for a `no-cache` answer: a tile unchanged since is a 304 "
              f"without a body. Mapping fps with it against the passes without a server around it, in units of "
              f"the machine's speed in each pass (fps times the frame reader's CPU per frame, `{REFERENCE}`: "
              f"decoding and preparing the same frames in every pass, a reference measured in the pass; this "
              f"virtual machine's cores swing in speed from pass to pass): {ratios[CLIENT][0]:.3f} (95 % interval "
              f"{ratios[CLIENT][1]:.3f} .. {ratios[CLIENT][2]:.3f}; raw fps {raw_ratios[CLIENT][0]:.3f}, "
              f"{raw_ratios[CLIENT][1]:.3f} .. {raw_ratios[CLIENT][2]:.3f}); a server with no client, which does "
              f"nothing: {ratios[IDLE][0]:.3f} ({ratios[IDLE][1]:.3f} .. {ratios[IDLE][2]:.3f}, the noise of the "
              f"measure; raw fps {raw_ratios[IDLE][0]:.3f}, {raw_ratios[IDLE][1]:.3f} .. {raw_ratios[IDLE][2]:.3f}). "
              f"The process's CPU per frame (mapping and "
              f"server; raw, it swings with fps: this machine's speed swings, not only its share of the cores) in "
              f"units of the same reference against the same passes: {cpu_ratios[CLIENT][0]:.3f} ({cpu_ratios[CLIENT][1]:.3f} .. "
              f"{cpu_ratios[CLIENT][2]:.3f}; with no client {cpu_ratios[IDLE][0]:.3f}, {cpu_ratios[IDLE][1]:.3f} .. "
              f"{cpu_ratios[IDLE][2]:.3f}). By the server's own thread clocks: "
              f"{own:.2f} ms per frame, {100 * own / base_cpu:.1f} % of the mapping's CPU (answering: "
              f"{per_request:.2f} ms per request; work OpenCV hands to its threads is not in them); the client's "
              f"own CPU: {statistics.median(r['client_cpu_ms'] for r in rows[CLIENT]):.2f} ms per frame. "
              f"Target (no measurable slowdown, 3 %): **{verdict}**.", "",
              f"What the client itself costs, against the server with no client of the same round (both "
              f"relative to the passes around them; the server's copy of the map, which a server costs with "
              f"or without a client, cancels): speed-relative fps {_shown(client_fps)}, CPU per frame "
              f"{_shown(client_cpu)}, the answering threads {answers:.2f} ms per frame; against 3 %: "
              f"{client_verdict}.", "",
              f"Without a cache (every tile fetched whole, {statistics.median(r['tiles'] for r in rows[NO_CACHE]):.0f} "
              f"a pass, most of them ~100 KB PNGs it already has): speed-relative fps {ratios[NO_CACHE][0]:.3f} "
              f"({ratios[NO_CACHE][1]:.3f} .. {ratios[NO_CACHE][2]:.3f}), CPU per frame {cpu_ratios[NO_CACHE][0]:.3f} "
              f"({cpu_ratios[NO_CACHE][1]:.3f} .. {cpu_ratios[NO_CACHE][2]:.3f}), the server's own CPU "
              f"{verdicts[NO_CACHE][0]:.2f} ms per frame; against 3 %: {verdicts[NO_CACHE][1]}. Latencies are those "
              f"the client saw on loopback while the mapping ran flat out."]
    greedy_order, greedy_rows = greedy
    if greedy_rows:
        effects = sandwich_effects(greedy_order, [r["relative_fps"] for r in greedy_rows])
        lines += ["", f"A greedy client: {GREEDY_CONNECTIONS} connections of another process asking without pause "
                  f"(after each status, 30 tiles of the 9 x 9 around the vehicle at the three zooms beyond "
                  f"`max_zoom`, each fetched whole), with the server's CPU budget (`map_server.cpu_share` "
                  f"{load_config().map_server.cpu_share:g} of a core) and without (`cpu_share` 0), "
                  f"{args.greedy_passes} passes each, every one between two passes without a server "
                  f"(the interval, of so few passes, is rough):", "",
                  "| condition | median fps | fps in units of the machine's speed / that of the two around it: mean "
                  "(95 % interval) | the server's own CPU ms per frame: answers + in the worker (median) "
                  "| answers a pass (median) | answers that waited for the budget (median) |",
                  "|---|---|---|---|---|---|"]
        for cond in GREEDIES:
            rs = [r for o, r in zip(greedy_order, greedy_rows) if o == cond]
            lines.append(f"| {cond} | {statistics.median(r['fps'] for r in rs):.1f} "
                         f"| {_shown(_ratio(effects[cond]))} | {_own(rs)} "
                         f"| {statistics.median(r['requests'] for r in rs):.0f} "
                         f"| {statistics.median(r.get('budget_waits') or 0 for r in rs):.0f} |")
    if live:
        lines += ["", f"Live: {args.live_frames} frames of the same simulation fed at {FPS:g} fps through a drop-oldest queue of "
                  f"`capture.queue_size` frames, as a camera is (the server's Python code waits while the "
                  f"worker maps a frame, `MappingPipeline.worker_first`), no telemetry (pixel-frame tiles), "
                  f"{args.live_passes} passes each, interleaved:", "",
                  "| live condition | frames mapped (median) | dropped (median) | worker ms per frame (median) "
                  "| CPU ms per frame (median) | the server's own CPU ms per frame (median) "
                  "| client requests (tiles; not modified) | latency median / max ms |",
                  "|---|---|---|---|---|---|---|---|"]
        for cond, rs in live.items():
            req, latency, _ = _requests(rs) if cond in CLIENTS else ("-", "-", "-")
            lines.append(f"| {cond} | {statistics.median(r['frames'] for r in rs):.0f} "
                         f"| {statistics.median(r['dropped'] for r in rs):.0f} "
                         f"| {statistics.median(r['worker_ms'] for r in rs):.1f} "
                         f"| {statistics.median(r['cpu_ms'] for r in rs):.2f} | {_own(rs)} | {req} | {latency} |")
        mapped = {c: statistics.median(r["frames"] for r in live[c]) for c in live}
        cpu = {c: statistics.median(r["cpu_ms"] for r in live[c]) for c in live}
        ok = mapped[CLIENT] >= 0.98 * mapped[NO_SERVER]
        lines += ["", f"Live target (the frames mapped with the client within 2 % of those without): "
                  f"**{'met' if ok else 'NOT met'}** ({mapped[CLIENT]:.0f} against "
                  f"{mapped[NO_SERVER]:.0f}); the server's CPU {cpu[CLIENT] - cpu[NO_SERVER]:+.2f} ms "
                  f"per frame."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1500, help="frames of the flight mapped flat out (default 1500: "
                    "a few seconds a pass, a few dozen client rounds)")
    ap.add_argument("--live-frames", type=int, default=300, help="frames of the live passes' flight (default 300: 10 s)")
    ap.add_argument("--passes", type=int, default=10, help="flat-out passes per condition with a server (default 10)")
    ap.add_argument("--live-passes", type=int, default=3, help="live passes per condition (default 3)")
    ap.add_argument("--hz", type=float, default=5.0, help="client rounds per second (default 5)")
    ap.add_argument("--out", default=str(REPO / "docs" / "benchmarks.md"),
                    help="markdown file whose mapserver section is replaced (- = print only)")
    ap.add_argument("--no-live", dest="live", action="store_false", help="replays only (no live passes)")
    ap.add_argument("--json", metavar="FILE", help="also write every pass's measures (JSON) to FILE")
    ap.add_argument("--client", metavar="URL", help=argparse.SUPPRESS)  # internal: the client process
    ap.add_argument("--no-revalidate", dest="revalidate", action="store_false", help=argparse.SUPPRESS)
    ap.add_argument("--greedy", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--greedy-passes", type=int, default=3,
                    help="flat-out passes with a greedy client, with and without the CPU budget (default 3; 0: none)")
    args = ap.parse_args(argv)
    if args.client:
        return client_main(args.client, args.hz, args.revalidate, args.greedy)
    if min(args.frames, args.live_frames) < 30 or min(args.passes, args.live_passes) < 1 or not args.hz > 0:
        print("error: --frames and --live-frames >= 30, --passes and --live-passes >= 1, --hz > 0", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("photomap").setLevel(logging.WARNING)
    start, load0 = time.perf_counter(), load_average()
    order, passes, live = pass_order(args.passes), [], None
    with tempfile.TemporaryDirectory(prefix="bench-mapserver-") as tmp:
        tmp_dir = Path(tmp)
        log.info("simulating %d frames of %dx%d", args.frames, *SIZE)
        flight = simulate_flight(tmp_dir / "flight", n_frames=args.frames, size=SIZE, fps=FPS, seed=2,
                                 video_codec="mjpg")
        for i, cond in enumerate(order):
            row = one_pass(flight, tmp_dir / f"out{i}", cond, args.hz)
            passes.append(row)
            log.info("pass %d of %d, %s: %.1f fps%s", i + 1, len(order), cond, row["fps"],
                     f", {row['requests']} requests" if "requests" in row else "")
        greedy_order = ([NO_SERVER] + [GREEDY, NO_SERVER, GREEDY_FREE, NO_SERVER] * args.greedy_passes
                        if args.greedy_passes > 0 else [])
        greedy = []
        for i, cond in enumerate(greedy_order):
            row = one_pass(flight, tmp_dir / f"greedy{i}", cond, args.hz)
            greedy.append(row)
            log.info("greedy pass %d of %d, %s: %.1f fps%s", i + 1, len(greedy_order), cond, row["fps"],
                     f", {row['requests']} requests" if "requests" in row else "")
        if args.live:
            if args.live_frames != args.frames:
                log.info("simulating %d frames of %dx%d for the live passes", args.live_frames, *SIZE)
                flight = simulate_flight(tmp_dir / "live-flight", n_frames=args.live_frames, size=SIZE, fps=FPS,
                                         seed=2, video_codec="mjpg")
            live = {NO_SERVER: [], CLIENT: []}
            for k in range(args.live_passes):
                for cond in live:
                    row = one_pass(flight, tmp_dir / f"live{k}-{CONDITIONS.index(cond)}", cond, args.hz, live=True)
                    live[cond].append(row)
                    log.info("live pass %d, %s: %d mapped, %d dropped, %.1f worker ms/frame", k + 1, cond,
                             row["frames"], row["dropped"], row["worker_ms"])
    body = render(args, order, passes, time.perf_counter() - start, (load0, load_average()), live,
                  (greedy_order, greedy))
    if args.json:
        Path(args.json).write_text(json.dumps({"order": order, "passes": passes, "live": live,
                                               "greedy_order": greedy_order, "greedy": greedy}, indent=1))
    print(body)
    if args.out != "-":
        replace_section(Path(args.out), "mapserver", body)
        log.info("wrote the mapserver section of %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
