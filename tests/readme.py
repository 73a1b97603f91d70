"""The README's Python examples, for the tests that run them as a user would copy them."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def python_block(after: str, must_hold: str) -> str:
    """The first ```python block of README.md after the text matching regex ``after``; it must
    contain ``must_hold`` (so that a test runs the block it is about)."""
    text = (ROOT / "README.md").read_text()
    block = re.search(after + r".*?```python\n(.*?)```", text, re.S).group(1)
    assert must_hold in block  # the block under test
    return block
