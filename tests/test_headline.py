"""The headline (evaluation/headline.py) on constructed runs whose numbers are known: the
winner and its margin are the verdict's ranking, the consistency words follow the NEES / NIS
verdicts, and the next command is one that works for the run's config."""

from __future__ import annotations

import shlex

import pytest
from ddfuse.evaluation.headline import consistency_word, headline
from ddfuse.evaluation.scores import RunSummary
from ddfuse.evaluation.verdict import TIE, tie
from hypothesis import given, settings
from hypothesis import strategies as st

NAMES = ["ekf", "ekf_igvc", "smoother", "smoother_lagged", "batch"]


def _nees(mean: float, verdict: str | None) -> dict:
    return {"n": 300, "dof": 3, "mean": mean, "expected": 3.0, "ratio": mean / 3.0,
            "band": [2.5, 3.5], "below": 0.02, "above": 0.02, "outside": 0.04,
            "verdict": verdict}


def _nis(ratio: float, verdict: str, kind: str, topic: str = "/odom") -> dict:
    return {"sensor": topic, "kind": kind, "accepted": 600, "rejected": 0,
            "n": 600, "dof": 1, "mean": ratio, "expected": 1.0, "ratio": ratio,
            "band": [0.001, 5.0], "below": 0.02, "above": 0.02, "outside": 0.04,
            "verdict": verdict}


def _run(scores: dict[str, float], *, truth: bool = True, common: bool = True,
         gps_fixes: int = 300, gps_sensor: bool = True, holdout: str | None = None,
         **est) -> RunSummary:
    """A RunSummary of tracks with the given scores [m]: ATE (and the same on the common
    stamps) with truth, else GPS hold-out RMSE."""
    ests = {}
    for n, v in scores.items():
        e = {"samples": 500, "span_s": [0.0, 100.0], **est.get(n, {})}
        if truth:
            e["ate_rmse_m"] = v * 1.01  # own stamps: a little off the common ones
            if common:
                e["ate_common_rmse_m"] = v
        else:
            e["gps_holdout_rmse_m"] = v
        ests[n] = e
    sensors = [{"name": "odom", "topic": "/odom", "kind": "odometry", "use": ["v"]}]
    if gps_sensor:
        sensors.append({"name": "fix", "topic": "/fix", "kind": "gps", "use": ["xy"]})
    return RunSummary.from_json({
        "bag": "/data/b.bag", "config": "/data/b.yaml", "duration_s": 120.0, "lag_s": 10.0,
        "estimators": ests, "gps_holdout": holdout,
        "gps_holdout_fixes": 60 if holdout else None,
        "ate_common": {"stamps": 300, "of": "ekf", "span_s": [0.0, 100.0]}
        if truth and common else None,
        "data": {"t0": 0.0, "gps_fixes": gps_fixes, "sensors": sensors,
                 "ground_truth_samples": 1000 if truth else 0}})


scores = st.dictionaries(st.sampled_from(NAMES), st.floats(0.01, 5.0), min_size=2,
                         max_size=5)


@settings(max_examples=60, deadline=None)
@given(scores, st.booleans(), st.booleans())
def test_the_winner_and_margin_are_the_lowest_score_and_the_gap_to_the_first_not_tied(
        s, truth, common):
    h = headline(_run(s, truth=truth, common=common))
    order = sorted(s, key=s.get)
    assert [p.name for p in h.order] == order
    assert h.score == ("ate_common_rmse_m" if truth and common else
                       "ate_rmse_m" if truth else "gps_holdout_rmse_m")
    own = {n: v * (1.01 if truth and not common else 1.0) for n, v in s.items()}
    best = order[0]
    tied = [n for n in order if tie(own[best], own[n])]
    assert h.tied == len(tied) and order[:h.tied] == tied
    first = h.lines()[0]
    assert first.startswith(f"Best: {best}") and f"{own[best]:.3f} m" in first
    rest = [n for n in order if n not in tied]
    if rest:
        assert h.margin_m == pytest.approx(own[rest[0]] - own[best])
        assert h.margin_rel == pytest.approx(1 - own[best] / own[rest[0]])
        assert h.margin_rel > TIE
        assert f"{h.margin_m:.3f} m ({100 * h.margin_rel:.0f}%) lower than the next, " \
               f"{rest[0]}" in first
    else:
        assert h.margin_m is None and "lower than" not in first


def test_an_offline_winner_is_followed_by_the_best_real_time_track():
    h = headline(_run({"batch": 0.08, "smoother_lagged": 0.2, "smoother": 0.3, "ekf": 0.5}))
    lines = h.lines()
    assert lines[0].startswith("Best: batch (offline), ATE on common stamps 0.080 m; "
                               "0.120 m (60%) lower than the next, smoother_lagged "
                               "(lagged by 10 s) 0.200 m.")
    assert lines[1] == ("Best in real time: smoother 0.300 m, 0.200 m (40%) lower than the "
                        "next, ekf 0.500 m.")


def test_no_score_says_why_and_names_no_winner():
    h = headline(RunSummary.from_json({"bag": "j.bag", "estimators": {"ekf": {"samples": 10}},
                                       "data": {"gps_fixes": 0, "sensors": []}}))
    assert h.best is None and h.lines()[0].startswith(
        "No winner: the bag has neither ground truth nor GPS fixes")


@pytest.mark.parametrize("nees, nis, word", [
    (("Pass", 3.1), None, "consistent"),
    (("Fail", 12.0), None, "over-confident"),
    (("Warn", 1.8), None, "mildly under-confident"),
    (None, [(0.2, "Fail", "v"), (1.0, "Pass", "gps")], "under-confident"),
    (None, [(9.0, "Fail", "gps"), (0.1, "Fail", "v")], "mixed"),
    (None, [(1.0, "Pass", "gps")], "consistent"),
    (None, None, "not checked"),
])
def test_one_consistency_word_from_the_nees_else_the_nis(nees, nis, word):
    e = {}
    if nees:
        e["nees"] = _nees(nees[1], nees[0])
    if nis:
        e["nis"] = {f"/t{k} {kind}": _nis(r, v, kind, f"/t{k}")
                    for k, (r, v, kind) in enumerate(nis)}
    m = _run({"ekf": 0.1, "smoother": 0.2}, ekf=e)
    assert consistency_word("ekf", m.estimators["ekf"], m, copied=False) == word
    assert dict(headline(m).consistency)["ekf"] == word


def _next(m: RunSummary) -> list[str]:
    h = headline(m)
    return shlex.split(h.next_command) if h.next_command else []


def test_without_truth_a_gps_hold_out_is_suggested_only_where_there_is_gps():
    no_truth = _run({"ekf": 1.0}, truth=False)
    no_truth = RunSummary.from_json({**no_truth.to_json(), "estimators": {
        "ekf": {"samples": 100}, "smoother": {"samples": 100}}})
    assert _next(no_truth)[:5] == ["ddfuse", "run", "/data/b.bag", "--gps-holdout", "every:5"]
    jackal = RunSummary.from_json({**no_truth.to_json(), "data": {
        "gps_fixes": 0, "sensors": [{"name": "o", "topic": "/odom", "kind": "odometry"}]}})
    assert "--gps-holdout" not in _next(jackal)


def test_a_consistency_failure_suggests_tune_with_the_runs_hold_out():
    m = _run({"ekf": 0.5, "smoother": 0.2}, truth=False, holdout="every:5",
             ekf={"nis": {"/fix gps": _nis(8.0, "Fail", "gps", "/fix")}})
    assert _next(m) == ["ddfuse", "run", "/data/b.bag", "--tune", "--gps-holdout", "every:5",
                        "-o", "ddfuse-tuned"]


def test_a_low_rate_nis_beside_a_passing_nees_is_explained_not_tuned():
    m = _run({"ekf": 0.12, "smoother": 0.1},
             ekf={"nees": _nees(2.9, "Pass"), "nis": {"/odom v": _nis(0.19, "Fail", "v")}})
    h = headline(m)
    assert "ekf /odom v" in h.caveat and "process noise" in h.caveat
    cmd = _next(m)
    assert cmd[:3] == ["ddfuse", "run", "/data/b.bag"] and cmd[3:5] == [
        "--gps-holdout", "window:48:78"]


def test_a_config_not_beside_the_bag_is_passed_with_c():
    m = _run({"ekf": 0.5, "smoother": 0.2}, ekf={"nees": _nees(20.0, "Fail")})
    m = RunSummary.from_json({**m.to_json(), "config": "/elsewhere/my config.yaml"})
    assert _next(m) == ["ddfuse", "run", "/data/b.bag", "-c", "/elsewhere/my config.yaml",
                        "--tune", "-o", "ddfuse-tuned"]


def test_no_next_command_when_no_estimator_estimated():
    m = _run({"ekf": 1.0}, truth=False)
    m = RunSummary.from_json({**m.to_json(), "estimators": {
        "ekf": {"samples": 0, "error": "no estimate: it never started"}}})
    h = headline(m)
    assert h.next_command is None and not any(x.startswith("Next:") for x in h.lines())
    assert h.consistency == (("ekf", "no estimate"),)


def _bursty(m: RunSummary, model: str | None) -> RunSummary:
    d = m.to_json()
    d["data"]["gps_bursts"] = [{"topic": "/fix", "episodes": 12, "fixes": 85,
                                "largest_m": 95.0, "longest_s": 6.0}]
    return RunSummary.from_json({**d, "gps_model": model})


@pytest.mark.parametrize("model", ["default", "gaussian"])
def test_gps_bursts_under_a_gating_model_suggest_the_robust_model_first(model):
    """Bursts outrank a consistency failure (tuning would fit the noise to them); with
    nothing else to score the run the command withholds fixes too."""
    failing = _run({"ekf": 0.5, "smoother": 0.2}, ekf={"nees": _nees(20.0, "Fail")})
    h = headline(_bursty(failing, model))
    assert _next(_bursty(failing, model)) == [
        "ddfuse", "run", "/data/b.bag", "--gps-model", "dcs", "-o", "ddfuse-dcs"]
    assert "12 bursts" in h.next_why and f"'{model}'" in h.next_why
    unscored = _run({"ekf": 1.0}, truth=False)
    unscored = RunSummary.from_json({**unscored.to_json(), "estimators": {
        "ekf": {"samples": 100}}})
    assert _next(_bursty(unscored, model))[3:7] == [
        "--gps-model", "dcs", "--gps-holdout", "every:5"]
    held = _run({"ekf": 0.5, "smoother": 0.2}, truth=False, holdout="window:50:80")
    assert _next(_bursty(held, model))[3:7] == [
        "--gps-model", "dcs", "--gps-holdout", "window:50:80"]


@pytest.mark.parametrize("model", ["dcs", "cauchy", None])
def test_gps_bursts_under_a_robust_or_unrecorded_model_suggest_no_model(model):
    m = _bursty(_run({"ekf": 0.5, "smoother": 0.2}, ekf={"nees": _nees(20.0, "Fail")}), model)
    assert "--gps-model" not in _next(m) and "--tune" in _next(m)


def test_a_gps_model_from_the_command_line_is_carried_into_the_next_command():
    m = _run({"ekf": 0.5, "smoother": 0.2}, ekf={"nees": _nees(20.0, "Fail")})
    d = {**m.to_json(), "gps_model": "dcs", "gps_model_option": True}
    assert _next(RunSummary.from_json(d)) == [
        "ddfuse", "run", "/data/b.bag", "--gps-model", "dcs", "--tune", "-o", "ddfuse-tuned"]
    d["gps_model_option"] = False  # the config's own dcs: nothing to carry
    assert "--gps-model" not in _next(RunSummary.from_json(d))


def test_no_hold_out_is_offered_for_want_of_truth_when_the_truth_is_there():
    """Every track ended in error (a datum 4462 km off): nothing scored, but the bag has its
    truth; a hold-out 'for want of ground truth' would be wrong. The errors say what to fix."""
    m = _run({"ekf": 1.0}, truth=False)
    m = RunSummary.from_json({**m.to_json(), "has_ground_truth": True, "estimators": {
        "ekf": {"samples": 21, "error": "numerical breakdown at t=2.1: ..."}}})
    assert headline(m).next_command is None
    m = RunSummary.from_json({**m.to_json(), "has_ground_truth": False})
    assert _next(m)[3:5] == ["--gps-holdout", "every:5"]


def test_the_hold_out_nees_checks_every_track_that_has_one():
    """Without truth the NIS line cannot check a lagged or batch track (they share the
    smoother's innovations); a NEES on the withheld fixes can, and gets its own line with the
    same words; a track without one is not named in it, and a run without one has no line."""
    held = {"n": 150, "dof": 2, "mean": 6.9, "expected": 2.0, "ratio": 3.45, "band": [0.05, 7.4],
            "below": 0.0, "above": 0.55, "outside": 0.55, "verdict": "Fail"}
    ok = {**held, "mean": 2.1, "ratio": 1.05, "above": 0.04, "outside": 0.06, "verdict": "Pass"}
    m = _run({"ekf": 3.6, "smoother_lagged": 3.2, "batch": 3.3}, truth=False,
             holdout="window:150:210", ekf={"gps_holdout_nees": held},
             smoother_lagged={"gps_holdout_nees": ok})
    m = RunSummary.from_json({**m.to_json(), "gps_holdout_scored_fixes": 150})
    h = headline(m)
    assert dict(h.holdout) == {"ekf": "over-confident", "smoother_lagged": "consistent"}
    line = next(x for x in h.lines() if x.startswith("Hold-out consistency"))
    assert line == ("Hold-out consistency (NEES on the 150 withheld fixes: does the covariance "
                    "cover the error?): ekf over-confident, smoother_lagged consistent.")
    assert dict(h.consistency)["smoother_lagged"] == "not checked"  # the NIS line's, unchanged
    plain = headline(_run({"ekf": 3.6, "batch": 3.3}, truth=False, holdout="every:5"))
    assert not plain.holdout and not any(x.startswith("Hold-out") for x in plain.lines())
