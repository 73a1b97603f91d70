"""``OUTDIR/report.html``: one self-contained page (inline CSS, PNG figures embedded as base64,
no script, nothing fetched) rendered from a run's saved results only (``evaluation.results``).

``render_report(outdir)`` is what ``ddfuse run`` calls after the run (outside the timed part)
and what ``ddfuse report OUTDIR`` calls on its own. The figures are also written to
``OUTDIR/plots/*.png``.
"""

from __future__ import annotations

import base64
import datetime
import html
import math
import re
import time
from collections.abc import Callable
from pathlib import Path

from ddfuse.evaluation import consistency, figure_helper, metrics, plots
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.headline import headline
from ddfuse.evaluation.html_style import CSS as _CSS
from ddfuse.evaluation.html_style import fmt as _fmt
from ddfuse.evaluation.html_style import verdict_cell as _verdict_cell
from ddfuse.evaluation.metrics import OutageDrift
from ddfuse.evaluation.report_figures import (  # noqa: F401 - the report's figures and captions
    captions,
    finish_seconds,
    latency_note,
    make_figures,
    why_no_figure,
)
from ddfuse.evaluation.report_tuning import tuning_section
from ddfuse.evaluation.results import SavedRun, load_run
from ddfuse.evaluation.run_files import REPORT_FILE
from ddfuse.evaluation.scores import DataFacts, EstimatorScores, RunSummary
from ddfuse.evaluation.verdict import (
    CALIBRATION_SIGMAS,
    REJECTED_THROUGHOUT,
    SEES_AFTER,
    TIE_RULE,
    _topic_kind,
    averaged_per_keyframe,
    calibration_title,
    calibration_value,
    final_states,
    gate_rejections,
    outage_drift,
    ranking,
    sensor_samples,
    signed,
    tie,
    track_kind,
    unresolved,
    verdict_lines,
)


def _pct(v: float | None) -> str:
    return _fmt(None if v is None else 100 * v, ".1f")


def _se2_rmse(e: EstimatorScores) -> float | None:
    a = e.ate.se2 if e.ate else None
    return a.position_m.rmse if a and a.position_m else None


def _rpe_rmse(e: EstimatorScores, key: str) -> float | None:
    r = (e.rpe or {}).get(key)
    return r.position_m.rmse if r and r.position_m else None


def _summary_table(m: RunSummary, cfg=None) -> str:
    """One row per track, in the verdict's ranking (``verdict.ranking``; unranked tracks last):
    scores, consistency, speed. ``cfg``: the run's Config, for the
    estimators not run (``not_run``)."""
    lag = m.lag_s
    ests = m.estimators
    common = any(e.ate_common_rmse_m is not None for e in ests.values())
    cols = [  # (header, getter, format, lower-is-better column to mark the best of)
        # the verdict ranks on the common stamps: the best is marked there, not on each
        # track's own ATE (other stamps, another span), which may name another winner
        ("ATE, common stamps [m]", lambda e: e.ate_common_rmse_m, ".3f", True),
        ("ATE RMSE [m]", lambda e: e.ate_rmse_m, ".3f", not common),
        ("ATE max [m]", lambda e: e.ate_max_m, ".3f", True),
        ("ATE SE(2)-aligned RMSE [m]", _se2_rmse, ".3f", True),
        ("heading RMSE [deg]", lambda e: e.yaw_rmse_deg, ".2f", True),
        ("RPE 1 s [m]", lambda e: _rpe_rmse(e, "1s"), ".3f", True),
        ("RPE 10 m [m]", lambda e: _rpe_rmse(e, "10m"), ".3f", True),
        ("GPS hold-out RMSE [m]", lambda e: e.gps_holdout_rmse_m, ".3f", True),
        ("hold-out NEES", lambda e: e.gps_holdout_nees and e.gps_holdout_nees.mean, ".2f",
         False),
        ("NEES mean", lambda e: e.nees_mean, ".2f", False),
        ("runtime [s]", lambda e: e.runtime_s, ".2f", False),
        # no speed for an estimator that never estimated (it only turned measurements away)
        ("RTF [x]", lambda e: e.rtf if e.samples != 0 else None, ".0f", False),
        ("update p50 / p99 [ms]", None, None, False),
    ]
    present = [c for c in cols if c[1] is None or any(c[1](e) is not None for e in ests.values())]
    head = "".join(f"<th>{html.escape(c[0])}</th>" for c in present)
    best = {}
    for h, get, _, lower in present:
        vals = [get(e) for e in ests.values() if get and get(e) is not None]
        if lower and vals:
            best[h] = min(vals)
    rows = []
    offline = [n for n, e in ests.items() if track_kind(n) == "offline" and e.update_ms]
    order = ranking(m).order  # the verdict's ranking, as the terminal's table
    for name in order + [n for n in ests if n not in order]:
        e = ests[name]
        cells = [f'<td class="l"><b>{html.escape(name)}</b></td>',
                 f'<td class="l">{html.escape(track_kind(name, lag))}</td>']
        for h, get, spec, _ in present:
            if get is None:
                u = e.update_ms
                star = " *" if name in offline else ""
                cells.append(f"<td>{_fmt(u and u.p50)} / {_fmt(u and u.p99)}{star}</td>")
                continue
            v = get(e)
            # the verdict's tie rule: the best and every value that ties with it
            cls = ' class="best"' if v is not None and h in best and tie(v, best[h]) \
                and len(ests) > 1 else ""
            text = _fmt(v, spec)
            spacing = _rpe_spacing(e, h)
            if spacing and v is not None:
                text += f" ({spacing})"
            if h == "NEES mean" and v is not None:
                text += f" ({_verdict_cell(e.nees.verdict if e.nees else None)})"
            if h == "hold-out NEES" and v is not None:
                text += f" ({_verdict_cell(e.gps_holdout_nees.verdict)})"
            cells.append(f"<td{cls}>{text}</td>")
        fx = e.final_xy
        cells.append(f"<td>({fx[0]:.2f}, {fx[1]:.2f})</td>" if fx else "<td>–</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    shown = {c[0] for c in present}
    notes = [f"Green bold: the best in its column and every value that ties with it (they "
             f"{TIE_RULE}, the verdict's rule)." if len(ests) > 1 and best else ""]
    if shown & {"ATE RMSE [m]", "ATE max [m]", "heading RMSE [deg]"}:
        notes.append("ATE against the ground truth without alignment (every track in the "
                     "run's local frame)" + ("; SE(2)-aligned: after the rigid motion that "
                                             "minimises it" if "ATE SE(2)-aligned RMSE [m]"
                                             in shown else "") + ".")
    if "ATE, common stamps [m]" in shown:
        notes.append("ATE, common stamps: every track and the truth interpolated at the same "
                     "stamps over the span all tracks share, what the verdict ranks on (no "
                     "best marked on each track's own ATE, whose stamps and span differ).")
    rpe = [w for h, w in (("RPE 1 s [m]", "1 s"), ("RPE 10 m [m]", "10 m of path"))
           if h in shown]
    if rpe:
        notes.append(f"RPE over {' and over '.join(rpe)}, consecutive pairs; in brackets the "
                     "pairs' mean spacing where it differs from the nominal one by over "
                     f"{100 * RPE_SPACING_SLACK:.0f}% (a keyframe track's pairs are keyframes "
                     "apart).")
    if "GPS hold-out RMSE [m]" in shown:
        notes.append("GPS hold-out RMSE: distance to the GPS fixes withheld from the "
                     "estimators.")
    if "hold-out NEES" in shown:
        notes.append("Hold-out NEES: the same distances normalised by the track's position "
                     "covariance plus the fix's own (2 dof), with its verdict: whether the "
                     "estimator's covariance covers its hold-out error.")
    if "NEES mean" in shown:
        notes.append("NEES mean against the truth, with its verdict.")
    if "RTF [x]" in shown:
        notes.append("RTF: seconds of data per second of estimator wall time (decoding "
                     "excluded).")
    if "update p50 / p99 [ms]" in shown:
        notes += [latency_note(n, ests[n]) for n in offline]
    notes.append(f"Final (x, y): the last position in {plots.frame(m)['short']}.")
    skipped = not_run(m, cfg)
    if skipped:
        notes.append("Not run: " + "; ".join(f"{n}: {why}" for n, why in skipped) + ".")
    return (f'<table><tr><th class="l">estimator</th><th class="l">output</th>{head}'
            f"<th>final (x, y) [m]</th></tr>{''.join(rows)}</table>"
            f'<p class="note">{html.escape(" ".join(n for n in notes if n))}</p>')


# An RPE column's pairs whose mean spacing (``RpeScore.mean_delta``) differs from
# the nominal one by more than this share show it.
RPE_SPACING_SLACK = 0.05
_RPE_NOMINAL = {"RPE 1 s [m]": ("1s", 1.0, "s"), "RPE 10 m [m]": ("10m", 10.0, "m")}


def _rpe_spacing(e: EstimatorScores, header: str) -> str:
    """'pairs 1.20 s apart' where the column's pairs are not the nominal distance apart."""
    if header not in _RPE_NOMINAL:
        return ""
    key, nominal, unit = _RPE_NOMINAL[header]
    r = (e.rpe or {}).get(key)
    d = r.mean_delta if r else None
    if d is None or abs(d - nominal) <= RPE_SPACING_SLACK * nominal:
        return ""
    return f"pairs {d:.2f} {unit} apart"


def run_config(run: SavedRun):
    """The run's ``ddfuse.estimation.config.Config``, parsed back from the config text the run saved
    (relative landmark maps resolved against the output directory); None when no text was
    saved or it no longer loads here (an absolute map path that is gone, a key this version
    refuses): ``not_run`` then judges on the sensors metrics.json lists."""
    if not run.config_text:
        return None
    from ddfuse.estimation.config import parse_config_text
    from ddfuse.estimation.errors import ConfigError

    try:
        return parse_config_text(run.config_text, "the run's saved config", run.outdir)
    except ConfigError:
        return None


def not_run(m: RunSummary, cfg=None) -> list[tuple[str, str]]:
    """(name, why) of each estimator of the registry (``evaluation.estimators``) that this run
    does not have: not among the estimators asked for, off by default, or not allowed by the
    config (the registry's own rule, ``EstimatorSpec.allowed``). ``cfg``: the run's Config
    (``run_config``); without it, one rebuilt from the sensors metrics.json lists. Results
    written before metrics.json recorded ``estimators_requested`` are judged on the config
    alone."""
    from ddfuse.estimation.config import Config, RobotConfig, SensorConfig
    from ddfuse.evaluation.estimators import SPECS

    sensors = m.data.sensors if m.data else None
    if cfg is None and sensors:
        cfg = Config(sensors=[SensorConfig(kind=s.kind, topic=s.topic, name=s.name,
                                           use=tuple(s.use)) for s in sensors])
        if cfg.of_kind("wheels"):
            # parse_config refuses wheel speeds without robot.wheel_radius and track_width, so
            # the run's config had them; metrics.json does not record their values (NaN: given,
            # value unknown), and the rules only ask whether they are there (dr's did not)
            cfg.robot = RobotConfig(wheel_radius=math.nan, track_width=math.nan)
    ran = set(m.estimators or {})
    requested = m.estimators_requested
    out = []
    for name, spec in SPECS.items():
        got = ran & set(spec.produces)
        if got:
            # one estimator, several tracks: a track not asked for was computed all the same
            # (--estimators ekf,smoother_lagged runs the smoother, whose filtered track is then
            # left out) and is said, not silently missing
            for track in spec.produces:
                if track not in ran and requested and track not in requested:
                    out.append((track, f"computed for {', '.join(sorted(got))} (the same "
                                       "estimator) but not asked for (--estimators "
                                       f"{','.join(requested)})"))
            continue
        if cfg is not None and not spec.allowed(cfg):
            why = f"needs {spec.needs}, which the config does not have"
        elif not spec.default and name not in (requested or ()):
            why = f"off by default, --estimators {name} runs it; it needs {spec.needs}"
        elif requested and name not in requested:
            why = f"not among the estimators asked for (--estimators {','.join(requested)})"
        elif requested:
            why = "asked for, but it produced no track"
        else:
            why = "not among the estimators asked for (--estimators)"
        out.append((name, why))
    return out


def _nis_table(m: RunSummary) -> str:
    rows = []
    seen: dict[str, str] = {}
    gated = gate_rejections(m)
    for name, e in m.estimators.items():
        nis = e.nis or {}
        key = repr(sorted(nis.items()))
        if not nis:
            continue
        if key in seen:
            rows.append(f'<tr><td class="l"><b>{html.escape(name)}</b></td>'
                        f'<td class="l" colspan="9">same innovations as {seen[key]}</td></tr>')
            continue
        seen[key] = name
        for label, s in nis.items():
            c = s.nis
            band = c.band
            topic, kind = _topic_kind(label, s)
            acc, rej, text = s.accepted, s.rejected, html.escape(label)
            if averaged_per_keyframe(name, kind):
                # one row per keyframe (the samples since the last one averaged): the gate's
                # decisions are per sample, in the estimator's rejected counts
                n = sensor_samples(m, topic, kind)
                rej = (e.rejected or {}).get(f"{topic}: gate", 0)
                # the samples it turned away for other reasons (before it started) are none
                dropped = sum(v for k, v in (e.rejected or {}).items()
                              if k.rpartition(": ")[0] == topic
                              and _reason(k) not in ("gate", _RECOVERY))
                acc = "–" if n is None else max(n - rej - dropped, 0)
                text += (f", averaged per keyframe ({s.accepted + s.rejected} values"
                         + (f" of {n} samples" if n is not None else "") + ")")
            mean = c.mean if s.accepted else None  # nothing accepted: no mean
            g = gated.get(topic)
            verdict = ('<span class="Fail">rejected throughout</span>'
                       if g and name in g.throughout and kind == g.kind
                       else _verdict_cell(c.verdict))
            rows.append(
                f'<tr><td class="l"><b>{html.escape(name)}</b></td>'
                f'<td class="l">{text}</td><td>{_fmt(c.dof, "g")}</td>'
                f"<td>{acc}</td><td>{rej}</td>"
                f"<td>{_fmt(mean)} / {_fmt(c.expected, 'g')}</td>"
                f"<td>{f'[{band[0]:.3g}, {band[1]:.3g}]' if band else '–'}</td>"
                f"<td>{_pct(c.below)}</td><td>{_pct(c.above)}</td>"
                f"<td>{verdict}</td></tr>")
        logged = {_topic_kind(label, s)[0] for label, s in nis.items()}
        for topic, info in gated.items():
            if name in info.by and topic not in logged:
                # gated, but no NIS row (the smoother's heading when every sample was rejected)
                r, tot = info.by[name]
                what = f"{topic} {info.kind}" if info.kind else topic
                rows.append(
                    f'<tr><td class="l"><b>{html.escape(name)}</b></td>'
                    f'<td class="l">{html.escape(what)} (no NIS logged)</td><td>–</td>'
                    f"<td>{'–' if tot is None else tot - r}</td><td>{r}</td>"
                    + "<td>–</td>" * 4 + "<td>"
                    + ('<span class="Fail">rejected throughout</span>'
                       if name in info.throughout else '<span class="na">–</span>')
                    + "</td></tr>")
    if not rows:
        return "<p>No innovations were logged.</p>"
    c = consistency
    return ('<table><tr><th class="l">estimator</th><th class="l">sensor, measurement</th>'
            "<th>dim</th><th>gate accepted</th><th>gate rejected</th><th>mean NIS / expected</th>"
            "<th>95% band</th><th>% below</th><th>% above</th><th>verdict</th></tr>"
            + "".join(rows) + "</table>"
            f'<p class="note">NIS = r<sup>T</sup>S<sup>-1</sup>r of each innovation (EKF) or '
            "measurement residual against the prediction (smoother). The % below and above "
            "count every innovation, those the gate rejected too (as above the band); the "
            "mean counts the accepted ones (a gross outlier the gate rejects would dominate "
            "it; '–' where the gate accepted none). Averaged per keyframe (the smoother's "
            "heading): one value per keyframe, of the samples since the previous one "
            "averaged; its gate counts are of the samples, from the estimator's rejected "
            "counts. Rejected throughout: the gate rejected at least "
            f"{100 * REJECTED_THROUGHOUT:.0f}% of the sensor's samples, so nothing of it was "
            "fused (see the verdict). "
            "A consistent estimator has about 2.5% below and 2.5% above the band and a mean "
            f"equal to the dimension. Pass: at most {100 * c.PASS_OUTSIDE:.0f}% outside and "
            f"mean/expected in [{c.PASS_RATIO[0]:g}, {c.PASS_RATIO[1]:g}]; Warn: at most "
            f"{100 * c.WARN_OUTSIDE:.0f}% and [{c.WARN_RATIO[0]:g}, {c.WARN_RATIO[1]:g}]; "
            f"else Fail; no verdict under {c.MIN_SAMPLES} values. Many above the band: the "
            "filter is over-confident (or the sensor noisier than configured); many below: "
            "pessimistic (noise overstated).</p>")


def _calibration_table(m: RunSummary) -> str:
    """Each estimator's calibration states at the end of the run (``final_state``)."""
    finals = final_states(m)
    if not finals:
        return ""
    labels = list(dict.fromkeys(label for st in finals.values() for label in st))
    rows = []
    for label in labels:
        head = calibration_title(label)
        cells = []
        for st in finals.values():
            s = st.get(label)
            cells.append("–" if s is None or s.value is None
                         else calibration_value(label, s.value, s.sigma))
        rows.append(f'<tr><td class="l">{html.escape(head)}</td>'
                    + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return ("<h2>Calibration at the end of the run</h2><table><tr><th class='l'>state</th>"
            + "".join(f"<th>{html.escape(n)}</th>" for n in finals) + "</tr>" + "".join(rows)
            + "</table><p class='note'>Each estimator's estimate and its own 1-sigma at the "
            "end of the run (the smoother's filtered and lagged outputs meet at the newest "
            "keyframe there). Heading offset: heading reading = heading + offset; gyro bias: "
            "gyro reading = yaw rate + bias; k_v, k_w: true speed and yaw rate over the "
            "odometry's. The estimators read the same data, so values further apart than "
            f"{CALIBRATION_SIGMAS:g} combined sigmas mean at least one is biased (the verdict "
            "names them).</p>")


def _outage_table(m: RunSummary) -> str:
    outs = m.gps_outages or []
    if not outs:
        return ""
    t0 = m.t0
    rows = []
    for k, o in enumerate(outs):
        for name, e in m.estimators.items():
            d = (e.gps_outages or [None] * len(outs))[k]
            drift = outage_drift(d) if d else None
            if track_kind(name) != "real time" and d:
                drift_cell = f'<span class="na">– ({SEES_AFTER})</span>'
            elif drift is not None and math.isfinite(drift):
                drift_cell = signed(100 * drift)
            else:
                drift_cell = _fmt(None)
            rows.append(
                f"<tr><td>{o.t0 - t0:.1f}–{o.t1 - t0:.1f}</td>"
                f'<td class="l">{html.escape(name)}</td><td>{_fmt(d and d.distance_m, ".1f")}'
                f"</td><td>{_outage_error(d, 'start')}</td><td>{_outage_error(d, 'end')}"
                f"</td><td>{_fmt(d and d.error_max_m)}</td><td>{drift_cell}"
                f'</td><td class="l">{html.escape(str(d and d.reference or "–"))}</td></tr>')
    fixes = any(e.gps_outages[0] and e.gps_outages[0].block_s
                for e in m.estimators.values() if e.gps_outages)
    maxnote = (" Max error: the largest distance to a single withheld fix in the outage, that "
               "fix's noise included (start and end are block medians less their noise: "
               "'&lt; X (unresolved)' where that is under the noise X, with no drift)."
               if fixes else " Max error: the largest error against the truth in the outage.")
    return ("<h2>GPS outages</h2><table><tr><th>outage [s]</th><th class='l'>estimator</th>"
            "<th>distance [m]</th><th>error at start [m]</th><th>error at end [m]</th>"
            "<th>max error [m]</th><th>drift [% of distance]</th><th class='l'>against</th>"
            "</tr>" + "".join(rows) + "</table><p class='note'>An outage is a stretch of at "
            "least 5 s (or 5 fix intervals) in which no GPS fix reached the estimators "
            "(withheld with --gps-holdout window:T0:T1, or absent in the bag). Drift = (error at "
            "end − error at start) / distance travelled in it, of the real-time tracks only: a "
            f"lagged or offline track {SEES_AFTER}, so its error there is smoothed, not "
            f"dead-reckoned.{maxnote}</p>")


def _outage_error(d: OutageDrift | None, which: str) -> str:
    """An outage's start or end error cell: '< X (unresolved)' below the fixes' noise X."""
    if d is None:
        return _fmt(None)
    if unresolved(d, which):
        return f"&lt; {d.error_noise_m:.2f} (unresolved)"
    return _fmt(d.error_start_m if which == "start" else d.error_end_m)


def _gps_fixes(m: RunSummary) -> str:
    d = m.data or DataFacts()
    n, held = d.gps_fixes or 0, d.gps_fixes_withheld or 0
    if not n:
        return "none"
    if held:
        return f"{n}, of which {held} withheld ({html.escape(str(m.gps_holdout))})"
    if m.gps_holdout:
        return f"{n}, none withheld ({html.escape(str(m.gps_holdout))} selected none)"
    return f"{n}, none withheld (no --gps-holdout)"


def _heading_offsets(d: DataFacts) -> str:
    """Each compass's offset as the GPS course measures it (``estimation.heading_survey``)."""
    rows = d.heading_offsets
    if not rows:
        return "not measured: no compass, GPS and odometry speed together"
    out = []
    for r in rows:
        med = r.median_rad
        # the windows about the median, so that a range across +-180 deg reads as one
        dev = [(w.offset_rad - med + math.pi) % (2 * math.pi) - math.pi for w in r.windows]
        out.append(f"{html.escape(r.sensor)}: yaw minus GPS course "
                   f"{signed(math.degrees(med), '+.1f')}"
                   f" deg (median of {len(dev)} windows of {r.window_s:.0f} s), windows "
                   f"{signed(math.degrees(med + min(dev)), '+.1f')} to "
                   f"{signed(math.degrees(med + max(dev)), '+.1f')}"
                   " deg")
    return "; ".join(out)


def _warnings(m: RunSummary) -> str:
    w = m.warnings
    if not w:
        return ""
    items = "".join(f"<li>{html.escape(line)}</li>" for line in w)
    # about the config and about the data (a topic mostly dropped, a silent one) alike
    return f"<h2>Warnings</h2><div class='verdict'><ul>{items}</ul></div>"


def _facts(m: RunSummary) -> str:
    d = m.data or DataFacts()
    rows = [("bag", html.escape(str(m.bag))),
            ("duration", f"{_fmt(m.duration_s, '.1f')} s"),
            ("measurements decoded", f"{m.messages} (decoded in {_fmt(m.decode_s, '.2f')} s)"),
            ("path length", f"{_fmt(d.path_length_m, '.1f')} m"
             + (f" (through {metrics.FIX_BLOCK_S:g} s block medians of the GPS fixes)"
                if d.path_length_from == "GPS fixes" else
                f" (from the {d.path_length_from})" if d.path_length_from else "")
             if d.path_length_m is not None
             else "not measured: no ground truth or GPS fixes to measure it on"),
            ("ground truth", f"{html.escape(str(d.ground_truth_topic))}: "
                             f"{d.ground_truth_samples} samples"
             if d.ground_truth_samples else "none"),
            ("GPS fixes", _gps_fixes(m)),
            ("GPS against the odometry", _gps_bursts(d)),
            ("landmarks in the map", str(d.landmarks if d.landmarks is not None else 0)),
            ("heading offset, measured", _heading_offsets(d)),
            ("local frame", html.escape(plots.frame(m)["text"]))]
    rej = m.rejected_messages or {}
    rows.append(("messages dropped as invalid", ", ".join(
        f"{html.escape(k)}: {v}" for k, v in rej.items()) or "none"))
    facts = "".join(f'<tr><td class="l">{k}</td><td class="l">{v}</td></tr>' for k, v in rows)
    srows = "".join(
        f'<tr><td class="l">{html.escape(s.name)}</td><td class="l">{html.escape(s.topic)}'
        f'</td><td class="l">{html.escape(s.kind)}</td><td class="l">'
        f'{html.escape(", ".join(s.use))}</td><td class="l">'
        + html.escape(", ".join(f"{t} {n}" for t, n in s.measurements.items()) or "none")
        + "</td></tr>" for s in d.sensors or [])
    return (f"<table>{facts}</table><table><tr><th class='l'>sensor</th><th class='l'>topic</th>"
            "<th class='l'>kind</th><th class='l'>fused</th><th class='l'>measurements</th></tr>"
            f"{srows}</table>")


def _gps_model(m: RunSummary, cfg) -> str:
    """The run's ``gps.model``, and the config's where the command line set another."""
    if m.gps_model is None:
        return "not recorded"
    given = getattr(getattr(cfg, "gps", None), "model", None)
    if given is not None and given != m.gps_model:
        return f"{m.gps_model} (--gps-model; the config's is {given})"
    return m.gps_model


def _gps_bursts(d: DataFacts) -> str:
    """The GPS topics that disagreed with the odometry in bursts (``scores.GpsBursts``)."""
    if not d.gps_bursts:
        return "none found"
    return "; ".join(f"{html.escape(str(b.topic))}: {b.episodes} bursts ({b.fixes} fixes, up to "
                     f"{_fmt(b.largest_m, '.0f')} m, the longest {_fmt(b.longest_s, '.1f')} s)"
                     for b in d.gps_bursts)


def estimator_options(cfg) -> str:
    """The estimator options in effect (the config's ``ekf`` and ``ekf_igvc`` keys, defaults
    included), e.g. "ekf.rate: event; ekf_igvc.motion: icc"; "–" without a saved config."""
    if cfg is None:
        return "–"
    return f"ekf.rate: {cfg.ekf.rate}; ekf_igvc.motion: {cfg.ekf_igvc.motion}"


def _config(run: SavedRun, cfg) -> str:
    """The Configuration section; ``cfg``: ``run_config(run)``."""
    m = run.summary
    rows = [("estimators", ", ".join(m.estimators)),
            ("not run", "; ".join(f"{n}: {why}" for n, why in not_run(m, cfg)) or "–"),
            ("estimator options", estimator_options(cfg)),
            ("smoother lag", f"{m.lag_s} s"),
            ("GPS model", _gps_model(m, cfg)),
            ("GPS hold-out", str(m.gps_holdout or "none")),
            ("initial pose", str(m.initial_pose or "each estimator's default")),
            ("config file", str(m.config or "–"))]
    table = "".join(f'<tr><td class="l">{k}</td><td class="l">{html.escape(v)}</td></tr>'
                    for k, v in rows)
    text = html.escape(run.config_text) if run.config_text else "(no config file text saved)"
    t0 = m.data.t0 if m.data else None
    events = "".join(
        f"<details><summary>{html.escape(n)}: {event_summary(e)}</summary><pre>"
        + html.escape("\n".join([relative_event(x, t0) for x in e.events or []]
                                 + _rejection_lines(e.rejected or {})))
        + "</pre></details>"
        for n, e in m.estimators.items())
    when = (" (t: seconds since the first measurement, as in the figures)" if t0 is not None
            else " (t: the bag's time stamps)")
    return (f"<table>{table}</table><pre>{text}</pre><h3>Estimator events{when}</h3>"
            f"{events}")


# The estimators count a gate lock-out recovery under this reason in their ``log.rejected``,
# but the measurement that triggers one is fused (its covariance widened first) and the gating
# table counts it as accepted: it is no rejection.
_RECOVERY = "lockout_recovery"


def _reason(key: str) -> str:
    """The reason of a metrics.json ``rejected`` key "sensor: reason"."""
    return key.rsplit(": ", 1)[-1]


def event_summary(e: EstimatorScores) -> str:
    """The events header of one estimator's scores: its events, the measurements
    the gate rejected (the gating table's "gate rejected", summed over its sensors), those
    dropped for other reasons, and its gate lock-out recoveries (each fused a measurement)."""
    rej = e.rejected or {}
    gate = sum(v for k, v in rej.items() if _reason(k) == "gate")
    recovered = sum(v for k, v in rej.items() if _reason(k) == _RECOVERY)
    other = sum(rej.values()) - gate - recovered
    n = len(e.events or [])
    total = n if e.events_total is None else e.events_total
    parts = [f"first {n} of {total} events" if total > n
             else f"{n} event{'' if n == 1 else 's'}"]
    if gate:
        parts.append(f"{gate} rejected by the gate")
    if other:
        parts.append(f"{other} dropped for other reasons")
    if recovered:
        parts.append(f"{recovered} lock-out recover{'y' if recovered == 1 else 'ies'} "
                     "(measurement accepted)")
    return ", ".join(parts)


def _rejection_lines(rej: dict) -> list[str]:
    return [f"lock-out recovery, measurement accepted {k.rsplit(': ', 1)[0]}: {v}"
            if _reason(k) == _RECOVERY else f"rejected {k}: {v}" for k, v in rej.items()]


_EVENT_T = re.compile(r"^t=(-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?):")


def relative_event(line: str, t0: float | None) -> str:
    """An estimator event "t=STAMP: text" with its bag stamp made seconds since ``t0`` (the
    first measurement); other lines, or without ``t0``, unchanged."""
    hit = _EVENT_T.match(line)
    if hit is None or t0 is None:
        return line
    # the stamp was written to 1 ms: the first measurement's can land a fraction before t0
    dt = round(float(hit.group(1)) - t0, 3) + 0.0  # + 0.0: no "-0.000"
    return f"t={dt:.3f} s:{line[hit.end():]}"


def _figure(png: bytes, caption: str, alt: str) -> str:
    b64 = base64.b64encode(png).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _no_figure(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def build_html(run: SavedRun, figures: list[tuple[str, bytes | None, str]],
               render_s: float) -> str:
    """The report page for ``run`` with its rendered ``figures``."""
    m = run.summary
    cfg = run_config(run)  # parsed once: the summary table and the configuration use it
    bag = Path(str(m.bag)).name
    verdict = "".join(f"<li>{html.escape(line)}</li>" for line in verdict_lines(m))
    # the winner's line in bold: the first thing read
    top = "".join(f"<p><b>{html.escape(line)}</b></p>" if k == 0 else
                  f"<p>{html.escape(line)}</p>" for k, line in enumerate(headline(m).lines()))
    figs = "".join(_figure(png, cap, name) if png is not None else _no_figure(cap)
                   for name, png, cap in figures)
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    t0 = m.data.t0 if m.data else None
    if t0 is None:
        times = ""
    else:
        when = (" = " + datetime.datetime.fromtimestamp(t0, datetime.timezone.utc).strftime(
            "%Y-%m-%d %H:%M:%S UTC") if t0 > 1e8 else "")
        times = (f" Times are seconds since the first measurement (bag stamp {t0:.3f} s{when}),"
                 " in the tables, the events and the figures alike.")
    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>ddfuse report: {html.escape(bag)}</title><style>{_CSS}</style></head><body>"
        f"<h1>ddfuse report: {html.escape(bag)}</h1>"
        f"<div class='headline' id='headline'>{top}</div>"
        f"<p class='sub'>{_fmt(m.duration_s, '.1f')} s of data, "
        f"{len(m.estimators)} estimator outputs. Rendered {stamp} from the results in "
        f"{html.escape(str(run.outdir))} (figures in {render_s:.1f} s).{times}</p>"
        "<details class='verdict'><summary>The verdict in full: the method, each "
        "estimator's consistency per sensor, caveats</summary>"
        f"<ul>{verdict}</ul></details>"
        f"{_warnings(m)}"
        f"<h2>Summary</h2>{_summary_table(m, cfg)}"
        f"{tuning_section(run.outdir, m) if run.outdir else ''}"
        f"<h2>Consistency and gating per sensor</h2>{_nis_table(m)}"
        f"{_calibration_table(m)}"
        f"{_outage_table(m)}"
        f"<h2>Figures</h2>{figs}"
        f"<h2>Data</h2>{_facts(m)}"
        f"<h2>Configuration</h2>{_config(run, cfg)}"
        "</body></html>\n")


def render_report(outdir: str | Path, progress: Callable[[float], None] | None = None,
                  helper: figure_helper.Helper | None = None) -> Path:
    """Render ``outdir``/report.html from the saved results in ``outdir``; returns its path.
    Raises ``results.ResultsError`` (one line, naming the path) when there are none.

    Part of the figures is drawn in a second process (``figure_helper``): ``helper``, one the
    caller started for ``outdir`` before importing this module, else one started here where
    it is worth it (``figure_helper.wanted``). It is ended before this returns."""
    own = helper is None
    if own:
        helper = figure_helper.start(Path(outdir), figure_helper.LATE_START_S)
    try:
        run = load_run(outdir)
        t_a = time.perf_counter()
        figures = make_figures(run, progress, helper)
        page = build_html(run, figures, time.perf_counter() - t_a)
        return write_text(run.outdir / REPORT_FILE, page)
    finally:
        if helper is not None:
            helper.close()
