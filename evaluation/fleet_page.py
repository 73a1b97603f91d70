"""``OUTDIR/fleet.html``: a fleet summary (``fleet.json``'s content, ``evaluation.fleet``) as one
self-contained page: inline style (``evaluation.html_style``, the report's), no script, nothing
fetched; links to each bag's own report.html, relative, so the folder can be moved whole.

``fleet_html(doc)`` is pure (the dict in, the page's text out); ``write_fleet_page(doc,
outdir)`` writes it. What it shows: across bags how often and by how much each estimator won,
per bag its ranking and winner (or its one-line error), and per bag and estimator its score,
NEES and NIS verdicts, real-time factor and error.
"""

from __future__ import annotations

import datetime
import html
from pathlib import Path

from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.html_style import CSS, fmt, verdict_cell

__all__ = ["FLEET_HTML", "fleet_html", "write_fleet_page"]

FLEET_HTML = "fleet.html"
_SCORED_ON = {"ate": "ATE", "holdout": "GPS hold-out"}
_EXTRA_CSS = """
td.err{color:#c0211b;max-width:40em;white-space:normal;text-align:left}
td.rank{max-width:24em}tr.failed td{background:#fff4f3}
"""


def _e(v) -> str:
    return html.escape(str(v))


def _scored_on(kind: str | None) -> str:
    return _e(_SCORED_ON.get(kind, kind)) if kind else '<span class="na">–</span>'


def _bag_cell(b: dict) -> str:
    name = _e(b["bag"])
    link = f'<a href="{html.escape(b["report"], quote=True)}">{name}</a>' if b.get("report") \
        else name
    return f'<td class="l" title="{html.escape(str(b.get("path")), quote=True)}">{link}</td>'


def _win_lines(doc: dict) -> str:
    """One line per estimator that was scored: wins out of the bags scored, mean and largest
    margin; then the bags without a winner."""
    lines = []
    for name, s in doc["estimators"].items():
        won = f"won {s['wins']} of the {s['scored']} bags it was scored on outright"
        if s["wins"]:
            won += (f", by {fmt(s['mean_margin_m'])} m ({fmt(s['mean_margin_pct'], '.1f')} %) "
                    f"on average over the runner-up, at most {fmt(s['max_margin_m'])} m")
        if s["tied_first"]:
            won += f"; tied for first on {s['tied_first']}"
        lines.append(f"<li><b>{_e(name)}</b> {won}</li>")
    ties = sum(1 for b in doc["bags"] if not b["error"] and not b["winner"] and b["tied"])
    if ties:
        lines.append(f"<li>{ties} bag{'s' if ties > 1 else ''} without an outright winner "
                     "(the best two tie)</li>")
    if doc["bags_failed"]:
        lines.append(f"<li>{doc['bags_failed']} of {doc['bags_total']} bags failed: their "
                     "rows below say why</li>")
    return "".join(lines) or "<li>no bag was scored</li>"


def _standings_table(doc: dict) -> str:
    head = ("<tr><th class='l'>estimator</th><th>bags scored</th><th>wins</th>"
            "<th>tied for first</th><th>mean margin [m]</th><th>largest margin [m]</th>"
            "<th>mean margin [%]</th></tr>")
    rows = "".join(
        f"<tr><td class='l'><b>{_e(n)}</b></td><td>{s['scored']}</td><td>{s['wins']}</td>"
        f"<td>{s['tied_first']}</td><td>{fmt(s['mean_margin_m'])}</td>"
        f"<td>{fmt(s['max_margin_m'])}</td><td>{fmt(s['mean_margin_pct'], '.1f')}</td></tr>"
        for n, s in doc["estimators"].items())
    return f"<table id='standings'>{head}{rows}</table>"


def _bags_table(doc: dict) -> str:
    head = ("<tr><th class='l'>bag</th><th class='l'>scored on</th><th class='l'>winner</th>"
            "<th>margin [m]</th><th>margin [%]</th><th class='l'>ranking, best first</th>"
            "<th>wall [s]</th></tr>")
    rows = []
    for b in doc["bags"]:
        if b["error"]:
            rows.append(f"<tr class='failed'>{_bag_cell(b)}<td class='err' colspan='6'>"
                        f"ERROR: {_e(b['error'])}</td></tr>")
            continue
        winner = (f"<span class='best'>{_e(b['winner'])}</span>" if b["winner"]
                  else "tie: " + _e(", ".join(b["tied"])) if b["tied"]
                  else '<span class="na">no score</span>')
        rows.append(f"<tr>{_bag_cell(b)}<td class='l'>{_scored_on(b['score'])}</td>"
                    f"<td class='l'>{winner}</td><td>{fmt(b['margin_m'])}</td>"
                    f"<td>{fmt(b['margin_pct'], '.1f')}</td>"
                    f"<td class='l rank'>{_e(', '.join(b['ranking']))}</td>"
                    f"<td>{fmt(b['wall_s'], '.1f')}</td></tr>")
    return f"<table id='bags'>{head}{''.join(rows)}</table>"


def _nis_cell(verdicts: dict) -> str:
    if not verdicts:
        return '<span class="na">–</span>'
    return ", ".join(f"{_e(k)} {verdict_cell(v)}" for k, v in verdicts.items())


def _held(r: dict) -> str:
    """The row's hold-out NEES with its verdict (rows of fleets written before it: –)."""
    v = r.get("gps_holdout_nees_mean")
    if v is None:
        return '<span class="na">–</span>'
    return f"{fmt(v, '.2f')} {verdict_cell(r.get('gps_holdout_nees_verdict'))}"


def _rows_table(doc: dict) -> str:
    head = ("<tr><th class='l'>bag</th><th class='l'>estimator</th><th class='l'>scored on</th>"
            "<th>score [m]</th><th>ATE RMSE [m]</th><th>GPS hold-out RMSE [m]</th>"
            "<th>hold-out NEES</th><th>NEES mean</th><th>NEES</th>"
            "<th class='l'>NIS per sensor</th><th>RTF [x]</th><th class='l'>error</th></tr>")
    bags = {b["bag"]: b for b in doc["bags"]}
    rows = []
    for r in doc["rows"]:
        b = bags[r["bag"]]
        if r["estimator"] is None:
            rows.append(f"<tr class='failed'>{_bag_cell(b)}<td class='err' colspan='11'>"
                        f"ERROR: {_e(r['error'])}</td></tr>")
            continue
        best = " class='best'" if r["estimator"] == b["winner"] or (
            r["estimator"] in b["tied"]) else ""
        err = f"<td class='err'>{_e(r['error'])}</td>" if r["error"] else "<td></td>"
        rows.append(f"<tr>{_bag_cell(b)}<td class='l'>{_e(r['estimator'])}</td>"
                    f"<td class='l'>{_scored_on(r['score'])}</td>"
                    f"<td{best}>{fmt(r['score_m'])}</td><td>{fmt(r['ate_rmse_m'])}</td>"
                    f"<td>{fmt(r['gps_holdout_rmse_m'])}</td>"
                    f"<td>{_held(r)}</td>"
                    f"<td>{fmt(r['nees_mean'], '.2f')}</td>"
                    f"<td>{verdict_cell(r['nees_verdict'])}</td>"
                    f"<td class='l'>{_nis_cell(r['nis_verdicts'])}</td>"
                    f"<td>{fmt(r['rtf'], '.0f')}</td>{err}</tr>")
    return f"<table id='rows'>{head}{''.join(rows)}</table>"


def fleet_html(doc: dict, stamp: str | None = None) -> str:
    """The page of a fleet summary ``doc`` (fleet.json's content); ``stamp``: when it was
    rendered (default: now, local time)."""
    from ddfuse.evaluation.verdict import TIE_RULE

    stamp = stamp or datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    n = doc["bags_total"]
    sub = (f"{doc['bags_ran']} of {n} bags ran, {doc['bags_failed']} failed, on "
           f"{_e(doc['engine'])}, in {fmt(doc['wall_s'], '.1f')} s. Rendered {stamp}.")
    note = ("Each bag is ranked on what its own report ranks on: position ATE (m, no "
            "alignment, each track's own stamps) where any estimator has one, else the RMS "
            "distance to the GPS fixes withheld from the estimators; lower is better. A bag "
            f"has an outright winner when its best two scores do not tie (they {TIE_RULE}, the "
            "report's rule); the margin is the runner-up's score minus the winner's, in m and "
            "in % of the runner-up's.")
    return (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>ddfuse fleet: {n} bags</title><style>{CSS}{_EXTRA_CSS}</style></head><body>"
        f"<h1>ddfuse fleet: {n} bags</h1><p class='sub'>{sub}</p>"
        f"<h2>Across bags</h2><div class='verdict'><ul>{_win_lines(doc)}</ul></div>"
        f"{_standings_table(doc)}<p class='note'>{_e(note)}</p>"
        f"<h2>Per bag</h2>{_bags_table(doc)}"
        "<p class='note'>A bag's name links to its own report (OUTDIR/&lt;bag&gt;/report.html)"
        " where one was rendered.</p>"
        f"<h2>Per bag and estimator</h2>{_rows_table(doc)}"
        "<p class='note'>Green bold: the bag's winner, or the estimators tied for first. NEES "
        "against the truth and NIS per sensor with their verdicts; RTF: seconds of data per "
        "second of estimator wall time.</p>"
        "</body></html>\n")


def write_fleet_page(doc: dict, outdir: str | Path) -> Path:
    """``outdir``/fleet.html from ``doc``; returns its path."""
    return write_text(Path(outdir) / FLEET_HTML, fleet_html(doc))
