"""Map many logged flights at once, on every core of this computer or on a Dask cluster.

Each INPUT is one flight: a video file or a folder of stills (as `photomap replay` takes them),
or a manifest (a .yaml/.yml/.csv file listing flights). Telemetry is found by a sidecar
convention unless the manifest says otherwise:

  video  DIR/NAME.EXT  ->  DIR/NAME.tlog, else DIR/NAME.SRT (DJI), else DIR/telemetry.tlog when
                           DIR holds no other video (the layout `photomap simulate` writes)
  stills DIR/          ->  DIR.tlog beside the folder, else the one *.tlog inside it; without
                           one, the stills' own EXIF GPS / DJI XMP (as replay does)

Each flight is mapped by the same function as `photomap replay` into DIR/<flight name>/ (the
same files), its log lines go to DIR/logs/<flight name>.log; DIR/batch.json says per flight ok
or failed (with the error on one line), frames, segments and wall time, and is rewritten as
flights finish; DIR/flights.geojson holds the footprint polygon of each georeferenced flight
(the covered outline of its map). A failed flight is reported and the others finish.

Runs on Dask `distributed` (the `batch` extra): a LocalCluster of --workers single-threaded
worker processes on this computer by default, or the cluster whose scheduler is at --scheduler
(then the inputs and DIR must have the same paths on every worker, e.g. a shared filesystem).

manifest (YAML; paths relative to the manifest; only `input` is required):
  flights:
    - input: 2026-06-12/north.mp4
      mavlink: 2026-06-12/north-fc.tlog   # `none`: no telemetry, not even a sidecar
      time_offset: 0.4                     # seconds added to frame times (--time-offset)
      video_start: 1781251200.0            # UNIX time of the first frame (--video-start)
    - input: 2026-06-12/survey/
      name: survey-south                   # default: the file or folder name
      geo: 2026-06-12/geo.txt              # stills positions (--geo)
  or CSV with the header  input,name,mavlink,time_offset,video_start,geo

examples:
  photomap batch season/*.mp4 --out maps/season
  photomap batch flights.yaml --out maps/june --workers 4
  photomap batch flights.csv --out /shared/maps --scheduler tcp://10.0.0.5:8786
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import yaml

from photomap.config import Config
from photomap.drivers.srt import srt_beside
from photomap.errors import InputError, PhotomapError

log = logging.getLogger(__name__)

BATCH_EXTRA_HINT = "photomap batch needs Dask: pip install 'ifmi-photomap[batch]' (dask[distributed])"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".ts", ".webm", ".h264", ".wmv")
MANIFEST_SUFFIXES = (".yaml", ".yml", ".csv")
MANIFEST_KEYS = ("input", "name", "mavlink", "time_offset", "video_start", "geo")
NO_TELEMETRY = "none"


@dataclass(frozen=True)
class FlightSpec:
    """One flight to map.

    input : video file, folder or glob of stills (absolute).
    name : folder name under the batch's output folder (unique in the batch).
    mavlink : telemetry log (absolute path), None = the stills' own telemetry or none.
    time_offset : seconds added to frame times to get telemetry times (None = the config's).
    video_start : UNIX time of the first frame (None: the replay's own rules).
    geo : OpenDroneMap geo.txt of the stills, or None.
    """

    input: str
    name: str
    mavlink: str | None = None
    time_offset: float | None = None
    video_start: float | None = None
    geo: str | None = None


# ---------------------------------------------------------------------------------- flights
def sidecar_telemetry(input_path: str | Path) -> str | None:
    """The telemetry log that belongs to a flight by the sidecar convention (module docstring)."""
    p = Path(input_path)
    if p.is_file():
        own = p.with_suffix(".tlog")
        if own.is_file():
            return str(own)
        srt = srt_beside(p)
        if srt is not None:
            return str(srt)
        shared = p.parent / "telemetry.tlog"
        videos = [q for q in p.parent.iterdir() if q.is_file() and q.suffix.lower() in VIDEO_SUFFIXES]
        if shared.is_file() and videos == [p]:
            return str(shared)
        return None
    if p.is_dir():
        beside = p.parent / f"{p.name}.tlog"
        if beside.is_file():
            return str(beside)
        inside = sorted(p.glob("*.tlog"))
        if len(inside) == 1:
            return str(inside[0])
    return None


def _default_name(input_path: str) -> str:
    p = Path(input_path)
    if any(c in input_path for c in "*?["):  # a glob: name it after its folder
        p = Path(input_path.split("*")[0].split("?")[0].split("[")[0] or ".").resolve()
        return p.name or "flight"
    return (p.stem if p.is_file() or p.suffix else p.name) or "flight"


def _safe(name: str) -> str:
    out = "".join(c if c.isalnum() or c in "-_.+" else "_" for c in name.strip()).strip(".")
    return out or "flight"


def unique_names(specs: Sequence[FlightSpec]) -> list[FlightSpec]:
    """The flights with unique folder names: a repeated name gets its parent folder's name in
    front (``video`` of ``a/video.mp4`` and ``b/video.mp4`` -> ``a-video``, ``b-video``), then
    ``-2``, ``-3`` ..."""
    counts: dict[str, int] = {}
    for s in specs:
        counts[s.name] = counts.get(s.name, 0) + 1
    named = []
    for s in specs:
        name = s.name
        if counts[name] > 1:
            parent = _safe(Path(s.input).resolve().parent.name)
            name = f"{parent}-{name}" if parent else name
        named.append(name)
    seen: dict[str, int] = {}
    out = []
    for s, name in zip(specs, named):
        k = seen.get(name, 0) + 1
        seen[name] = k
        out.append(FlightSpec(s.input, name if k == 1 else f"{name}-{k}", s.mavlink, s.time_offset,
                              s.video_start, s.geo))
    return out


def _number(value, key: str, where: str) -> float | None:
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {key} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {key} must be finite, got {value!r}")
    return v


def _flight_from_entry(entry: dict, base: Path, where: str) -> FlightSpec:
    unknown = sorted(set(entry) - set(MANIFEST_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(map(str, unknown))} "
                         f"(known: {', '.join(MANIFEST_KEYS)})")
    raw = entry.get("input")
    if not raw or not str(raw).strip():
        raise InputError(f"{where}: no input")
    raw = str(raw).strip()
    path = raw if os.path.isabs(raw) else str(base / raw)
    mavlink = entry.get("mavlink")
    mavlink = str(mavlink).strip() if mavlink is not None else ""
    if mavlink.lower() == NO_TELEMETRY:
        mavlink_path: str | None = NO_TELEMETRY
    elif mavlink:
        looks_like_file = ":" not in mavlink or os.path.isabs(mavlink)
        mavlink_path = str(base / mavlink) if looks_like_file and not os.path.isabs(mavlink) else mavlink
    else:
        mavlink_path = None
    geo = entry.get("geo")
    geo = str(base / str(geo).strip()) if geo and str(geo).strip() else None
    name = entry.get("name")
    name = _safe(str(name)) if name and str(name).strip() else _safe(_default_name(path))
    return FlightSpec(path, name, mavlink_path, _number(entry.get("time_offset"), "time_offset", where),
                      _number(entry.get("video_start"), "video_start", where), geo)


def read_manifest(path: str | Path) -> list[FlightSpec]:
    """The flights a manifest lists (YAML or CSV, see the module docstring); paths are taken
    relative to the manifest's folder. InputError on a bad file, naming the entry."""
    path = Path(path)
    base = path.resolve().parent
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read manifest {path}: {exc.strerror or exc}") from None
    entries: list[tuple[dict, str]] = []
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
        if not reader.fieldnames or "input" not in [f.strip() for f in reader.fieldnames]:
            raise InputError(f"manifest {path}: the CSV header must name an 'input' column "
                             f"(columns: {', '.join(MANIFEST_KEYS)})")
        for i, row in enumerate(reader, start=2):
            entries.append(({k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in row.items()
                             if k is not None and v not in (None, "")}, f"{path}:{i}"))
    else:
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise InputError(f"manifest {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
        if isinstance(data, dict):
            data = data.get("flights")
        if not isinstance(data, list):
            raise InputError(f"manifest {path} must hold a list of flights (or `flights:` with one)")
        for i, item in enumerate(data):
            if isinstance(item, str):
                item = {"input": item}
            if not isinstance(item, dict):
                raise InputError(f"manifest {path}: flight {i + 1} must be a mapping with an input")
            entries.append((item, f"{path}: flight {i + 1}"))
    if not entries:
        raise InputError(f"manifest {path} lists no flight")
    return [_flight_from_entry(e, base, where) for e, where in entries]


def discover_flights(inputs: Sequence[str]) -> list[FlightSpec]:
    """The flights named on the command line: manifests expanded, sidecar telemetry found,
    names made unique. Inputs that do not exist are kept (their flight fails with the reason)."""
    specs: list[FlightSpec] = []
    for raw in inputs:
        if Path(raw).suffix.lower() in MANIFEST_SUFFIXES and Path(raw).is_file():
            specs.extend(read_manifest(raw))
        else:
            path = raw if any(c in raw for c in "*?[") else str(Path(raw).resolve())
            specs.append(FlightSpec(path, _safe(_default_name(raw))))
    if not specs:
        raise InputError("no flight to map")
    out = []
    for s in specs:
        mavlink = s.mavlink
        if mavlink is None:
            mavlink = sidecar_telemetry(s.input)
        elif mavlink == NO_TELEMETRY:
            mavlink = None
        out.append(FlightSpec(s.input, s.name, mavlink, s.time_offset, s.video_start, s.geo))
    return unique_names(out)


# ---------------------------------------------------------------------------------- one flight
def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if isinstance(exc, PhotomapError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def map_flight(spec: FlightSpec, out_root: str, cfg: Config, threads: int | dict[str, int] = 1) -> dict:
    """Map one flight into ``out_root/<spec.name>`` with :func:`photomap.cli.replay.replay`.

    The Dask task of :func:`run_batch` (also fine to call directly). Never raises: returns the
    flight's entry of ``batch.json`` (``status`` ``ok`` or ``failed`` with ``error`` on one line,
    ``frames``, ``registered``, ``segments``, ``wall_time_s``, ``georeferenced``) and, under
    ``footprint``, its GeoJSON feature (None unless georeferenced).

    ``threads``: OpenCV threads for this flight, or ``{host: threads}`` (the worker looks its
    own host up; 1 when absent), also the most ``mapping.opencv_threads`` may give the flight's
    pipeline; BLAS/OpenMP pools are pinned to 1 thread (see :func:`run_batch`).
    Log lines of the ``photomap`` loggers go to ``out_root/logs/<name>.log`` while the flight runs.
    """
    import cv2
    from threadpoolctl import threadpool_limits

    from photomap.cli.replay import replay

    _malloc_for_arrays()
    from photomap.io.catalogue import flight_footprint

    t0 = time.monotonic()
    entry: dict = {"name": spec.name, "input": spec.input, "mavlink": spec.mavlink, "out": spec.name,
                   "status": "failed", "error": None, "frames": None, "registered": None, "segments": None,
                   "georeferenced": False, "wall_time_s": None, "worker": _worker_address()}
    n = threads if isinstance(threads, int) else threads.get(_host(entry["worker"]), 1)
    n = max(1, int(n))
    entry["threads"] = n
    root = Path(out_root)
    logger = logging.getLogger("photomap")
    handler = None
    saved = (logger.level, logger.propagate)
    try:
        (root / "logs").mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(root / "logs" / f"{spec.name}.log", mode="w", encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        logger.propagate = False  # the batch's console shows one line per flight
        old_cv = cv2.getNumThreads()
        cv2.setNumThreads(n)
        # the pipeline sets OpenCV's pool to mapping.opencv_threads for its run: at most n here
        # (else 2 workers of 2 threads each spin on 2 cores: ~0.6 CPU ms a 320x240 frame wasted)
        wanted = cfg.mapping.opencv_threads
        if wanted <= 0 or wanted > n:
            cfg = cfg.updated({"mapping": {"opencv_threads": n}})
        try:
            with threadpool_limits(limits=1):  # BLAS/OpenMP: 1 (see run_batch: measured)
                if spec.time_offset is not None:
                    cfg = cfg.updated({"telemetry": {"time_offset": spec.time_offset}})
                summary = replay(spec.input, root / spec.name, cfg, progress=False, mavlink=spec.mavlink,
                                 video_start=spec.video_start, geo=spec.geo)
        finally:
            cv2.setNumThreads(old_cv)
        entry.update({"frames": summary.get("frames_in"), "registered": summary.get("registered"),
                      "segments": summary.get("segments"),
                      "georeferenced": bool(summary.get("georeference"))})
        if not summary.get("registered"):
            entry["error"] = "no frame could be mapped"
        else:
            entry["status"] = "ok"
            try:
                entry["footprint"] = flight_footprint(root / spec.name, {"name": spec.name, "input": spec.input})
            except (PhotomapError, OSError) as exc:
                logger.warning("no footprint for flight %s: %s", spec.name, exc)
    except Exception as exc:  # one flight's failure is its entry, never the batch's
        entry["error"] = _one_line(exc)
        if not isinstance(exc, PhotomapError):
            logger.error("flight %s failed:\n%s", spec.name, traceback.format_exc())
        else:
            logger.error("flight %s failed: %s", spec.name, entry["error"])
    finally:
        if handler is not None:
            logger.removeHandler(handler)
            handler.close()
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
    entry["wall_time_s"] = round(time.monotonic() - t0, 3)
    return entry


def _worker_address() -> str | None:
    try:
        from distributed import get_worker
        return get_worker().address
    except (ImportError, ValueError):  # not in a Dask worker
        return None


def _host(address: str | None) -> str:
    if not address:
        return ""
    rest = address.split("://", 1)[-1]
    return rest.rsplit(":", 1)[0]


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads_per_host(workers: dict[str, dict], cores: dict[str, int]) -> dict[str, int]:
    """Threads each flight may use on each host so that flights never oversubscribe the cores:
    ``max(1, cores of the host // task slots on the host)`` (a slot = one worker thread).

    ``workers``: the scheduler's ``{address: {"nthreads": n, ...}}``; ``cores``: ``{address:
    usable cores}`` as each worker reports them.
    """
    slots: dict[str, int] = {}
    host_cores: dict[str, int] = {}
    for addr, info in workers.items():
        host = _host(addr)
        slots[host] = slots.get(host, 0) + max(1, int(info.get("nthreads") or 1))
        host_cores[host] = max(host_cores.get(host, 1), int(cores.get(addr) or 1))
    return {h: max(1, host_cores[h] // slots[h]) for h in slots}


# ---------------------------------------------------------------------------------- the batch
# Dask starts worker processes with MALLOC_TRIM_THRESHOLD_=65536 (to give memory back to the OS).
# Setting it switches off glibc's dynamic mmap threshold: every array above 128 kB is then mmap'ed
# and unmapped again, page faults and all. Measured on a 400-frame replay: 2.3x the wall time and
# 15x the system time. Local workers get the variable unset; workers of an existing cluster get
# the thresholds raised in the task (:func:`_malloc_for_arrays`).
_MMAP_THRESHOLD = 32 * 1024 * 1024


# Worker processes come from a fork server that has imported the mapping once (where the OS has
# one): a spawned worker imports Python, Dask, NumPy, OpenCV and photomap anew, ~0.9 CPU s and
# ~1 s before its first flight starts; forked from the server, ~0.05 s. The server is a
# single-threaded process that never ran any mapping (forking this process, whose scheduler and
# client threads run, could deadlock a child).
_PRELOAD = ["distributed", "photomap.cli.batch", "photomap.cli.replay", "photomap.io.geotiff", "rasterio"]


def _fork_server_context(config: dict) -> dict:
    """``config`` plus the start method of local worker processes: a fork server preloading the
    mapping where available, else Dask's default."""
    import multiprocessing
    from multiprocessing import forkserver

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return config
    import dask
    from distributed.utils import get_mp_context

    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        get_mp_context().set_forkserver_preload(_PRELOAD)  # after Dask's own (set once, on first use)
    forkserver.ensure_running()  # its imports overlap the scheduler's start
    return {**config, "distributed.worker.multiprocessing-method": "forkserver"}


def local_cluster(workers: int, *, processes: bool = True, threads_per_worker: int = 1):
    """A Dask LocalCluster for mapping: ``workers`` workers (processes forked from a server that
    has imported the mapping, or threads of this process), on loopback only, without Dask's
    memory trimming (see above)."""
    import dask
    distributed = _require_dask()
    config: dict = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
    if processes:
        config = _fork_server_context(config)
    where = {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"} if processes else {"dashboard_address": None}
    with dask.config.set(config):
        return distributed.LocalCluster(n_workers=workers, threads_per_worker=threads_per_worker,
                                        processes=processes, silence_logs=logging.ERROR, **where)


def _malloc_for_arrays() -> bool:
    """In a process started with MALLOC_TRIM_THRESHOLD_ set (a Dask worker of a cluster we did
    not start), keep frame-sized arrays on the heap: raise glibc's mmap and trim thresholds.
    Returns True when it changed them."""
    if not os.environ.get("MALLOC_TRIM_THRESHOLD_") or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, _MMAP_THRESHOLD)) and bool(
            libc.mallopt(m_trim_threshold, 2 * _MMAP_THRESHOLD))
    except (OSError, AttributeError):
        return False


def _require_dask():
    try:
        import distributed
    except ImportError:
        raise InputError(BATCH_EXTRA_HINT) from None
    return distributed


def _summary(results: dict[str, dict], specs: Sequence[FlightSpec], started: float, meta: dict) -> dict:
    flights = []
    for s in specs:
        e = results.get(s.name)
        if e is None:
            e = {"name": s.name, "input": s.input, "mavlink": s.mavlink, "out": s.name, "status": "pending"}
        flights.append({k: v for k, v in e.items() if k != "footprint"})
    done = [f for f in flights if f["status"] != "pending"]
    return {**meta, "flights_total": len(specs), "ok": sum(f["status"] == "ok" for f in flights),
            "failed": sum(f["status"] == "failed" for f in flights), "pending": len(flights) - len(done),
            "wall_time_s": round(time.monotonic() - started, 3), "complete": len(done) == len(flights),
            "flights": flights}


def _line(k: int, n: int, e: dict) -> str:
    if e["status"] == "ok":
        geo = ", georeferenced" if e.get("georeferenced") else ""
        return (f"[{k}/{n}] {e['name']}: ok, {e['frames']} frames, {e['registered']} registered, "
                f"{e['segments']} segment(s){geo}, {e['wall_time_s']:.1f} s")
    return f"[{k}/{n}] {e['name']}: FAILED: {e['error']} ({e['wall_time_s'] or 0:.1f} s)"


def run_batch(specs: Sequence[FlightSpec], out_dir: str | Path, cfg: Config, *,
              scheduler: str | None = None, workers: int | None = None, processes: bool = True,
              progress: bool = False, echo: Callable[[str], None] | None = print) -> dict:
    """Map ``specs`` on Dask into ``out_dir``; returns the body of ``batch.json``.

    Parameters
    ----------
    scheduler : address of a running Dask scheduler (``tcp://host:8786``); None = a LocalCluster
        of ``workers`` (default: the usable cores) single-threaded workers, closed at the end.
    processes : LocalCluster workers as processes (default) or as threads of this process.
        Measured (tools/bench_batch.py, docs/benchmarks.md, 4 flights of 400 frames on the busy
        2-core machine, where neither got more than about one core): threads were 3-15 % faster,
        as a process costs about 1.5 CPU s of start-up and imports; both were within the runs'
        spread of each other. Processes stay the default: a flight whose decoder crashes takes
        only its own worker down, each flight's memory is returned when it ends, its log file
        gets only its lines, and two pipelines in one process share one GIL (the mapping holds
        it between OpenCV/numpy calls), which a machine with free cores would feel.
    progress : a bar on stderr (only when it is a terminal); ``echo`` gets one line per finished
        flight (None: silent).

    Threads: every flight gets ``cores // task slots`` OpenCV threads (``cv2.setNumThreads``) on
    its host (a slot = one worker thread), so that workers x threads never exceed the cores, and
    its BLAS/OpenMP pools pinned to 1 thread (threadpoolctl): the mapping's matrix products are
    small, and a 400-frame replay with the pools raised to 2 took 30-43 s against 4-9 s pinned to
    1 on this (busy) 2-core machine. Local workers are started without Dask's
    ``MALLOC_TRIM_THRESHOLD_`` (:func:`local_cluster`: 2.3x faster); workers of an existing
    cluster get glibc's thresholds raised in the task instead.
    """
    distributed = _require_dask()
    from tqdm import tqdm

    from photomap.cli.wiring import stderr_is_terminal
    from photomap.io.catalogue import write_catalogue
    from photomap.io.trajectory_files import write_json

    out = Path(out_dir).resolve()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {out}: {exc.strerror}") from None
    started = time.monotonic()
    quiet = logging.getLogger("distributed")
    saved_level = quiet.level
    if not log.isEnabledFor(logging.DEBUG):  # Dask's own INFO lines only with -v
        quiet.setLevel(logging.WARNING)
    cluster = None
    if scheduler:
        try:
            client = distributed.Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {_one_line(exc)}") from None
    else:
        n = workers or usable_cores()
        if n < 1:
            raise InputError(f"--workers must be at least 1, got {n}")
        cluster = local_cluster(n, processes=processes)
        client = distributed.Client(cluster)
    results: dict[str, dict] = {}
    try:
        info = client.scheduler_info()
        workers_info = info.get("workers", {})
        if not workers_info:
            client.wait_for_workers(1, timeout=60)
            workers_info = client.scheduler_info().get("workers", {})
        cores = client.run(usable_cores)
        threads = threads_per_host(workers_info, cores)
        meta = {"out": str(out), "scheduler": scheduler or "LocalCluster",
                "processes": processes if not scheduler else None, "workers": len(workers_info),
                "worker_threads": sum(int(w.get("nthreads") or 1) for w in workers_info.values()),
                "threads_per_flight": threads}
        log.info("batch of %d flight(s) on %d worker(s) (%s); threads per flight: %s", len(specs),
                 len(workers_info), meta["scheduler"], threads)
        futures = {client.submit(map_flight, s, str(out), cfg, threads, key=f"photomap-flight-{s.name}",
                                 pure=False): s for s in specs}
        bar = tqdm(total=len(specs), unit="flight", disable=not (progress and stderr_is_terminal()),
                   file=sys.stderr, dynamic_ncols=True)
        try:
            for k, future in enumerate(distributed.as_completed(futures), start=1):
                spec = futures[future]
                try:
                    entry = future.result()
                except Exception as exc:  # the worker died (KilledWorker), cancelled, ...
                    entry = {"name": spec.name, "input": spec.input, "mavlink": spec.mavlink, "out": spec.name,
                             "status": "failed", "error": f"worker lost: {_one_line(exc)}",
                             "frames": None, "registered": None, "segments": None, "georeferenced": False,
                             "wall_time_s": None}
                results[spec.name] = entry
                if echo is not None:
                    (bar.write if not bar.disable else echo)(_line(k, len(specs), entry))
                bar.update(1)
                write_json(out / "batch.json", _summary(results, specs, started, meta))
        finally:
            bar.close()
            for f in futures:
                if not f.done():
                    f.cancel()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
        quiet.setLevel(saved_level)
    write_catalogue(out / "flights.geojson",
                    [results[s.name].get("footprint") for s in specs if s.name in results])
    summary = _summary(results, specs, started, meta)
    write_json(out / "batch.json", summary)
    return summary


# ---------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="video file, folder of stills, or a manifest (.yaml/.yml/.csv) listing flights")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="address of a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: "
                             "a local cluster on this computer)")
    parser.add_argument("--workers", type=int, metavar="N",
                        help="local cluster: flights mapped at once, one worker process each "
                             "(default: the number of cores)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace, cfg: Config) -> int:
    _require_dask()
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    specs = discover_flights(args.inputs)
    summary = run_batch(specs, args.out, cfg, scheduler=args.scheduler, workers=args.workers,
                        progress=not (args.no_progress or args.quiet))
    out = Path(args.out)
    print(f"batch: {summary['ok']} of {summary['flights_total']} flight(s) mapped, {summary['failed']} failed, "
          f"{summary['wall_time_s']:.1f} s; {out / 'batch.json'}, {out / 'flights.geojson'}")
    return 0 if summary["failed"] == 0 else 1


__all__ = ["FlightSpec", "discover_flights", "map_flight", "read_manifest", "run_batch", "sidecar_telemetry",
           "threads_per_host", "unique_names"]
