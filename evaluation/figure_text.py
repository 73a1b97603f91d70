"""Text that fits its panel: a title broken into lines no wider than the panel's column."""

from __future__ import annotations

import re

from matplotlib.font_manager import FontProperties
from matplotlib.textpath import TextToPath

_MEASURE = TextToPath()


def text_width_pt(text: str, fontsize: float) -> float:
    """Width (pt) of one line of ``text`` at ``fontsize`` (pt) in matplotlib's default font."""
    w, _, _ = _MEASURE.get_text_width_height_descent(text, FontProperties(size=fontsize),
                                                     ismath=False)
    return float(w)


def fit_lines(text: str, width_pt: float, fontsize: float) -> str:
    """``text`` with line breaks so that no line is wider than ``width_pt`` at ``fontsize``.

    Lines break after a space or a ``/`` (a ROS topic breaks between its namespaces), greedily;
    existing line breaks are kept. A single piece wider than ``width_pt`` (no break point in it)
    gets a line of its own and stays whole."""
    out = []
    for para in text.split("\n"):
        line = ""
        for piece in re.split(r"(?<=[ /])", para):
            if line and text_width_pt((line + piece).rstrip(), fontsize) > width_pt:
                out.append(line.rstrip())
                line = piece.lstrip()
            else:
                line += piece
        out.append(line.rstrip())
    return "\n".join(out)
