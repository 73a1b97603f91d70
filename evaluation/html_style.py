"""The look shared by ddfuse's HTML pages (the run's report.html, the fleet's fleet.html): one
inline style sheet and the cell formats, so that both pages read alike and neither fetches
anything. Text in, text out: no numpy, no matplotlib."""

from __future__ import annotations

import math

__all__ = ["CSS", "fmt", "verdict_cell"]

CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1400px;
box-sizing:border-box;margin:1.5em auto;padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;
margin-top:1.8em}.sub{color:#666;margin-top:0}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em}
th,td{border:1px solid #ddd;padding:.25em .45em;text-align:right;white-space:nowrap}
th{background:#f3f3f3;white-space:normal;max-width:7.5em;vertical-align:bottom}
td.l,th.l{text-align:left}td.l{white-space:normal;min-width:6em}
tr:nth-child(even) td{background:#fafafa}
.verdict{background:#f4f8ff;border-left:4px solid #3b73d1;padding:.5em 1em;margin:1em 0}
.verdict li{margin:.25em 0}.verdict summary{cursor:pointer;font-weight:bold}
.headline{background:#eef6ee;border-left:4px solid #0a6b2c;padding:.3em 1em;margin:.6em 0;
font-size:1.05em}.headline p{margin:.35em 0}.best{font-weight:bold;color:#0a6b2c}
.Pass{color:#0a6b2c;font-weight:bold}.Warn{color:#b36b00;font-weight:bold}
.Fail{color:#c0211b;font-weight:bold}.na{color:#999}
figure{margin:1em 0}figure img{width:100%;height:auto;border:1px solid #eee}
figcaption{color:#555;font-size:.9em;max-width:1100px}
pre{background:#f6f6f6;padding:.7em;overflow-x:auto;font-size:.85em}
.note{color:#555;font-size:.88em;max-width:1100px}
"""


def fmt(v, spec: str = ".3f") -> str:
    """``v`` formatted with ``spec``; a grey dash for None or a non-finite value (HTML)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return '<span class="na">–</span>'
    return format(v, spec)


def verdict_cell(v: str | None) -> str:
    """A Pass / Warn / Fail verdict in its colour (HTML); a grey dash for None."""
    return f'<span class="{v}">{v}</span>' if v else '<span class="na">–</span>'
