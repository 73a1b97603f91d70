"""ddfuse: pose estimation for differential-drive robots from ROS bags, EKFs beside a GTSAM
fixed-lag smoother.

The notebook facade (each name is imported on first use, so ``import ddfuse`` stays cheap and
leaves matplotlib's backend alone)::

    import ddfuse
    cfg = ddfuse.load_config("data/sample_husky.yaml")     # a Config
    stream = ddfuse.read_bag("data/sample_husky.bag", cfg)  # time-ordered measurements, SI units
    result = ddfuse.run(stream, ddfuse.build_estimators(cfg, stream, ["ekf", "smoother"]))
    ddfuse.score(result).estimators["ekf"].ate_rmse_m  # m; .to_json(): metrics.json's dict
    fig = ddfuse.plots.trajectories(ddfuse.SavedRun.from_result(result, cfg=cfg))

``ddfuse.run_bag(bag, cfg, outdir)`` does all of ``ddfuse run``: decode, run, score, write.

Sub-packages (one import direction: factors <- estimation <- ekf_baseline <- evaluation):
``ddfuse.factors`` (GTSAM factors and the shared kinematics), ``ddfuse.estimation``
(measurements, config, bag and live input, the smoother, the runner), ``ddfuse.ekf_baseline``
(the specified EKFs), ``ddfuse.evaluation`` (metrics, consistency, plots, report, simulation,
the command line), ``ddfuse.data`` (the shipped sample bags and configs).
"""

from __future__ import annotations

from importlib import import_module

# name -> (module, attribute); attribute None: the module itself
_FACADE = {
    "load_config": ("ddfuse.estimation.config", "load_config"),
    "read_bag": ("ddfuse.estimation.bags", "read_stream"),
    "build_estimators": ("ddfuse.evaluation.estimators", "build"),
    "run": ("ddfuse.estimation.runner", "run"),
    "score": ("ddfuse.evaluation.pipeline", "score"),
    "run_bag": ("ddfuse.evaluation.pipeline", "run_bag"),
    "SavedRun": ("ddfuse.evaluation.results", "SavedRun"),
    "load_run": ("ddfuse.evaluation.results", "load_run"),
    "plots": ("ddfuse.evaluation.plots", None),
}

__all__ = ["__version__", *_FACADE]


def _version() -> str:
    """The installed distribution's version ("0+unknown" in a source tree never installed)."""
    # read when first asked for: importlib.metadata costs every ddfuse process ~25-50 ms
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ddfuse")
    except PackageNotFoundError:
        return "0+unknown"


def __getattr__(name: str):
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    try:
        module, attr = _FACADE[name]
    except KeyError:
        raise AttributeError(f"module 'ddfuse' has no attribute {name!r}") from None
    value = import_module(module)
    if attr is not None:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
