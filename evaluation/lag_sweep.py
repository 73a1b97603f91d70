"""``ddfuse lag-sweep``: the fixed-lag smoother's accuracy, latency and CPU against its lag.

One bag is decoded once; the smoother runs over it once per lag (and the EKF once, as the
reference the smoother should approach as the lag goes to zero), each scored by
:func:`ddfuse.evaluation.pipeline.score`: position RMSE against truth when the bag has it, else
against the GPS fixes withheld by ``--gps-holdout``; the 3-dof NEES when there is truth; update
latency percentiles and the real-time factor.

The command line is ``ddfuse lag-sweep [BAG] [-c CONFIG] [--lags 0.5,2,10,30]
[--gps-holdout SPEC] [--json FILE]`` (``evaluation/cli/lag_sweep.py``).
"""

from __future__ import annotations

from pathlib import Path

from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config, with_gps_model
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.measurements import GpsFix
from ddfuse.estimation.runner import initial_pose, parse_holdout, run
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.pipeline import score

__all__ = ["lag_sweep", "format_table"]

DEFAULT_LAGS = (0.5, 2.0, 10.0, 30.0)
_TRACKS = ("smoother", "smoother_lagged")


def lag_sweep(bag: str | Path, config: str | Path, lags=DEFAULT_LAGS, holdout: str | None = None,
              reference: str | None = "ekf", engine=None,
              gps_model: str | None = None) -> list[dict]:
    """Rows ``{"estimator", "lag_s", "rmse_m", "score", "nees_mean", "rtf", "update_ms"}``, one
    per (lag, smoother track) plus one for ``reference`` (lag None). ``score`` says what the
    RMSE and the NEES are against: "truth" (the pose NEES) or "gps_holdout" (the withheld
    fixes' NEES, 2 dof: ``gps_holdout_nees``). A truncated or damaged bag is swept on what
    could be read; its BagError is raised after the sweep, with the rows as ``rows``.

    ``engine``: an entered ``engine.Engine`` that runs each lag (and the reference) as its own
    task, each decoding the bag where it runs (the same rows; timing fields aside); None or a
    serial one decodes the bag once here and runs them in turn.

    A sweep with nothing to score against (no ground truth and no ``holdout``, or a hold-out
    that withholds no fix) raises ValueError saying so: before decoding when the config
    shows it (no ground_truth topic, or no gps sensor to withhold from), else after decoding,
    before any estimator runs. ``gps_model`` replaces the config's ``gps.model`` (every
    point's, the reference's too)."""
    cfg = with_gps_model(load_config(config), gps_model)
    for name in ["smoother"] + ([reference] if reference else []):
        if not registry.SPECS[name].allowed(cfg):
            raise ValueError(f"{config}: {name} needs {registry.SPECS[name].needs}, which the "
                             "config does not have")
    _check_scorable(cfg, config, holdout)
    points = ([(reference, None)] if reference else []) + [("smoother", float(x)) for x in lags]
    if engine is not None and engine.kind != "serial":
        return _on_engine(engine, [(str(bag), str(config), holdout, n, lag, gps_model)
                                   for n, lag in points])
    stream, damaged = _decode(bag, cfg)
    against = _scored_against(stream, bag, cfg, holdout)
    pose = initial_pose(cfg.initial_pose, stream)
    rows = [r for name, lag in points
            for r in _point_rows(stream, cfg, holdout, against, pose, name, lag)]
    if damaged is not None:
        raise _swept_damaged(damaged, rows)
    return rows


def _decode(bag, cfg):
    """(stream, None), or (what could be read, its BagError) for a damaged bag."""
    try:
        return read_stream(bag, cfg), None
    except BagError as e:
        if e.partial is None or not e.partial.measurements:
            raise
        return e.partial, e


def _swept_damaged(damaged: BagError | str, rows: list[dict]) -> BagError:
    err = BagError(f"{damaged}; swept on what could be read")
    err.rows = rows
    return err


def _point_rows(stream, cfg, holdout, against: str, pose, name: str,
                lag: float | None) -> list[dict]:
    """The rows of one point of the sweep: ``name`` (the smoother with ``lag``, or the
    reference estimator) run over ``stream`` and scored."""
    spec = registry.SPECS[name]
    ests = {name: spec.build(cfg, stream, pose, lag)}
    m = score(run(stream, ests, holdout=holdout), cfg=cfg)  # run's antenna model
    rows = []
    for track in (_TRACKS if name == "smoother" else spec.produces):
        e = m.estimators[track]
        truth = against == "truth"
        held = e.gps_holdout_nees.mean if e.gps_holdout_nees else None
        rows.append({"estimator": track, "lag_s": lag,
                     "rmse_m": e.ate_rmse_m if truth else e.gps_holdout_rmse_m,
                     "score": against,
                     "nees_mean": e.nees_mean if truth else held, "rtf": e.rtf,
                     "update_ms": e.update_ms.to_json() if e.update_ms else None})
    return rows


def sweep_point(task: tuple) -> tuple[list[dict], str | None]:
    """One point of the sweep on a worker: ``task`` = (bag, config, holdout, name, lag,
    gps_model); its rows and the bag's damage (one line) or None. ValueError as
    ``lag_sweep``'s."""
    bag, config, holdout, name, lag, gps_model = task
    cfg = with_gps_model(load_config(config), gps_model)
    stream, damaged = _decode(bag, cfg)
    against = _scored_against(stream, bag, cfg, holdout)
    pose = initial_pose(cfg.initial_pose, stream)
    rows = _point_rows(stream, cfg, holdout, against, pose, name, lag)
    return rows, None if damaged is None else str(damaged)


def _on_engine(engine, tasks: list[tuple]) -> list[dict]:
    done: dict[int, tuple] = {}
    for o in engine.map(sweep_point, tasks):
        if o.error is not None:
            raise ValueError(o.error.removeprefix("ValueError: "))
        done[o.index] = o.value
    rows = [r for i in range(len(tasks)) for r in done[i][0]]
    damaged = next((d for _, d in done.values() if d), None)
    if damaged is not None:
        raise _swept_damaged(damaged, rows)
    return rows


_NEEDS = ("lag-sweep needs ground truth or --gps-holdout (e.g. every:5) to score the smoother "
          "against")
_NOTHING = "lag-sweep has nothing to score the smoother against"


def _check_scorable(cfg, config, holdout: str | None) -> None:
    """Before decoding: ValueError when the config alone shows there is nothing to score
    against (no ground_truth topic and no hold-out), or a hold-out is asked for without a gps
    sensor to withhold fixes of (with or without truth: 'run' refuses it the same way)."""
    if holdout and not cfg.of_kind("gps"):
        raise ValueError(f"--gps-holdout {holdout}: {config} has no gps sensor")
    if cfg.ground_truth_topic:
        return
    if not holdout:
        raise ValueError(f"{_NEEDS}: {config} names no ground_truth topic")


def _scored_against(stream, bag, cfg, holdout: str | None) -> str:
    """What the decoded ``stream`` lets the sweep score against: "truth" when it has ground
    truth, else "gps_holdout" when ``holdout`` withholds at least one of its fixes (the rule
    ``ddfuse.estimation.runner.run`` applies, from the first measurement's stamp); ValueError
    otherwise."""
    if stream.ground_truth:
        return "truth"
    topic = f"no ground truth on {cfg.ground_truth_topic}" if cfg.ground_truth_topic else \
        "no ground truth"
    if not holdout:
        raise ValueError(f"{_NEEDS}: {bag} has {topic}")
    fixes = [m for m in stream.measurements if isinstance(m, GpsFix)]
    if not fixes or not parse_holdout(holdout)(fixes, stream.measurements[0].t):
        raise ValueError(f"{_NOTHING}: {bag} has {topic} and --gps-holdout {holdout} "
                         f"withholds none of its {len(fixes)} GPS fixes")
    return "gps_holdout"


def format_table(rows: list[dict]) -> str:
    """A markdown table of :func:`lag_sweep` rows."""

    def f(v, spec):
        return "-" if v is None else format(v, spec)

    against = rows[0]["score"] if rows else "truth"
    out = [f"| estimator | lag s | RMSE m ({against}) | NEES ({against}) | RTF | "
           "update p50 / p99 / max ms |",
           "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        u = r["update_ms"] or {}
        out.append(f"| {r['estimator']} | {f(r['lag_s'], 'g')} | {f(r['rmse_m'], '.3f')} | "
                   f"{f(r['nees_mean'], '.2f')} | {f(r['rtf'], '.0f')} | "
                   f"{f(u.get('p50'), '.3f')} / {f(u.get('p99'), '.3f')} / "
                   f"{f(u.get('max'), '.2f')} |")
    return "\n".join(out)
