"""The files ``ddfuse run --tune`` adds to an output directory, and reading tuning.json back.

Kept apart from ``evaluation.run_tuned`` (which runs the pipeline, so imports the estimators,
numba and gtsam) so that the report can name and read them without loading any of that."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["SHIPPED_DIR", "TUNED_CONFIG", "TUNING_FILE", "read_tuning"]

SHIPPED_DIR = "shipped"  # OUT/shipped/: the run with the config as given
TUNED_CONFIG = "tuned.yaml"
TUNING_FILE = "tuning.json"


def read_tuning(outdir: str | Path) -> dict | None:
    """``outdir``/tuning.json as a dictionary; None when there is none or it cannot be read
    (a directory of a run without ``--tune``)."""
    try:
        d = json.loads((Path(outdir) / TUNING_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None
