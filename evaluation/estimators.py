"""The estimators ``ddfuse run`` knows by name, and which of them a config's sensors allow."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ddfuse.estimation.config import Config
from ddfuse.estimation.dead_reckoning import odometry_source

if TYPE_CHECKING:
    from ddfuse.estimation.estimator import Estimator
    from ddfuse.estimation.measurements import Stream


@dataclass(frozen=True)
class EstimatorSpec:
    name: str
    description: str
    allowed: Callable[[Config], bool]
    # (config, stream, start pose, lag s, the tracks of ``produces`` wanted) -> the estimator
    make: Callable[[Config, Stream, tuple | None, float | None, frozenset[str]], Estimator]
    produces: tuple[str, ...]  # the output tracks it gives (the smoother's lagged one too)
    needs: str  # the sensors ``allowed`` asks for, in words (for error messages)
    default: bool = True  # run when no estimators are named (if the config allows it)

    def build(self, cfg: Config, stream: Stream, pose: tuple | None, lag: float | None,
              tracks=None) -> Estimator:
        """The estimator, giving the tracks of ``produces`` that are in ``tracks`` (default:
        all of them)."""
        return self.make(cfg, stream, pose, lag, frozenset(
            t for t in self.produces if tracks is None or t in tracks))


def _has(*kinds: str) -> Callable[[Config], bool]:
    return lambda cfg: all(cfg.of_kind(k) for k in kinds)


def _motion(cfg: Config) -> bool:
    return bool(cfg.of_kind("odometry") or cfg.of_kind("wheels"))


# The estimators' classes are imported when one is built: the registry's names and rules
# (the report's "not run" list, the CLI's checks) then load no gtsam, numba or scipy.
def _ekf(cfg, st, pose, lag, _):
    from ddfuse.ekf_baseline.unicycle import UnicycleEkf

    return UnicycleEkf(cfg, initial_pose=pose)


def _ekf_igvc(cfg, st, pose, lag, _):
    from ddfuse.ekf_baseline.igvc import IgvcEkf

    return IgvcEkf(cfg, initial_pose=pose, datum=st.datum)


def _ekf_landmark(cfg, st, pose, lag, _):
    from ddfuse.ekf_baseline.landmark import LandmarkEkf

    return LandmarkEkf(cfg, initial_pose=pose, landmarks=st.landmarks)


def _ekf_slam(cfg, st, pose, lag, _):
    from ddfuse.ekf_baseline.landmark import LandmarkSlamEkf

    return LandmarkSlamEkf(cfg, initial_pose=pose)


def _smoother(cfg, st, pose, lag, tracks, keep_all=None):
    from ddfuse.estimation.smoother import FixedLagSmoother

    return FixedLagSmoother(cfg, initial_pose=pose, landmarks=st.landmarks, lag=lag,
                            lagged="smoother_lagged" in tracks, keep_all=keep_all)


def _batch(cfg, st, pose, lag, _):
    from ddfuse.estimation.smoother import BatchSmoother

    return BatchSmoother(cfg, initial_pose=pose, landmarks=st.landmarks, lag=lag)


def _dr(cfg, st, pose, lag, _):
    from ddfuse.estimation.dead_reckoning import DeadReckoning

    return DeadReckoning(cfg, initial_pose=pose)


SPECS: dict[str, EstimatorSpec] = {s.name: s for s in (
    EstimatorSpec("ekf", "unicycle EKF (seed 003) with gyro-bias and heading-offset states",
                  _motion, _ekf,
                  ("ekf",), "an odometry or wheels sensor"),
    EstimatorSpec("ekf_igvc", "11-state GPS-guided EKF (seed 000)",
                  lambda cfg: _motion(cfg) and bool(cfg.of_kind("gps")),
                  _ekf_igvc,
                  ("ekf_igvc",), "an odometry or wheels sensor, and gps"),
    EstimatorSpec("ekf_landmark", "range/bearing EKF in the known landmark map (seed 002)",
                  lambda cfg: _motion(cfg) and bool(cfg.of_kind("landmarks")),
                  _ekf_landmark,
                  ("ekf_landmark",), "an odometry or wheels sensor, and landmarks"),
    EstimatorSpec("ekf_slam", "EKF-SLAM, landmarks augmented into the state (seed 002)",
                  # range alone cannot place a new landmark: every sighting would be rejected
                  lambda cfg: _motion(cfg) and any("bearing" in s.use
                                                   for s in cfg.of_kind("landmarks")),
                  _ekf_slam,
                  ("ekf_slam",), "an odometry or wheels sensor, and landmarks with bearing"),
    EstimatorSpec("smoother", "ISAM2 fixed-lag smoother: filtered and lagged outputs",
                  _motion, _smoother,
                  ("smoother", "smoother_lagged"), "an odometry or wheels sensor"),
    EstimatorSpec("batch", "Levenberg-Marquardt over the whole run (offline reference)",
                  _motion, _batch,
                  ("batch",), "an odometry or wheels sensor"),
    EstimatorSpec("dr", "dead reckoning: the wheel odometry integrated alone (baseline)",
                  lambda cfg: odometry_source(cfg) is not None,
                  _dr,
                  ("dr",), "an odometry sensor using v and yaw_rate, or wheels with the "
                  "robot's geometry",
                  default=False),
)}
TRACK_TO_SPEC = {track: spec.name for spec in SPECS.values() for track in spec.produces}


def build(cfg: Config, stream, names: list[str] | str | None = None, *,
          lag: float | None = None,
          pose: tuple[float, float, float] | None = None,
          tracks: list[str] | None = None) -> dict[str, Estimator]:
    """The named estimators (``select``'s names; default: every default one the config
    allows), built as ``ddfuse run`` builds them, for ``ddfuse.estimation.runner.run`` or an online
    session: the start pose from the config (``initial_pose: ground_truth``: the stream's
    first truth pose) unless ``pose`` (x, y, yaw) is given, the landmark maps and datum from
    ``stream`` (a Stream, or a primed BagStream), the smoother's lag from the config unless
    ``lag`` (s). ``tracks``: the output tracks that will be used (default: all of them); the
    smoother skips its lagged output (docs/design/performance.md) when 'smoother_lagged' is
    not among them. With both 'smoother' and 'batch', the batch is a ``SharedBatch`` of the
    smoother: one online run, its graph solved at the end."""
    from ddfuse.estimation.runner import initial_pose

    chosen = select(cfg, names)
    if pose is None:
        pose = initial_pose(cfg.initial_pose, stream)
    lag = cfg.smoother.lag if lag is None else lag
    wanted = None if tracks is None else set(tracks)
    if not ("smoother" in chosen and "batch" in chosen):
        return {n: SPECS[n].build(cfg, stream, pose, lag, wanted) for n in chosen}
    # The batch solves the graph the smoother's online run builds: with both, one online run
    # keeps every factor and the batch solves it at the end (SharedBatch), not a second one.
    from ddfuse.estimation.smoother import SharedBatch

    spec = SPECS["smoother"]
    smoother = _smoother(cfg, stream, pose, lag, frozenset(
        t for t in spec.produces if wanted is None or t in wanted), keep_all=True)
    built = {}
    for n in chosen:
        built[n] = (smoother if n == "smoother" else SharedBatch(smoother) if n == "batch"
                    else SPECS[n].build(cfg, stream, pose, lag, wanted))
    return built


def names_list(names, what: str = "estimators") -> list[str] | None:
    """``names`` as a list of estimator (or track) names: a list or other iterable of strings
    as it is, a string as the CLI reads ``--estimators`` (comma-separated: "ekf,smoother"), None
    as None (the default set). ``what`` names the parameter in the errors: TypeError for
    anything else (a bare string would otherwise be taken letter by letter: "unknown estimator
    'e'"), ValueError for a string that names no estimator."""
    if names is None:
        return None
    if isinstance(names, str):
        out = [n.strip() for n in names.split(",") if n.strip()]
        if not out:
            raise ValueError(f"{what}: expected comma-separated estimator names, got {names!r} "
                             "(None for the default set)")
        return out
    if isinstance(names, (bytes, dict)) or not hasattr(names, "__iter__"):
        raise TypeError(f"{what}: expected a list of estimator names (or one string of "
                        f"comma-separated names), got {type(names).__name__} {names!r}")
    out = list(names)
    for n in out:
        if not isinstance(n, str):
            raise TypeError(f"{what}: expected estimator names (strings), got "
                            f"{type(n).__name__} {n!r} in {out!r}")
    return out


def left_out(cfg: Config) -> list[str]:
    """Why the default set leaves out an estimator the config's sensors nearly allow, one line
    each, for the terminal: ekf_slam with landmark sensors that give range only -- one range
    cannot place a new landmark, so it would reject every sighting (as 'range_only_unmapped')
    and dead-reckon; ekf_landmark, which knows the map, uses them."""
    marks = cfg.of_kind("landmarks")
    if not (_motion(cfg) and marks) or SPECS["ekf_slam"].allowed(cfg):
        return []
    topics = ", ".join(s.topic for s in marks)
    return [f"ekf_slam left out: the landmark sensors ({topics}) give range only (use: "
            "[range]), and EKF-SLAM cannot place a new landmark from one range (it would reject "
            "every sighting and dead-reckon); ekf_landmark, which knows the map, uses them"]


def select(cfg: Config, names: list[str] | str | None) -> list[str]:
    """Estimator names to build for ``names`` (a list, or a comma-separated string as
    ``names_list`` reads it; tracks such as 'smoother_lagged' map to their estimator);
    default: every default estimator (all but 'dr') the config's sensors allow. Unknown or
    disallowed names raise ValueError saying why, naming the parameter ("estimators: ...");
    anything but a list or a string raises TypeError."""
    names = names_list(names)
    if not names:
        out = [n for n, s in SPECS.items() if s.default and s.allowed(cfg)]
        if not out:
            have = ", ".join(sorted({s.kind for s in cfg.sensors})) or "none"
            raise ValueError(f"no estimator can run on the config's sensors ({have}): every one "
                             f"needs {SPECS['ekf'].needs}, the motion between the measurements")
        return out
    out: list[str] = []
    for n in names:
        # the parameter, not the CLI's --estimators flag: the CLI refuses unknown names itself
        # (evaluation.cli.arguments.estimator_list), and a disallowed one's "estimators: ..."
        # still reads as its option
        if n not in TRACK_TO_SPEC:
            raise ValueError(f"estimators: unknown estimator {n!r} "
                             f"(known: {', '.join(TRACK_TO_SPEC)})")
        spec = SPECS[TRACK_TO_SPEC[n]]
        if not spec.allowed(cfg):
            raise ValueError(f"estimators: {n} ({spec.description}) needs {spec.needs}, "
                             "which the config does not have")
        if spec.name not in out:
            out.append(spec.name)
    return out
