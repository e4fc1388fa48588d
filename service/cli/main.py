"""The ``photomap`` command: a thin layer over importable functions.

Each command lives in its own module, which exposes ``add_arguments(parser)`` and
``main(args, cfg) -> int``. Errors a user can act on (:class:`PhotomapError`) are printed on one
line and mapped to an exit code; no traceback reaches the user unless ``--debug`` is given.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading

from photomap import __version__
from photomap.cli.oplog import LOG_FORMATS, setup_logging
from photomap.config import load_config
from photomap.errors import PhotomapError

# command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("photomap.cli.demo", "simulate a flight over the bundled terrain, map it, print where the map is"),
    "run": ("photomap.cli.run", "map live from a camera (V4L2) until stopped"),
    "replay": ("photomap.cli.replay", "map a logged video or a folder of images"),
    "simulate": ("photomap.cli.simulate", "fly a virtual camera over a terrain image: video, telemetry, ground truth"),
    "calibrate": ("photomap.cli.calibrate", "fit the camera's lens model (distortion) to views of a checkerboard"),
    "evaluate": ("photomap.eval.evaluate", "compare a run's trajectory with ground truth: errors, ATE, drift, plots"),
    "batch": ("photomap.cli.batch", "map many logged flights at once on every core or a Dask cluster"),
    "merge": ("photomap.cli.merge", "merge the maps of several runs over one site into one map"),
    "recover": ("photomap.cli.recover", "rebuild the map of a killed run (or one whose final write failed) from its checkpoint"),
    "export": ("photomap.cli.export", "export a run for GIS and ground stations: GeoTIFF, web tiles, KML/GeoJSON, evo, report"),
}

EXIT_INTERRUPTED = 130


def _common(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("configuration")
    g.add_argument("--config", metavar="FILE", help="YAML file overriding config/default.yaml")
    g.add_argument("--set", metavar="KEY=VALUE", action="append", default=[], dest="overrides",
                   help="override one config key, e.g. --set mosaic.blend=feather (repeatable)")
    g.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    g.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    g.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    g.add_argument("--log-format", choices=LOG_FORMATS, default="text",
                   help="log lines on stderr as text (default) or json: one object per line with "
                        "time, level, logger, message and the record's fields (journald, log shippers)")
    g.add_argument("--status-interval", type=_seconds, default=5.0, metavar="SECONDS",
                   help="run, replay: log a status line (fps, frames, dropped, segments, latency, "
                        "telemetry link) at INFO every SECONDS; 0 = never. A replay on a terminal "
                        "shows its progress bar instead (default 5)")


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="photomap",
        description="Live aerial photo maps from a down-looking drone camera (iFMI registration).",
    )
    parser.add_argument("--version", action="version", version=f"photomap {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in COMMANDS.items():
        mod = importlib.import_module(module)
        p = sub.add_parser(name, help=help_text, description=(mod.__doc__ or help_text).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        _common(p)
        p.set_defaults(_module=mod)
    return parser


def _setup_logging(verbose: int, quiet: bool, log_format: str = "text") -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 0 else logging.INFO)
    setup_logging(level, log_format)


def main(argv: list[str] | None = None) -> int:
    # SIGTERM acts like Ctrl-C (KeyboardInterrupt): a clean "interrupted" rather than an abrupt
    # death while a command starts up; a mapping run installs its own handler that writes the map
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    command, args = "photomap", None
    try:
        args = build_parser().parse_args(argv)
        command = f"photomap {args.command}"
        _setup_logging(args.verbose, args.quiet, args.log_format)
        cfg = load_config(args.config, args.overrides)
        return int(args._module.main(args, cfg) or 0)
    except PhotomapError as exc:
        if args is not None and args.debug:
            raise
        print(f"{command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"{command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if argv is None and threading.current_thread() is threading.main_thread():
            # the command is over (its outputs written): a Ctrl-C or SIGTERM from now on ends the
            # process at once, not with a KeyboardInterrupt traceback from the interpreter's shutdown
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


if __name__ == "__main__":
    sys.exit(main())
