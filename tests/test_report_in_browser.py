"""The report as a reader sees it: data/sample_husky.bag's report opened in headless Chromium
at 1 400 x 900 px (``tests/browser.py``), laid out, its figures decoded."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from browser import Page

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def sample_report(tmp_path_factory) -> Path:
    from ddfuse.evaluation import cli

    out = tmp_path_factory.mktemp("browser") / "out"
    assert cli.main(["run", str(ROOT / "data" / "sample_husky.bag"), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def page(sample_report):
    with Page(sample_report / "report.html", width=1400, height=900) as p:
        yield p


def test_nothing_is_wider_than_a_1400_px_window(page):
    width, scroll = page.eval("[window.innerWidth, document.documentElement.scrollWidth]")
    assert width == 1400
    assert scroll <= width, f"the page scrolls sideways: {scroll} px wide"
    wide = page.eval("[...document.querySelectorAll('table, figure, pre')]"
                     ".filter(e => e.getBoundingClientRect().right > window.innerWidth)"
                     ".map(e => e.tagName + ': ' + e.innerText.slice(0, 60))")
    assert not wide, wide


def test_every_figure_is_drawn_and_nothing_comes_from_the_network(page):
    imgs = page.eval("[...document.images].map(i => [i.complete, i.naturalWidth, "
                     "i.getBoundingClientRect().width, i.src.slice(0, 22)])")
    assert len(imgs) >= 3
    for complete, natural, shown, src in imgs:
        assert complete and natural > 0, (src, natural)
        assert shown > 600, f"a figure drawn only {shown:.0f} px wide"
        assert src.startswith("data:image/"), src
    fetched = page.eval("performance.getEntriesByType('resource').map(e => e.name)")
    assert not [u for u in fetched if not u.startswith("data:")], fetched


def test_the_reader_sees_the_winner_and_margin_first(page, sample_report):
    """The headline is the first block under the title, wholly in the first 1400 x 900 screen,
    and names the winner and its margin on the score metrics.json has."""
    m = json.loads((sample_report / "metrics.json").read_text())
    scores = {n: e["ate_common_rmse_m"] for n, e in m["estimators"].items()
              if e.get("ate_common_rmse_m") is not None}
    order = sorted(scores, key=scores.get)
    box = page.eval("(() => { const h = document.getElementById('headline'); "
                    "const r = h.getBoundingClientRect(); return [r.top, r.bottom, h.innerText,"
                    " h.previousElementSibling.tagName] })()")
    top, bottom, text, before = box
    assert before == "H1" and top > 0 and bottom < 900, box
    first = text.splitlines()[0]
    best = re.match(r"Best: (\w+)[^,]*, ATE on common stamps ([0-9.]+) m", first)
    assert best, first
    assert best.group(1) == order[0]
    assert float(best.group(2)) == pytest.approx(scores[order[0]], abs=5e-4)
    nxt = next(n for n in order if scores[n] - scores[order[0]] > 0.05 * scores[n])
    gap = re.search(r"; ([0-9.]+) m \(\d+%\) lower than the next, (\w+)", first)
    assert gap and gap.group(2) == nxt
    assert float(gap.group(1)) == pytest.approx(scores[nxt] - scores[order[0]], abs=1e-3)
    # the full verdict is there, folded: a click away
    assert page.eval("document.querySelector('details.verdict').open") is False
    assert "Best here" in page.eval("document.querySelector('details.verdict').textContent")


def test_figures_are_shown_at_their_own_size_so_their_fonts_are_as_drawn(page):
    """No figure is scaled down on the page (the figures are drawn with fonts >= 9 pt at
    DPI, ``plots.legible``): shown at least as wide as its pixels, less a scroll bar's."""
    imgs = page.eval("[...document.images].map(i => [i.alt, i.naturalWidth, "
                     "i.getBoundingClientRect().width])")
    for alt, natural, shown in imgs:
        assert shown >= 0.97 * natural, (alt, natural, shown)
        assert shown >= 0.95 * page.eval("document.body.clientWidth - 32"), alt


def test_what_tuning_changed_is_visible_and_fits(tmp_path):
    """``run --tune`` on a 30 s simulated drive whose config states the GPS noise 3x too
    large: the section is on the page, its table shows the GPS value before and after, and it
    fits the window."""
    import yaml
    from ddfuse.evaluation import cli

    bag = tmp_path / "husky.bag"
    assert cli.main(["simulate", "husky", "--seed", "3", "--duration", "30", "-o", str(bag)]) == 0
    d = yaml.safe_load(bag.with_suffix(".yaml").read_text())
    d["sensors"]["gps"][0]["noise"]["horizontal"] *= 3.0
    off = tmp_path / "off.yaml"
    off.write_text(yaml.safe_dump(d, sort_keys=False))
    out = tmp_path / "out"
    assert cli.main(["run", str(bag), "-c", str(off), "--tune", "-o", str(out),
                     "--estimators", "ekf,smoother"]) == 0
    with Page(out / "report.html") as p:
        width, scroll = p.eval("[window.innerWidth, document.documentElement.scrollWidth]")
        assert scroll <= width, f"the page scrolls sideways: {scroll} px wide"
        section = p.eval("(() => { const h = [...document.querySelectorAll('h2')]"
                         ".find(e => e.innerText.startsWith('What tuning changed')); if (!h) "
                         "return null; let e = h.nextElementSibling; while (e && e.tagName "
                         "!= 'TABLE') e = e.nextElementSibling; return [h.getBoundingClientRect()"
                         ".height, [...e.rows].map(r => [...r.cells].map(c => c.innerText))] "
                         "})()")
    assert section is not None, "no 'What tuning changed' heading"
    height, rows = section
    assert height > 0
    gps = next((r for r in rows if r[0].startswith("sensors.gps[0].noise.horizontal")), None)
    assert gps is not None, rows
    true = yaml.safe_load(bag.with_suffix(".yaml").read_text())["sensors"]["gps"][0]["noise"]
    # the config's value as given, and the tuned one nearer the simulator's truth than it
    assert float(gps[1]) == pytest.approx(3 * true["horizontal"], rel=1e-3), gps
    assert abs(float(gps[2]) - true["horizontal"]) < abs(float(gps[1]) - true["horizontal"]), gps
