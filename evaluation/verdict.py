"""A short plain-language verdict from a run's scores (pure: ``scores.RunSummary`` in, text out).

Which estimator is better on the best score available (position ATE against the truth, else the
RMSE to withheld GPS fixes), by how much; whether the EKF ties or wins; whether each estimator is
consistent (NEES, NIS verdicts of ``evaluation.consistency``); drift in GPS outages. Two scores
within ``TIE`` of each other (relative) are called a tie: a few percent is within what another
noise draw or a slightly different tuning changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ddfuse.estimation.estimator import wrap_angle
from ddfuse.evaluation.consistency import Consistency, SensorNis
from ddfuse.evaluation.metrics import OutageDrift
from ddfuse.evaluation.scores import CalibrationState, EstimatorScores, RunSummary

TIE = 0.05  # relative difference under which two scores tie
# The one tie rule, for the verdict and the report's tables alike (``tie``).
TIE_RULE = f"differ by at most {100 * TIE:.0f}% of the larger"
# Two estimators' final calibration states further apart than this many of their combined
# sigmas: at least one of them is biased. Both estimate from the same data, so their errors are
# correlated and the combined sigma overstates the gap's: the test errs towards silence.
CALIBRATION_SIGMAS = 3.0
# calibration state (metrics final_state, SI): (what it is, display unit, factor, format)
CALIBRATION_DISPLAY = {"bg": ("gyro bias", "deg/s", 180.0 / math.pi, ".3f"),
                       "hoff": ("heading offset", "deg", 180.0 / math.pi, ".2f"),
                       "k_v": ("odometry speed scale k_v", "", 1.0, ".4f"),
                       "k_w": ("odometry yaw-rate scale k_w", "", 1.0, ".4f")}


def final_states(m: RunSummary) -> dict[str, dict[str, CalibrationState]]:
    """Per estimator that has any, its calibration states at the end (``final_state``):
    {estimator: {label: state}}."""
    finals = {n: e.final_state.states if e.final_state else {}
              for n, e in m.estimators.items()}
    return {n: st for n, st in finals.items() if st}


def calibration_title(label: str) -> str:
    """What calibration state ``label`` is, with its display unit: 'heading offset [deg]'."""
    kind, _, sensor = label.partition(":")
    title, unit, _, _ = CALIBRATION_DISPLAY.get(kind, (kind, "", 1.0, ".4g"))
    return title + (f" ({sensor})" if sensor else "") + (f" [{unit}]" if unit else "")


def calibration_value(label: str, value: float, sigma: float | None) -> str:
    """'value +- sigma' of calibration state ``label`` (SI) in its display unit."""
    _, _, k, spec = CALIBRATION_DISPLAY.get(label.partition(":")[0], ("", "", 1.0, ".4g"))
    return f"{k * value:{spec}}" + ("" if sigma is None else f" ± {k * sigma:{spec}}")
OFFLINE = {"batch": "offline: the whole run at once"}
# the scores a ranking is on (EstimatorScores fields): against the truth, else withheld fixes
ATE, HOLDOUT = "ate_rmse_m", "gps_holdout_rmse_m"


def track_kind(name: str, lag_s: float | None = None) -> str:
    """'real time', 'lagged by N s' or 'offline' for a track name."""
    if name in OFFLINE:
        return "offline"
    if name.endswith("_lagged"):
        return f"lagged by {lag_s:g} s" if lag_s else "lagged"
    return "real time"


def _score(m: RunSummary) -> tuple[str | None, str]:
    """The ``EstimatorScores`` field to rank by (``ATE`` or ``HOLDOUT``) and a sentence saying
    what it is."""
    ests_d = m.estimators
    ests = ests_d.values()
    if any(e.ate_rmse_m is not None for e in ests):
        return ATE, ("Score: RMS position error against the ground truth (ATE, no "
                     "alignment, lower is better).")
    if any(e.gps_holdout_rmse_m is not None for e in ests):
        n, scored = m.gps_holdout_fixes, m.gps_holdout_scored_fixes
        k = m.gps_holdout_outliers or 0
        which = (f"{n} GPS fixes withheld from every estimator" if scored in (None, n) else
                 f"{scored} of the {n} GPS fixes withheld from every estimator (those at which "
                 "every estimator has an estimate)" if scored + k < n else
                 f"{scored} of the {n} GPS fixes withheld from every estimator")
        gross = (f" {k} withheld fix{'es' if k > 1 else ''} that no estimator comes near "
                 f"(beyond every one's GPS gate: gross GPS error{'s' if k > 1 else ''}) "
                 f"{'are' if k > 1 else 'is'} left out for all alike." if k else "")
        return HOLDOUT, (f"Score: RMS distance to the {which} (no ground truth; "
                         "lower is better)." + gross)
    own = {n: e.gps_holdout_span_s for n, e in ests_d.items()
           if e.gps_holdout_span_s and e.gps_holdout_m}
    if m.gps_holdout_fixes and m.gps_holdout_scored_fixes == 0 and own:
        # each track could be scored only on the fixes in its own span: not comparable
        t0 = m.t0
        spans = ", ".join(f"{n} {a - t0:.0f}-{b - t0:.0f} s ({ests_d[n].gps_holdout_m.n} "
                          "fixes)" for n, (a, b) in own.items())
        return None, (f"No score: the bag has no ground truth, and none of the "
                      f"{m.gps_holdout_fixes} GPS fixes withheld (--gps-holdout "
                      f"{m.gps_holdout}) lies inside every estimator's span ({spans}), "
                      "so no two estimators can be scored on the same fixes; their distances "
                      "to the fixes in their own spans (gps_holdout_m in metrics.json) are not "
                      "comparable.")
    if m.gps_holdout and not m.gps_holdout_fixes:
        return None, (f"No score: the bag has no ground truth, and --gps-holdout "
                      f"{m.gps_holdout} withheld no GPS fix (its window is outside the "
                      f"{m.duration_s or 0:.0f} s of data, or the bag has no fixes).")
    if m.gps_holdout:
        n = m.gps_holdout_fixes
        fixes = m.data.gps_fixes if m.data else None
        used = (n if fixes is None else fixes) - n
        why = (" Every fix was withheld, so the estimators that start from GPS never did."
               if used <= 0 else "")
        return None, (f"No score: the bag has no ground truth, and no estimator has an estimate "
                      f"at the {n} GPS fixes --gps-holdout {m.gps_holdout} withheld.{why}")
    if m.data is not None and m.data.gps_fixes == 0:
        return None, ("No score: the bag has neither ground truth nor GPS fixes, so nothing "
                      "tells which estimate is right; compare the final positions and the "
                      "tracks.")
    return None, ("No score: the bag has no ground truth and no GPS fixes were withheld "
                  "(run with --gps-holdout every:5, or window:T0:T1 for an outage).")


def signed(v: float, spec: str = "+.2f") -> str:
    """``v`` formatted with its sign (``spec`` has the '+'), but none where it rounds to zero:
    "0.00", not "-0.00" or "+0.00" (a drift or offset of nothing has no direction)."""
    text = format(v, spec)
    return text[1:] if text[:1] in "+-" and not any(c in "123456789" for c in text) else text


def _signed_pct(v: float) -> str:
    """A fraction as a signed percentage with one decimal; no sign where it rounds to zero."""
    return signed(100 * v, "+.1f") + "%"


def _m(v: float) -> str:
    """Metres to the millimetre, to the tenth of one under 10 cm (centimetre-level scores
    printed to the mm would hide differences of 10 %)."""
    return f"{v:.4f}" if abs(v) < 0.1 else f"{v:.3f}"


def tie(va: float, vb: float) -> bool:
    """Whether two scores tie (``TIE_RULE``): |va - vb| <= TIE max(va, vb). The report's
    tables mark the best of a column and every value that ties with it by this same rule."""
    d = abs(va - vb)
    return (d / max(va, vb) if max(va, vb) > 0 else 0.0) <= TIE


_tie = tie


def _call(a: str, va: float, b: str, vb: float) -> str | None:
    """Who wins between ``a`` and ``b`` (lower is better); None for a tie."""
    return None if _tie(va, vb) else (a if va < vb else b)


def _compare(a: str, va: float, b: str, vb: float) -> str:
    """'a' against 'b' in words (lower is better)."""
    d = abs(va - vb)
    rel = d / max(va, vb) if max(va, vb) > 0 else 0.0
    dm = f"{d:.3f}" if max(va, vb) >= 0.1 else f"{d:.4f}"  # to the precision of the scores
    if _tie(va, vb):
        return (f"{a} ({_m(va)} m) and {b} ({_m(vb)} m) tie: they differ by {dm} m "
                f"({100 * rel:.1f}%).")
    win, lose, vw, vl = (a, b, va, vb) if va < vb else (b, a, vb, va)
    return (f"{win} is better: {_m(vw)} m against {lose}'s {_m(vl)} m, {dm} m "
            f"({100 * rel:.1f}%) lower.")


def _direction(s: Consistency) -> str:
    """Which way a failing consistency summary leans: a mean well over the expected one (or
    only the upper tail off) is over-confidence, well under (or only the lower tail) is
    pessimism; with the mean within [2/3, 1.5] of the expected one it is the tails alone
    (errors not Gaussian), said with their shares."""
    ratio, above, below = s.ratio, s.above or 0.0, s.below or 0.0
    if ratio is None:
        return ""
    tail = 0.05  # twice the nominal 2.5% on one side of the 95% band
    if 2 / 3 <= ratio <= 1.5:
        return f"tails: {100 * below:.1f}% below, {100 * above:.1f}% above the band"
    if ratio > 1.5 or (above > tail >= below):
        return "over-confident"
    return "pessimistic"


ABSOLUTE_KINDS = {"gps", "heading", "landmark"}
# Kinds that test one sensor's one noise setting under different names: the odometry's speed
# and yaw rate (ekf: 'v', 'yaw_rate') are one 'odometry' measurement elsewhere (ekf_igvc).
_KIND_GROUP = {"v": "odometry", "yaw_rate": "odometry", "odometry": "odometry"}
# A sensor whose samples an estimator's gate rejected at least this share of: rejected
# throughout (nothing of it fused; a wrong heading offset, a wrong noise).
REJECTED_THROUGHOUT = 0.95
# Measurement type (metrics data.sensors 'measurements') of a NIS kind, for its sample count.
_KIND_TYPE = {"heading": "Heading", "gps": "GpsFix", "gyro": "GyroYawRate",
              "accel": "ForwardAccel", "landmark": "LandmarkObservation"}


def _topic_kind(label: str, st: SensorNis) -> tuple[str, str]:
    """A NIS row's sensor topic and kind (metrics ``nis`` entries carry them; else from the
    label 'topic kind')."""
    topic, _, kind = label.rpartition(" ")
    return st.sensor or topic or label, st.kind or kind


def averaged_per_keyframe(name: str, kind: str) -> bool:
    """Whether a track's NIS row of ``kind`` holds one value per keyframe (the smoother's
    heading: the samples since the last keyframe averaged into one factor), not one per
    sample: the smoother's tracks and the batch."""
    return kind == "heading" and (name.startswith("smoother") or name in OFFLINE)


def sensor_samples(m: RunSummary, topic: str, kind: str | None = None) -> int | None:
    """How many measurements of ``kind`` (or of any kind, the most) sensor ``topic`` gave
    (``data.sensors``)."""
    for s in (m.data.sensors if m.data else None) or []:
        if s.topic == topic or s.name == topic:
            meas = s.measurements or {}
            if kind in _KIND_TYPE and _KIND_TYPE[kind] in meas:
                return int(meas[_KIND_TYPE[kind]])
            return max(meas.values(), default=None)
    return None


@dataclass(frozen=True)
class GateRejection:
    """What the gates did to one sensor (``gate_rejections``): its gated ``kind`` (None where
    no NIS row names it), per estimator fusing it ``by`` {track: (rejected, samples)}, the
    tracks that rejected at least REJECTED_THROUGHOUT of them (``throughout``), and whether
    every track fusing the sensor did (``everyone``)."""

    kind: str | None
    by: dict[str, tuple[int, int | None]]
    throughout: list[str]
    everyone: bool


def gate_rejections(m: RunSummary) -> dict[str, GateRejection]:
    """Per sensor topic that some estimator's gate rejected samples of (``rejected['topic:
    gate']``, counted per sample whatever its NIS rows hold): ``GateRejection``."""
    ests = m.estimators
    topics = list(dict.fromkeys(topic for e in ests.values() for k in e.rejected or {}
                                for topic, _, reason in [k.rpartition(": ")] if reason == "gate"))
    out: dict[str, GateRejection] = {}
    for topic in topics:
        kind, per_row = None, {}
        for n, e in ests.items():
            for label, st in (e.nis or {}).items():
                t, k = _topic_kind(label, st)
                if t == topic and (st.rejected or 0) > 0 and not averaged_per_keyframe(n, k):
                    kind = kind or k
                    per_row[n] = (st.accepted or 0) + st.rejected
        n_all = sensor_samples(m, topic, kind)
        by = {}
        for n, e in ests.items():
            fuses = any(_topic_kind(label, st)[0] == topic
                        for label, st in (e.nis or {}).items()) or any(
                k.rpartition(": ")[0] == topic for k in e.rejected or {})
            if not fuses or e.samples == 0:
                continue
            r = (e.rejected or {}).get(f"{topic}: gate", 0)
            by[n] = (r, per_row.get(n) or n_all)
        thr = [n for n, (r, tot) in by.items() if tot and r >= REJECTED_THROUGHOUT * tot]
        out[topic] = GateRejection(kind, by, thr, bool(by) and len(thr) == len(by))
    return out


def _rejected_throughout(m: RunSummary, name: str) -> dict[tuple[str, str | None], str]:
    """The sensors ``name``'s gate rejected throughout: {(topic, kind or None): 'topic kind
    rejected by the gate throughout (r/N): not fused'}."""
    out = {}
    for topic, info in gate_rejections(m).items():
        if name in info.throughout:
            r, tot = info.by[name]
            what = f"{topic} {info.kind}" if info.kind else topic
            out[(topic, info.kind)] = (f"{what} rejected by the gate throughout "
                                          f"({r}/{tot}): not fused")
    return out


def _units(nis: dict[str, SensorNis]) -> dict[tuple[str, str], list[str]]:
    """What a NIS dictionary tests: (topic, kind group) -> its labels."""
    out: dict[tuple[str, str], list[str]] = {}
    for label, st in nis.items():
        topic, kind = _topic_kind(label, st)
        out.setdefault((topic, _KIND_GROUP.get(kind, kind)), []).append(label)
    return out


def _gated_units(m: RunSummary | None, name: str) -> set[tuple[str, str]]:
    """The (topic, kind) a track's gate decided on though it logged no NIS row for them
    (a sensor rejected throughout: ``gate_rejections``)."""
    if not m:
        return set()
    return {(t, info.kind) for t, info in gate_rejections(m).items()
            if info.kind and name in info.by}


def _shown_units(nis: dict[str, SensorNis], m: RunSummary | None, name: str
                 ) -> list[tuple[str, str]]:
    """What a track tests, by its own kind names, for its consistency line."""
    own = [_topic_kind(label, st) for label, st in nis.items()]
    return list(dict.fromkeys(own + sorted(_gated_units(m, name) - set(own))))


def _covered(units) -> str:
    """'/odom odometry, /imu/data gyro and heading, /fix gps'."""
    by: dict[str, list[str]] = {}
    for topic, kind in units:
        by.setdefault(topic, []).append(kind)
    return ", ".join(f"{t} {' and '.join(k)}" for t, k in by.items())


_HEADS = ("consistent", "partly consistent", "not consistent")


def _consistency(name: str, e: EstimatorScores, seen_nis: dict, m: RunSummary | None = None,
                 others: dict | None = None) -> tuple[str, str | None]:
    """One estimator's consistency in a sentence, and its head ('consistent', 'partly ...',
    None when not measurable). ``others``: {owner: units tested} of the other estimators, to
    say what this one does not test."""
    parts = []
    nees = e.nees
    if nees and nees.verdict:
        v = nees.verdict
        txt = f"NEES {v} (mean {nees.mean:.2f} for {nees.expected:g} expected"
        if v != "Pass":
            txt += f", {_direction(nees)}"
        parts.append(txt + ")")
    nis = e.nis or {}
    gone = _rejected_throughout(m, name) if m else {}
    key = repr(sorted(nis.items()))
    judged_nis = {label: st for label, st in nis.items()
                  if not any(_topic_kind(label, st)[0] == t and k in (None, _topic_kind(
                      label, st)[1]) for t, k in gone)}
    if nis and key in seen_nis:
        parts.append(f"NIS as {seen_nis[key]} (the same filter)")
    else:
        if nis:
            seen_nis[key] = name
        parts += list(gone.values())
        by: dict[str, list[str]] = {}
        for label, st in judged_nis.items():
            v = st.nis.verdict
            if v is None:
                continue
            per_kf = (", averaged per keyframe" if averaged_per_keyframe(
                name, _topic_kind(label, st)[1]) else "")
            note = (f" ({_direction(st.nis)}, mean/expected {st.nis.ratio:.2f}{per_kf})"
                    if v != "Pass" else (f" ({per_kf[2:]})" if per_kf else ""))
            by.setdefault(v, []).append(label + note)
        parts += [f"NIS {v}: {', '.join(by[v])}" for v in ("Fail", "Warn", "Pass") if v in by]
    nees_v = nees.verdict if nees else None
    judged = [s.nis.verdict for s in judged_nis.values() if s and s.nis.verdict]
    judged += ["Fail"] * len(gone)  # a sensor not fused at all is no consistent one
    fails = judged.count("Fail")
    bad = nees_v in ("Fail", "Warn") or fails > 0
    # without truth the NIS is all there is: failing on half the sensors or more is no
    # 'partly'
    head = "not consistent" if nees_v == "Fail" or (
        nees_v is None and judged and 2 * fails >= len(judged)) else (
        "partly consistent" if bad else "consistent")
    if not parts:
        why = ("no covariance to test against the truth" if e.ate_rmse_m is not None
               else "no truth")
        return f"{name}: consistency not measurable ({why}, no innovations logged).", None
    kinds = {s.kind for s in nis.values()}
    dr = (f" It fuses no absolute measurement here ({', '.join(sorted(map(str, kinds)))} "
          "only): it is dead reckoning.") if nis and not kinds & ABSOLUTE_KINDS else ""
    mine = set(_units(nis)) | _gated_units(m, name)
    lacks = sorted({u for o, us in (others or {}).items() if o != name for u in us} - mine)
    if head == "consistent" and lacks:
        head = "consistent on the sensors it tests"
    cover = ""
    if nis and key not in seen_nis or seen_nis.get(key) == name:
        cover = f" (tests {_covered(_shown_units(nis, m, name))}" + (
            f"; not {_covered(lacks)}, which others test" if lacks else "") + ")"
    return f"{name}{cover}: {head}. " + "; ".join(parts) + "." + dr, head


def _coverage_caution(heads: dict[str, str], units: dict[str, set]) -> str | None:
    """Where one estimator is called more consistent than another that tests sensors it does
    not, the calls are not a comparison of the methods: say so, with the verdicts on what
    both test."""
    pairs = []
    for a, ha in heads.items():
        for b, hb in heads.items():
            if a in units and b in units and ha.startswith("consistent") and \
                    hb != ha and units[b] - units[a]:
                pairs.append((a, b))
    if not pairs:
        return None
    a, b = pairs[0]
    both = sorted(units[a] & units[b])  # a set's order varies per process: the report must not
    return (f"The consistency calls cover different sensors: {a} tests no "
            f"{_covered(sorted(units[b] - units[a]))} residuals, which {b} does, so its "
            f"'{heads[a]}' beside {b}'s '{heads[b]}' is no difference between the methods"
            + (f"; compare them on what both test ({_covered(both)}) in the NIS table."
               if both else "."))


def _noise_hints(ests: dict[str, EstimatorScores]) -> list[str]:
    """Where two or more estimators test a sensor's residuals (their own NIS, not a lagged or
    batch track's copy) and all find them off in the same direction (NIS Fail, all pessimistic
    or all over-confident), the cause is the config's noise value for that sensor, which they
    all read, not either method: one line per direction naming the sensors. Grouped by sensor
    topic: the estimators name one sensor's measurements differently ('odom v' and 'odom
    yaw_rate' in one, 'odom odometry' in another)."""
    tests: dict[str, dict[str, tuple[str | None, list, list]]] = {}
    for e in ests.values():
        nis = e.nis or {}
        if e.samples == 0 or not nis:
            continue
        owner = repr(sorted(nis.items()))  # tracks of one filter share its NIS
        for label, st in nis.items():
            topic, kind = _topic_kind(label, st)
            ok = st.nis.verdict == "Fail" and st.nis.ratio is not None
            d, ratios, kinds = tests.setdefault(topic, {}).get(owner, ("", [], []))
            # one row of the sensor not failing, or failing the other way: no config hint
            new = _direction(st.nis) if ok else None
            d = new if d in ("", new) else None
            tests[topic][owner] = (d, ratios + [st.nis.ratio] if ok else ratios,
                                   kinds + [kind] if ok else kinds)
    by_dir: dict[str, list[str]] = {}
    for topic, owners in tests.items():
        dirs = {d for d, _, _ in owners.values()}
        if len(owners) < 2 or len(dirs) != 1 or not dirs & {"pessimistic", "over-confident"}:
            continue
        ratios = [r for _, rs, _ in owners.values() for r in rs]
        kinds = list(dict.fromkeys(k for _, _, ks in owners.values() for k in ks))
        lo, hi = f"{min(ratios):.2f}", f"{max(ratios):.2f}"
        by_dir.setdefault(dirs.pop(), []).append(
            f"{topic} ({', '.join(kinds)}: {lo if lo == hi else f'{lo}-{hi}'})")
    return [f"Every estimator that tests them finds these residuals {d} (NIS mean/expected): "
            f"{', '.join(labels)}. The config's noise for them is "
            f"{'larger' if d == 'pessimistic' else 'smaller'} than the data's, alike for all "
            "estimators: those consistency verdicts are about the config, not about which "
            "method is better." for d, labels in by_dir.items()]


# NIS kinds of a rate measurement (speed, yaw rate, acceleration): their innovation is mostly
# the predicted change of the twist since the last sample, whose spread is the process noise.
RATE_KINDS = {"v", "yaw_rate", "odometry", "gyro", "accel", "wheels"}


def low_rate_nis(m: RunSummary) -> list[tuple[str, str, float]]:
    """(track, NIS label, mean/expected) of every rate-sensor NIS row (``RATE_KINDS``) that
    fails pessimistic, of the tracks that log their own innovations (not a copy) and whose
    pose NEES against the truth does not fail (the pose covariance is right: what is off is
    the prediction of the twist alone). Without truth nothing tells that from overstated
    sensor noise: none."""
    out, seen = [], set()
    for n, e in m.estimators.items():
        key = repr(sorted((e.nis or {}).items()))
        if e.samples == 0 or not e.nis or key in seen:
            continue
        seen.add(key)
        if not (e.nees and e.nees.verdict in ("Pass", "Warn")):
            continue
        for label, st in e.nis.items():
            c = st.nis
            if (_topic_kind(label, st)[1] in RATE_KINDS and c.verdict == "Fail"
                    and _direction(c) == "pessimistic"):
                out.append((n, label, c.ratio))
    return out


def process_noise_line(m: RunSummary) -> str | None:
    """One line on rate sensors whose NIS fails pessimistic: the likely cause is the process
    noise of the twist (the motion model), not the sensor's noise; None without such rows."""
    rows = low_rate_nis(m)
    if not rows:
        return None
    return ("Low NIS on rate sensors (" + ", ".join(f"{n} {lab} {r:.2f}" for n, lab, r in rows)
            + " of the expected) beside a NEES that passes is the motion model, not the "
            "sensors: a speed or yaw-rate "
            "innovation is mostly the predicted change of the twist since the last sample, "
            "whose process noise (robot.twist_walk; absent, sized from robot.max_accel / "
            "max_yaw_accel, the largest accelerations) a drive that mostly accelerates less "
            "never uses; the config's sensor noise can be the true one (as on the simulated "
            "sample bag) and this NIS still fail.")


def _gate_lines(m: RunSummary) -> list[str]:
    """A sensor every estimator fusing it rejected (nearly) throughout: one line for all."""
    out = []
    for topic, info in gate_rejections(m).items():
        if not info.everyone:
            continue
        counts = {f"{r}/{tot}" for r, tot in info.by.values()}
        each = (f"{counts.pop()} each" if len(counts) == 1 else ", ".join(
            f"{n} {r}/{tot}" for n, (r, tot) in info.by.items()))
        what = f"{topic} {info.kind}" if info.kind else topic
        check = ("heading_offset / noise" if info.kind == "heading" else "noise, "
                 "lever arm / delay" if info.kind == "gps" else "noise")
        out.append(f"Every estimator rejected {what} throughout ({each}): nothing of it was "
                   f"fused, alike for all; check the config's {check} for {topic}.")
    return out


# Share of a track's ATE from which the pairing's own error is stated: 0.3 moves an ATE by
# 5 % (TIE) when the two errors are independent (they add in quadrature).
ASSOCIATION_SHARE = 0.3


def _association_caution(m: RunSummary, scored: dict) -> str | None:
    """The ATE pairs each estimate with the nearest truth sample (evo's rule); where that
    alone is a sizeable share of a track's ATE (sparse truth, outputs between its samples),
    say so with the figures (``metrics.association_error``)."""
    ests = m.estimators
    hit = {n: ests[n].ate_association_rmse_m for n in scored
           if (ests[n].ate_association_rmse_m or 0.0) > ASSOCIATION_SHARE * scored[n]}
    if not hit:
        return None
    dt = m.data.ground_truth_interval_s if m.data else None
    every = f" every {dt:.3g} s" if dt else ""
    return ("Caution: the truth is sampled" + every + ", and each estimate is paired with the "
            "nearest truth sample (evo's rule, no interpolation). A track exactly on the true "
            "path would score from that pairing alone: "
            + ", ".join(f"{n} {_m(hit[n])} m (its ATE {_m(scored[n])} m)" for n in hit)
            + ". Differences of that size between tracks output at different stamps are not "
            "accuracy.")


# A track's span differing from the common one (the intersection every track is ranked over)
# by more than this is stated: a late start skips the first seconds (often the worst), an early
# stop keeps only the first ones. Under it: a keyframe track's first keyframe at the first fix.
SPAN_SLACK_S = 1.0


def _ranked_scores(m: RunSummary, key: str, scored: dict) -> tuple[dict, str | None]:
    """The scores to rank on: for the ATE, every track's RMSE on the common span and stamps
    (``pipeline._common_ate``) where all scored tracks have one, with a sentence saying so;
    else the scores themselves."""
    c = m.ate_common
    ests = m.estimators
    common = {n: ests[n].ate_common_rmse_m for n in scored}
    if key != ATE or not c or None in common.values():
        return scored, None
    t0 = m.t0
    span = c.span_s
    # max: t0 and the span come rounded from different places ("-0.0-399.9 s")
    where = (f" within the common span {max(span[0] - t0, 0.0):.1f}-{span[1] - t0:.1f} s"
             if span else "")
    return common, (f"Ranked on the same moments for every track: the {c.stamps} stamps of "
                    f"{c.of}{where}, every track and the truth interpolated there (each "
                    "track's own ATE, over all its samples as evo pairs them, is in the "
                    "table).")


def _own_ate_line(scored: dict, ranked: dict, best: str, tied: list[str]) -> str | None:
    """Where each track's own ATE (its own span and stamps) ranks another track first, one
    outside the ``tied`` best ones."""
    own_best = min(scored, key=scored.get)
    if scored is ranked or own_best in tied:
        return None
    order = sorted(scored, key=scored.get)
    return ("Over each track's own samples and span (the table's ATE) the order differs: "
            + ", ".join(f"{n} {_m(scored[n])} m" for n in order)
            + f"; there {own_best} is best, not {best}.")


def _span_lines(m: RunSummary) -> list[str]:
    """Tracks whose own span differs from the common one by more than SPAN_SLACK_S: which
    start later or stop earlier than the others, by how much, and what the ranking covers."""
    c = m.ate_common
    spans = {n: e.span_s for n, e in m.estimators.items()
             if e.span_s and e.ate_common_rmse_m is not None}
    if not c or not c.span_s or len(spans) < 2:
        return []
    t0 = m.t0
    lo, hi = c.span_s
    first = min(a for a, _ in spans.values())
    last = max(b for _, b in spans.values())
    out = []
    for n, (a, b) in spans.items():
        if a - first > SPAN_SLACK_S:
            out.append(f"{n} starts {a - first:.1f} s after the first track (at {a - t0:.1f} s): "
                       f"every track is ranked from {lo - t0:.1f} s, so the others' first "
                       f"{a - first:.1f} s, often their worst, count for none.")
        if last - b > SPAN_SLACK_S:
            why = " (an error: it stopped early)" if m.estimators[n].error else ""
            out.append(f"{n} ends {last - b:.1f} s before the last track, at {b - t0:.1f} s"
                       f"{why}: every track is ranked only up to {hi - t0:.1f} s; the table's "
                       "ATE covers each track's own span.")
    return out


def interruption(error: str | None) -> bool:
    """Whether an estimator's error is a Ctrl-C that caught it (inside an update or its
    finish), not a failure of its own (``ddfuse.estimation.runner.run``)."""
    return bool(error) and error.startswith("interrupted (Ctrl-C)")


def _stopped_early(m: RunSummary) -> list[str]:
    """The tracks left out of the ranking: a real error, or an interruption after which the
    track ends more than SPAN_SLACK_S before the last one (Ctrl-C ends every track at the same
    message; one caught inside its update keeps what it had, which is all of it)."""
    ests = m.estimators
    ends = [e.span_s[1] for e in ests.values() if e.span_s]
    last = max(ends) if ends else None
    out = []
    for n, e in ests.items():
        if not e.error:
            continue
        span = e.span_s
        if not interruption(e.error) or span is None or last is None or (
                last - span[1] > SPAN_SLACK_S):
            out.append(n)
    return out


def unresolved(d: OutageDrift, which: str = "end") -> bool:
    """Whether an outage's error at its ``which`` ('start' or 'end'), scored through block
    medians of noisy fixes (``metrics.outage_drift``), lies below their noise there: not
    resolved (the value is |median| less the noise, clipped at 0: not an error size)."""
    v, noise = (d.error_start_m if which == "start" else d.error_end_m), d.error_noise_m
    return v is not None and noise is not None and v < noise


def outage_drift(d: OutageDrift) -> float | None:
    """An outage's drift per metre where both its errors are resolved, else None."""
    if d.drift_per_m is None or unresolved(d, "start") or unresolved(d, "end"):
        return None
    return d.drift_per_m


SEES_AFTER = "sees fixes after the outage"


def _outage_lines(m: RunSummary) -> list[str]:
    """Per GPS outage: the real-time tracks ranked by their error at its end (dead reckoning
    through it), with their drift; the lagged and offline tracks, which see the fixes after
    the outage, named apart and not ranked on drift; unresolved ends said as '< noise'."""
    ests = m.estimators
    lag = m.lag_s
    t0 = m.t0
    out = []
    for o_idx, o in enumerate(m.gps_outages or []):
        rows = {n: e.gps_outages[o_idx] for n, e in ests.items()
                if e.gps_outages and e.gps_outages[o_idx]
                and e.gps_outages[o_idx].error_end_m is not None}
        if not any(d.drift_per_m is not None for d in rows.values()):
            continue
        any_d = next(iter(rows.values()))
        if any_d.block_s:
            # noisy fixes: path and errors from their medians over a few seconds
            # (metrics.outage_drift), less the noise left in those medians
            how = (f"{any_d.distance_m:.0f} m travelled by the withheld GPS fixes' medians "
                   f"over {any_d.block_s:g} s; start and end errors from the median of the "
                   f"fixes in its first and last {any_d.block_s:g} s, less their noise of "
                   f"{any_d.error_noise_m:.2f} m")
        else:
            how = f"{any_d.distance_m:.0f} m travelled, scored against the {any_d.reference}"

        def said(n: str, rows: dict = rows) -> str:
            d = rows[n]
            if unresolved(d):
                return f"{n} < {d.error_noise_m:.2f} m (unresolved)"
            drift = outage_drift(d)
            return f"{n} {d.error_end_m:.2f} m" + (
                f" ({_signed_pct(drift)})" if drift is not None else "")

        live = sorted((n for n in rows if track_kind(n) == "real time"),
                      key=lambda n: rows[n].error_end_m)
        later = [n for n in rows if track_kind(n) != "real time"]
        text = f"GPS outage {o.t0 - t0:.0f}-{o.t1 - t0:.0f} s ({how})"
        if live:
            text += (", real-time tracks (dead reckoning through it) by their error at its end, "
                     "with its growth per metre travelled: " + ", ".join(map(said, live)) + ".")
        else:
            text += "."
        if later:
            text += (" Not ranked on drift, as each " + SEES_AFTER + " ("
                     + ", ".join(f"{n}: {track_kind(n, lag)}" for n in later) + "), so its "
                     "error there is smoothed, not dead-reckoned: "
                     + ", ".join(map(said, later)) + ".")
        if any_d.block_s:
            text += (f" Errors under {any_d.error_noise_m:.2f} m are within the fixes' noise "
                     "there: not resolved, and no drift is given for them.")
        out.append(text)
    return out


def _holdout_caution(m: RunSummary, best: str) -> str:
    """What a hold-out of single fixes measures, with the GPS residuals' correlation time to
    the best track where the run measured it (``metrics.correlation_time``)."""
    tail = (" Read it with the GPS NIS below, and with a window hold-out (an outage), where "
            "dead reckoning has to carry the estimate.")
    corr = m.estimators[best].gps_residual_corr_s
    interval = m.data.gps_fix_interval_s if m.data else None
    interp = m.gps_holdout_interpolation_rmse_m
    k = m.gps_holdout_interpolation_outliers or 0
    left = (f" ({k} gross error{'s' if k > 1 else ''} among them left out)" if k else "")
    ref = (f" For reference, the used fixes interpolated in time{left}, no estimator, score "
           f"{interp:.3f} m." if interp is not None else "")
    if corr is None or not interval:
        return ("Caution: GPS errors are often correlated in time, so a fix withheld between two "
                "used ones lies close to them; this score then rewards following the GPS "
                "closely." + ref + tail)
    if corr < interval:
        return (f"The GPS residuals to {best} are uncorrelated from one fix to the next "
                f"({interval:.2g} s apart): the withheld fixes are independent checks." + ref)
    return (f"Caution: the GPS residuals to {best} stay correlated for {corr:.1f} s, "
            f"{corr / interval:.0f} fix intervals of {interval:.2g} s: a withheld fix carries "
            "nearly the error of the used ones beside it, so this score rewards following the "
            "GPS closely: a track that averages over longer spans can score worse without being "
            "less accurate." + ref + tail)


def _calibration_gaps(m: RunSummary) -> list[str]:
    """Per calibration state, the pair of estimators whose final values lie furthest apart in
    combined sigmas, where that exceeds CALIBRATION_SIGMAS."""
    finals = final_states(m)
    labels = list(dict.fromkeys(label for st in finals.values() for label in st))
    out = []
    for label in labels:
        have = [(n, st[label]) for n, st in finals.items()
                if label in st and st[label].value is not None and st[label].sigma]
        worst = None
        for i, (a, sa) in enumerate(have):
            for b, sb in have[i + 1:]:
                d = sa.value - sb.value
                if label.startswith("hoff"):  # an angle: the short way round
                    d = wrap_angle(d)
                z = abs(d) / math.hypot(sa.sigma, sb.sigma)
                if z > CALIBRATION_SIGMAS and (worst is None or z > worst[0]):
                    worst = (z, a, sa, b, sb)
        if worst:
            z, a, sa, b, sb = worst
            out.append(
                f"{a} and {b} end the run with different {calibration_title(label)}: "
                f"{calibration_value(label, sa.value, sa.sigma)} against "
                f"{calibration_value(label, sb.value, sb.sigma)}, "
                f"{z:.1f} combined sigmas apart. From the same data that is more than their "
                "stated uncertainty allows: at least one of them is biased there (see the "
                "calibration table).")
    return out


@dataclass(frozen=True)
class Ranking:
    """What a run's tracks are ranked on and their order (lower is better). ``key``: the
    ``EstimatorScores`` field of each track's own score (``ATE`` or ``HOLDOUT``), None when
    nothing scores them; ``what``: a sentence saying what the score is (or why there is none);
    ``how``: how the ranking is taken (common stamps, tracks left out), or None; ``own``: each
    ranked track's own score [m]; ``scored``: the scores ranked on [m] (``own``, or for the ATE
    every track's RMSE on the common stamps, ``EstimatorScores.ate_common_rmse_m``);
    ``halted``: the tracks left out, having stopped with an error."""

    key: str | None
    what: str
    how: str | None = None
    own: dict[str, float] = field(default_factory=dict)
    scored: dict[str, float] = field(default_factory=dict)
    halted: tuple[str, ...] = ()

    @property
    def figure(self) -> str | None:
        """The ``EstimatorScores`` field of the figures ranked on (``scored``)."""
        if not self.scored:
            return None
        return "ate_common_rmse_m" if self.scored is not self.own else self.key

    @property
    def order(self) -> list[str]:
        """The ranked tracks, best first."""
        return sorted(self.scored, key=self.scored.get)

    @property
    def tied(self) -> list[str]:
        """The best track and every one that ties with it (``TIE_RULE``), best first."""
        order = self.order
        return [n for n in order if _tie(self.scored[order[0]], self.scored[n])]


def ranking(m: RunSummary) -> Ranking:
    """The run's ranking: the score ``_score`` chooses, on the common stamps where every ranked
    track has them (``_ranked_scores``); the tracks that stopped with an error left out."""
    ests = m.estimators
    key, what = _score(m)
    # an estimator that stopped with an error scored only its first part of the run: left out
    # of the ranking (otherwise its first seconds, or the common span cut to them, decide);
    # one that Ctrl-C caught inside an update is no failure: left out only if it ends early
    halted = [n for n in _stopped_early(m) if key and getattr(ests[n], key) is not None]
    if not key or len(halted) >= sum(getattr(e, key) is not None for e in ests.values()):
        return Ranking(key, what)
    own = {n: getattr(e, key) for n, e in ests.items()
           if getattr(e, key) is not None and n not in halted}
    scored, how = _ranked_scores(m, key, own)
    if halted:
        how = (how + " " if how else "") + (
            "Not ranked, having stopped with an error (said below): " + ", ".join(halted) + ".")
    return Ranking(key, what, how, own, scored, tuple(halted))


def verdict_lines(m: RunSummary | dict) -> list[str]:
    """The verdict as a list of sentences (plain text). ``m``: the run's scores, or a
    metrics.json dictionary (``RunSummary.from_json``)."""
    if isinstance(m, dict):
        m = RunSummary.from_json(m)
    ests = m.estimators
    r = ranking(m)
    key = r.key
    lines = [r.what + (" " + r.how if r.how else "")]
    lag = m.lag_s
    if r.scored:
        own, scored, ranked, best, tied = r.own, r.scored, r.order, r.order[0], r.tied

        def named(n: str) -> str:
            kind = track_kind(n, lag)
            return f"{n} with {_m(scored[n])} m" + ("" if kind == "real time" else f" ({kind})")

        if len(tied) == 1:
            lines.append(f"Best here: {named(best)}.")
        else:
            lines.append(f"Best here, tied (each and the best {TIE_RULE}): "
                         + ", ".join(named(n) for n in tied) + ".")
        ekfs = [n for n in ranked if n.startswith("ekf")]
        live = [n for n in ranked if track_kind(n) == "real time" and n.startswith("smoother")]
        if ekfs and live:
            a, b = ekfs[0], live[0]
            text = ("Real-time head to head, best EKF against the smoother's filtered output: "
                    + _compare(a, scored[a], b, scored[b]))
            if scored is not own and _call(a, scored[a], b, scored[b]) != _call(
                    a, own[a], b, own[b]):
                # over their own spans and stamps the two ATEs average over other moments
                text += (" Over each one's own samples (the table's ATE) the call differs: "
                         + _compare(a, own[a], b, own[b]))
            lines.append(text)
        for n in ranked:
            if track_kind(n) != "real time" and n not in tied:
                lines.append(f"{n} ({track_kind(n, lag)}): {_m(scored[n])} m.")
        own_line = _own_ate_line(own, scored, best, tied)
        if own_line:
            lines.append(own_line)
        if key == ATE:
            lines += _span_lines(m)
            caution = _association_caution(m, own)
            if caution:
                lines.append(caution)
        if key == HOLDOUT and str(m.gps_holdout or "").startswith("every"):
            lines.append(_holdout_caution(m, best))
        elif key == HOLDOUT and m.gps_holdout_interpolation_rmse_m is not None:
            lines.append("For reference, the used fixes interpolated in time across the withheld "
                         "ones (a straight line over an outage), no estimator, score "
                         f"{m.gps_holdout_interpolation_rmse_m:.3f} m.")
    seen: dict = {}
    # an estimator with no estimate has nothing to be consistent about ("stopped early" below)
    live = {n: e for n, e in ests.items() if e.samples != 0}
    owners: dict[str, set] = {}
    for n, e in live.items():
        key = repr(sorted((e.nis or {}).items()))
        if e.nis and key not in {repr(sorted((live[o].nis or {}).items())) for o in owners}:
            owners[n] = set(_units(e.nis)) | _gated_units(m, n)
    heads = {}
    for n, e in live.items():
        text, head = _consistency(n, e, seen, m, owners)
        lines.append(text)
        if head and n in owners:
            heads[n] = head
    caution = _coverage_caution(heads, owners)
    if caution:
        lines.append(caution)
    lines += _gate_lines(m)
    lines += _noise_hints(ests)
    rate = process_noise_line(m)
    if rate:
        lines.append(rate)
    lines += _outage_lines(m)
    lines += _calibration_gaps(m)
    stopped = _stopped_early(m)
    for n, e in ests.items():
        if n in stopped:
            lines.append(f"{n} stopped early: {e.error}.")
        elif e.error:
            lines.append(f"{n}: {e.error}; its estimate ends with the others' (within "
                         f"{SPAN_SLACK_S:g} s), so it is ranked: an interruption is no "
                         "failure of the estimator.")
    if m.input_error:
        lines.append(f"The bag is damaged; these results cover what could be read: "
                     f"{m.input_error}.")
    if m.interrupted:
        lines.append(f"The run was stopped early ({m.interrupted}); these results cover what "
                     "was processed.")
    return lines
