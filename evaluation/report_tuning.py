"""The report's section "What tuning changed", for an output directory of ``ddfuse run --tune``
(``evaluation.run_tuned``): each tuned value, config before and tuned after, with its standard
error and status; each estimator's score, NEES and NIS verdict per sensor with the config as
given (OUT/shipped/metrics.json) and tuned (this directory's), side by side; a sentence on
whether the ranking changed. Also the one line ``ddfuse run --tune`` prints on the terminal
(``change_line``). Pure: saved results in, HTML or text out.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

from ddfuse.evaluation.html_style import fmt
from ddfuse.evaluation.run_files import INCOMPLETE, METRICS_FILE
from ddfuse.evaluation.scores import RunSummary
from ddfuse.evaluation.tuning_files import SHIPPED_DIR, TUNED_CONFIG, read_tuning
from ddfuse.evaluation.verdict import HOLDOUT, _ranked_scores, _score

__all__ = ["change_line", "scores", "shipped_summary", "tuning_section"]

_WRAP = ' style="white-space:normal;max-width:40em"'  # the long reasons wrap in their cell


def _n(v, spec: str = ".3g") -> str:
    return fmt(v, spec)


def _v(verdict: str | None) -> str:
    return f'<span class="{verdict}">{verdict}</span>' if verdict else ""


def shipped_summary(outdir: Path) -> tuple[RunSummary | None, str | None]:
    """The given config's run in ``outdir``/shipped: (its RunSummary, None), or (None, why
    there is none)."""
    d = Path(outdir) / SHIPPED_DIR
    if (d / INCOMPLETE).exists():
        return None, f"its results in {SHIPPED_DIR}/ are incomplete (the run was stopped)"
    try:
        m = RunSummary.from_json(json.loads((d / METRICS_FILE).read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None, f"{SHIPPED_DIR}/{METRICS_FILE} is missing or cannot be read"
    if m.interrupted:
        return None, (f"was stopped early ({m.interrupted}): its results in {SHIPPED_DIR}/ "
                      "cover part of the bag only")
    return m, None


def scores(m: RunSummary) -> tuple[str | None, dict[str, float]]:
    """What the verdict ranks ``m``'s estimators on (``verdict``: ATE on the common stamps,
    else the GPS hold-out RMSE) as (column label, {estimator: score, m}); (None, {}) when
    there is no score. Estimators that stopped with an error are left out."""
    key, _ = _score(m)
    if key is None:
        return None, {}
    own = {n: getattr(e, key) for n, e in m.estimators.items()
           if getattr(e, key) is not None and not e.error}
    ranked, common = _ranked_scores(m, key, own)
    label = ("GPS hold-out RMSE" if key == HOLDOUT else
             "ATE, common stamps" if common else "ATE RMSE")
    return label, ranked


def _nis_verdicts(e) -> dict[str, tuple[float | None, str | None]]:
    return {label: (s.nis.ratio, s.nis.verdict) for label, s in (e.nis or {}).items()}


def _was(v: dict) -> str:
    if v.get("before") is not None:
        return _n(v["before"])
    what = "the messages' covariance" if v.get("source") == "messages" else "default"
    return f'<span class="na">({what} {_n(v.get("start"))})</span>'


def _values_table(t: dict) -> str:
    rows = []
    for v in t.get("values") or []:
        se = v.get("se_log")
        pm = _n(100 * se, ".0f") if se is not None and v.get("status") != "not informed" else ""
        status = html.escape(v.get("status") or "")
        cls = ' class="best"' if status == "tuned" else ""
        rows.append(f'<tr><td class="l">{html.escape(v.get("key", ""))} '
                    f'[{html.escape(v.get("unit", ""))}]</td><td>{_was(v)}</td>'
                    f'<td{cls}>{_n(v.get("after")) if v.get("status") != "not informed" else "–"}'
                    f'</td><td>{pm}</td><td class="l">{status}</td>'
                    f'<td class="l"{_WRAP}>{html.escape(v.get("reason") or "")}</td></tr>')
    if not rows:
        return ""
    pairs = t.get("pairs") or []
    note = ("Pairs the data do not tell apart (correlation of their estimates beyond 0.9): "
            + "; ".join(f"{p['a']} / {p['b']} ({p['correlation']:+.2f})" for p in pairs) + "."
            if pairs else "No pair of tuned values is beyond 0.9 in correlation: the data tell "
            "them apart.")
    return ("<table><tr><th class='l'>value</th><th>config</th><th>tuned</th><th>+- [%]</th>"
            f"<th class='l'>status</th><th class='l'>why</th></tr>{''.join(rows)}</table>"
            f'<p class="note">+-: the standard error of the tuned value, relative (from the '
            f"Fisher information of the innovations). A value in brackets: the config states "
            f"none; what the estimators used instead. {html.escape(note)}</p>")


def _breakable(topic: str) -> str:
    """``topic`` escaped, free to break after a slash or an underscore: unbroken, a long one
    (/husky_velocity_controller/odom) ran over its neighbours' headers."""
    return html.escape(topic).replace("/", "/<wbr>").replace("_", "_<wbr>")


def _comparison_table(shipped: RunSummary, tuned: RunSummary) -> str:
    label, s_scores = scores(shipped)
    _, t_scores = scores(tuned)
    names = [n for n in tuned.estimators if n in shipped.estimators]
    sensors: list[str] = []
    for n in names:
        for e in (shipped.estimators[n], tuned.estimators[n]):
            sensors += [k for k in (e.nis or {}) if k not in sensors]
    nees = any(r.estimators[n].nees_mean is not None for r in (shipped, tuned) for n in names)
    head = (f"<th>{html.escape(label)} [m], given</th><th>tuned</th>" if label else "")
    head += "<th>NEES mean, given</th><th>tuned</th>" if nees else ""
    held = any(r.estimators[n].gps_holdout_nees is not None for r in (shipped, tuned)
               for n in names)
    head += "<th>hold-out NEES, given</th><th>tuned</th>" if held else ""
    head += "".join(f"<th>NIS {_breakable(k)}: given → tuned</th>" for k in sensors)
    best_t = min(t_scores.values()) if t_scores else None
    rows = []
    for n in names:
        a, b = shipped.estimators[n], tuned.estimators[n]
        cells = [f'<td class="l"><b>{html.escape(n)}</b></td>']
        if label:
            cls = ' class="best"' if best_t is not None and t_scores.get(n) == best_t else ""
            cells += [f"<td>{_n(s_scores.get(n), '.3f')}</td>",
                      f"<td{cls}>{_n(t_scores.get(n), '.3f')}</td>"]
        for e in (a, b) if nees else ():
            cells.append(f"<td>{_n(e.nees_mean, '.2f')} "
                         f"{_v(e.nees.verdict if e.nees else None)}</td>")
        for e in (a, b) if held else ():
            h = e.gps_holdout_nees
            cells.append(f"<td>{_n(h and h.mean, '.2f')} {_v(h.verdict if h else None)}</td>")
        na, nb = _nis_verdicts(a), _nis_verdicts(b)
        for k in sensors:
            if k not in na and k not in nb:
                cells.append("<td></td>")
                continue
            ra, va = na.get(k, (None, None))
            rb, vb = nb.get(k, (None, None))
            # two lines per cell: one line per sensor would not fit a 1400 px window
            cells.append(f"<td>{_n(ra, '.3f')} {_v(va)}<br>→ {_n(rb, '.3f')} {_v(vb)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    note = ("NIS: mean over expected per sensor (1 is consistent) with its verdict. "
            + ("NEES mean against the truth with its verdict (expected: the pose's dimension). "
               if nees else "No NEES: the bag has no ground truth. ")
            + ("Hold-out NEES: the withheld fixes' distance normalised by the track's position "
               "covariance plus the fix's own (expected 2): whether the covariance covers the "
               "hold-out error, the score beside it being how large that error is. " if held
               else "")
            + ("Green bold: the best score with the tuned config." if label else
               "No score: neither ground truth nor withheld GPS fixes."))
    return (f"<table><tr><th class='l'>estimator</th>{head}</tr>{''.join(rows)}</table>"
            f'<p class="note">{html.escape(note)}</p>')


def _order(sc: dict[str, float]) -> list[str]:
    return sorted(sc, key=sc.get)


def ranking_sentence(shipped: RunSummary, tuned: RunSummary) -> str:
    """Whether, and for which estimators, the ranking on the verdict's score changed."""
    label, s = scores(shipped)
    _, t = scores(tuned)
    common = [n for n in t if n in s]
    if not label or len(common) < 2:
        return ("No ranking to compare: fewer than two estimators have a score (ground truth "
                "or withheld GPS fixes) with both configs.")
    a = _order({n: s[n] for n in common})
    b = _order({n: t[n] for n in common})
    if a == b:
        return (f"The ranking on {label} is the same with both configs: "
                f"{', '.join(a)} (best first).")
    moved = [f"{n} {a.index(n) + 1} → {b.index(n) + 1}" for n in b if a.index(n) != b.index(n)]
    best = (f" The best is now {b[0]} ({t[b[0]]:.3f} m), was {a[0]} ({s[a[0]]:.3f} m)."
            if a[0] != b[0] else f" The best is {b[0]} with both.")
    return (f"The ranking on {label} changed (rank given → tuned): {'; '.join(moved)}."
            + best)


def _intro(t: dict) -> str:
    held = (f", the GPS fixes of --gps-holdout {t['gps_holdout']} kept out of the fit"
            if t.get("gps_holdout") else "")
    n = sum(1 for v in t.get("values") or [] if v.get("status") != "not informed")
    return (f"This run used the config tuned on this bag ({TUNED_CONFIG}: {n} of "
            f"{len(t.get('values') or [])} values set by maximum likelihood of the "
            f"{t.get('estimator')} EKF's innovations{held}; {t.get('estimator_runs')} "
            f"estimator runs, {_n(t.get('wall_s'), '.1f')} s; docs/design/tuning.md). The "
            f"config as given ({t.get('config')}) ran too, on the same estimators; its results "
            f"and report are in {SHIPPED_DIR}/. Every estimator read the same values, one "
            "config each time.")


def tuning_section(outdir: str | Path, m: RunSummary) -> str:
    """The section's HTML for the run ``m`` saved in ``outdir``; '' when ``outdir`` has no
    tuning.json or one written for another run in it (its ``run_config`` is not the config
    ``m`` ran with)."""
    t = read_tuning(outdir)
    if t is None or t.get("run_config") != m.config:
        return ""
    parts = ["<h2>What tuning changed</h2>"]
    if not t.get("applied"):
        parts.append('<div class="verdict"><ul><li>Nothing: the tuned values were not '
                     f"applied: {html.escape(str(t.get('why_not')))}. The results on this page "
                     "are the config's as given.</li></ul></div>")
        return "".join(parts) + _values_table(t)
    shipped, why = shipped_summary(outdir)
    lines = [_intro(t)]
    if shipped is not None:
        lines.append(ranking_sentence(shipped, m))
    else:
        lines.append(f"No side-by-side scores: the given config's run {why}.")
    parts.append('<div class="verdict"><ul>'
                 + "".join(f"<li>{html.escape(x)}</li>" for x in lines) + "</ul></div>")
    parts.append(_values_table(t))
    if shipped is not None:
        parts.append(_comparison_table(shipped, m))
    return "".join(parts)


def _fail_count(e) -> int:
    return sum(1 for s in (e.nis or {}).values() if s.nis.verdict == "Fail")


def change_line(t: dict, tuned: RunSummary, shipped: RunSummary | None) -> str:
    """One line for the terminal: what tuning changed for the best estimator of the tuned run
    (its score, NEES, hold-out NEES and count of NIS Fail, given → tuned), or why nothing was
    applied."""
    if not t.get("applied"):
        return f"tuning changed nothing: {t.get('why_not')}; the results are the config's"
    n = sum(1 for v in t.get("values") or [] if v.get("status") != "not informed")
    what = f"{n} value{'s' if n != 1 else ''} tuned ({TUNED_CONFIG}, tuning.json)"
    if shipped is None:
        return f"tuning: {what}; the given config's run did not finish"
    label, t_sc = scores(tuned)
    _, s_sc = scores(shipped)
    names = [k for k in tuned.estimators if k in shipped.estimators]
    if label and t_sc:
        best = min(t_sc, key=t_sc.get)
    elif names:
        best = names[0]
    else:
        return f"tuning: {what}; no estimator to compare"
    a, b = shipped.estimators.get(best), tuned.estimators[best]
    parts = []
    if label and best in t_sc:
        parts.append(f"{label} {_plain(s_sc.get(best), '.3f')} -> {_plain(t_sc[best], '.3f')} m")
    if b.nees_mean is not None or (a is not None and a.nees_mean is not None):
        parts.append(f"NEES {_plain(a.nees_mean if a else None, '.2f')} -> "
                     f"{_plain(b.nees_mean, '.2f')}")
    ha, hb = a.gps_holdout_nees if a else None, b.gps_holdout_nees
    if ha is not None or hb is not None:
        parts.append("hold-out NEES " + " -> ".join(c.brief() if c else "-" for c in (ha, hb)))
    parts.append(f"NIS Fail on {_fail_count(a) if a else '-'} -> {_fail_count(b)} of "
                 f"{len(b.nis or {})} sensors")
    return f"tuning: {what}; for {best} (best with it): " + ", ".join(parts)


def _plain(v, spec: str) -> str:
    bad = v is None or (isinstance(v, float) and not math.isfinite(v))
    return "-" if bad else format(v, spec)
