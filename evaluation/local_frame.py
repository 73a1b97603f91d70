"""The name of a run's local frame, from its summary (no plotting library: ``online`` prints
it in its header, the report and the figures in their captions and axes)."""

from __future__ import annotations

import math
from collections.abc import Mapping

from ddfuse.evaluation.scores import RunSummary


def frame(summary: RunSummary | Mapping) -> dict[str, str]:
    """The local frame of a run (from its ``RunSummary``'s data facts and initial pose; a
    metrics.json dictionary, even a partial one, is read into one): ``kind`` ('enu': about
    the GPS datum; 'map': the landmark map's; 'truth': the ground truth's, every estimator
    starting at its first pose; 'given': the configured initial pose's; 'start': the start
    pose), ``text`` (a sentence for the report), ``short`` (for titles), ``x``/``y`` (axis
    names without unit)."""
    if isinstance(summary, Mapping):  # online_frame's facts, a hand-built dictionary
        summary = RunSummary.from_json(summary)
    d = summary.data
    datum, landmarks = (d.datum, d.landmarks) if d else (None, None)
    ip = summary.initial_pose
    if datum:
        lat, lon, alt = datum
        return {"kind": "enu", "x": "x east", "y": "y north", "short": "ENU about the GPS datum",
                "text": f"ENU about the GPS datum {lat:.6f}°, {lon:.6f}°, {alt:.1f} m (x east, "
                        "y north)"}
    if landmarks:
        return {"kind": "map", "x": "x (map)", "y": "y (map)", "short": "the landmark map's frame",
                "text": "the landmark map's frame (x, y as in the map; no GPS)"}
    if ip == "first ground-truth pose":
        return {"kind": "truth", "x": "x", "y": "y", "short": "the ground truth's frame",
                "text": "the ground truth's frame: every estimator starts at the first truth "
                        "pose (no GPS, no landmark map)"}
    if isinstance(ip, (list, tuple)) and len(ip) == 3:
        return {"kind": "given", "x": "x", "y": "y", "short": "the initial pose's frame",
                "text": f"the frame the configured initial pose ({ip[0]:.2f} m, "
                        f"{ip[1]:.2f} m, {math.degrees(ip[2]):.1f}°) is given in (no GPS, "
                        "no landmark map)"}
    return {"kind": "start", "x": "x", "y": "y", "short": "the start-pose frame",
            "text": "the start pose: origin where the robot started, x at heading 0 (the "
                    "first absolute heading reading where its offset is configured, else "
                    "the robot's initial heading); no GPS, no landmark map"}
