"""The headline of a run (pure: ``scores.RunSummary`` in, a ``Headline`` out): which estimator
is best on the score the verdict ranks on and by how much, one consistency word per estimator,
and the one next command that would tell more. The terminal (after ``ddfuse run``) and the top
of the report print the same ``Headline.lines()``; the format is in docs/design/headline.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from ddfuse.estimation.config import GATING_GPS_MODELS
from ddfuse.estimation.gps_watch import ROBUST_MODEL
from ddfuse.evaluation.scores import EstimatorScores, RunSummary
from ddfuse.evaluation.verdict import (
    HOLDOUT,
    TIE,
    _direction,
    _rejected_throughout,
    low_rate_nis,
    ranking,
    track_kind,
)

# The score ranked on (``Ranking.figure``): its short name in the headline and the table.
SCORE_NAMES = {"ate_common_rmse_m": "ATE on common stamps",
               "ate_rmse_m": "ATE",
               HOLDOUT: "GPS hold-out RMSE"}
# A GPS outage the next command withholds when the run had none: WINDOW_S s from 40 % of the
# data (past the start-up, with data after it to end the outage).
WINDOW_S, WINDOW_AT = 30.0, 0.4


@dataclass(frozen=True)
class Place:
    """One ranked track: its ``name``, output kind (``verdict.track_kind``) and score [m]."""

    name: str
    kind: str
    score_m: float


@dataclass(frozen=True)
class Headline:
    """A run's answer in brief. ``score``: the ``EstimatorScores`` field ranked on
    (``verdict.Ranking.figure``), None when nothing scores the tracks (``no_score`` says why);
    ``order``: the ranked tracks, best first; ``tied``: how many of them (from the first) tie
    (``verdict.TIE_RULE``); ``margin_m`` / ``margin_rel``: the best's lead over the first track
    that does not tie with it (m, share of that track's score), None when all tie;
    ``realtime``: the same for the real-time tracks (best, next) where the best overall is not
    one; ``consistency``: (track, word) per track with an estimate, ``basis`` what the words rest
    on; ``next_command`` (a shell command line) and ``next_why``; ``caveat``: one line where a
    failing consistency test has a known cause that is no fault (``verdict.low_rate_nis``);
    ``holdout``: (track, word) per track with a NEES on the withheld GPS fixes
    (``gps_holdout_nees``), the word as ``consistency_word``'s, and ``holdout_fixes`` how many."""

    score: str | None
    order: tuple[Place, ...]
    tied: int
    margin_m: float | None
    margin_rel: float | None
    realtime: tuple[Place, Place] | None
    consistency: tuple[tuple[str, str], ...]
    basis: str
    next_command: str | None
    next_why: str
    no_score: str | None = None
    caveat: str | None = None
    holdout: tuple[tuple[str, str], ...] = ()
    holdout_fixes: int | None = None

    @property
    def best(self) -> Place | None:
        return self.order[0] if self.order else None

    def lines(self) -> list[str]:
        """The headline as plain-text lines, the same in the terminal and the report."""
        out = [self._best_line()]
        if self.realtime:
            a, b = self.realtime
            out.append(f"Best in real time: {a.name} {a.score_m:.3f} m, "
                       + _lead(a.score_m, b))
        out.append(f"Consistency ({self.basis}): "
                   + ", ".join(f"{n} {w}" for n, w in self.consistency) + "."
                   if self.consistency else "Consistency: no estimator produced an estimate.")
        if self.holdout:
            out.append(f"Hold-out consistency (NEES on the {self.holdout_fixes} withheld fixes: "
                       "does the covariance cover the error?): "
                       + ", ".join(f"{n} {w}" for n, w in self.holdout) + ".")
        if self.caveat:
            out.append(self.caveat)
        if self.next_command:
            out.append(f"Next: {self.next_command}  ({self.next_why})")
        return out

    def _best_line(self) -> str:
        if not self.order:
            return f"No winner: {self.no_score}"
        best, name = self.order[0], SCORE_NAMES[self.score]
        text = f"Best: {_named(best)}, {name} {best.score_m:.3f} m"
        ties = self.order[1:self.tied]
        if ties:
            text += ", tied with " + ", ".join(f"{_named(p)} {p.score_m:.3f} m" for p in ties)
        nxt = self.order[self.tied] if self.tied < len(self.order) else None
        if nxt is None:
            return text + (f" (all within {100 * TIE:.0f}% of the best)." if ties
                           else " (the only one scored).")
        return text + "; " + _lead(best.score_m, nxt)


def _named(p: Place) -> str:
    return p.name if p.kind == "real time" else f"{p.name} ({p.kind})"


def _lead(best_m: float, nxt: Place) -> str:
    d = nxt.score_m - best_m
    rel = d / nxt.score_m if nxt.score_m > 0 else 0.0
    return (f"{d:.3f} m ({100 * rel:.0f}%) lower than the next, {_named(nxt)} "
            f"{nxt.score_m:.3f} m.")


def _margin(order: list[Place], tied: int) -> tuple[float | None, float | None]:
    if tied >= len(order):
        return None, None
    d = order[tied].score_m - order[0].score_m
    return d, (d / order[tied].score_m if order[tied].score_m > 0 else 0.0)


def consistency_word(name: str, e: EstimatorScores, m: RunSummary, copied: bool) -> str:
    """One word on an estimate's consistency: from its NEES against the truth where it has
    one, else from its own NIS (a track whose NIS rows are another track's copy is 'not
    checked' without a NEES: the filter's innovations say nothing of its own covariance).
    'consistent' (Pass), 'over-confident' / 'under-confident' (the mean off, or one tail),
    'heavy-tailed' (the mean right, the tails off), 'mixed' (sensors failing both ways);
    'mildly ' before a Warn; 'not checked' without either."""
    if e.samples == 0:
        return "no estimate"
    if e.nees and e.nees.verdict:
        return _word(e.nees.verdict, [_direction(e.nees)])
    if copied or not e.nis:
        return "not checked"
    gone = _rejected_throughout(m, name)
    verdicts = [st.nis.verdict for st in e.nis.values() if st.nis.verdict]
    if not verdicts and not gone:
        return "not checked"
    worst = "Fail" if gone or "Fail" in verdicts else "Warn" if "Warn" in verdicts else "Pass"
    dirs = [_direction(st.nis) for st in e.nis.values() if st.nis.verdict == worst]
    return _word(worst, dirs + ["over-confident"] * len(gone))


def _word(verdict: str, directions: list[str]) -> str:
    if verdict == "Pass":
        return "consistent"
    words = {"over-confident" if d == "over-confident" else "under-confident"
             if d == "pessimistic" else "heavy-tailed" for d in directions if d}
    word = words.pop() if len(words) == 1 else "mixed"
    return ("mildly " if verdict == "Warn" else "") + word


def _command(*words: str) -> str:
    import shlex

    return " ".join(shlex.quote(w) for w in words)


def _bag_args(m: RunSummary) -> list[str]:
    """The bag, ``-c CONFIG`` where the config is not the one ``shipped.config_for`` finds
    beside the bag (BAG.yaml), and ``--gps-model`` where the run's came from the command line."""
    bag = str(m.bag or "BAG")
    args = [bag]
    if m.config and Path(m.config) != Path(bag).with_suffix(".yaml") and (
            Path(m.config).parent.name != "configs" or Path(m.config).stem != Path(bag).stem):
        args += ["-c", str(m.config)]
    if m.gps_model_option and m.gps_model:
        args += ["--gps-model", m.gps_model]
    return args


def _has_gps(m: RunSummary) -> bool:
    """Whether the config has a gps sensor and the bag gave it fixes (a hold-out can work)."""
    sensors = (m.data.sensors if m.data else None) or []
    return any(s.kind == "gps" for s in sensors) and bool(m.data and m.data.gps_fixes)


def _failing(m: RunSummary) -> list[str]:
    """The tracks with a failing consistency test that points at the config's noise: NEES
    Fail, a sensor rejected throughout, or a NIS Fail of its own (not a copy of another
    track's) other than a rate sensor's low NIS beside a NEES that does not fail
    (``verdict.low_rate_nis``: the process noise)."""
    rate = {(n, lab) for n, lab, _ in low_rate_nis(m)}
    out, seen = [], set()
    for n, e in m.estimators.items():
        key = repr(sorted((e.nis or {}).items()))
        own = key not in seen  # a copy of another track's NIS (the same filter) fails with it
        seen.add(key)
        if e.samples != 0 and ((e.nees and e.nees.verdict == "Fail")
                               or _rejected_throughout(m, n) or own and any(
                st.nis.verdict == "Fail" and (n, lab) not in rate
                for lab, st in (e.nis or {}).items())):
            out.append(n)
    return out


def _gated_bursts(m: RunSummary) -> list:
    """The data's GPS topics with bursts of disagreement (``scores.GpsBursts``) where the run's
    GPS model gates each fix; [] where the run used a robust one or did not record its model."""
    if m.gps_model not in GATING_GPS_MODELS or m.data is None:
        return []
    return list(m.data.gps_bursts or ())


def next_step(m: RunSummary, scored: bool) -> tuple[str | None, str]:
    """The one next command that tells more about this run, and why (only commands that work
    for its config): the robust GPS model where the GPS came in bursts and the run's model
    gates (with a hold-out where nothing else scores the tracks); a GPS hold-out where nothing
    scores the tracks and the bag has fixes;
    ``ddfuse run --tune`` where a consistency test fails (``_failing``); a GPS outage (``window:``)
    where the bag has GPS and the run had none; else, with a smoother and a score,
    ``ddfuse lag-sweep``; none where no estimator produced an estimate."""
    if not any(e.samples != 0 for e in m.estimators.values()):
        return None, ""  # nothing estimated: the errors in the table say what to fix first
    args = _bag_args(m)
    has_gps = _has_gps(m)
    bursts = _gated_bursts(m)
    if bursts:
        holdout = [m.gps_holdout] if m.gps_holdout else [] if scored else ["every:5"]
        holdout = ["--gps-holdout", *holdout] if holdout else []
        b = bursts[0]
        return (_command("ddfuse", "run", *args, "--gps-model", ROBUST_MODEL, *holdout, "-o",
                         f"ddfuse-{ROBUST_MODEL}"),
                f"GPS {b.topic} disagreed with the odometry in {b.episodes} bursts (up to "
                f"{b.largest_m:.0f} m), which gps.model '{m.gps_model}' gates fix by fix: the "
                "robust model weighs such fixes in every estimator")
    if not scored and m.has_ground_truth:
        return None, ""  # the truth is there, the tracks failed: their errors say what to fix
    if not scored and has_gps and not m.gps_holdout:
        return (_command("ddfuse", "run", *args, "--gps-holdout", "every:5", "-o",
                         "ddfuse-holdout"),
                "no ground truth: every 5th GPS fix withheld from all estimators scores them")
    failing = _failing(m)
    if failing:
        holdout = ["--gps-holdout", m.gps_holdout] if m.gps_holdout else []
        return (_command("ddfuse", "run", *args, "--tune", *holdout, "-o", "ddfuse-tuned"),
                f"a consistency test fails ({', '.join(failing)}): --tune fits the config's "
                "noise values to this bag and runs every estimator with both configs, side by "
                "side (values that fit the sensors can still score worse)")
    outage = bool(m.gps_outages) or str(m.gps_holdout or "").startswith("window")
    if has_gps and not outage and m.duration_s and m.duration_s > 2 * WINDOW_S:
        t0 = math.floor(WINDOW_AT * m.duration_s)
        t1 = min(t0 + WINDOW_S, math.floor(m.duration_s) - 5)
        return (_command("ddfuse", "run", *args, "--gps-holdout", f"window:{t0:g}:{t1:g}",
                         "-o", "ddfuse-outage"),
                "a GPS outage: how far each estimate drifts when dead reckoning carries it")
    if scored and any(n.startswith("smoother") for n in m.estimators):
        return (_command("ddfuse", "lag-sweep", *args),
                "the smoother's score against its lag")
    return None, ""


def headline(m: RunSummary | dict) -> Headline:
    """The run's ``Headline`` from its scores (a RunSummary or a metrics.json dictionary)."""
    if isinstance(m, dict):
        m = RunSummary.from_json(m)
    r = ranking(m)
    lag = m.lag_s
    order = [Place(n, track_kind(n, lag), r.scored[n]) for n in r.order]
    tied = len(r.tied) if order else 0
    margin_m, margin_rel = _margin(order, tied)
    realtime = None
    live = [p for p in order if p.kind == "real time"]
    if order and order[0].kind != "real time" and len(live) >= 2:
        realtime = (live[0], live[1])
    seen, words = set(), []
    nees = any(e.nees and e.nees.verdict for e in m.estimators.values())
    for n, e in m.estimators.items():
        key = repr(sorted((e.nis or {}).items()))
        copied = bool(e.nis) and key in seen
        seen.add(key)
        words.append((n, consistency_word(n, e, m, copied)))
    basis = ("NEES against the ground truth" if nees
             else "NIS of each estimator's own innovations; no ground truth")
    cmd, why = next_step(m, bool(order))
    rate = low_rate_nis(m)
    caveat = None
    if rate:
        caveat = ("NIS Fail, below the band, on rate sensors (" + ", ".join(
            f"{n} {lab}" for n, lab, _ in rate) + "): the motion model's process noise, sized "
            "for the largest accelerations, not the sensor noise (see the verdict).")
    held = tuple((n, _word(e.gps_holdout_nees.verdict, [_direction(e.gps_holdout_nees)]))
                 for n, e in m.estimators.items()
                 if e.samples and e.gps_holdout_nees and e.gps_holdout_nees.verdict)
    return Headline(r.figure, tuple(order), tied, margin_m, margin_rel, realtime, tuple(words),
                    basis, cmd, why, None if order else r.what.removeprefix("No score: "),
                    caveat, held, m.gps_holdout_scored_fixes if held else None)
