"""A 2D similarity pose graph: drift correction of keyframe poses with loop closures and priors.

Chained frame-to-frame (or keyframe-to-keyframe) iFMI registrations drift: every small rotation
or scale error bends and stretches the rest of the track. Pfingsthorn, Birk et al. answered it
with a pose graph whose constraints are the iFMI registrations weighted by their POMF peak; this
module is that graph, solved by sparse Levenberg-Marquardt (or ``scipy.optimize.least_squares``)
with a robust loss so that one wrong loop closure cannot wreck the map.

Conventions (:mod:`photomap.geometry`): OpenCV pixel coordinates (x right, y down, origin at the
centre of the top-left pixel). A node pose ``T_i`` (3x3) maps pixels of keyframe ``i`` to map
pixels. It is a similarity parametrised as ``(x, y, theta, log s)``::

    T_i(p) = s R(theta) (p - c) + (x, y),     R(theta) = [[cos, -sin], [sin, cos]]

where ``c = ((w - 1) / 2, (h - 1) / 2)`` is the centre of the frame (so ``(x, y)`` is the map
position of the frame centre, as in ``trajectory.csv``), ``theta = atan2(M[1,0], M[0,0])``
(radians; positive turns clockwise on screen with y down) and ``s = sqrt(det(M[:2, :2]))``.
Parametrising about the centre keeps rotation and translation nearly uncorrelated.

An edge ``(i, j, Z_ij)`` measures ``Z_ij`` (3x3 or 2x3) mapping pixels of ``j`` to pixels of
``i``: exactly :meth:`Registrar.register(frame_i, frame_j).matrix` at the pixel scale of the
node poses. Its residual compares ``T_i^-1 T_j`` with ``Z_ij`` (in pixels of frame ``i``)::

    r_t     = e^-s_i R(-theta_i) ((x_j, y_j) - (x_i, y_i)) + c - Z_ij(c)      [px]
    r_theta = wrap(theta_j - theta_i - angle(Z_ij))                          [rad]
    r_logs  = log s_j - log s_i - log scale(Z_ij)

each divided by its standard deviation. From a registration confidence ``q`` in (0, 1]:
``sigma_t = sigma_px / q`` and ``sigma_theta = sigma_logs = sigma_t / r`` with ``r`` half the
frame diagonal (a rotation or scale error of ``sigma_theta`` moves the frame's corners by
``sigma_t`` pixels), i.e. information ``= q^2 diag(1, 1, r^2, r^2) / sigma_px^2``.

Priors (each with its own standard deviation):
- a locked node (hard: its parameters are not optimised); with no locked node and no position
  prior in map pixels, node 0 is locked (the gauge);
- a position prior: the map position of a node's centre, in map pixels (e.g. GPS converted by a
  georeference);
- a GPS prior in local metres ``(east, north)``: the map is tied to it by a free global
  similarity (map px -> local metres) estimated with the poses (:attr:`PoseGraphResult.map_to_enu`);
- a heading prior: ``theta_i = heading_i + offset`` with one free global ``offset`` (map "up" vs
  north is unknown), ``heading`` clockwise from north as MAVLink's yaw when the image's up is the
  vehicle's forward axis; with a single free offset they constrain relative headings;
- a scale prior from altitude: ``log s_i = log h_i + k`` with one free global ``k`` (the map's
  pixels per metre are unknown), i.e. scale ratios follow altitude ratios.

The robust loss (``soft_l1``, ``cauchy``, ``huber`` with ``f_scale`` in sigmas, or ``linear``) is
applied per residual block (an edge or a prior), to the squared Mahalanobis norm of the block,
not per component: an edge is one measurement and is down-weighted as a whole.

Pure: arrays in, arrays out; no I/O, no threads.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from photomap.config import PosegraphConfig
from photomap.geometry import pose_scale

__all__ = ["EDGE_KINDS", "ROBUST_LOSSES", "PoseGraph", "PoseGraphResult", "optimize", "correction",
           "interpolate_corrections", "pose_params", "pose_matrix"]


EDGE_KINDS = ("sequential", "loop", "map", "join")
ROBUST_LOSSES = ("linear", "soft_l1", "cauchy", "huber")
_NP = 4  # parameters per node: x, y, theta, log s


def _wrap(a: np.ndarray | float) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return np.remainder(np.asarray(a) + np.pi, 2.0 * np.pi) - np.pi


def _as3x3(m: np.ndarray, what: str) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    if m.shape != (3, 3) or not np.isfinite(m).all():
        raise ValueError(f"{what} must be a finite 2x3 or 3x3 matrix, got shape {m.shape}")
    if m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0] <= 0:
        raise ValueError(f"{what} is not a similarity (determinant <= 0)")
    return m


def pose_params(pose: np.ndarray, center: Sequence[float]) -> np.ndarray:
    """``(x, y, theta, log s)`` of a 2x3/3x3 pose about the pixel ``center`` (see module doc)."""
    m = _as3x3(pose, "pose")
    c = np.asarray(center, dtype=np.float64)
    xy = m[:2, :2] @ c + m[:2, 2]
    theta = math.atan2(m[1, 0], m[0, 0])
    logs = 0.5 * math.log(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])
    return np.array([xy[0], xy[1], theta, logs])


def pose_matrix(params: np.ndarray, center: Sequence[float]) -> np.ndarray:
    """3x3 poses from ``(..., 4)`` parameters ``(x, y, theta, log s)`` about ``center``."""
    p = np.asarray(params, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64)
    s = np.exp(p[..., 3])
    co, si = s * np.cos(p[..., 2]), s * np.sin(p[..., 2])
    out = np.zeros(p.shape[:-1] + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = co, -si, si, co
    out[..., 0, 2] = p[..., 0] - co * c[0] + si * c[1]
    out[..., 1, 2] = p[..., 1] - si * c[0] - co * c[1]
    out[..., 2, 2] = 1.0
    return out


class PoseGraph:
    """Nodes (keyframe poses), edges (relative registrations) and priors; see the module doc.

    Parameters
    ----------
    frame_size : (width, height) of the keyframes in the pixels the poses and edges use.
    params : the ``posegraph`` settings; here ``sigma_px`` (translation standard deviation, px, of
        an edge of confidence 1) and ``min_confidence`` (confidences are clipped to at least this
        before weighting).
    """

    def __init__(self, frame_size: tuple[int, int], params: PosegraphConfig = PosegraphConfig()) -> None:
        w, h = frame_size
        sigma_px, min_confidence = params.sigma_px, params.min_confidence
        if w <= 0 or h <= 0:
            raise ValueError("frame_size must be > 0")
        self.frame_size = (int(w), int(h))
        self.center = ((w - 1) / 2.0, (h - 1) / 2.0)
        self.radius = 0.5 * math.hypot(w, h)
        self.sigma_px = float(sigma_px)
        self.min_confidence = float(min_confidence)
        self._nodes: list[np.ndarray] = []  # initial (x, y, theta, log s)
        self._edges: list[tuple[int, int, np.ndarray, np.ndarray, str]] = []  # i, j, z(4), sigmas(4), kind
        self.fixed: set[int] = set()
        self._position: list[tuple[int, float, float, float]] = []  # node, x, y, sigma_px
        self._gps: list[tuple[int, float, float, float]] = []  # node, east, north, sigma_m
        self._heading: list[tuple[int, float, float]] = []  # node, heading rad, sigma rad
        self._scale: list[tuple[int, float, float]] = []  # node, log altitude, sigma (log)

    # ------------------------------------------------------------------ building
    @property
    def num_nodes(self) -> int:
        return len(self._nodes)

    @property
    def num_edges(self) -> int:
        return len(self._edges)

    @property
    def has_priors(self) -> bool:
        """True when some node has a position, GPS, heading or altitude prior."""
        return bool(self._position or self._gps or self._heading or self._scale)

    @property
    def edge_kinds(self) -> list[str]:
        return [e[4] for e in self._edges]

    @property
    def edge_pairs(self) -> np.ndarray:
        """(E, 2) node indices ``(i, j)`` of the edges, in the order they were added."""
        return np.array([(e[0], e[1]) for e in self._edges], dtype=np.int64).reshape(-1, 2)

    def initial_poses(self) -> np.ndarray:
        """(N, 3, 3) poses the nodes were added with."""
        return pose_matrix(np.array(self._nodes).reshape(-1, _NP), self.center)

    def _node(self, i: int) -> int:
        if not 0 <= int(i) < len(self._nodes):
            raise ValueError(f"node {i} does not exist ({len(self._nodes)} nodes)")
        return int(i)

    def add_node(self, pose: np.ndarray) -> int:
        """Add a keyframe with its initial pose (2x3/3x3, keyframe px -> map px); its index."""
        self._nodes.append(pose_params(pose, self.center))
        return len(self._nodes) - 1

    def edge_sigmas(self, confidence: float) -> np.ndarray:
        """Standard deviations ``(px, px, rad, log)`` of an edge of registration ``confidence``."""
        q = min(max(float(confidence), self.min_confidence), 1.0)
        st = self.sigma_px / q
        return np.array([st, st, st / self.radius, st / self.radius])

    def add_edge(self, i: int, j: int, matrix: np.ndarray, confidence: float = 1.0,
                 kind: str = "sequential", sigmas: Sequence[float] | None = None) -> int:
        """Add a measurement ``matrix`` mapping pixels of node ``j`` to pixels of node ``i``.

        ``sigmas`` = ``(sigma_x, sigma_y [px], sigma_theta [rad], sigma_logs)`` overrides the
        weighting from ``confidence`` (:meth:`edge_sigmas`). Returns the edge index.
        """
        i, j = self._node(i), self._node(j)
        if i == j:
            raise ValueError(f"an edge needs two different nodes, got {i} twice")
        if kind not in EDGE_KINDS:
            raise ValueError(f"edge kind must be one of {EDGE_KINDS}, got {kind!r}")
        m = _as3x3(matrix, "edge matrix")
        c = np.asarray(self.center)
        zt = m[:2, :2] @ c + m[:2, 2]
        z = np.array([zt[0], zt[1], math.atan2(m[1, 0], m[0, 0]),
                      0.5 * math.log(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])])
        sig = self.edge_sigmas(confidence) if sigmas is None else np.asarray(sigmas, dtype=np.float64)
        if sig.shape != (4,) or not (np.isfinite(sig).all() and (sig > 0).all()):
            raise ValueError("sigmas must be 4 positive numbers (px, px, rad, log scale)")
        self._edges.append((i, j, z, sig, kind))
        return len(self._edges) - 1

    def copy(self) -> PoseGraph:
        """An independent copy (cheap: the lists are copied, their entries shared; no method
        changes an entry in place, they append to or replace the lists)."""
        other = copy.copy(self)
        for name in ("_nodes", "_edges", "_position", "_gps", "_heading", "_scale"):
            setattr(other, name, list(getattr(self, name)))
        other.fixed = set(self.fixed)
        return other

    def drop_edges(self, indices: Sequence[int]) -> None:
        """Remove edges (e.g. :attr:`PoseGraphResult.outliers`); later edges' indices shift down."""
        gone = {int(k) for k in indices}
        if any(not 0 <= k < len(self._edges) for k in gone):
            raise ValueError(f"edge indices must be in [0, {len(self._edges)}), got {sorted(gone)}")
        self._edges = [e for k, e in enumerate(self._edges) if k not in gone]

    def set_poses(self, poses: np.ndarray) -> None:
        """Replace every node's pose (the starting point of the next :func:`optimize`), e.g.
        with a previous result's ``poses`` before adding new keyframes and edges."""
        poses = np.asarray(poses, dtype=np.float64)
        if len(poses) != len(self._nodes):
            raise ValueError(f"{len(poses)} poses for {len(self._nodes)} nodes")
        if poses.ndim != 3 or poses.shape[1:] not in ((2, 3), (3, 3)):
            raise ValueError(f"poses must be (n, 2, 3) or (n, 3, 3), got {poses.shape}")
        c = np.asarray(self.center)
        xy = poses[:, :2, :2] @ c + poses[:, :2, 2]  # all nodes at once, as pose_params does one
        theta = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        logs = 0.5 * np.log(poses[:, 0, 0] * poses[:, 1, 1] - poses[:, 0, 1] * poses[:, 1, 0])
        self._nodes = list(np.column_stack([xy, theta, logs]))

    def absorb(self, other: PoseGraph, transform: np.ndarray) -> int:
        """Append ``other``'s nodes (their poses mapped through ``transform``, 3x3: other's map px
        -> this map's px), edges and priors; returns the index of its first node here.

        Both graphs must use the same frame size. Priors on absolute quantities (GPS, heading,
        altitude) stay as they are: the map-to-world globals are shared from now on.
        """
        if tuple(other.frame_size) != tuple(self.frame_size):
            raise ValueError(f"graphs of frames {other.frame_size} and {self.frame_size} cannot be joined")
        t = _as3x3(transform, "transform")
        base = len(self._nodes)
        for pose in other.initial_poses():
            self.add_node(t @ pose)
        self._edges.extend((i + base, j + base, z, sig, kind) for i, j, z, sig, kind in other._edges)
        self.fixed |= {base + k for k in other.fixed}
        st = pose_scale(t)
        self._position.extend((n + base, *(t[:2, :2] @ (x, y) + t[:2, 2]), s * st) for n, x, y, s in other._position)
        self._gps.extend((n + base, e, nn, s) for n, e, nn, s in other._gps)
        self._heading.extend((n + base, h, s) for n, h, s in other._heading)
        self._scale.extend((n + base, a, s) for n, a, s in other._scale)
        return base

    def window(self, newest: int) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
        """The graph of the ``newest`` nodes (the last added), held by the older nodes they have
        edges to, which come along locked; returns ``(subgraph, nodes, edges)``: the subgraph's
        node ``k`` is node ``nodes[k]`` here, its edge ``e`` edge ``edges[e]``.

        Optimising it moves only the newest nodes: a solve's size stays bounded however long the
        graph grows (its factorisation needs ~8 KB per free node), and the older part of the map
        is the fixed reference the newest part is fitted to. Edges between two older nodes are
        left out; priors come along with their nodes.
        """
        n = len(self._nodes)
        first = max(0, n - max(1, int(newest)))
        pairs = self.edge_pairs
        touching = np.flatnonzero((pairs >= first).any(axis=1))
        held = np.unique(pairs[touching][pairs[touching] < first])
        nodes = np.concatenate([held, np.arange(first, n)])
        index = np.full(n, -1, dtype=np.int64)
        index[nodes] = np.arange(len(nodes))
        sub = copy.copy(self)
        sub._nodes = [self._nodes[k] for k in nodes.tolist()]
        sub._edges = [(int(index[i]), int(index[j]), z, sig, kind)
                      for i, j, z, sig, kind in (self._edges[e] for e in touching.tolist())]
        sub.fixed = set(range(len(held))) | {int(index[k]) for k in self.fixed if k >= first}
        for name in ("_position", "_gps", "_heading", "_scale"):  # priors: (node, ...)
            setattr(sub, name, [(int(index[k]), *rest) for k, *rest in getattr(self, name) if index[k] >= 0])
        return sub, nodes, touching

    def fix(self, node: int) -> None:
        """Lock a node: its pose is not optimised."""
        self.fixed.add(self._node(node))

    def add_position_prior(self, node: int, xy: Sequence[float], sigma_px: float) -> None:
        """The node's frame centre is at map pixel ``xy`` (+- ``sigma_px``)."""
        self._position.append((self._node(node), float(xy[0]), float(xy[1]), _positive(sigma_px)))

    def add_gps_prior(self, node: int, east_north: Sequence[float], sigma_m: float) -> None:
        """The node's frame centre is at local ``(east, north)`` metres (+- ``sigma_m``).

        Any local tangent plane works (e.g. :func:`photomap.geo.georef.enu_from_latlon` about the first
        fix); the map -> metres similarity is estimated (needs fixes at 2 or more places).
        """
        self._gps.append((self._node(node), float(east_north[0]), float(east_north[1]), _positive(sigma_m)))

    def add_heading_prior(self, node: int, heading_rad: float, sigma_rad: float) -> None:
        """The node's pose angle is ``heading_rad`` plus a free global offset (+- ``sigma_rad``)."""
        self._heading.append((self._node(node), float(heading_rad), _positive(sigma_rad)))

    def add_scale_prior(self, node: int, altitude_m: float, sigma_rel: float) -> None:
        """The node's pose scale is proportional to ``altitude_m`` (+- ``sigma_rel``, relative)."""
        if not altitude_m > 0:
            raise ValueError(f"altitude must be > 0 for a scale prior, got {altitude_m}")
        self._scale.append((self._node(node), math.log(altitude_m), _positive(sigma_rel)))


def _positive(v: float) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"a standard deviation must be > 0, got {v}")
    return v


@dataclass(frozen=True)
class PoseGraphResult:
    """The optimised graph.

    ``poses`` (N, 3, 3) keyframe px -> map px. ``edge_errors`` (E, 4) are the edge residuals
    ``(px, px, rad, log s)`` at the solution (module doc), ``edge_norms`` (E,) their Mahalanobis
    norms (in sigmas); ``outliers`` the indices of edges whose norm exceeds ``outlier_sigma``: the
    caller drops them (and says so) and may re-optimise. ``prior_outliers`` maps "position",
    "gps", "heading", "scale" to the indices (in the order added) of priors beyond it.
    ``heading_offset`` (rad, pose angle minus heading), ``log_scale_offset`` (log s minus log
    altitude) and ``map_to_enu`` (2x3, map px -> east, north metres) are the free globals, None
    when the graph has no such priors. ``cost`` is the robust cost (0.5 sum rho), as scipy's.
    """

    poses: np.ndarray
    edge_errors: np.ndarray
    edge_norms: np.ndarray
    outliers: np.ndarray
    prior_outliers: dict[str, np.ndarray]
    heading_offset: float | None
    log_scale_offset: float | None
    map_to_enu: np.ndarray | None
    initial_cost: float
    cost: float
    nfev: int
    success: bool
    message: str
    ignored_gps_priors: int = 0  # GPS priors at fewer than 2 distinct places fix nothing


# ---------------------------------------------------------------------- robust loss per block

def _robust_weight(u: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """``g(u) = sqrt(rho(u) / u)`` and ``g'(u)`` for scipy's loss ``rho`` (``u`` = squared norm)."""
    if loss == "linear":
        return np.ones_like(u), np.zeros_like(u)
    if loss == "soft_l1":
        q = np.sqrt(1.0 + u)
        g = np.sqrt(2.0 / (1.0 + q))
        return g, -1.0 / (2.0 * g * q * (1.0 + q) ** 2)
    if loss == "huber":
        big = u > 1.0
        ub = np.where(big, u, 1.0)
        g = np.where(big, np.sqrt((2.0 * np.sqrt(ub) - 1.0) / ub), 1.0)
        return g, np.where(big, (1.0 - np.sqrt(ub)) / (2.0 * ub ** 2 * g), 0.0)
    # cauchy: rho = log1p(u); a series near 0 avoids the cancellation in (u/(1+u) - log1p u)/u^2
    small = u < 1e-3
    us = np.where(small, 1.0, u)
    g2 = np.where(small, 1.0 - u / 2.0 + u ** 2 / 3.0 - u ** 3 / 4.0, np.log1p(us) / us)
    dg2 = np.where(small, -0.5 + 2.0 * u / 3.0 - 0.75 * u ** 2, (us / (1.0 + us) - np.log1p(us)) / us ** 2)
    g = np.sqrt(g2)
    return g, dg2 / (2.0 * g)


@dataclass
class _Block:
    """Residual blocks of one kind: ``r`` (B, k) and ``jac`` (B, k, m) whitened, over ``cols``."""

    r: np.ndarray
    jac: np.ndarray
    cols: np.ndarray  # (B, m) parameter index per Jacobian column, -1 = locked (dropped)


class _Problem:
    """The least-squares problem of a :class:`PoseGraph`: parameter layout, residuals, Jacobian."""

    def __init__(self, graph: PoseGraph, loss: str, f_scale: float) -> None:
        self.loss, self.f2 = loss, f_scale ** 2
        self.ignored_gps = 0
        n = graph.num_nodes
        self.x0_nodes = np.array(graph._nodes).reshape(n, _NP)
        fixed = set(graph.fixed)
        if not fixed and not graph._position and n:
            fixed = {0}
        self.fixed = np.zeros(n, bool)
        self.fixed[list(fixed)] = True
        free = np.flatnonzero(~self.fixed)
        self.node_col = np.full(n, -1, dtype=np.int64)
        self.node_col[free] = _NP * np.arange(len(free))
        k = _NP * len(free)
        self.c = np.asarray(graph.center)

        e = graph._edges
        self.ei = np.array([x[0] for x in e], dtype=np.int64)
        self.ej = np.array([x[1] for x in e], dtype=np.int64)
        self.ez = np.array([x[2] for x in e]).reshape(-1, 4)
        self.esig = np.array([x[3] for x in e]).reshape(-1, 4)

        p = graph._position
        self.pn = np.array([x[0] for x in p], dtype=np.int64)
        self.pxy = np.array([x[1:3] for x in p]).reshape(-1, 2)
        self.psig = np.array([x[3] for x in p])

        h = graph._heading
        self.hn = np.array([x[0] for x in h], dtype=np.int64)
        self.hv = np.array([x[1] for x in h])
        self.hsig = np.array([x[2] for x in h])
        self.h_col = -1
        x0g: list[float] = []
        if h:
            self.h_col, k = k, k + 1
            d = self.x0_nodes[self.hn, 2] - self.hv
            x0g.append(math.atan2(np.sin(d).mean(), np.cos(d).mean()))

        s = graph._scale
        self.sn = np.array([x[0] for x in s], dtype=np.int64)
        self.sv = np.array([x[1] for x in s])
        self.ssig = np.array([x[2] for x in s])
        self.s_col = -1
        if s:
            self.s_col, k = k, k + 1
            x0g.append(float((self.x0_nodes[self.sn, 3] - self.sv).mean()))

        gps = graph._gps
        self.gn = np.array([x[0] for x in gps], dtype=np.int64)
        # (east, -north): map px (y down) -> metres is then a proper similarity
        self.gm = np.array([(x[1], -x[2]) for x in gps]).reshape(-1, 2)
        self.gsig = np.array([x[3] for x in gps])
        self.g_col = -1
        if gps:
            zp = self.x0_nodes[self.gn, 0] + 1j * self.x0_nodes[self.gn, 1]
            zm = self.gm[:, 0] + 1j * self.gm[:, 1]
            if np.ptp(zp.real) + np.ptp(zp.imag) < 1e-9 or np.ptp(zm.real) + np.ptp(zm.imag) < 1e-9:
                self.ignored_gps = len(gps)  # fewer than 2 distinct places: GPS fixes nothing
                self.gn = self.gn[:0]
                self.gm, self.gsig = self.gm[:0], self.gsig[:0]
            else:
                a = np.c_[zp, np.ones_like(zp)]
                alpha, beta = np.linalg.lstsq(a, zm, rcond=None)[0]
                self.g_col, k = k, k + 4
                x0g += [alpha.real, alpha.imag, beta.real, beta.imag]

        self.num_params = k
        self.x0 = np.concatenate([self.x0_nodes[free].ravel(), np.array(x0g)])
        self._cache: tuple[bytes, np.ndarray, scipy.sparse.csr_matrix] | None = None

    # -------------------------------------------------------------- parameters
    def node_params(self, x: np.ndarray) -> np.ndarray:
        p = self.x0_nodes.copy()
        free = ~self.fixed
        p[free] = x[:_NP * int(free.sum())].reshape(-1, _NP)
        return p

    def _cols(self, nodes: np.ndarray) -> np.ndarray:
        """(B, 4) parameter columns of ``nodes``, -1 for locked ones."""
        base = self.node_col[nodes][:, None]
        return np.where(base >= 0, base + np.arange(_NP), -1)

    # -------------------------------------------------------------- blocks
    def edge_block(self, p: np.ndarray) -> _Block:
        pi, pj = p[self.ei], p[self.ej]
        d = pj[:, :2] - pi[:, :2]
        es = np.exp(-pi[:, 3])
        co, si = es * np.cos(pi[:, 2]), es * np.sin(pi[:, 2])
        u = np.c_[co * d[:, 0] + si * d[:, 1], -si * d[:, 0] + co * d[:, 1]]  # e^-s R(-theta) d
        r = np.c_[u + self.c - self.ez[:, :2],
                  _wrap(pj[:, 2] - pi[:, 2] - self.ez[:, 2]),
                  pj[:, 3] - pi[:, 3] - self.ez[:, 3]]
        jac = np.zeros((len(r), 4, 2 * _NP))
        # r_t: d/d(x_j, y_j) = B = e^-s R(-theta_i), d/d(x_i, y_i) = -B
        jac[:, 0, 4], jac[:, 0, 5], jac[:, 1, 4], jac[:, 1, 5] = co, si, -si, co
        jac[:, :2, 0:2] = -jac[:, :2, 4:6]
        jac[:, 0, 2], jac[:, 1, 2] = u[:, 1], -u[:, 0]  # d/d theta_i
        jac[:, :2, 3] = -u  # d/d log s_i
        jac[:, 2, 2], jac[:, 2, 6] = -1.0, 1.0
        jac[:, 3, 3], jac[:, 3, 7] = -1.0, 1.0
        cols = np.hstack([self._cols(self.ei), self._cols(self.ej)])
        return _Block(r / self.esig, jac / self.esig[:, :, None], cols)

    def position_block(self, p: np.ndarray) -> _Block:
        r = (p[self.pn, :2] - self.pxy) / self.psig[:, None]
        jac = np.zeros((len(r), 2, 2))
        jac[:, 0, 0] = jac[:, 1, 1] = 1.0 / self.psig
        return _Block(r, jac, self._cols(self.pn)[:, :2])

    def heading_block(self, p: np.ndarray, x: np.ndarray) -> _Block:
        phi = x[self.h_col] if self.h_col >= 0 else 0.0
        r = _wrap(p[self.hn, 2] - phi - self.hv) / self.hsig
        jac = np.stack([1.0 / self.hsig, -1.0 / self.hsig], axis=1)[:, None, :]
        cols = np.c_[self._cols(self.hn)[:, 2], np.full(len(r), self.h_col)]
        return _Block(r[:, None], jac, cols)

    def scale_block(self, p: np.ndarray, x: np.ndarray) -> _Block:
        kappa = x[self.s_col] if self.s_col >= 0 else 0.0
        r = (p[self.sn, 3] - kappa - self.sv) / self.ssig
        jac = np.stack([1.0 / self.ssig, -1.0 / self.ssig], axis=1)[:, None, :]
        cols = np.c_[self._cols(self.sn)[:, 3], np.full(len(r), self.s_col)]
        return _Block(r[:, None], jac, cols)

    def gps_block(self, p: np.ndarray, x: np.ndarray) -> _Block:
        b = len(self.gn)
        if not b:
            return _Block(np.zeros((0, 2)), np.zeros((0, 2, 6)), np.zeros((0, 6), np.int64))
        a, bb, tx, ty = x[self.g_col:self.g_col + 4]
        xy = p[self.gn, :2]
        pred = np.c_[a * xy[:, 0] - bb * xy[:, 1] + tx, bb * xy[:, 0] + a * xy[:, 1] + ty]
        sig = self.gsig[:, None]
        jac = np.zeros((b, 2, 6))
        jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0], jac[:, 1, 1] = a, -bb, bb, a
        jac[:, 0, 2], jac[:, 1, 2] = xy[:, 0], xy[:, 1]  # d/da
        jac[:, 0, 3], jac[:, 1, 3] = -xy[:, 1], xy[:, 0]  # d/db
        jac[:, 0, 4] = jac[:, 1, 5] = 1.0
        cols = np.c_[self._cols(self.gn)[:, :2], np.tile(self.g_col + np.arange(4), (b, 1))]
        return _Block((pred - self.gm) / sig, jac / sig[:, :, None], cols)

    def blocks(self, x: np.ndarray) -> dict[str, _Block]:
        p = self.node_params(x)
        return {"edge": self.edge_block(p), "position": self.position_block(p),
                "heading": self.heading_block(p, x), "scale": self.scale_block(p, x),
                "gps": self.gps_block(p, x)}

    # -------------------------------------------------------------- least squares
    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_matrix]:
        """Robustified residuals (``|r'|^2 = f^2 rho(|r|^2 / f^2)`` per block) and their Jacobian."""
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        # the Jacobian assembled as CSR directly: the k rows of a block share its columns (no
        # COO triplets, no conversion; int32 column indices)
        res, counts, cols, vals = [], [], [], []
        for blk in self.blocks(x).values():
            nb, k = blk.r.shape
            if not nb:
                continue
            s = (blk.r ** 2).sum(axis=1)
            g, dg = _robust_weight(s / self.f2, self.loss)
            res.append((blk.r * g[:, None]).ravel())
            # d(g r)/dx = g J + r (2 g'(u) / f^2) (r^T J)
            jt = blk.jac * g[:, None, None] + blk.r[:, :, None] * (
                (2.0 * dg / self.f2)[:, None] * np.einsum("bk,bkm->bm", blk.r, blk.jac))[:, None, :]
            valid = blk.cols >= 0
            keep = np.broadcast_to(valid[:, None, :], jt.shape)
            counts.append(np.repeat(np.count_nonzero(valid, axis=1), k))
            cols.append(np.broadcast_to(blk.cols.astype(np.int32)[:, None, :], jt.shape)[keep])
            vals.append(jt[keep])
        f = np.concatenate(res) if res else np.zeros(0)
        indptr = np.zeros(len(f) + 1, np.int32)
        if counts:
            np.cumsum(np.concatenate(counts), out=indptr[1:])
        jac = scipy.sparse.csr_matrix(
            (np.concatenate(vals) if vals else np.zeros(0), np.concatenate(cols) if cols else np.zeros(0, np.int32),
             indptr), shape=(len(f), self.num_params))
        self._cache = (key, f, jac)
        return f, jac


def _solve_spd(a: scipy.sparse.csc_matrix, b: np.ndarray) -> np.ndarray:
    """``a x = b`` for a sparse symmetric positive definite ``a`` (the damped normal equations).

    SuperLU in symmetric mode: a minimum-degree ordering of ``a`` itself, no pivoting (which would
    undo it). COLAMD orders for ``a^T a`` instead: on pose graphs with many loops its factors
    were 1.5-2x larger (memory of every solve, growing faster than the graph over a long flight).
    A system SuperLU finds singular falls back to :func:`scipy.sparse.linalg.spsolve` (NaN
    where singular, as before)."""
    try:
        return scipy.sparse.linalg.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                        options={"SymmetricMode": True}).solve(b)
    except RuntimeError:
        return scipy.sparse.linalg.spsolve(a, b, permc_spec="COLAMD")


def _levenberg_marquardt(prob: _Problem, x0: np.ndarray, max_nfev: int, ftol: float, xtol: float,
                         callback: Callable[[], object]) -> tuple[np.ndarray, int, bool, str, float]:
    """Levenberg-Marquardt with Marquardt's diagonal scaling; each step a sparse direct solve.

    Returns ``(x, nfev, success, message, cost)``. Damping update after Nielsen (1999).
    """
    x = x0
    f, jac = prob.evaluate(x)
    cost, nfev, mu, nu = 0.5 * float(f @ f), 1, 1e-4, 2.0
    while nfev < max_nfev:
        g = jac.T @ f
        if np.abs(g).max() <= 1e-12 * max(cost, 1.0):
            return x, nfev, True, "gradient vanished", cost
        a = (jac.T @ jac).tocsc()
        d = a.diagonal()
        d = np.maximum(d, 1e-12 * max(float(d.max()), 1e-300))
        while nfev < max_nfev:
            h = _solve_spd(a + scipy.sparse.diags(mu * d, format="csc"), -g)
            xn = x + h
            callback()
            fn, jn = prob.evaluate(xn)
            nfev += 1
            cn = 0.5 * float(fn @ fn)
            predicted = 0.5 * float(h @ (mu * d * h - g))
            if predicted > 0 and cn < cost:
                rho = (cost - cn) / predicted
                small_step = np.linalg.norm(h) <= xtol * (np.linalg.norm(x) + xtol)
                small_gain = cost - cn <= ftol * cost
                x, f, jac, cost = xn, fn, jn, cn
                mu, nu = mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
                if small_step or small_gain:
                    return x, nfev, True, "converged", cost
                break
            mu, nu = mu * nu, nu * 2.0
            if mu > 1e16:
                return x, nfev, True, "no further decrease", cost
    return x, nfev, False, "the maximum number of evaluations is exceeded", cost


def optimize(graph: PoseGraph, params: PosegraphConfig = PosegraphConfig(), *, ftol: float = 1e-10,
             xtol: float = 1e-10, callback: Callable[[], object] | None = None) -> PoseGraphResult:
    """Optimise the node poses of ``graph``.

    Parameters
    ----------
    params : the ``posegraph`` settings used here:
    robust : loss per residual block: "cauchy" (default: redescending, so a wrong loop closure
        ends up with almost no pull), "soft_l1" or "huber" (their pull is bounded but does not
        vanish: a confident wrong edge in a weakly constrained part of the graph still bends
        it), or "linear" (plain squares).
    f_scale : Mahalanobis norm (in sigmas) of a block where the robust loss starts to bend.
    max_nfev : at most this many evaluations of the residuals.
    outlier_sigma : an edge or prior whose Mahalanobis norm at the solution exceeds this is
        reported in ``outliers`` / ``prior_outliers``.
    solver : "lm": Levenberg-Marquardt, each step a sparse direct solve of the normal equations
        (SuperLU, symmetric mode, minimum-degree order: :func:`_solve_spd`); "trf":
        ``scipy.optimize.least_squares(method="trf", tr_solver="lsmr")``. Both use the analytic
        sparse Jacobian (4 columns per node, a few per global); "trf"'s iterative LSMR steps get
        slow on long, ill-conditioned graphs.
    callback : called with no argument before each evaluation of the residuals (e.g. to let
        another thread go first); its result is ignored.
    """
    robust, f_scale, max_nfev = params.robust, params.f_scale, params.max_nfev
    outlier_sigma, solver = params.outlier_sigma, params.solver
    if graph.num_nodes == 0:
        raise ValueError("the pose graph has no nodes")
    prob = _Problem(graph, robust, f_scale)
    callback = callback or (lambda: None)

    def evaluate(v: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_matrix]:
        callback()
        return prob.evaluate(v)

    f0, _ = prob.evaluate(prob.x0)
    initial_cost = 0.5 * float(f0 @ f0)
    if prob.num_params == 0 or f0.size == 0:
        x, nfev, success, message, cost = prob.x0, 1, True, "nothing to optimise", initial_cost
    elif solver == "lm":
        x, nfev, success, message, cost = _levenberg_marquardt(prob, prob.x0, max_nfev, ftol, xtol, callback)
    else:
        sol = scipy.optimize.least_squares(
            lambda v: evaluate(v)[0], prob.x0, jac=lambda v: evaluate(v)[1], method="trf",
            tr_solver="lsmr", tr_options={"atol": 1e-10, "btol": 1e-10}, x_scale="jac", ftol=ftol,
            xtol=xtol, gtol=1e-10, max_nfev=max_nfev)
        x, nfev, success, message, cost = sol.x, int(sol.nfev), bool(sol.success), sol.message, float(sol.cost)
    blocks = prob.blocks(x)
    p = prob.node_params(x)
    edge = blocks["edge"]
    norms = np.linalg.norm(edge.r, axis=1)
    prior_outliers = {name: np.flatnonzero(np.linalg.norm(blocks[name].r, axis=1) > outlier_sigma)
                      for name in ("position", "gps", "heading", "scale")}
    map_to_enu = None
    if prob.g_col >= 0:
        a, b, tx, ty = x[prob.g_col:prob.g_col + 4]
        map_to_enu = np.array([[a, -b, tx], [-b, -a, -ty]])  # (east, -north) -> (east, north)
    outliers = np.flatnonzero(norms > outlier_sigma)
    return PoseGraphResult(
        poses=pose_matrix(p, graph.center), edge_errors=edge.r * prob.esig, edge_norms=norms,
        outliers=outliers, prior_outliers=prior_outliers,
        heading_offset=float(_wrap(x[prob.h_col])) if prob.h_col >= 0 else None,
        log_scale_offset=float(x[prob.s_col]) if prob.s_col >= 0 else None,
        map_to_enu=map_to_enu, initial_cost=initial_cost, cost=cost, nfev=nfev, success=success,
        message=message, ignored_gps_priors=prob.ignored_gps)


# ---------------------------------------------------------------------- applying the result

def correction(old_pose: np.ndarray, new_pose: np.ndarray) -> np.ndarray:
    """3x3 ``C = new @ old^-1`` mapping old map px to new map px (``C @ old == new``).

    A frame posed relative to a keyframe (``P_f = P_k @ rel``) is corrected by the keyframe's
    ``C``: ``C @ P_f``.
    """
    old, new = _as3x3(old_pose, "old pose"), _as3x3(new_pose, "new pose")
    return new @ np.linalg.inv(old)


def interpolate_corrections(keyframe_indices: Sequence[int], corrections: np.ndarray,
                            frame_indices: Sequence[int], *, blend: bool = False,
                            pivots: np.ndarray | None = None) -> np.ndarray:
    """Per-frame 3x3 corrections (old map px -> new map px) from the keyframes' corrections.

    Without ``blend`` a frame takes the correction of the last keyframe at or before it (the
    keyframe it was registered against, so its measured relative pose is kept exactly). With
    ``blend`` a frame between keyframes ``a < f < b`` gets a similarity whose angle and log scale
    are interpolated linearly (fraction ``(f - a) / (b - a)``) and which maps its pivot (``pivots``,
    (F, 2) old map px, e.g. the frame centre's old position; default the map origin) to the same
    linear blend of ``C_a(pivot)`` and ``C_b(pivot)``. Frames before the first or after the last
    keyframe take that keyframe's correction.
    """
    kf = np.asarray(keyframe_indices, dtype=np.int64).ravel()
    cs = np.asarray(corrections, dtype=np.float64)
    if cs.ndim == 3 and cs.shape[1:] == (2, 3):
        cs = np.concatenate([cs, np.broadcast_to([[[0.0, 0.0, 1.0]]], (len(cs), 1, 3))], axis=1)
    if len(kf) == 0 or cs.shape != (len(kf), 3, 3) or not np.isfinite(cs).all():
        raise ValueError("need one finite 2x3/3x3 correction per keyframe, and at least one keyframe")
    order = np.argsort(kf, kind="stable")
    kf, cs = kf[order], cs[order]
    if np.any(np.diff(kf) == 0):
        raise ValueError("keyframe indices must be unique")
    fr = np.asarray(frame_indices, dtype=np.float64).ravel()
    a = np.clip(np.searchsorted(kf, fr, side="right") - 1, 0, len(kf) - 1)
    out = cs[a].copy()
    if not blend or len(kf) == 1:
        return out
    b = np.minimum(a + 1, len(kf) - 1)
    inside = (fr > kf[a]) & (fr < kf[b])
    if not inside.any():
        return out
    piv = np.zeros((len(fr), 2)) if pivots is None else np.asarray(pivots, dtype=np.float64).reshape(len(fr), 2)
    ia, ib, pv = a[inside], b[inside], piv[inside]
    lam = ((fr[inside] - kf[ia]) / (kf[ib] - kf[ia]))[:, None]
    ca, cb = cs[ia], cs[ib]
    th_a = np.arctan2(ca[:, 1, 0], ca[:, 0, 0])
    th = th_a + lam[:, 0] * _wrap(np.arctan2(cb[:, 1, 0], cb[:, 0, 0]) - th_a)
    ls_a = 0.5 * np.log(np.linalg.det(ca[:, :2, :2]))
    ls = ls_a + lam[:, 0] * (0.5 * np.log(np.linalg.det(cb[:, :2, :2])) - ls_a)
    target = (1 - lam) * (np.einsum("fij,fj->fi", ca[:, :2, :2], pv) + ca[:, :2, 2]) + \
        lam * (np.einsum("fij,fj->fi", cb[:, :2, :2], pv) + cb[:, :2, 2])
    # a similarity about the pivot: p -> s R (p - pivot) + target
    m = pose_matrix(np.c_[target, th, ls], (0.0, 0.0))
    m[:, :2, 2] -= np.einsum("fij,fj->fi", m[:, :2, :2], pv)
    out[inside] = m
    return out
