"""What ``ddfuse tune`` found (``evaluation.tune``): per parameter its outcome, and the run's."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ddfuse.evaluation.tune_params import Param


@dataclass
class Tuned:
    """One parameter's outcome. ``value`` is the tuned value (SI), or None where it was left as
    the config had it (``status`` 'not informed'); ``status``: 'tuned', 'not informed',
    'at lower bound', 'at upper bound'; ``reason`` in words; ``se_log``: the standard error of
    its log (a relative standard error, to first order), None when not computed. Status
    'negligible': a process noise informed at the start, driven down NEGLIGIBLE-fold or more
    to where the innovations no longer show it; ``value`` is that small value."""

    param: Param
    value: float | None
    status: str
    reason: str = ""
    se_log: float | None = None
    information: float | None = None


@dataclass
class TuneResult:
    """What :func:`tune` found: per parameter a :class:`Tuned`, the pairs the data do not tell
    apart (labels and the correlation of their estimates), the objective at the start and the
    end, how many estimator runs it took and how long (s)."""

    estimator: str
    tuned: list[Tuned]
    pairs: list[tuple[str, str, float]] = field(default_factory=list)
    nll_start: float = math.nan
    nll_end: float = math.nan
    innovations: int = 0
    runs: int = 0
    iterations: int = 0
    wall_s: float = 0.0
    message: str = ""
    # landmark sensor -> the bearing sigma (rad) of its independent model (the first stage of
    # _staged_search), which the correlation time's rule takes (tune_rules.correlation)
    corr_sigma: dict[str, float] = field(default_factory=dict)

    def values(self) -> list[float | None]:
        return [t.value for t in self.tuned]
