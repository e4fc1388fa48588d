"""Keyframes of a map segment, loop closures against old keyframes, and pose-graph correction.

When the predicted footprint of a new keyframe overlaps keyframes far back in the chain (a
revisit), the new keyframe is registered against them (iFMI needs no features: candidates are
chosen by predicted overlap, and the predicted relative pose is the prior). A confident result is
a loop-closure edge; the pose graph (:mod:`photomap.core.posegraph`, robust loss) then corrects every
keyframe, and the caller re-poses the frames registered against them and re-renders the map.

Pure computation on frames the caller hands in; keyframe images are kept by the caller (see
:class:`photomap.mapping.pipeline.MappingPipeline`), so memory stays bounded.

Conventions: poses are 3x3, input-frame pixels -> map pixels of the segment; registration runs at
the working resolution (``working_scale``) and is converted as in :mod:`photomap.core.tracking`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from photomap.config import MappingConfig, PosegraphConfig
from photomap.core.features import MIN_OVERLAP, MIN_SCORE, OverlapCheck, ifmi_confirmed, verify_overlap
from photomap.core.ifmi import Prior, Registrar, Registration
from photomap.core.posegraph import PoseGraph, correction, optimize
from photomap.geometry import pose_angle_deg, pose_scale, scaling


# a loop found by appearance on periodic ground: no other iFMI candidate above this fraction of the best
PERIODIC_CLEAR = 0.5
# ... and at most this many of them wait for a second one that agrees
PERIODIC_WAITING = 16


@dataclass(frozen=True)
class KeyframePriors:
    """Telemetry of a keyframe for the pose graph (each None when unknown).

    ``yaw``: camera heading, radians clockwise from north; ``height``: above the ground, metres;
    ``east_north``: position in metres on a local tangent plane shared by the whole run.
    """

    yaw: float | None = None
    height: float | None = None
    east_north: tuple[float, float] | None = None


@dataclass(frozen=True)
class LoopCandidate:
    """Keyframe ``new`` to be registered against the older keyframe ``ref``: ``predicted`` is the
    3x3 input px of ``new`` -> input px of ``ref`` from the current poses, ``prior`` its
    registration prior (at the working resolution). ``by_appearance``: found by its place
    signature, not near the predicted position (drift may have carried the estimate anywhere):
    registered without a prior, kept only when the overlap check confirms it, and never held to
    the prediction."""

    ref: int
    new: int
    predicted: np.ndarray
    prior: Prior | None
    by_appearance: bool = False
    seen_from: int | None = None  # the frame registered, when not ``new`` itself (posed relative to it)

    @property
    def image(self) -> int:
        """The frame whose image was registered against ``ref``."""
        return self.new if self.seen_from is None else self.seen_from


@dataclass(frozen=True)
class LoopMeasurement:
    """The registration of a :class:`LoopCandidate`: ``measured`` (3x3, input px of ``new`` -> of
    ``ref``) or None when its ``confidence`` is below ``loop_min_confidence``. ``periodic``: a
    loop by appearance on periodic ground (confirmed by its own peak, not by the overlap check):
    it waits for a second one that agrees with it."""

    candidate: LoopCandidate
    measured: np.ndarray | None
    confidence: float
    periodic: bool = False


@dataclass
class Keyframe:
    index: int  # frame index
    pose: np.ndarray  # 3x3, current estimate


class KeyframeGraph:
    """The keyframes of one segment and the constraints between them.

    Parameters
    ----------
    registrar : Registrar
        At the working resolution.
    frame_size : (w, h)
        Input frame size (pixels of the poses).
    working_scale : float
        Working resolution / input resolution.
    load_small : callable
        ``frame index -> grey image at the working resolution`` of a keyframe (kept by the caller).
    params : MappingConfig
        The ``mapping`` settings used here: a loop closure links keyframes at least
        ``loop_min_gap`` keyframes apart; candidates are the keyframes whose centre lies within
        ``loop_radius`` frame diagonals of the new one, at most ``loop_candidates`` (nearest
        first); an edge needs a registration confidence of ``loop_min_confidence``; a loop found
        by appearance on periodic ground needs ``trust_confidence``.
    graph_params : PosegraphConfig
        The ``posegraph`` settings: edge noise, robust loss, solver, prior sigmas.
    """

    def __init__(self, registrar: Registrar, frame_size: tuple[int, int], working_scale: float,
                 load_small: Callable[[int], np.ndarray], params: MappingConfig = MappingConfig(),
                 graph_params: PosegraphConfig = PosegraphConfig()) -> None:
        self.registrar = registrar
        self.frame_size = frame_size
        self.centre = np.array([(frame_size[0] - 1) / 2.0, (frame_size[1] - 1) / 2.0, 1.0])
        self.diagonal = math.hypot(*frame_size)
        self._to_small = scaling(working_scale)
        self._from_small = np.linalg.inv(self._to_small)
        self.load_small = load_small
        self.min_gap = params.loop_min_gap
        self.radius = params.loop_radius
        self.min_confidence = params.loop_min_confidence
        self.max_candidates = params.loop_candidates
        self.trust_confidence = params.trust_confidence
        self.graph_params = graph_params
        self.graph = PoseGraph(frame_size, graph_params)
        self.keyframes: list[Keyframe] = []
        self._node: dict[int, int] = {}  # frame index -> node
        self.loops = 0
        self.rejected_loops = 0
        self._periodic: list[LoopMeasurement] = []  # loops by appearance on periodic ground, waiting

    def add_keyframe(self, index: int, pose: np.ndarray, edge: tuple[int, np.ndarray, float] | None,
                     priors: KeyframePriors | None = None) -> None:
        """A new keyframe; ``edge`` = (reference keyframe index, measured 3x3, confidence).

        ``priors`` (from telemetry) become priors of its node: heading, height (scale) and
        position, with the sigmas of the ``posegraph`` settings.
        """
        node = self.graph.add_node(pose)
        self._node[index] = node
        self.keyframes.append(Keyframe(index, np.array(pose, dtype=np.float64)))
        if edge is not None and edge[0] in self._node:
            self.graph.add_edge(self._node[edge[0]], node, edge[1], edge[2], kind="sequential")
        if priors is None:
            return
        g = self.graph_params
        if priors.yaw is not None:
            self.graph.add_heading_prior(node, priors.yaw, math.radians(g.heading_sigma_deg))
        if priors.height is not None and priors.height > 0:
            self.graph.add_scale_prior(node, priors.height, g.altitude_sigma)
        if priors.east_north is not None:
            self.graph.add_gps_prior(node, priors.east_north, g.gps_sigma_m)

    def pose_of(self, index: int) -> np.ndarray:
        """The current 3x3 pose of keyframe ``index`` (KeyError if it is not in this graph)."""
        return self.keyframes[self._node[index]].pose

    def loop_candidates(self) -> list[LoopCandidate]:
        """Old keyframes to register the newest against (their centres within ``loop_radius``
        frame diagonals of its predicted centre, nearest first, at most ``loop_candidates``)."""
        if len(self.keyframes) <= self.min_gap:
            return []
        new = self.keyframes[-1]
        centre = new.pose @ self.centre
        scale = pose_scale(new.pose)
        limit = self.radius * self.diagonal * scale
        old = self.keyframes[:-self.min_gap]
        dist = np.array([np.hypot(*(k.pose @ self.centre - centre)[:2]) for k in old])
        out = []
        for i in [i for i in np.argsort(dist) if dist[i] < limit][:self.max_candidates]:
            predicted = np.linalg.inv(old[i].pose) @ new.pose  # input px of new -> of ref
            small = self._to_small @ predicted @ self._from_small
            prior = Prior(angle_deg=pose_angle_deg(small), angle_tol_deg=10.0,
                          scale=pose_scale(small), scale_tol=0.1)
            out.append(LoopCandidate(old[i].index, new.index, predicted, prior))
        return out

    def recent(self) -> list[int]:
        """The newest ``loop_min_gap`` keyframes (frame indices): too near in the chain to close a loop."""
        return [kf.index for kf in self.keyframes[-self.min_gap:]]

    def appearance_candidates(self, refs: list[int]) -> list[LoopCandidate]:
        """Candidates of the newest keyframe against the old keyframes ``refs`` (found by their
        place signatures): the predicted pose from the current poses, no registration prior."""
        new = self.keyframes[-1]
        return [LoopCandidate(ref, new.index, np.linalg.inv(self.pose_of(ref)) @ new.pose, None, True)
                for ref in refs if ref in self._node and ref != new.index]

    def measure_loops(self, image: np.ndarray, candidates: list[LoopCandidate],
                      registrar: Registrar | None = None,
                      callback: Callable[[], object] | None = None) -> list[LoopMeasurement]:
        """Register the new keyframe (``image``, grey at the working resolution) against each
        candidate. Reads nothing that changes (safe in another thread while the graph grows, given
        a ``registrar`` of its own). ``callback`` is called with no argument before each
        registration (e.g. to let another thread go first)."""
        registrar = registrar or self.registrar
        prepared = registrar.prepare(image) if candidates else None
        out = []
        for cand in candidates:
            if callback is not None:
                callback()
            ref = registrar.prepare(self.load_small(cand.ref))
            reg = registrar.register(ref, prepared, cand.prior)
            ok, periodic = reg.confidence >= self.min_confidence, False
            if ok and cand.by_appearance:  # nothing predicted it: the images must confirm it
                check = None if ref.blank or prepared.blank else verify_overlap(ref.gray, prepared.gray, reg.matrix)
                ok = check is not None and ifmi_confirmed(reg, check)
                periodic = not ok and check is not None and self._periodic_peak(reg, check)
                ok = ok or periodic
            measured = None
            if ok:
                measured = self._from_small @ np.vstack([reg.matrix, [0, 0, 1]]) @ self._to_small
            out.append(LoopMeasurement(cand, measured, float(reg.confidence), periodic))
        return out

    def _periodic_peak(self, reg: Registration, check: OverlapCheck) -> bool:
        """On periodic ground the overlap check aligns as well one period away (it passes but for
        its ratio): there iFMI's own peak may stand when it is strong (``trust_confidence``) and
        stands clear (every other candidate at most ``PERIODIC_CLEAR`` as high). A strictly
        periodic floor never passes; a floor of tiles that differ often does, wrongly too: such
        a loop waits for a second that agrees with it (:meth:`add_loops`)."""
        if reg.confidence < self.trust_confidence or not check.passes(MIN_SCORE, math.inf, MIN_OVERLAP):
            return False
        best = reg.candidates[0] if reg.candidates else None
        others = [c.peak for c in reg.candidates[1:] if best is not None and not Registrar._same(c, best)]
        return best is not None and max(others, default=0.0) <= PERIODIC_CLEAR * reg.confidence

    def _implied(self, m: LoopMeasurement) -> np.ndarray:
        """3x3 map px -> map px: how the loop ``m`` would move the keyframe ``new`` (current poses)."""
        c = m.candidate
        return self.pose_of(c.ref) @ m.measured @ np.linalg.inv(self.pose_of(c.new))

    def _agree(self, a: LoopMeasurement, b: LoopMeasurement) -> bool:
        """Two loops move the map alike where the newer keyframe lies (within 2 % of a frame
        diagonal, 1 deg, 1 % of scale)."""
        x = self.pose_of(max(a.candidate.new, b.candidate.new, key=self._node.__getitem__)) @ self.centre
        ca, cb = self._implied(a), self._implied(b)
        shift = np.hypot(*((ca - cb) @ x)[:2])
        rot = cb @ np.linalg.inv(ca)
        angle = abs(math.degrees(math.atan2(rot[1, 0], rot[0, 0])))
        return shift <= 0.02 * self.diagonal * pose_scale(ca) and angle <= 1.0 and abs(math.log(pose_scale(rot))) <= 0.01

    def add_loops(self, measurements: list[LoopMeasurement]) -> int:
        """Loop edges from confident measurements that agree with their prediction (a revisit
        after drift may differ from it, but not wildly; one found by appearance is not held to
        it: the robust loss of the pose graph judges it); returns how many were added."""
        added = 0
        for m in measurements:
            if m.measured is None:
                continue
            if m.periodic:  # in only with a second one, of another keyframe, that agrees with it
                if m.candidate.ref not in self._node or m.candidate.new not in self._node:
                    continue
                partner = next((p for p in self._periodic if p.candidate.image != m.candidate.image
                                and self._agree(p, m)), None)
                if partner is None:
                    self._periodic = (self._periodic + [m])[-PERIODIC_WAITING:]
                    continue
                self._periodic.remove(partner)
                for p in (partner, m):
                    self.graph.add_edge(self._node[p.candidate.ref], self._node[p.candidate.new], p.measured,
                                        p.confidence, kind="loop")
                added += 2
                continue
            # a loop found by appearance is never held to the (drifted) prediction
            if not m.candidate.by_appearance and \
                    np.linalg.norm((m.measured - m.candidate.predicted) @ self.centre) > 0.25 * self.diagonal:
                self.rejected_loops += 1
                continue
            self.graph.add_edge(self._node[m.candidate.ref], self._node[m.candidate.new], m.measured,
                                m.confidence, kind="loop")
            added += 1
        self.loops += added
        return added

    def close_loops(self, image: np.ndarray, extra: Sequence[LoopCandidate] = ()) -> int:
        """Try the newest keyframe (``image`` at the working resolution) against old ones nearby
        (and the ``extra`` candidates); returns the loop edges added."""
        return self.add_loops(self.measure_loops(image, self.loop_candidates() + list(extra)))

    def absorb(self, other: KeyframeGraph, transform: np.ndarray,
               edge: tuple[int, int, np.ndarray, float]) -> None:
        """Take in the keyframes of another segment's graph, now linked to this one.

        ``transform`` (3x3) maps the other segment's map px to this map's px; ``edge`` = (keyframe
        here, keyframe there, measured 3x3: input px of the latter -> of the former, confidence).
        """
        base = self.graph.absorb(other.graph, transform)
        for k, kf in enumerate(other.keyframes):
            self._node[kf.index] = base + k
            self.keyframes.append(Keyframe(kf.index, transform @ kf.pose))  # in node order
        here, there, measured, confidence = edge
        self.graph.add_edge(self._node[here], self._node[there], measured, confidence, kind="join")
        self.loops += other.loops
        self.rejected_loops += other.rejected_loops

    def snapshot(self) -> PoseGraph:
        """A copy of the graph to optimise elsewhere (another thread) while this one grows."""
        return self.graph.copy()

    @staticmethod
    def solve(graph: PoseGraph, params: PosegraphConfig, callback: Callable[[], object] | None = None,
              newest: int | None = None) -> tuple[np.ndarray, list[int]]:
        """Optimise ``graph`` (a snapshot); returns its poses and the loop edges it dropped.

        A loop closure that the robust solution flags as an outlier is dropped and the graph
        solved again without it. ``callback``: as in :func:`~photomap.core.posegraph.optimize`.
        ``newest``: move only the newest this many keyframes (:meth:`PoseGraph.window`; the
        others keep their poses); None: all.
        """
        sub, nodes, edges = (graph, None, None) if newest is None or graph.num_nodes <= newest \
            else graph.window(newest)
        result = optimize(sub, params, callback=callback)
        dropped = [int(k) for k in result.outliers if sub.edge_kinds[k] == "loop"]
        if dropped:
            sub.drop_edges(dropped)
            result = optimize(sub, params, callback=callback)
        if nodes is None:
            return result.poses, dropped
        poses = graph.initial_poses()
        poses[nodes] = result.poses
        return poses, [int(edges[k]) for k in dropped]

    def apply(self, poses: np.ndarray, dropped: list[int]) -> dict[int, np.ndarray]:
        """Take a solution of a snapshot; returns the 3x3 correction of every keyframe.

        Keyframes added after the snapshot follow the correction of its last keyframe (they are
        chained from it). Edge indices of the snapshot are still valid here: edges are only
        appended between a snapshot and its solution. The ``dropped`` loop edges are removed here too.
        """
        if dropped:
            self.rejected_loops += len(dropped)
            self.loops -= len(dropped)
            self.graph.drop_edges(dropped)
        n = len(poses)
        old = np.array([kf.pose for kf in self.keyframes])  # (k, 3, 3)
        new = old.copy()
        new[:n] = poses
        new[n:] = correction(old[n - 1], poses[n - 1]) @ old[n:]  # chained from the snapshot's last
        fixes = new @ np.linalg.inv(old)  # old map px -> new map px, every keyframe at once
        for kf, pose in zip(self.keyframes, new):
            kf.pose = pose
        self.graph.set_poses(new)
        return dict(zip([kf.index for kf in self.keyframes], fixes))

    def optimize(self) -> dict[int, np.ndarray]:
        """Optimise the graph now; returns the 3x3 correction of every keyframe (by frame index)."""
        return self.apply(*self.solve(self.snapshot(), self.graph_params))
