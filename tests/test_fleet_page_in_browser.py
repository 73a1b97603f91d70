"""fleet.html as a reader sees it: a fleet of two simulated drives and a damaged bag opened in
headless Chromium at 1 400 x 900 px (``tests/browser.py``): the wins across bags as fleet.json
counts them, the failed bag's row with its error, each bag's link to its report, nothing wider
than the window and nothing fetched."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from browser import Page

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def fleet_out(tmp_path_factory) -> Path:
    from ddfuse.evaluation.cli import main

    tmp = tmp_path_factory.mktemp("fleet_page")
    bags = tmp / "bags"
    for seed in (1, 2):
        assert main(["simulate", "husky", "--seed", str(seed), "--duration", "10", "-o",
                     str(bags / f"drive{seed}.bag")]) == 0
    (bags / "broken.bag").write_bytes(b"not a bag at all")
    (bags / "broken.yaml").write_bytes((bags / "drive1.yaml").read_bytes())
    out = tmp / "out"
    assert main(["fleet", str(bags), "-o", str(out), "--estimators", "ekf,ekf_igvc,smoother",
                 "--jobs", "1"]) == 0
    return out


@pytest.fixture(scope="module")
def page(fleet_out):
    with Page(fleet_out / "fleet.html", width=1400, height=900) as p:
        yield p


def _table(page, id_: str) -> list[list[str]]:
    return page.eval(f"[...document.getElementById('{id_}').rows]"
                     ".map(r => [...r.cells].map(c => c.innerText.trim()))")


def test_nothing_is_wider_than_a_1400_px_window_and_nothing_is_fetched(page):
    width, scroll = page.eval("[window.innerWidth, document.documentElement.scrollWidth]")
    assert width == 1400 and scroll <= width, f"the page scrolls sideways: {scroll} px wide"
    wide = page.eval("[...document.querySelectorAll('table')]"
                     ".filter(e => e.getBoundingClientRect().right > window.innerWidth)"
                     ".map(e => e.id)")
    assert not wide, wide
    fetched = page.eval("performance.getEntriesByType('resource').map(e => e.name)")
    assert fetched == [], fetched


def test_the_reader_sees_each_estimators_wins_as_fleet_json_counts_them(page, fleet_out):
    doc = json.loads((fleet_out / "fleet.json").read_text())
    rows = _table(page, "standings")
    assert rows[0][:3] == ["estimator", "bags scored", "wins"]
    shown = {r[0]: (int(r[1]), int(r[2]), int(r[3])) for r in rows[1:]}
    assert shown == {n: (s["scored"], s["wins"], s["tied_first"])
                     for n, s in doc["estimators"].items()}
    assert sum(w for _, w, _ in shown.values()) == sum(1 for b in doc["bags"] if b["winner"])
    # the first screen says who won how often
    lines = page.eval("[...document.querySelectorAll('.verdict li')]"
                      ".map(e => [e.innerText, e.getBoundingClientRect().top])")
    for name, s in doc["estimators"].items():
        line = next((t for t, top in lines if t.startswith(f"{name} won ")), None)
        assert line is not None and f"won {s['wins']} of the {s['scored']} bags" in line, lines
    assert all(top < 900 for _, top in lines), lines


def test_the_failed_bag_is_a_row_with_its_error_and_the_others_link_their_reports(page,
                                                                                  fleet_out):
    doc = json.loads((fleet_out / "fleet.json").read_text())
    error = next(b["error"] for b in doc["bags"] if b["bag"] == "broken")
    assert "broken.bag" in error
    bags = {r[0]: r[1:] for r in _table(page, "bags")[1:]}
    assert set(bags) == {"broken", "drive1", "drive2"}
    assert bags["broken"] == [f"ERROR: {error}"]
    visible = page.eval("(() => { const r = [...document.querySelectorAll('#bags tr')]"
                        ".find(e => e.cells[0].innerText.trim() == 'broken');"
                        " const b = r.getBoundingClientRect(); return [b.width, b.height] })()")
    assert visible[0] > 300 and visible[1] > 0
    for name in ("drive1", "drive2"):
        b = next(b for b in doc["bags"] if b["bag"] == name)
        assert bags[name][1] in (b["winner"], f"tie: {', '.join(b['tied'])}")
    links = page.eval("[...document.querySelectorAll('#bags a')].map(a => [a.innerText, a.href])")
    assert sorted(t for t, _ in links) == ["drive1", "drive2"]
    for text, href in links:
        target = Path(href.removeprefix("file://"))
        assert target == (fleet_out / text / "report.html").resolve() and target.is_file()
