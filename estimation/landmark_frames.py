"""Bearings of one frame with an error in common: the model of a landmark sensor's
``noise.bearing_common`` (rad), written once for every estimator.

A camera's detections of one image share the image's heading error (its rotation at the
exposure, the truth's heading at that stamp): the sightings of one frame (one sensor, one stamp)
have bearing errors ``n_i = c + e_i`` with ``c ~ N(0, sigma_c^2)`` common to the frame and
``e_i ~ N(0, d_i)`` their own (``d_i`` = the sighting's ``bearing_var``, the config's
``noise.bearing`` squared), so the frame's bearing covariance is ``D + sigma_c^2 11'``. Ranges
stay independent.

The frame is fused sighting by sighting, each as the *conditional* measurement given the
frame's earlier (accepted) sightings, which is the stacked update with the full covariance
split by the chain rule ``p(n_1..n_K) = prod_k p(n_k | n_1..n_k-1)`` (exact for a linear model;
an EKF re-linearises each at the current estimate). Given the earlier residuals ``r_j``, the
common part's posterior has precision ``1 / sigma_c^2 + sum_j 1 / d_j`` and mean
``sum_j w_j r_j`` with ``w_j = (1 / d_j) / precision``; so sighting k's bearing residual is
``r_k - sum_j w_j r_j`` (its Jacobian ``H_k - sum_j w_j H_j``) with variance
``d_k + 1 / precision``, independent of the earlier ones. Its innovation and NIS are the
frame's likelihood term by term, so the gate, the NIS and ``ddfuse tune`` see the model too.
No sighting waits for the frame to end: no buffering, and a frame's first sighting is the
independent model's with variance ``d + sigma_c^2``.

A sighting the gate rejects does not join its frame. A sighting that starts a landmark in
EKF-SLAM initialises it only and does not join either (it is no update). ``bearing_common``
absent or 0: no frame, every sighting exactly as without this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ddfuse.estimation.config import Config
from ddfuse.estimation.measurements import LandmarkObservation

__all__ = ["FrameBearings", "FrameTerms"]


@dataclass
class FrameTerms:
    """What sighting k of a frame is fused with: ``earlier`` the frame's accepted sightings as
    (ref, measured bearing rad) -- ``ref`` is what the estimator stored to re-predict that
    sighting (a landmark position, a state slot) --, ``weights`` their w_j, and ``bearing_var``
    (rad^2) the conditional bearing variance to use instead of the sighting's own."""

    earlier: list = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    bearing_var: float = 0.0


class FrameBearings:
    """Per landmark sensor with ``noise.bearing_common`` > 0, its current frame: the stamp, the
    caller's frame key (the smoother's keyframe and offset: sightings on another key start a
    new frame) and its accepted sightings (ref, bearing, bearing variance)."""

    def __init__(self, cfg: Config) -> None:
        self.common = {}
        for s in cfg.of_kind("landmarks"):
            sc = float(s.noise.get("bearing_common", 0.0))
            if sc > 0.0:
                self.common[s.name] = sc * sc
        self._frames: dict[str, tuple[float, object, list]] = {}

    def __bool__(self) -> bool:
        return bool(self.common)

    def terms(self, m: LandmarkObservation, key: object = None) -> FrameTerms | None:
        """The conditional terms of sighting ``m`` (module docstring), or None where the
        independent model applies (no common part for its sensor, or a range-only sighting).
        ``key``: anything else that must match for two sightings to share a frame."""
        sc2 = self.common.get(m.sensor)
        if sc2 is None or not m.has_bearing:
            return None
        frame = self._frames.get(m.sensor)
        if frame is None or frame[0] != m.t or frame[1] != key:
            frame = (m.t, key, [])
            self._frames[m.sensor] = frame
        items = frame[2]
        prec = 1.0 / sc2 + sum(1.0 / d for _, _, d in items)
        return FrameTerms([(ref, zb) for ref, zb, _ in items],
                          [(1.0 / d) / prec for _, _, d in items],
                          float(m.bearing_var) + 1.0 / prec)

    def accepted(self, m: LandmarkObservation, ref: object) -> None:
        """Sighting ``m`` (after :meth:`terms`) was fused: it joins its frame, re-predicted
        later through ``ref``."""
        if m.sensor in self.common and m.has_bearing:
            self._frames[m.sensor][2].append((ref, float(m.bearing), float(m.bearing_var)))

    def reset(self) -> None:
        """Forget every frame (a filter restarted from scratch)."""
        self._frames.clear()
