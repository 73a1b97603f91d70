"""The README's picture of the report: the top of ``report.html`` of ``ddfuse run`` on the
sample bag, as headless Chromium lays it out in a 1400 x 1000 CSS-pixel window, scaled to
1000 px wide and reduced to 64 colours (under 150 kB).

    python docs/tools/report_screenshot.py [RUN_DIR] [-o docs/report.png]

Without RUN_DIR it runs ``ddfuse run`` on the embedded sample into a temporary folder first.
Needs Debian's ``chromium`` and the test extra (``pip install -e ".[test]"``: the DevTools
client in tests/browser.py uses ``websockets``)."""

from __future__ import annotations

import argparse
import base64
import io
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WINDOW = (1400, 1000)  # CSS px: the width the report's tables are laid out for
WIDTH = 1000  # px of the saved picture
COLOURS = 64


def screenshot(report: Path, out: Path) -> int:
    """Write the PNG of ``report``'s first window to ``out``; returns its size in bytes."""
    sys.path.insert(0, str(ROOT / "tests"))
    from browser import Page
    from PIL import Image

    with Page(report, width=WINDOW[0], height=WINDOW[1]) as page:
        shot = page.call("Page.captureScreenshot", format="png")
    img = Image.open(io.BytesIO(base64.b64decode(shot["data"]))).convert("RGB")
    img = img.resize((WIDTH, round(img.height * WIDTH / img.width)), Image.LANCZOS)
    img = img.quantize(colors=COLOURS, method=Image.Quantize.MEDIANCUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out, format="PNG", optimize=True)
    return out.stat().st_size


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", type=Path,
                    help="a 'ddfuse run -o' folder (default: run the sample now)")
    ap.add_argument("-o", "--output", type=Path, default=ROOT / "docs" / "report.png")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ddfuse-shot-") as tmp:
        run_dir = args.run_dir
        if run_dir is None:
            from ddfuse.evaluation import cli

            run_dir = Path(tmp) / "out"
            if cli.main(["run", "-o", str(run_dir)]) != 0:
                return 1
        size = screenshot(run_dir / "report.html", args.output)
    print(f"{args.output}: {size / 1000:.0f} kB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
