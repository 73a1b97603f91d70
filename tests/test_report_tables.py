"""The report's tables from a metrics dictionary alone: they show what the verdict ranks on,
with its tie rule, and say what each figure is (spacing, latency, unresolved errors)."""

from __future__ import annotations

import html
import re

from ddfuse.evaluation import report
from ddfuse.evaluation.scores import RunSummary


def _cells(table: str, name: str) -> list[str]:
    """The text of the cells of ``name``'s row (tags stripped), best-marked ones '**x**'."""
    row = re.search(rf"<tr>(<td class=\"l\"><b>{re.escape(name)}</b></td>.*?)</tr>",
                    table).group(1)
    out = []
    for attrs, body in re.findall(r"<td([^>]*)>(.*?)</td>", row):
        text = html.unescape(re.sub(r"<[^>]+>", "", body))
        out.append(f"**{text}**" if 'class="best"' in attrs else text)
    return out


def _headers(table: str) -> list[str]:
    return [html.unescape(re.sub(r"<[^>]+>", "", h))
            for h in re.findall(r"<th[^>]*>(.*?)</th>", table.split("</tr>")[0])]


def _est(**kw) -> dict:
    return {"nis": {}, "nees": None, "samples": 100, **kw}


def test_the_best_is_marked_on_the_common_stamps_the_verdict_ranks_on():
    """Sample bag: the verdict ties batch 0.0821 and smoother_lagged 0.0850 m (common stamps);
    the table showed only the own ATE (0.082 / 0.088) and bolded batch alone."""
    m = {"estimators": {
        "ekf": _est(ate_rmse_m=0.114, ate_common_rmse_m=0.115),
        "smoother_lagged": _est(ate_rmse_m=0.088, ate_common_rmse_m=0.0850),
        "batch": _est(ate_rmse_m=0.082, ate_common_rmse_m=0.0821)}, "lag_s": 10.0}
    t = report._summary_table(RunSummary.from_json(m))
    heads = _headers(t)
    i, j = heads.index("ATE, common stamps [m]"), heads.index("ATE RMSE [m]")
    assert _cells(t, "batch")[i] == "**0.082**" and _cells(t, "smoother_lagged")[i] == "**0.085**"
    assert _cells(t, "ekf")[i] == "0.115"
    assert not any(_cells(t, n)[j].startswith("**") for n in m["estimators"])  # own ATE
    assert "differ by at most 5% of the larger, the verdict's rule" in html.unescape(t)


def test_one_tie_rule_for_table_and_verdict():
    """0.100 against 0.1053: 5.03 % of the larger, 5.3 % of the smaller. The verdict called it
    a tie (|d|/max <= 5 %), the table did not (v <= 1.05 best). Both now: a tie."""
    from ddfuse.evaluation.verdict import tie, verdict_lines

    m = {"estimators": {"ekf": _est(ate_rmse_m=0.1053), "smoother": _est(ate_rmse_m=0.1)},
         "lag_s": 10.0}
    assert tie(0.1, 0.1053 - 0.0004) and not tie(0.1, 0.1054)
    m["estimators"]["ekf"]["ate_rmse_m"] = 0.1049 / 0.9995  # 0.10495: 4.7 % of the larger
    t = report._summary_table(RunSummary.from_json(m))
    assert _cells(t, "ekf")[2].startswith("**")
    assert "tie" in [x for x in verdict_lines(m) if x.startswith("Real-time")][0]
    m["estimators"]["ekf"]["ate_rmse_m"] = 0.1052  # 4.94 % of the larger, 5.2 % of 0.100
    t = report._summary_table(RunSummary.from_json(m))
    assert _cells(t, "ekf")[2] == "**0.105**"
    assert " tie: " in [x for x in verdict_lines(m) if x.startswith("Real-time")][0]


def test_rpe_cells_show_the_pairs_spacing_where_it_is_not_the_nominal_one():
    """Keyframe tracks' 'RPE 1 s' pairs are 1.2 s apart (mean_delta 1.1997)."""
    m = {"estimators": {
        "ekf": _est(rpe={"1s": {"position_m": {"rmse": 0.024}, "mean_delta": 1.0}}),
        "batch": _est(rpe={"1s": {"position_m": {"rmse": 0.011}, "mean_delta": 1.1997}})},
        "lag_s": 10.0}
    t = report._summary_table(RunSummary.from_json(m))
    k = _headers(t).index("RPE 1 s [m]")
    assert _cells(t, "ekf")[k] == "0.024"
    assert _cells(t, "batch")[k] == "**0.011 (pairs 1.20 s apart)**"


def test_the_offline_tracks_latency_is_footnoted():
    """batch p99 0.574 ms: its whole-run solve in finish() is in no percentile (bench's '*')."""
    u = {"p50": 0.001, "p99": 0.574, "mean": 0.0305, "n": 12296}
    m = {"estimators": {"ekf": _est(runtime_s=0.12, update_ms={**u, "p99": 0.037}),
                        "batch": _est(runtime_s=0.70, update_ms=u)}, "lag_s": 10.0}
    t = report._summary_table(RunSummary.from_json(m))
    assert _cells(t, "batch")[-2] == "0.001 / 0.574 *" and _cells(t, "ekf")[-2].endswith("0.037")
    assert ("* batch: the latencies are of its per-message updates; its whole-run solve runs "
            "once in finish(), in no latency percentile: 0.325 s of its 0.70 s runtime lie "
            "outside its per-message updates.") in t
    m["estimators"]["batch"]["finish_s"] = 0.301  # measured, as bench does
    assert "in no latency percentile: 0.301 s of its 0.70 s runtime." in \
        report._summary_table(RunSummary.from_json(m))


def _nis_rows(table: str) -> dict[tuple[str, str], list[str]]:
    out = {}
    for row in re.findall(r"<tr>(.*?)</tr>", table.split("<p")[0])[1:]:
        cells = [html.unescape(re.sub(r"<[^>]+>", "", c)) for c in
                 re.findall(r"<td[^>]*>(.*?)</td>", row)]
        out[(cells[0], cells[1])] = cells[2:]
    return out


def _row(sensor, kind, acc, rej, mean, verdict, ratio=None):
    return {"sensor": sensor, "kind": kind, "accepted": acc, "rejected": rej, "dof": 1.0,
            "mean": mean, "expected": 1.0, "ratio": ratio or mean, "band": [0.000982, 5.02],
            "below": 0.0, "above": 1.0 if not acc else 0.03, "verdict": verdict}


_SENSORS = {"sensors": [{"name": "/imu/data", "topic": "/imu/data", "kind": "imu",
                         "measurements": {"Heading": 3600, "GyroYawRate": 3600}}]}


def test_nis_table_gate_counts_of_the_smoothers_averaged_heading_and_of_none_accepted():
    """Sample bag: the smoother's heading row said 'gate accepted 300, rejected 0' (its 300
    keyframe averages, logged accepted) while its gate had rejected 1 of the 3600 samples.
    With heading_offset 0.0 every sample was rejected by every estimator: ekf's row showed a
    mean 137.145 of nothing accepted, the smoother's had no row at all and read 'consistent'."""
    m = {"data": _SENSORS, "estimators": {
        "ekf": _est(nis={"/imu/data heading": _row("/imu/data", "heading", 3598, 1, 0.99,
                                                   "Pass")}, rejected={"/imu/data: gate": 1}),
        "smoother": _est(nis={"/imu/data heading": _row("/imu/data", "heading", 300, 0, 1.08,
                                                        "Pass")},
                         rejected={"/imu/data: gate": 1})}}
    rows = _nis_rows(report._nis_table(RunSummary.from_json(m)))
    cells = rows[("smoother", "/imu/data heading, averaged per keyframe (300 values of 3600 "
                              "samples)")]
    assert cells[1:3] == ["3599", "1"]
    m["estimators"]["ekf"]["nis"]["/imu/data heading"] = _row(
        "/imu/data", "heading", 0, 3600, 137.145, "Fail")
    del m["estimators"]["smoother"]["nis"]["/imu/data heading"]
    m["estimators"]["smoother"]["nis"]["/fix gps"] = {
        **_row("/fix", "gps", 297, 0, 2.17, "Pass", 1.08), "dof": 2.0, "expected": 2.0}
    for e in m["estimators"].values():
        e["rejected"] = {"/imu/data: gate": 3600}
    rows = _nis_rows(report._nis_table(RunSummary.from_json(m)))
    ekf = rows[("ekf", "/imu/data heading")]
    assert ekf[1:4] == ["0", "3600", "– / 1"] and ekf[-1] == "rejected throughout"
    sm = rows[("smoother", "/imu/data heading (no NIS logged)")]
    assert sm[1:3] == ["0", "3600"] and sm[-1] == "rejected throughout"


def test_averaged_heading_rows_accepted_count_leaves_out_samples_dropped_before_the_start():
    m = {"data": _SENSORS, "estimators": {"smoother": _est(
        nis={"/imu/data heading": _row("/imu/data", "heading", 300, 0, 1.08, "Pass")},
        rejected={"/imu/data: gate": 2, "/imu/data: before_init": 195})}}
    cells = _nis_rows(report._nis_table(RunSummary.from_json(m)))[
        ("smoother", "/imu/data heading, averaged per keyframe (300 values of 3600 samples)")]
    assert cells[1:3] == ["3403", "2"]


def test_the_gps_model_row_says_where_the_command_line_overrode_the_config():
    from ddfuse.estimation.config import parse_config_text

    cfg = parse_config_text("sensors:\n  gps: [{topic: /fix}]\n")
    m = RunSummary.from_json({"gps_model": "dcs"})
    assert report._gps_model(m, cfg) == "dcs (--gps-model; the config's is default)"
    assert report._gps_model(RunSummary.from_json({"gps_model": "default"}), cfg) == "default"
    assert report._gps_model(RunSummary.from_json({}), cfg) == "not recorded"


def test_the_facts_name_each_gps_topic_that_came_in_bursts():
    m = RunSummary.from_json({"data": {"gps_bursts": [
        {"topic": "/fix", "episodes": 12, "fixes": 85, "largest_m": 94.6, "longest_s": 6.0}]}})
    facts = html.unescape(re.sub(r"<[^>]+>", " ", report._facts(m)))
    assert "GPS against the odometry  /fix: 12 bursts (85 fixes, up to 95 m, the longest " \
           "6.0 s)" in facts
    assert "GPS against the odometry  none found" in html.unescape(
        re.sub(r"<[^>]+>", " ", report._facts(RunSummary.from_json({}))))
