"""Placing one frame against another: iFMI first, checked, with a feature second opinion.

iFMI (:mod:`photomap.core.ifmi`) is the fast path. A placement is accepted at once when it
agrees with what the motion model expected (video: the common case, one registration per frame).
Otherwise (no expectation, a jump against it, a low confidence) the placement must be confirmed
by the images themselves: the overlap check of :func:`photomap.core.features.verify_overlap`
(gradients correlate at the placement and nowhere else nearly as well). When iFMI's placement
is not confirmed, a feature method (SIFT or ORB + RANSAC) gives a second opinion and
:func:`photomap.core.features.decide` keeps the confirmed one, or none: a frame that nothing
confirms is not glued (a confident wrong placement is worse than a new segment).

Conventions: matrices are 2x3 and map pixels of the *moving* frame to pixels of the *reference*,
at the working resolution of the registrar (:mod:`photomap.geometry`). Pure: arrays in, arrays
out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from photomap.core.features import (FeatureFrame, FeatureMatcher, decide, ifmi_confirmed,
                                    verify_overlap)
from photomap.core.ifmi import PreparedFrame, Prior, Registrar, Registration
from photomap.geometry import pose_angle_deg, pose_scale, to_h

__all__ = ["View", "Match", "Expectation", "PairMatcher"]


@dataclass(eq=False)
class View:
    """A frame as the matcher sees it: its iFMI spectra (working resolution) and, for the feature
    second opinion, the input image with the factor from its pixels to working pixels; the
    features are detected on first use and kept."""

    prepared: PreparedFrame
    image: np.ndarray | None = None
    image_scale: float = 1.0  # working px per image px
    features: FeatureFrame | None = field(default=None, repr=False)


@dataclass(frozen=True)
class Expectation:
    """Where the motion model expects the moving frame: ``matrix`` (2x3, working px), trusted
    within ``tol_px`` (frame centre), ``tol_deg`` and ``tol_scale`` (relative)."""

    matrix: np.ndarray
    tol_px: float
    tol_deg: float
    tol_scale: float

    def agrees(self, matrix: np.ndarray, centre: np.ndarray) -> bool:
        m, e = to_h(matrix), to_h(self.matrix)
        shift = float(np.hypot(*((m - e) @ centre)[:2]))
        angle = abs((pose_angle_deg(m) - pose_angle_deg(e) + 180.0) % 360.0 - 180.0)
        scale = abs(math.log(max(pose_scale(m), 1e-9) / max(pose_scale(e), 1e-9)))
        return shift <= self.tol_px and angle <= self.tol_deg and scale <= math.log1p(self.tol_scale)


@dataclass(frozen=True)
class Match:
    """The outcome of placing a moving frame against a reference.

    ``matrix`` (2x3 working px, moving -> reference) is the accepted placement (or iFMI's
    rejected one, for the record); ``confidence`` the placement's: iFMI's peak, or for a feature
    placement the overlap check's score (for weights and logs); ``method``
    ``ifmi``, ``sift`` or ``orb``; ``check`` the overlap check's score (NaN when the placement
    was accepted without one); ``how``: ``expected`` (agreed with the motion model), ``confident``
    (a strong, unambiguous iFMI peak with nothing expected), ``confirmed`` (by the overlap check)
    or ``rejected``.
    """

    matrix: np.ndarray
    confidence: float
    method: str
    accepted: bool
    check: float
    how: str
    registration: Registration

    @property
    def ambiguous(self) -> bool:
        return self.registration.ambiguous


class PairMatcher:
    """Registers, checks and, when needed, asks the features.

    Parameters
    ----------
    registrar : Registrar
        At the working resolution.
    min_confidence : float
        iFMI confidence below which a placement is never accepted from the motion model alone.
    trust_confidence : float
        With no expectation, an unambiguous iFMI placement at least this confident is accepted
        without a check (iFMI's wrong pairs score far below; the check costs a little).
    verify : bool
        False: the old rule (accept at ``min_confidence``), no check, no features.
    second_opinion : {"sift", "orb", "none"}
        Feature method asked when iFMI's placement is not confirmed.
    second_opinion_px : int
        Longer side (pixels) the features are detected at.
    """

    def __init__(self, registrar: Registrar, *, min_confidence: float = 0.12, trust_confidence: float = 0.3,
                 verify: bool = True, second_opinion: str = "sift", second_opinion_px: int = 640) -> None:
        self.registrar = registrar
        self.min_confidence = min_confidence
        self.trust_confidence = trust_confidence
        self.verify = verify
        self.features = (FeatureMatcher(second_opinion, working_size=second_opinion_px)
                         if verify and second_opinion != "none" else None)
        h, w = registrar.shape
        self.centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])

    def twin(self, registrar: Registrar) -> PairMatcher:
        """A matcher with the same settings, ``registrar`` and a feature detector of its own (for
        another thread: neither is shared)."""
        f = self.features
        return PairMatcher(registrar, min_confidence=self.min_confidence, trust_confidence=self.trust_confidence,
                           verify=self.verify, second_opinion="none" if f is None else f.kind,
                           second_opinion_px=640 if f is None else f.working_size)

    def view(self, small: np.ndarray, image: np.ndarray | None = None) -> View:
        """A frame at the working resolution (and the input image it came from, for features)."""
        prepared = self.registrar.prepare(small)
        scale = small.shape[1] / image.shape[1] if image is not None else 1.0
        return View(prepared, image, scale)

    def _features(self, view: View) -> FeatureFrame | None:
        if view.features is None and view.image is not None and self.features is not None:
            view.features = self.features.prepare(view.image, self.registrar.mask)  # none on masked pixels
        return view.features

    def match(self, reference: View, moving: View, prior: Prior | None = None,
              expected: Expectation | None = None, second_opinion: bool = True,
              always_check: bool = False) -> Match:
        """Place ``moving`` against ``reference`` (see the module docstring); without
        ``second_opinion`` the features are not asked; with ``always_check`` nothing is accepted
        unless the images confirm it (e.g. joining two map segments)."""
        reg = self.registrar.register(reference.prepared, moving.prepared, prior)
        nan = float("nan")
        if not self.verify:
            ok = reg.confidence >= self.min_confidence
            return Match(reg.matrix, reg.confidence, "ifmi", ok, nan, "confident" if ok else "rejected", reg)
        if reference.prepared.blank or moving.prepared.blank:  # no placement, nothing for the features
            return Match(reg.matrix, reg.confidence, "ifmi", False, nan, "rejected", reg)
        if not always_check:
            if expected is not None and reg.confidence >= self.min_confidence \
                    and expected.agrees(reg.matrix, self.centre):
                return Match(reg.matrix, reg.confidence, "ifmi", True, nan, "expected", reg)
            if expected is None and reg.confidence >= self.trust_confidence and not reg.ambiguous:
                return Match(reg.matrix, reg.confidence, "ifmi", True, nan, "confident", reg)
        ref_gray, mov_gray = reference.prepared.gray, moving.prepared.gray
        check = verify_overlap(ref_gray, mov_gray, reg.matrix)
        if ifmi_confirmed(reg, check):
            return Match(reg.matrix, reg.confidence, "ifmi", True, check.score, "confirmed", reg)
        ref_f = mov_f = feat = feat_check = None
        if second_opinion:
            ref_f, mov_f = self._features(reference), self._features(moving)
        if ref_f is not None and mov_f is not None:
            feat = self.features.register(ref_f, mov_f)  # no prior: it is what iFMI got wrong
            if feat.ok:
                # both images are resized to the working resolution by the same factor (to rounding)
                feat = feat.rescaled(moving.image_scale)
                feat_check = verify_overlap(ref_gray, mov_gray, feat.matrix)
        decision = decide(reg, check, feat, feat_check)
        if decision.accept:
            confidence = reg.confidence if decision.method == "ifmi" else decision.score
            return Match(decision.matrix, confidence, decision.method, True, decision.score, "confirmed", reg)
        return Match(reg.matrix, reg.confidence, "ifmi", False, decision.score, "rejected", reg)
