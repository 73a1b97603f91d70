"""The README's Python examples (and those of the docs it links for the library), for the tests
that run them as a user would copy them."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# where the examples are looked for, in order: the README, then its library reference
DOCS = (ROOT / "README.md", ROOT / "docs" / "api.md")


def python_block(after: str, must_hold: str) -> str:
    """The first ```python block after the text matching regex ``after`` in the first of DOCS
    that has that text (README.md before docs/api.md), dedented as a user pastes it from a list
    item; it must contain ``must_hold`` (so that a test runs the block it is about)."""
    for doc in DOCS:
        m = re.search(after + r".*?```python\n(.*?)```", doc.read_text(), re.S)
        if m:
            block = textwrap.dedent(m.group(1))
            assert must_hold in block  # the block under test
            return block
    raise AssertionError(f"no ```python block after {after!r} in {', '.join(map(str, DOCS))}")
