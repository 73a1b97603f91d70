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


def test_the_reader_sees_the_winner_with_the_score_metrics_json_has(page, sample_report):
    text = page.eval("document.body.innerText")
    m = json.loads((sample_report / "metrics.json").read_text())
    best = re.search(r"Best here[^:]*: (\w+) with ([0-9.]+) m", text)
    assert best, text[:2000]
    name, shown = best.group(1), float(best.group(2))
    scores = {n: e["ate_common_rmse_m"] for n, e in m["estimators"].items()
              if e.get("ate_common_rmse_m") is not None}
    assert name == min(scores, key=scores.get)
    assert shown == pytest.approx(scores[name], abs=5e-4)
    # the verdict is visible in the first screen, not below the fold
    top = page.eval("(() => { const r = [...document.querySelectorAll('li')]"
                    ".find(e => e.innerText.startsWith('Best here')); "
                    "return r ? r.getBoundingClientRect().top : null })()")
    assert top is not None and top < 900, top
