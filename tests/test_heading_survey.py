"""estimation.heading_survey: a compass's heading offset measured against the GPS course, and the
warnings it gives about the config (``ddfuse inspect``, ``ddfuse run``)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from ddfuse.estimation import heading_survey as hs
from ddfuse.estimation.baginfo import bag_info, offset_surveys, suggest_config
from ddfuse.estimation.measurements import Heading
from ddfuse.evaluation import cli
from ddfuse.evaluation.shipped import SAMPLE_BAG

TRUE_OFFSET = 0.35  # rad, the sample's simulated IMU (data/sample_husky.yaml)


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def survey(cfg, measurements) -> hs.OffsetSurvey:
    rec = hs.recorder_for(cfg)
    for m in measurements:
        rec.add(m)
    (sv,) = rec.surveys()
    return sv


def with_imu(cfg, **changes):
    return replace(cfg, sensors=[replace(s, **changes) if s.kind == "imu" else s
                                 for s in cfg.sensors])


def median_sigma(sv) -> float:
    return float(np.median([w.sigma for w in sv.windows]))


def lawnmower(rng, n: int = 75, speed: float = 1.0, dt: float = 0.4) -> np.ndarray:
    """A 30 s path with a half turn in it: (n, 2) m."""
    yaw = np.where(np.arange(n) < n // 2, 0.0, np.linspace(0.0, math.pi, n))
    yaw = yaw + 0.02 * rng.standard_normal(n)
    step = speed * dt * np.column_stack([np.cos(yaw), np.sin(yaw)])
    return np.cumsum(step, axis=0)


def test_a_window_gives_the_rotation_its_sigma_and_leaves_an_outlier_out():
    rng = np.random.default_rng(4)
    off, sd = 0.6, 0.7  # rad; m of GPS noise per axis
    c, s = math.cos(-off), math.sin(-off)
    errs, sigmas = [], []
    for _ in range(300):
        a = lawnmower(rng)
        b = a @ np.array([[c, s], [-s, c]]) + (30.0, -12.0) + sd * rng.standard_normal(a.shape)
        b[20] += (25.0, 30.0)  # a multipath outlier
        w = hs.fit_window(np.arange(len(a)) * 0.4, a, b)
        assert w.fixes == len(a) - 1
        errs.append(wrap(w.offset - off))
        sigmas.append(w.sigma)
    # the stated sigma is the spread of the estimates (for white noise)
    assert 0.8 < np.std(errs) / np.mean(sigmas) < 1.25
    assert abs(np.mean(errs)) < 4 * np.mean(sigmas) / math.sqrt(len(errs))


def test_a_window_where_the_robot_stands_still_gives_nothing():
    rng = np.random.default_rng(1)
    a = 0.3 * rng.standard_normal((40, 2))  # 0.4 m of wander: no rotation to fit
    assert hs.fit_window(np.arange(40.0), a, a + rng.standard_normal(a.shape)) is None
    assert hs.fit_window(np.arange(4.0), lawnmower(rng, 4), lawnmower(rng, 4)) is None


def test_offsets_on_both_sides_of_180_degrees_are_one_cluster():
    wins = tuple(hs.OffsetWindow(i, i + 1.0, math.radians(d), 0.01, 50, 8.0, 0.5)
                 for i, d in enumerate((179.0, -179.0, 178.0, -177.0)))
    sv = hs.OffsetSurvey("/imu", wins)
    assert abs(wrap(sv.median - math.pi)) < 1e-9  # 178, 179, 181, 183 deg
    assert sv.spread == pytest.approx(math.radians(5.0))


def test_the_sample_compass_offset_is_measured_and_the_config_agrees(sample_husky):
    cfg, stream = sample_husky
    sv = survey(cfg, stream.measurements)
    assert sv.sensor == "/imu/data" and len(sv.windows) == 4  # 120 s in windows of 30 s
    assert abs(wrap(sv.median - TRUE_OFFSET)) < 2 * median_sigma(sv)
    assert not sv.wanders
    assert hs.config_warnings([sv], cfg) == []  # estimated, walk 0: right for this compass
    assert hs.config_warnings([sv], with_imu(cfg, heading_offset=TRUE_OFFSET)) == []


def test_a_wrong_fixed_offset_is_named_with_the_measured_one(sample_husky):
    cfg, stream = sample_husky
    sv = survey(cfg, stream.measurements)
    (w,) = hs.config_warnings([sv], with_imu(cfg, heading_offset=0.0))
    assert w.startswith("/imu/data: heading_offset is fixed at +0.000 rad")
    assert f"{sv.median:+.3f} rad" in w and "'estimate'" in w


def test_an_offset_that_wanders_is_found_and_a_walk_suggested(sample_husky):
    cfg, stream = sample_husky
    t0, drift = stream.measurements[0].t, 0.5 / 120.0  # rad/s: 0.5 rad over the run
    moved = [replace(m, yaw=wrap(m.yaw + drift * (m.t - t0))) if isinstance(m, Heading) else m
             for m in stream.measurements]
    sv = survey(cfg, moved)
    for w in sv.windows:  # each window: the offset at its middle, to 4 sigma
        true = TRUE_OFFSET + drift * (0.5 * (w.t0 + w.t1) - t0)
        assert abs(wrap(w.offset - true)) < 4 * w.sigma + drift * (w.t1 - w.t0) / 4
    first, last = sv.windows[0], sv.windows[-1]
    expected = drift * (0.5 * (last.t0 + last.t1) - 0.5 * (first.t0 + first.t1))
    assert abs(sv.spread - expected) < 4 * math.sqrt(2) * median_sigma(sv)
    assert sv.wanders
    warnings = hs.config_warnings([sv], cfg)  # the sample states heading_offset_walk 0
    assert len(warnings) == 1 and "wanders by" in warnings[0]
    assert f"heading_offset_walk {hs.suggested_walk(sv)}" in warnings[0]
    assert hs.suggested_walk(sv) >= sv.spread / math.sqrt(sv.duration)
    # a fixed offset that wanders is wrong twice over: far from the median and not constant
    assert len(hs.config_warnings([sv], with_imu(cfg, heading_offset=-1.0))) == 2


@pytest.mark.slow
def test_the_husky_compass_offset_drifts_as_the_bag_notes_say(husky_bag):
    """../shared/data/README.md: the IMU's yaw relative to the GPS course drifts from about
    -225 deg early in the run to about -180 deg later (+135 to +180 deg)."""
    info = bag_info(husky_bag)
    (sv,) = offset_surveys(husky_bag, suggest_config(info))
    deg = [math.degrees(w.offset) % 360.0 for w in sv.windows]
    assert len(deg) == 13
    assert all(130.0 < d < 155.0 for d in deg[:3])
    assert all(160.0 < d < 190.0 for d in deg[-3:])
    assert sv.wanders
    (imu,) = suggest_config(info, [sv])["sensors"]["imu"]
    assert imu["noise"]["heading_offset_walk"] == hs.suggested_walk(sv) > 0.0
    assert imu["heading_offset"] == "estimate"


@pytest.mark.slow
def test_run_warns_about_a_wrong_fixed_offset_in_its_output_and_report(tmp_path, capsys):
    cfg_text = (SAMPLE_BAG.with_suffix(".yaml")).read_text()
    assert "heading_offset: estimate" in cfg_text
    bad = tmp_path / "bad.yaml"
    bad.write_text(cfg_text.replace("heading_offset: estimate", "heading_offset: 0.0"))
    out = tmp_path / "out"
    assert cli.main(["run", str(SAMPLE_BAG), "-c", str(bad), "-o", str(out),
                     "--estimators", "ekf"]) == 0
    err = capsys.readouterr().err
    assert "ddfuse: warning: /imu/data: heading_offset is fixed at +0.000 rad" in err
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["warnings"]) == 1 and m["warnings"][0] in err
    (row,) = m["data"]["heading_offsets"]
    assert abs(wrap(row["median_rad"] - TRUE_OFFSET)) < 0.05 and len(row["windows"]) == 4
    page = (out / "report.html").read_text()
    assert "<h2>Warnings" in page and "heading_offset is fixed at +0.000" in page
    assert "yaw minus GPS course +19." in page  # the measured offset, in the data facts


def test_inspect_without_a_usable_fix_reports_the_bag_and_no_offset(tmp_path, capsys):
    import bagwriter as bw

    t0 = 1_500_000_000.0
    recs = [("/odom", bw.odometry(t0 + 0.1 * i, 1.0, 0.0)) for i in range(200)]
    recs += [("/imu", bw.imu(t0 + 0.1 * i + 0.05, quat=bw.yaw_quat(0.3))) for i in range(200)]
    recs += [("/fix", bw.navsatfix(t0 + 0.5 * i, 42.0, -71.0, status=-1)) for i in range(40)]
    recs.sort(key=lambda r: r[1].stamp)
    bag = bw.write_bag(bw.bag_path(tmp_path, "nofix", "ros1"), "ros1", recs)
    info = bag_info(bag)
    assert offset_surveys(bag, suggest_config(info)) == []  # no datum, no course: nothing
    assert cli.main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "40 NO_FIX of 40" in out and "yaw minus GPS course" not in out


def test_online_warns_about_a_wrong_fixed_offset_as_run_does(tmp_path, capsys):
    cfg_text = SAMPLE_BAG.with_suffix(".yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(cfg_text.replace("heading_offset: estimate", "heading_offset: 0.0"))
    assert cli.main(["online", str(SAMPLE_BAG), "-c", str(bad), "--estimators", "ekf",
                     "--every", "60"]) == 0
    err = capsys.readouterr().err
    assert "ddfuse: warning: /imu/data: heading_offset is fixed at +0.000 rad" in err
    assert cli.main(["online", str(SAMPLE_BAG), "--estimators", "ekf", "--every", "60"]) == 0
    assert "warning" not in capsys.readouterr().err


@pytest.mark.slow
def test_gps_errors_correlated_over_30_s_do_not_make_a_constant_offset_wander():
    """husky-multipath: a constant compass offset, GPS errors a 30 s Gauss-Markov process.
    The windows scatter by more than DRIFT_RAD (each fit follows its window's GPS wander) with
    fit sigmas far smaller than that scatter; independent from window to window, so their
    successive ratio stays near 2 and nothing wanders. rl_husky_gps.bag's offset does."""
    from ddfuse.evaluation.montecarlo import seed_data

    sim, cfg, stream, _, _ = seed_data("husky-multipath", 1)
    sv = survey(cfg, stream.measurements)
    assert len(sv.windows) == 13 and sv.spread > hs.DRIFT_RAD > 8 * median_sigma(sv)
    assert sv.successive_ratio > 1.2 and not sv.wanders
    assert abs(wrap(sv.median - sim.scenario.imu.heading_offset)) < 0.05
    assert hs.config_warnings([sv], with_imu(cfg, heading_offset=0.35)) == []
