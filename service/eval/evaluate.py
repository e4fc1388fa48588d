"""Compare a run's trajectory with the ground truth of a simulated flight.

  photomap evaluate RUN_DIR --truth groundtruth.csv [--out DIR]

Reads RUN_DIR/trajectory.csv, joins it with the truth by frame index and prints per-pair errors
(translation, rotation, scale, success rate), the anchored position error and drift, the ATE and
the heading and scale errors. Writes evaluation.json (every summary number),
evaluation_frames.csv (per-frame anchored poses and errors) and, with matplotlib
(ifmi-photomap[plots]), evaluation_poses.png (x, y, heading, scale over frames) and
evaluation_trajectory.png (true vs estimated path) into --out (default RUN_DIR).
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
from pathlib import Path

import numpy as np

from photomap.errors import InputError
from photomap.core.records import GroundTruth
from photomap.geometry import angle_scale, apply_h
from photomap.eval.metrics import ROTATION_OK_DEG, SCALE_OK_PCT, TRANSLATION_OK_PX, evaluate_trajectory, infer_centre
from photomap.io.trajectory_files import (atomic_write_bytes, atomic_write_text, read_groundtruth, read_trajectory_csv,
                     write_json)

log = logging.getLogger(__name__)

PLOTS_HINT = "install ifmi-photomap[plots] for the figures"
POSES_PNG = "evaluation_poses.png"
TRAJECTORY_PNG = "evaluation_trajectory.png"
FRAMES_CSV = "evaluation_frames.csv"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", metavar="RUN_DIR", help="output folder of a run (trajectory.csv)")
    parser.add_argument("--truth", required=True, metavar="CSV",
                        help="groundtruth.csv written by `photomap simulate`")
    parser.add_argument("--out", metavar="DIR", help="where to write the results (default RUN_DIR)")


def evaluate_run(run_dir: str | Path, truth_csv: str | Path, out_dir: str | Path | None = None
                 ) -> dict:
    """Evaluate ``run_dir/trajectory.csv`` against ``truth_csv``; write the results to ``out_dir``.

    Writes ``evaluation.json`` (every summary number), ``evaluation_frames.csv`` (one row per
    evaluated frame: anchored poses and errors) and, with matplotlib, the two PNGs.

    Returns
    -------
    dict
        :func:`photomap.eval.metrics.evaluate_trajectory`'s result plus ``run_dir``, ``truth``,
        ``frame_centre``, ``thresholds`` and ``plots`` (paths of the PNGs written, empty without
        matplotlib). evaluation.json holds the same without the segments' ``per_frame`` lists.

    Raises InputError for a missing or malformed run dir or truth file.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run directory not found: {run_dir}")
    rows = read_trajectory_csv(run_dir / "trajectory.csv")
    truth = read_groundtruth(truth_csv)
    if not set(int(f) for f in truth.frame) & {r.frame for r in rows}:
        raise InputError(f"no frame of {run_dir / 'trajectory.csv'} is in {truth_csv}")
    posed = [r for r in rows if r.M is not None]
    try:
        centre = infer_centre(posed) if posed else (0.0, 0.0)
    except ValueError as exc:
        raise InputError(f"{run_dir / 'trajectory.csv'}: {exc}") from None

    result = {"run_dir": str(run_dir), "truth": str(truth_csv), "frame_centre": list(centre),
              "thresholds": {"translation_px": TRANSLATION_OK_PX, "rotation_deg": ROTATION_OK_DEG,
                             "scale_pct": SCALE_OK_PCT},
              **evaluate_trajectory(rows, truth, centre)}
    if result["frames_without_truth"]:
        log.warning("%d posed frames have no ground truth and are ignored",
                    len(result["frames_without_truth"]))

    out = Path(out_dir) if out_dir is not None else run_dir
    out.mkdir(parents=True, exist_ok=True)
    try:
        result["plots"] = [str(p) for p in write_plots(result, truth, centre, out)]
    except ImportError:
        log.info("matplotlib is missing: no figures")
        result["plots"] = []
    atomic_write_text(out / FRAMES_CSV, format_frames_csv(result["segments"]))
    summary = {k: v for k, v in result.items() if k not in ("segments", "headline")}
    summary["segments"] = [{k: v for k, v in s.items() if k != "per_frame"}
                           for s in result["segments"]]
    summary["headline"] = next((s for s in summary["segments"] if result["headline"] is not None
                                and s["segment"] == result["headline"]["segment"]), None)
    write_json(out / "evaluation.json", summary)
    return result


_PAIR_KEYS = ("pair_translation_px", "pair_rotation_deg", "pair_scale_pct")
_FRAME_KEYS = ("frame", "est_x", "est_y", "true_x", "true_y", "est_heading_deg",
               "true_heading_deg", "est_scale", "true_scale", "position_error_px",
               "heading_error_deg", "scale_error_pct")


def format_frames_csv(segments: list[dict]) -> str:
    """Per-frame table of every segment: anchored poses and errors (terrain px, deg, %).

    The pair errors of a row are those of the pair (previous glued frame, this frame); they are
    empty on a segment's first frame.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["segment", *_FRAME_KEYS, *_PAIR_KEYS])
    for s in segments:
        pf = s["per_frame"]
        for i, frame in enumerate(pf["frame"]):
            values = [f"{pf[k][i]:.6f}" for k in _FRAME_KEYS[1:]]
            pairs = [f"{pf[k][i - 1]:.6f}" if i else "" for k in _PAIR_KEYS]
            w.writerow([s["segment"], frame, *values, *pairs])
    return buf.getvalue()


# --- text ---------------------------------------------------------------------------------

def _n(v: float | None, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def format_table(result: dict) -> str:
    """A short plain-text table of the headline segment (and one line per other segment)."""
    lines = [f"frames {result['frames']}, posed {result['frames_posed']} "
             f"({100 * result['fraction_posed']:.1f} %), segments {len(result['segments'])}"]
    h = result["headline"]
    if h is None:
        lines.append("no posed frame with ground truth: nothing to evaluate")
        return "\n".join(lines)
    lines.append(f"headline: segment {h['segment']}, {h['frames_posed']} frames from frame "
                 f"{h['anchor_frame']}, true path {h['path_length_px']:.1f} px")
    lines.append(f"{'':24}{'median':>10}{'rms':>10}{'max':>10}{'final':>10}")
    p = h["pairs"]
    for label, key in (("pair translation px", "translation_px"), ("pair rotation deg", "rotation_deg"),
                       ("pair scale %", "scale_pct")):
        s = p[key]
        lines.append(f"{label:24}{_n(s['median']):>10}{_n(s['rms']):>10}{_n(s['max']):>10}")
    for label, key in (("position error px", "position_px"), ("heading error deg", "heading_deg"),
                       ("scale error %", "scale_pct")):
        s = h[key]
        lines.append(f"{label:24}{_n(s['median']):>10}{_n(s['rms']):>10}{_n(s['max']):>10}"
                     f"{_n(s['final']):>10}")
    t = result["thresholds"]
    rate = p["success_rate"]
    lines.append(f"pair success rate {_n(None if rate is None else 100 * rate, '.1f')} % "
                 f"(< {t['translation_px']:g} px, {t['rotation_deg']:g} deg, {t['scale_pct']:g} %)")
    lines.append(f"drift {_n(h['position_px']['drift_pct'], '.2f')} % of path, "
                 f"ATE {_n(h['ate']['rmse_px'], '.2f')} px ({_n(h['ate']['pct'], '.2f')} % of path)")
    for s in result["segments"]:
        if s is not h:
            lines.append(f"segment {s['segment']}: {s['frames_posed']} frames, drift "
                         f"{_n(s['position_px']['drift_pct'], '.2f')} %, ATE "
                         f"{_n(s['ate']['rmse_px'], '.2f')} px")
    return "\n".join(lines)


# --- plots --------------------------------------------------------------------------------

def _truth_curves(truth: GroundTruth, centre: tuple[float, float]) -> dict:
    order = np.argsort(truth.frame)
    H = truth.H[order]
    xy = apply_h(H, centre).reshape(-1, 2)
    ang_scale = np.array([angle_scale(m, centre) for m in H]).reshape(-1, 2)
    return {"frame": truth.frame[order], "x": xy[:, 0], "y": xy[:, 1],
            "heading": np.degrees(np.unwrap(np.radians(ang_scale[:, 0]))),
            "scale": ang_scale[:, 1]}


def write_plots(result: dict, truth: GroundTruth, centre: tuple[float, float], out_dir: Path
                ) -> list[Path]:
    """Write the two figures (Agg, no display); raises ImportError without matplotlib."""
    from matplotlib.figure import Figure

    tc = _truth_curves(truth, centre)
    fig = Figure(figsize=(10, 8), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True).ravel()
    panels = (("x", "x (terrain px)"), ("y", "y (terrain px, down)"),
              ("heading", "heading (deg)"), ("scale", "scale (terrain px / frame px)"))
    for ax, (key, label) in zip(axes, panels):
        ax.plot(tc["frame"], tc[key], color="k", lw=1.2, label="truth")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    for s in result["segments"]:
        pf = s["per_frame"]
        frames = np.asarray(pf["frame"])
        # heading on the truth's unwrapped branch: truth + wrapped error
        heading = np.interp(frames, tc["frame"], tc["heading"]) + np.asarray(pf["heading_error_deg"])
        est = {"x": pf["est_x"], "y": pf["est_y"], "heading": heading, "scale": pf["est_scale"]}
        for ax, (key, _) in zip(axes, panels):
            ax.plot(frames, est[key], ".", ms=3, label=f"estimate, segment {s['segment']}")
    axes[2].set_xlabel("frame")
    axes[3].set_xlabel("frame")
    axes[0].legend(fontsize="small")
    fig.suptitle("photomap: estimated (anchored at each segment's first frame) vs true pose")

    fig2 = Figure(figsize=(8, 8), layout="constrained")
    ax = fig2.subplots()
    ax.plot(tc["x"], tc["y"], color="k", lw=1.2, label="truth")
    for s in result["segments"]:
        pf = s["per_frame"]
        ax.plot(pf["est_x"], pf["est_y"], ".-", ms=3, lw=0.8, label=f"estimate, segment {s['segment']}")
        ax.plot(pf["true_x"][0], pf["true_y"][0], "o", mfc="none", color="k")
    ax.set_aspect("equal", adjustable="datalim")
    ax.invert_yaxis()
    ax.set_xlabel("x (terrain px)")
    ax.set_ylabel("y (terrain px, down)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    h = result["headline"]
    if h is not None:
        ax.set_title(f"trajectory (anchored): drift {_n(h['position_px']['drift_pct'], '.2f')} %, "
                     f"ATE {_n(h['ate']['rmse_px'], '.2f')} px")

    paths = []
    for figure, name in ((fig, POSES_PNG), (fig2, TRAJECTORY_PNG)):
        buf = io.BytesIO()
        figure.savefig(buf, format="png", dpi=100)
        atomic_write_bytes(out_dir / name, buf.getvalue())
        paths.append(out_dir / name)
    return paths


def main(args: argparse.Namespace, cfg: dict) -> int:
    """``photomap evaluate``: print the table, write evaluation.json and the figures."""
    result = evaluate_run(args.run_dir, args.truth, args.out)
    out = Path(args.out) if args.out else Path(args.run_dir)
    print(format_table(result))
    print(f"wrote {out / 'evaluation.json'}, {FRAMES_CSV}"
          + "".join(f", {Path(p).name}" for p in result["plots"]))
    if not result["plots"]:
        print(PLOTS_HINT)
    return 0
