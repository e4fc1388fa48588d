"""Trajectories of a run and their errors against ground truth (pure: arrays in, numbers out).

Conventions (:mod:`photomap.geometry`): pixel coordinates are OpenCV's (x right, y down, origin at the
centre of the top-left pixel). An estimated pose ``M`` (2x3, or 3x3 for a frame the run rectified:
see :func:`input_pose`) maps frame pixels to the pixels of its segment's map; a true pose ``H``
(3x3, possibly projective) maps frame pixels to terrain pixels. Both are taken at the input
video's resolution, so one frame-centre pixel ``centre`` serves both.

The estimated map of a segment is anchored to the terrain at the segment's first posed frame
``f0``: ``terrain_from_map = H[f0] @ inv(M[f0])``. Angles of a (possibly projective) transform are
those of its local linear map at the frame centre (for a similarity:
``degrees(atan2(M[1,0], M[0,0]))``), scales are ``sqrt(|det|)`` of that local map.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from photomap.core.records import GLUED, STATUSES, GroundTruth, PoseRow
from photomap.geo.georef import rectifying_homography
from photomap.geometry import (angle_scale, apply_h, frame_centre, local_linear, pose_angle_deg, pose_scale,
                               to_h, umeyama, wrap_deg)

__all__ = ["evaluate_trajectory", "segment_metrics", "pair_errors", "anchored_poses", "path_length",
           "infer_centre", "input_pose", "summary", "TRANSLATION_OK_PX", "ROTATION_OK_DEG",
           "SCALE_OK_PCT"]

TRANSLATION_OK_PX = 1.0
ROTATION_OK_DEG = 0.5
SCALE_OK_PCT = 1.0


def summary(values: np.ndarray) -> dict:
    """``{"median", "rms", "max", "n"}`` of ``|values|`` (None entries for no values)."""
    v = np.abs(np.asarray(values, dtype=float))
    if v.size == 0:
        return {"median": None, "rms": None, "max": None, "n": 0}
    return {"median": float(np.median(v)), "rms": float(np.sqrt(np.mean(v ** 2))),
            "max": float(v.max()), "n": int(v.size)}


def path_length(H_true: np.ndarray, centre: Sequence[float]) -> float:
    """Length (terrain px) of the polyline through the true frame centres, in the given order."""
    p = apply_h(np.asarray(H_true, dtype=float), centre).reshape(-1, 2)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


# --- metrics ------------------------------------------------------------------------------

def pair_errors(M_est: np.ndarray, H_true: np.ndarray, centre: Sequence[float]) -> dict:
    """Errors of the relative motion between consecutive poses.

    For each pair (i-1, i) the estimated ``inv(M[i-1]) @ M[i]`` and the true
    ``inv(H[i-1]) @ H[i]`` both map pixels of frame i to pixels of frame i-1.

    Returns
    -------
    dict of arrays (one entry per pair)
        ``translation_px``: distance between the estimated and true images of the frame centre
        (pixels of frame i-1); ``rotation_deg``: estimated minus true angle, wrapped;
        ``scale_pct``: ``100 * (s_est / s_true - 1)``.
    """
    M = to_h(M_est)
    H = to_h(H_true)
    n = max(len(M) - 1, 0)
    out = {k: np.zeros(n) for k in ("translation_px", "rotation_deg", "scale_pct")}
    for i in range(1, len(M)):
        E = np.linalg.solve(M[i - 1], M[i])
        T = np.linalg.solve(H[i - 1], H[i])
        out["translation_px"][i - 1] = np.linalg.norm(apply_h(E, centre) - apply_h(T, centre))
        a_e, s_e = angle_scale(E, centre)
        a_t, s_t = angle_scale(T, centre)
        out["rotation_deg"][i - 1] = wrap_deg(a_e - a_t)
        out["scale_pct"][i - 1] = 100.0 * (s_e / s_t - 1.0)
    return out


def anchored_poses(M_est: np.ndarray, H_true: np.ndarray, centre: Sequence[float]) -> dict:
    """Estimated poses in terrain pixels, anchored at the first pose, next to the truth.

    Returns arrays (one entry per pose): ``est_xy``/``true_xy`` (N, 2) frame-centre positions
    (terrain px), ``est_heading_deg``/``true_heading_deg``, ``est_scale``/``true_scale``
    (terrain px per frame px), and ``terrain_from_map`` (3x3).
    """
    M = to_h(M_est)
    H = to_h(H_true)
    terrain_from_map = H[0] @ np.linalg.inv(M[0])
    out: dict = {"terrain_from_map": terrain_from_map}
    for name, poses in (("est", terrain_from_map @ M), ("true", H)):
        xy = apply_h(poses, centre).reshape(-1, 2)
        ang_scale = np.array([angle_scale(P, centre) for P in poses]).reshape(-1, 2)
        out[f"{name}_xy"] = xy
        out[f"{name}_heading_deg"] = ang_scale[:, 0]
        out[f"{name}_scale"] = ang_scale[:, 1]
    return out


def segment_metrics(M_est: np.ndarray, H_true: np.ndarray, centre: Sequence[float],
                    frames: Sequence[int] | None = None, path_px: float | None = None,
                    thresholds: tuple[float, float, float] = (TRANSLATION_OK_PX, ROTATION_OK_DEG,
                                                              SCALE_OK_PCT)) -> dict:
    """All errors of one segment's glued poses against the truth of the same frames.

    Parameters
    ----------
    M_est : ndarray (N, 2, 3) or (N, 3, 3)
        Estimated poses (input frame -> segment map px), in frame order.
    H_true : ndarray (N, 3, 3)
        True poses (frame -> terrain px) of the same frames.
    centre : (float, float)
        Frame-centre pixel ``((w-1)/2, (h-1)/2)``.
    frames : sequence of int, optional
        Frame indices, only used to label the per-frame output.
    path_px : float, optional
        True path length (terrain px) the drift and ATE percentages refer to; default: the
        polyline through the true centres of these frames.
    thresholds : (px, deg, pct)
        A pair succeeds when all three errors are below these.

    Returns
    -------
    dict
        ``frames_posed``, ``anchor_frame``, ``path_length_px``, ``pairs`` (summaries of
        ``translation_px``, ``rotation_deg``, ``scale_pct`` and ``success_rate``),
        ``position_px`` (anchored position error summary, ``final``, ``drift_pct``),
        ``ate`` (``rmse_px``, ``pct``, ``scale`` of the fitted similarity), ``heading_deg`` and
        ``scale_pct`` (anchored error summaries with ``final``) and ``per_frame`` (lists).
    """
    M_est = np.asarray(M_est, dtype=float)
    M_est = M_est.reshape(-1, *M_est.shape[-2:])
    H_true = to_h(np.asarray(H_true, dtype=float).reshape(-1, 3, 3))
    n = len(M_est)
    if n == 0 or len(H_true) != n:
        raise ValueError("segment_metrics needs as many true poses as estimated ones (>= 1)")
    frames = list(range(n)) if frames is None else [int(f) for f in frames]
    length = path_length(H_true, centre) if path_px is None else float(path_px)

    pairs = pair_errors(M_est, H_true, centre)
    t_ok, r_ok, s_ok = thresholds
    ok = ((pairs["translation_px"] < t_ok) & (np.abs(pairs["rotation_deg"]) < r_ok)
          & (np.abs(pairs["scale_pct"]) < s_ok))
    pair_out = {k: summary(v) for k, v in pairs.items()}
    pair_out["success_rate"] = float(ok.mean()) if ok.size else None

    anc = anchored_poses(M_est, H_true, centre)
    pos_err = np.linalg.norm(anc["est_xy"] - anc["true_xy"], axis=1)
    head_err = wrap_deg(anc["est_heading_deg"] - anc["true_heading_deg"])
    scale_err = 100.0 * (anc["est_scale"] / anc["true_scale"] - 1.0)

    est_map_xy = apply_h(M_est, centre).reshape(-1, 2)
    ate: dict = {"rmse_px": None, "pct": None, "scale": None}
    if n >= 2:
        s, R, t = umeyama(est_map_xy, anc["true_xy"])
        aligned = s * est_map_xy @ R.T + t
        rmse = float(np.sqrt(np.mean(np.sum((aligned - anc["true_xy"]) ** 2, axis=1))))
        ate = {"rmse_px": rmse, "pct": 100.0 * rmse / length if length > 0 else None,
               "scale": s}

    def pct(v: float) -> float | None:
        return 100.0 * v / length if length > 0 else None

    return {
        "frames_posed": n,
        "anchor_frame": frames[0],
        "path_length_px": length,
        "pairs": pair_out,
        "position_px": {**summary(pos_err), "final": float(pos_err[-1]),
                        "drift_pct": pct(float(pos_err[-1]))},
        "ate": ate,
        "heading_deg": {**summary(head_err), "final": float(head_err[-1])},
        "scale_pct": {**summary(scale_err), "final": float(scale_err[-1])},
        "per_frame": {
            "frame": frames,
            "est_x": anc["est_xy"][:, 0].tolist(), "est_y": anc["est_xy"][:, 1].tolist(),
            "true_x": anc["true_xy"][:, 0].tolist(), "true_y": anc["true_xy"][:, 1].tolist(),
            "est_heading_deg": anc["est_heading_deg"].tolist(),
            "true_heading_deg": anc["true_heading_deg"].tolist(),
            "est_scale": anc["est_scale"].tolist(), "true_scale": anc["true_scale"].tolist(),
            "position_error_px": pos_err.tolist(),
            "heading_error_deg": np.asarray(head_err).tolist(),
            "scale_error_pct": scale_err.tolist(),
            "pair_translation_px": pairs["translation_px"].tolist(),
            "pair_rotation_deg": pairs["rotation_deg"].tolist(),
            "pair_scale_pct": pairs["scale_pct"].tolist(),
        },
    }


def infer_centre(rows: Sequence[PoseRow]) -> tuple[float, float]:
    """Frame-centre pixel implied by the rows' ``xy`` and ``M`` (``xy = M @ centre``).

    A centre ``((w-1)/2, (h-1)/2)`` is a multiple of 0.5 px, so the estimate is rounded to one.
    Raises ValueError when no row has both, or when rows disagree by more than 0.01 px.
    """
    cs = [np.linalg.solve(np.asarray(r.M)[:2, :2], np.asarray(r.xy) - np.asarray(r.M)[:2, 2])
          for r in rows if r.M is not None and r.xy is not None]
    if not cs:
        raise ValueError("no row has both a pose and a frame-centre position")
    c = np.median(np.array(cs), axis=0)
    if np.abs(np.array(cs) - c).max() > 0.01:
        raise ValueError("the rows' x, y are not the image of one frame-centre pixel")
    return round(2 * float(c[0])) / 2, round(2 * float(c[1])) / 2


def input_pose(row: PoseRow, centre: Sequence[float]) -> np.ndarray:
    """3x3 map of the row's *input* frame pixels to map pixels.

    A row whose frame the run rectified to its nadir view (columns ``rect_roll_deg``,
    ``rect_pitch_deg``, ``rect_fx_px``) has a pose ``M`` of that view's pixels; its input frame
    maps by ``M @ rectifying_homography(...)`` (projective). Other rows: ``M`` itself.
    """
    M = to_h(np.asarray(row.M, dtype=float)[:2])
    ex = row.extra
    roll, pitch, fx = ex.get("rect_roll_deg"), ex.get("rect_pitch_deg"), ex.get("rect_fx_px")
    if not all(isinstance(v, float) and math.isfinite(v) for v in (roll, pitch, fx)):
        return M
    w, h = int(round(2 * centre[0] + 1)), int(round(2 * centre[1] + 1))
    return M @ rectifying_homography(fx, w, h, math.radians(roll), math.radians(pitch))


def evaluate_trajectory(rows: Sequence[PoseRow], truth: GroundTruth,
                        centre: Sequence[float]) -> dict:
    """Join a run's rows with the truth by frame index and compute every segment's metrics.

    Only glued rows (status ``reference``/``registered`` with a pose) are evaluated. The path
    length of a segment runs along the truth through every frame from its first to its last
    glued frame. The headline is the segment with the most glued frames.

    Returns
    -------
    dict
        ``frames`` (rows), ``frames_posed``, ``fraction_posed``, ``frames_without_truth``,
        ``segments`` (list of :func:`segment_metrics` results plus ``segment``) and
        ``headline`` (the largest segment's result, or None when nothing is posed).
    """
    index = {int(f): i for i, f in enumerate(truth.frame)}
    missing = [r.frame for r in rows if r.glued and r.frame not in index]
    glued = sorted((r for r in rows if r.glued and r.frame in index), key=lambda r: r.frame)
    by_segment: dict[int, list[PoseRow]] = {}
    for r in glued:
        by_segment.setdefault(r.segment, []).append(r)

    segments = []
    order = np.argsort(truth.frame)
    sorted_frames = np.asarray(truth.frame)[order]
    for seg, seg_rows in sorted(by_segment.items()):
        first, last = seg_rows[0].frame, seg_rows[-1].frame
        span = order[(sorted_frames >= first) & (sorted_frames <= last)]
        res = segment_metrics(np.array([input_pose(r, centre) for r in seg_rows]),
                              np.array([truth.H[index[r.frame]] for r in seg_rows]),
                              centre, frames=[r.frame for r in seg_rows],
                              path_px=path_length(truth.H[span], centre))
        segments.append({"segment": seg, **res})

    headline = max(segments, key=lambda s: s["frames_posed"]) if segments else None
    n_rows = len(rows)
    n_posed = sum(1 for r in rows if r.glued)
    return {
        "frames": n_rows,
        "frames_posed": n_posed,
        "fraction_posed": n_posed / n_rows if n_rows else 0.0,
        "frames_without_truth": missing,
        "segments": segments,
        "headline": headline,
    }
