"""Poses from pairwise registrations: reference/keyframe choice, motion prior, map segments.

Each frame is placed against the current reference by a :class:`~photomap.core.matching.PairMatcher`
(iFMI; the overlap check and a feature second opinion when the placement is not what the motion
model expected). Pure: frames (at the working resolution, with their input image for the
features) in, poses out; no I/O, no threads.

Conventions: a pose is a 2x3 matrix mapping pixels of a frame at the *input* resolution to map
pixels. The map of a segment is the first frame of that segment scaled by ``map_scale`` (map
pixels per input pixel). Registration runs on frames downscaled by ``working_scale``; its results
are converted back to input pixels here (OpenCV pixel centres: ``x_small = f * (x + 0.5) - 0.5``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from photomap.config import MappingConfig
from photomap.core.ifmi import Prior, Registration
from photomap.core.matching import Expectation, Match, PairMatcher, View
from photomap.geometry import pose_angle_deg, pose_scale, scaling, to_h

REFERENCE = "reference"
REGISTERED = "registered"
LOW_CONFIDENCE = "low_confidence"

_HINT = Prior(angle_deg=0.0, angle_tol_deg=180.0, scale=1.0, scale_tol=10.0)


@dataclass
class TrackStep:
    """What the tracker made of one frame."""

    status: str  # reference | registered | low_confidence
    pose: np.ndarray | None  # 2x3, input pixels -> map pixels of `segment`; None if not posed
    confidence: float
    segment: int
    registration: Registration | None = None
    events: list[str] = field(default_factory=list)
    # a new segment was anchored at this earlier (low-confidence) frame: it is the segment's
    # reference, with pose ``anchor_pose``
    anchor: int | None = None
    anchor_pose: np.ndarray | None = None
    # the frame it was registered against, and the measured 3x3 (input pixels of this frame ->
    # input pixels of that reference); ``keyframe``: this frame is now the reference
    reference: int | None = None
    relative: np.ndarray | None = None
    keyframe: bool = False
    # telemetry expected another motion than the images show (vision won): what was seen
    disagreement: str | None = None
    # which method placed the frame (ifmi, sift, orb) and how it was accepted
    method: str = "ifmi"
    how: str = ""


@dataclass
class _Reference:
    view: View
    pose: np.ndarray  # 3x3 input pixels -> map pixels
    index: int
    sample: Any = None  # its telemetry sample, if any
    best: float = 0.0  # the best iFMI confidence of a frame registered against it


class Tracker:
    """Chains pairwise placements into poses.

    Each frame is placed against the current reference. With ``keyframes`` the reference
    stays while the confidence against it is at least ``keyframe_confidence`` times the best
    confidence seen against it (so the rule adapts to the ground's texture), and while the next
    frame is predicted to be less than ``keyframe_max_shift`` frame sizes away (error then grows per
    keyframe, not per frame); otherwise every registered frame becomes the next reference (and
    so does a frame the features placed). A frame that no placement is accepted for is not posed,
    the reference is kept and the next frames are tried against it. When a frame fails against
    the reference but is placed against the previous (failed) frame, the link to the map is lost
    but the camera still sees coherent ground: a new segment is anchored at that previous frame.
    After ``max_lost_frames`` failures in a row a new segment starts at the current frame.

    ``matcher`` places frames (at the working resolution); ``working_scale`` is the working
    resolution over the input resolution; ``params`` the ``mapping`` settings (``map_scale``,
    ``max_lost_frames``, ``keyframes``, ``keyframe_confidence``, ``keyframe_max_shift``,
    ``motion_prior`` and its tolerances); ``telemetry_prior(reference_sample, sample)`` gives the
    expected registration from telemetry.
    """

    def __init__(self, matcher: PairMatcher, working_scale: float = 1.0,
                 params: MappingConfig = MappingConfig(), *,
                 telemetry_prior: Callable[[Any, Any], Prior | None] | None = None) -> None:
        self.matcher = matcher
        self.registrar = matcher.registrar
        self._to_small = scaling(working_scale)
        self._from_small = np.linalg.inv(self._to_small)
        self._map = np.diag([params.map_scale, params.map_scale, 1.0])
        self.max_lost_frames = params.max_lost_frames
        self.keyframes = params.keyframes
        self.keyframe_confidence = params.keyframe_confidence
        self.keyframe_max_shift = params.keyframe_max_shift
        self.motion_prior = params.motion_prior
        self.prior_angle_tol_deg = params.prior_angle_tol_deg
        self.prior_scale_tol = params.prior_scale_tol
        self.telemetry_prior = telemetry_prior
        self.segment = -1  # the current map segment
        self.segments = 0  # segments started so far (a new one gets the next number)
        self._ref: _Reference | None = None
        self._last: tuple[int, np.ndarray] | None = None  # (index, 3x3 pose) of the last posed frame
        self._velocity: np.ndarray | None = None  # 3x3 motion between the last two posed frames
        self._lost = 0
        self._pending: tuple[int, View, Any] | None = None  # the last frame that failed
        self._previous: tuple[int, View, np.ndarray] | None = None  # the last posed frame: index, view, 3x3 pose
        self._chained = False  # the current frame was placed through the previous one

    def _new_segment(self, view: View, index: int, events: list[str], sample: Any = None) -> TrackStep:
        self.segment = self.segments
        self.segments += 1
        self._ref = _Reference(view, self._map.copy(), index, sample)
        self._last, self._velocity, self._lost = (index, self._map.copy()), None, 0
        self._pending = None
        self._previous = (index, view, self._map.copy())
        if self.segment > 0:
            events.append(f"link lost: map segment {self.segment} started at frame {index}")
        return TrackStep(REFERENCE, self._map[:2].copy(), 1.0, self.segment, events=events,
                         keyframe=True)

    def _next_shift(self, matrix: np.ndarray) -> float:
        """Predicted displacement of the next frame from the reference, in frame sizes.

        The current frame's centre offset in the reference plus one more step of the
        constant-velocity model: when it gets large, the overlap with the reference would be too
        small for the next frame, so the current frame becomes the keyframe (sparse stills).
        """
        h, w = self.registrar.shape
        c = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        shift = np.hypot(*(matrix @ c - c[:2]))
        if self._velocity is not None:
            v = self._to_small @ self._velocity @ self._from_small
            shift += np.hypot(*(v @ c - c)[:2])
        return float(shift / min(h, w))

    def rejoin(self, segment: int, transform: np.ndarray) -> None:
        """The current segment joined ``segment``: go on in its map frame (``transform``, 3x3: map
        px of the current segment -> map px of ``segment``)."""
        self.correct(transform)
        self.segment = segment

    def correct(self, c: np.ndarray) -> None:
        """Apply a pose-graph correction (3x3, old map px -> new map px) to the tracking state."""
        if self._ref is not None:
            self._ref.pose = c @ self._ref.pose
        if self._last is not None:
            self._last = (self._last[0], c @ self._last[1])
        if self._previous is not None:
            self._previous = (self._previous[0], self._previous[1], c @ self._previous[2])

    def _prior(self, index: int) -> tuple[Prior | None, Expectation | None]:
        """Expected registration against the reference, from a constant-velocity model.

        Without a motion model (start, gaps) the expectation is "no rotation, no scale change"
        with no restriction: it is only tried as an extra hypothesis when the search is weak.
        """
        if not self.motion_prior:
            return None, None
        if self._last is None or self._velocity is None or index - self._last[0] != 1:
            return _HINT, None
        last_index, last_pose = self._last
        predicted = last_pose @ self._velocity
        rel = self._to_small @ np.linalg.inv(self._ref.pose) @ predicted @ self._from_small
        angle, scale = pose_angle_deg(rel), pose_scale(rel)
        # the expected shift decides between near-equal translation peaks (periodic ground):
        # within a few pixels plus a quarter of the frame-to-frame step
        step = self._to_small @ self._velocity @ self._from_small
        h, w = self.registrar.shape
        c = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        tol = 4.0 + 0.25 * float(np.hypot(*(step @ c - c)[:2]))
        prior = Prior(angle_deg=angle, angle_tol_deg=self.prior_angle_tol_deg, scale=scale,
                      scale_tol=self.prior_scale_tol, shift=(float(rel[0, 2]), float(rel[1, 2])),
                      shift_tol=tol)
        expected = Expectation(rel[:2].copy(), 2.0 * tol, min(self.prior_angle_tol_deg, 10.0),
                               min(self.prior_scale_tol, 0.1))
        return prior, expected

    def _place(self, ref: _Reference, view: View, index: int, sample: Any) -> tuple[Match, str | None]:
        """Place ``view`` against ``ref``: with the telemetry prior when there is one (vision
        decides on disagreement), else the motion model's; then free (any rotation, features
        allowed) when that is not accepted. Returns the match and, when telemetry was overruled,
        what it disagreed about."""
        tprior = self.telemetry_prior(ref.sample, sample) if self.telemetry_prior else None
        motion, expected = self._prior(index)
        if tprior is not None and motion is not None and motion.shift is not None:
            tprior = dataclasses.replace(tprior, shift=motion.shift, shift_tol=motion.shift_tol)
        if tprior is not None:
            told = self.matcher.match(ref.view, view, tprior, expected, second_opinion=False)
            if told.accepted and told.confidence >= self.keyframe_confidence:
                return told, None
            free = self.matcher.match(ref.view, view, motion, expected)
            if free.accepted and (not told.accepted or free.confidence > told.confidence + 0.05):
                if tprior.admits(free.matrix):  # a better peak, not a disagreement
                    return free, None
                return free, (f"frame {index}: telemetry disagrees with the images (expected "
                              f"{tprior.angle_deg if tprior.angle_deg is not None else float('nan'):.1f} deg, "
                              f"{tprior.scale if tprior.scale is not None else float('nan'):.3f}; images say "
                              f"{pose_angle_deg(free.matrix):.1f} deg, {pose_scale(free.matrix):.3f}): vision wins")
            return told, None
        restricted = motion is not None and motion is not _HINT
        match = self.matcher.match(ref.view, view, motion, expected, second_opinion=not restricted)
        if not match.accepted and restricted:  # a turn the motion model did not expect
            match = self.matcher.match(ref.view, view, None, None)
            if match.accepted and not expected.agrees(match.matrix, self.matcher.centre):
                # ... or a jump: on periodic ground a peak one period off wins against a
                # reference far back; the previous frame, one small step away, decides
                match = self._through_previous(ref, view, index) or match
        elif restricted and match.how == "confirmed" and match.confidence < self.matcher.min_confidence:
            # the motion model's search found only a weak peak that the overlap check let through:
            # a near miss passes that check too (frames out of order, a sudden turn). A free
            # search that finds a clearly stronger placement wins.
            free = self.matcher.match(ref.view, view, None, None, second_opinion=False)
            if free.accepted and free.confidence > max(match.confidence, self.matcher.min_confidence):
                match = free
        return match, None

    def _through_previous(self, ref: _Reference, view: View, index: int) -> Match | None:
        """The frame placed against the previous frame (posed, not the reference) where the
        constant-velocity model expects it, composed with that frame's pose: a placement
        against ``ref`` (working px) that the three frames agree on, or None. The frame then
        becomes the next reference (the old one is too far for this ground)."""
        if self._previous is None or self._velocity is None or self._previous[0] != index - 1 \
                or self._previous[0] == ref.index:
            return None
        _, prev_view, prev_pose = self._previous
        step = self._to_small @ self._velocity @ self._from_small  # frame -> previous, working px
        h, w = self.registrar.shape
        c = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
        tol = 4.0 + 0.25 * float(np.hypot(*(step @ c - c)[:2]))
        prior = Prior(angle_deg=pose_angle_deg(step), angle_tol_deg=self.prior_angle_tol_deg, scale=pose_scale(step),
                      scale_tol=self.prior_scale_tol, shift=(float(step[0, 2]), float(step[1, 2])), shift_tol=tol)
        expected = Expectation(step[:2].copy(), 2.0 * tol, min(self.prior_angle_tol_deg, 10.0),
                               min(self.prior_scale_tol, 0.1))
        placed = self.matcher.match(prev_view, view, prior, expected, second_opinion=False)
        if not placed.accepted or placed.how != "expected":
            return None
        to_ref = self._to_small @ np.linalg.inv(ref.pose) @ prev_pose @ self._from_small
        self._chained = True
        return dataclasses.replace(placed, matrix=(to_ref @ to_h(placed.matrix))[:2])

    def step(self, frame: np.ndarray, index: int, sample: Any = None, image: np.ndarray | None = None
             ) -> TrackStep:
        """Pose frame ``index`` (``frame`` at the working resolution, grey or BGR; ``image`` the
        input frame it was downscaled from, for the feature second opinion).

        ``sample`` is the frame's telemetry (or None); with ``telemetry_prior`` it gives the
        expected rotation and scale against the reference.
        """
        view = self.matcher.view(frame, image)
        events: list[str] = []
        self._chained = False
        if self._ref is None:
            return self._new_segment(view, index, events, sample)
        match, disagreement = self._place(self._ref, view, index, sample)
        anchor = None
        if not match.accepted and self._pending is not None and self._pending[0] == index - 1:
            pending_index, pending, pending_sample = self._pending
            retry = self.matcher.match(pending, view, _HINT)
            if retry.accepted:
                anchor = pending_index
                self._new_segment(pending, anchor, events, pending_sample)
                match = retry
        if not match.accepted:
            self._lost += 1
            if self._lost > self.max_lost_frames:
                return self._new_segment(view, index, events, sample)
            self._pending = (index, view, sample)
            return TrackStep(LOW_CONFIDENCE, None, match.confidence, self.segment, match.registration, events,
                             disagreement=disagreement, method=match.method, how=match.how)
        self._pending = None
        rel = self._from_small @ to_h(match.matrix) @ self._to_small  # input px of frame -> of reference
        pose = self._ref.pose @ rel
        if self._last is not None and index - self._last[0] == 1:
            self._velocity = np.linalg.inv(self._last[1]) @ pose
        elif self._last is not None:
            self._velocity = None
        self._last = (index, pose)
        self._previous = (index, view, pose)
        self._lost = 0
        step = TrackStep(REGISTERED, pose[:2].copy(), match.confidence, self.segment, match.registration,
                         events, reference=self._ref.index, relative=rel, disagreement=disagreement,
                         method=match.method, how=match.how)
        if match.method == "ifmi":
            self._ref.best = max(self._ref.best, match.confidence)
        if not self.keyframes or match.method != "ifmi" or self._chained \
                or match.confidence < self.keyframe_confidence * self._ref.best \
                or self._next_shift(match.matrix) > self.keyframe_max_shift:
            self._ref = _Reference(view, pose, index, sample)
            step.keyframe = True
        if anchor is not None:
            step.anchor, step.anchor_pose = anchor, self._map[:2].copy()
        return step
