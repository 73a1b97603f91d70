"""``ddfuse compare``: two sets of scores side by side, per bag and estimator, for a CI gate.

``load_scores(path)`` reads a metrics.json, a run directory (its metrics.json) or a fleet.json
into ``{(bag, estimator): Score}``; ``compare(base, new, tol_m, tol_pct)`` pairs them and calls
each pair ``same``, ``better``, ``worse``, ``lost`` (a score before, an error or none now),
``gained``, ``missing`` (in the baseline only), ``new`` (in the new run only) or
``incomparable`` (ranked on different scores: ATE against GPS hold-out). A change counts only
beyond both tolerances: ``|new - base| > max(tol_m, tol_pct % of base)``. Worse, lost and
missing are regressions.

The score is the fleet's (``fleet.rows_of``: position ATE in m where the run has ground truth,
else the RMS distance to withheld GPS fixes). Two single runs are paired by estimator whatever
their bags' names, so a committed baseline of a bag stays comparable after the bag moves.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from ddfuse.estimation.errors import DdfuseError

__all__ = ["DEFAULT_TOL_M", "DEFAULT_TOL_PCT", "REGRESSIONS", "Pair", "Score", "compare",
           "load_scores"]

DEFAULT_TOL_M = 0.01  # m: below a centimetre a change is noise for a ground robot
DEFAULT_TOL_PCT = 5.0  # %: verdict.TIE, the report's own tie rule
REGRESSIONS = frozenset({"worse", "lost", "missing"})


@dataclass(frozen=True)
class Score:
    """One estimator's score on one bag: ``kind`` 'ate' or 'holdout' (None: no score),
    ``value`` m, and its ``error`` (a failed bag or estimator), as fleet rows hold them."""

    kind: str | None
    value: float | None
    error: str | None = None


@dataclass(frozen=True)
class Pair:
    """A (bag, estimator) in either input, its two scores and what changed: ``status`` (see
    the module), ``delta_m`` new minus base and ``delta_pct`` of base where both are scores."""

    bag: str
    estimator: str | None
    status: str
    base: Score | None
    new: Score | None
    delta_m: float | None = None
    delta_pct: float | None = None


def _from_rows(rows: list[dict]) -> dict[tuple[str, str | None], Score]:
    return {(r["bag"], r["estimator"]): Score(r.get("score"), r.get("score_m"), r.get("error"))
            for r in rows}


def load_scores(path: str | Path) -> dict[tuple[str, str | None], Score]:
    """The scores in ``path``: a fleet.json (every bag's rows; a failed bag as estimator None
    with its error), a metrics.json or a directory holding one (the bag's stem as bag).
    DdfuseError naming the path when it is none of these."""
    from ddfuse.evaluation.fleet import FLEET_JSON, rows_of
    from ddfuse.evaluation.scores import RunSummary

    path = Path(path)
    if path.is_dir():
        cands = [path / "metrics.json", path / FLEET_JSON]
        found = [c for c in cands if c.is_file()]
        if not found:
            raise DdfuseError(f"{path}: a directory without metrics.json or {FLEET_JSON}")
        path = found[0]
    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise DdfuseError(f"{path}: cannot read ({e.strerror or e})") from None
    except ValueError as e:
        raise DdfuseError(f"{path}: not JSON ({e})") from None
    if isinstance(doc, dict) and isinstance(doc.get("rows"), list) and "bags" in doc:
        return _from_rows(doc["rows"])
    if not (isinstance(doc, dict) and isinstance(doc.get("estimators"), dict)):
        raise DdfuseError(f"{path}: neither a metrics.json (no 'estimators') nor a "
                          f"{FLEET_JSON} (no 'rows')")
    try:
        m = RunSummary.from_json(doc)
        rows = rows_of(m)
    except (TypeError, ValueError, KeyError, AttributeError) as e:
        raise DdfuseError(f"{path}: a metrics.json ddfuse cannot read ({e})") from None
    bag = Path(m.bag).stem if m.bag else path.parent.name
    return _from_rows([{"bag": bag, **r} for r in rows])


def _status(b: Score, n: Score, tol_m: float, tol_pct: float) -> tuple[str, float | None,
                                                                        float | None]:
    if b.value is None and n.value is None:
        return "same", None, None
    if n.value is None:
        return "lost", None, None
    if b.value is None:
        return "gained", None, None
    if b.kind != n.kind:
        return "incomparable", None, None
    d = n.value - b.value
    pct = 100.0 * d / b.value if b.value > 0 else None
    if abs(d) <= max(tol_m, tol_pct / 100.0 * abs(b.value)):
        return "same", round(d, 6), None if pct is None else round(pct, 3)
    return ("worse" if d > 0 else "better"), round(d, 6), None if pct is None else round(pct, 3)


def compare(base: dict, new: dict, tol_m: float = DEFAULT_TOL_M,
            tol_pct: float = DEFAULT_TOL_PCT) -> list[Pair]:
    """Every (bag, estimator) of ``base`` and ``new`` (``load_scores``) paired, baseline order
    first. Two single runs (one bag each) are paired by estimator alone, under the new bag's
    name."""
    if len({b for b, _ in base}) == 1 and len({b for b, _ in new}) == 1:
        name = next(iter(new))[0]
        base = {(name, e): s for (_, e), s in base.items()}
    pairs = []
    for key in [*base, *(k for k in new if k not in base)]:
        b, n = base.get(key), new.get(key)
        if n is None:
            pairs.append(Pair(*key, "missing", b, None))
        elif b is None:
            pairs.append(Pair(*key, "new", None, n))
        else:
            status, d, pct = _status(b, n, tol_m, tol_pct)
            pairs.append(Pair(*key, status, b, n, d, pct))
    return pairs


def to_json(pairs: list[Pair], tol_m: float, tol_pct: float) -> dict:
    """The comparison as ``--json`` writes it: the tolerances, the counts per status, and
    every pair."""
    counts: dict[str, int] = {}
    for p in pairs:
        counts[p.status] = counts.get(p.status, 0) + 1
    return {"tol_m": tol_m, "tol_pct": tol_pct,
            "regressions": sum(1 for p in pairs if p.status in REGRESSIONS),
            "counts": counts, "pairs": [asdict(p) for p in pairs]}
