"""The recording clock stepping back mid-bag (header stamps and record times alike) is found in
the write order of a ROS1 bag, of a ROS2 sqlite3 or MCAP bag (``ros2_write_order``), or the
arrival order of live input, said in one warning, and the messages after it re-timed by the
step: the stream is the one recorded without the step.

Before: 10 s of data interleaved (or dropped as 'late' with advice to raise reorder_window),
ekf ATE 0.114 -> 1.115 m and NEES 2.9 -> 417 on the sample, batch 6.3 m, no warning (ROS2 bags:
1157 measurements dropped as late, ekf ATE 1.115 m, no warning)."""

from __future__ import annotations

import math
import pickle
import re
import struct
import sys
from dataclasses import replace
from pathlib import Path

import bagedit
import numpy as np
import pytest
import yaml
from ddfuse.estimation import ros2_write_order
from ddfuse.estimation.bags import BagStream, read_stream
from ddfuse.estimation.clock_steps import ClockSteps
from ddfuse.estimation.config import load_config
from ddfuse.estimation.live import LiveConverter
from ddfuse.evaluation.simulate.bag_writer import make_typestore, write_bag
from ddfuse.evaluation.simulate.simulator import simulate
from rosbags.highlevel import AnyReader

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"
SAMPLE_CFG = ROOT / "data" / "sample_husky.yaml"
STEP_AT, STEP = 40.0, 10.0  # s into the bag, s back


@pytest.fixture(scope="module")
def stepped(tmp_path_factory) -> Path:
    return bagedit.step_back(SAMPLE, tmp_path_factory.mktemp("step") / "step.bag", STEP_AT, STEP)


@pytest.fixture(scope="module")
def clean():
    return read_stream(SAMPLE, load_config(SAMPLE_CFG))


def test_clock_steps_finds_a_backward_record_time_and_retimes_what_follows():
    steps = ClockSteps(1.0)
    out = [steps.retime("/a", t, t) for t in (10.0, 10.1, 10.2)]
    out += [steps.retime("/a", t, t) for t in (0.3, 0.4)]  # 10 s back
    assert [round(t, 6) for t, _ in out] == [10.0, 10.1, 10.2, 10.2, 10.3]
    assert [round(s, 6) for _, s in steps.steps] == [9.9]
    assert steps.retimed == {"/a": 2}
    # a small backward jitter is not a step
    assert ClockSteps(1.0).retime("/a", 5.0, 5.0) == (5.0, 5.0)
    jitter = ClockSteps(1.0)
    jitter.retime("/a", 5.0, 5.0)
    assert jitter.retime("/a", 4.5, 4.5) == (4.5, 4.5) and not jitter.steps


def test_one_garbled_record_time_is_not_a_step():
    """A record time far ahead (a damaged chunk) that the next record comes back from."""
    steps = ClockSteps(1.0)
    out = [steps.retime("/a", t, rt) for t, rt in ((1.0, 1.0), (1.1, 1e6), (1.2, 1.2))]
    assert out[2] == (1.2, 1.2) and not steps.steps
    # a forward gap that the records keep, then a real step back, is still a step
    for t in [5.0 + 0.1 * k for k in range(ClockSteps.OUTLIER_RUN + 2)] + [0.2]:
        steps.retime("/a", t, t)
    assert [round(s, 6) for _, s in steps.steps] == [5.9]


def test_a_topic_stamped_by_another_clock_keeps_its_stamps():
    steps = ClockSteps(1.0)
    for k in range(3):
        steps.retime("/sys", 10.0 + 0.1 * k, 10.0 + 0.1 * k)
        steps.retime("/gps", 10.05 + 0.1 * k, 10.0 + 0.1 * k)  # the receiver's clock
    t_sys, rt = steps.retime("/sys", 0.3, 0.3)
    t_gps, _ = steps.retime("/gps", 10.35, 0.3)  # its stamp did not step
    assert math.isclose(t_sys, 10.2) and math.isclose(rt, 10.2)
    assert t_gps == 10.35 and steps.retimed == {"/sys": 1}


def test_a_stepped_sample_bag_gives_the_clean_stream_and_one_warning(stepped, clean):
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(stepped, cfg)
    ms = list(bs)
    assert len(ms) == len(clean.measurements)  # nothing dropped
    assert not bs.rejected
    t = np.array([m.t for m in ms])
    t_clean = np.array([m.t for m in clean.measurements])
    # the step is measured from the record times: exact to a message interval
    assert np.max(np.abs(t - t_clean)) < 0.05
    [w] = [w for w in bs.warnings if "clock stepped back" in w]
    assert str(stepped) in w and re.search(r"stepped back by (9\.9\d|10\.0\d) s", w)
    assert abs(float(re.search(r" at t=([\d.]+) s", w).group(1)) - STEP_AT) < 0.1
    for topic in ("/odom", "/imu/data", "/fix"):
        assert topic in w


def test_a_topic_whose_stamps_did_not_step_is_not_moved(tmp_path, clean):
    bag = bagedit.step_back(SAMPLE, tmp_path / "gps_clock.bag", STEP_AT, STEP,
                            stamps_kept=("/fix",))
    s = read_stream(bag, load_config(SAMPLE_CFG))
    fixes = [m.t for m in s.measurements if m.sensor == "/fix"]
    assert fixes == [m.t for m in clean.measurements if m.sensor == "/fix"]
    assert len(s.measurements) == len(clean.measurements)


def test_live_input_whose_receive_clock_steps_back_is_retimed():
    cfg = replace(load_config(SAMPLE_CFG), initial_pose=None)
    conv = LiveConverter(cfg)
    with AnyReader([SAMPLE]) as reader:
        conns = [c for c in reader.connections if c.topic == "/imu/data"]
        stamps = []
        for i, (c, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
            if i >= 600:
                break
            msg = reader.deserialize(raw, c.msgtype)
            back = STEP if i >= 300 else 0.0
            if back:  # the header stamp and the receive time alike
                msg.header.stamp.sec -= int(back)
            ms = conv.convert("/imu/data", msg, received=rec_ns * 1e-9 - back)
            stamps.append(ms[0].t)
    assert np.all(np.diff(stamps) > 0)  # no jump back
    assert not conv.rejected
    [w] = conv.warnings
    assert "live input" in w and "stepped back by 9.9" in w and "/imu/data (300)" in w


@pytest.mark.slow
def test_a_stepped_sample_run_scores_as_the_clean_one(stepped, tmp_path):
    """ekf ATE on the stepped sample within 10 % of the clean bag's (0.114 m)."""
    clean, _ = bagedit.ekf_metrics(SAMPLE, SAMPLE_CFG, tmp_path / "clean")
    ekf, warnings = bagedit.ekf_metrics(stepped, SAMPLE_CFG, tmp_path / "stepped")
    assert ekf["ate_rmse_m"] < 1.1 * clean["ate_rmse_m"]
    assert any("clock stepped back" in w for w in warnings)


@pytest.mark.slow
def test_a_stepped_husky_bag_keeps_every_message(husky_bag, tmp_path):
    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    bag = bagedit.step_back(husky_bag, tmp_path / "step.bag", 100.0, STEP)
    clean, s = read_stream(husky_bag, cfg), read_stream(bag, cfg)
    assert len(s.measurements) == len(clean.measurements)
    t = np.array([m.t for m in s.measurements])
    assert np.max(np.abs(t - [m.t for m in clean.measurements])) < 0.05


# --- ROS2 bags: sqlite3 and MCAP, read in write order ------------------------------------------

ROS2 = ("sqlite3", "mcap")
# a test of the reading order in one storage format in the default suite, both in the slow one
SQLITE_FAST = ("sqlite3", pytest.param("mcap", marks=pytest.mark.slow))
MCAP_FAST = (pytest.param("sqlite3", marks=pytest.mark.slow), "mcap")
SIM_FORMAT = {"sqlite3": "ros2", "mcap": "mcap"}  # ``ddfuse simulate --format`` names
SPEED = 1.0  # m/s, the husky scenario's top speed (its 40 m lawnmower legs)


def step_back_ros2(src: Path, dest: Path, fmt: str, at_s: float, by_s: float, *,
                   compression: str | None = None, lag_s: dict[str, float] | None = None,
                   split_s: float | None = None) -> Path:
    """A copy of the ROS2 bag ``src`` (written in record-time order, as the simulator writes)
    in which the recording clock stepped back by ``by_s`` s when ``at_s`` s had been recorded:
    the record time and header stamp of every message after it ``by_s`` s earlier, written
    in the order recorded. ``compression``: rosbags' mode ('storage': zstd MCAP chunks, as
    ros2 bag record writes them, the default for MCAP; 'message': zstd per message; 'none', the
    default for sqlite3). ``lag_s``: topic -> s its messages reach the writer late (their
    record times kept), as a recorder's threads deliver them. ``split_s``: the recording split
    into two files there (s of recording, as ``ros2 bag record --max-bag-duration`` does)."""
    from rosbags.rosbag2 import Reader

    lag = {topic: round(s * 1e9) for topic, s in (lag_s or {}).items()}
    out: list[list] = [[]]  # the messages of each file, in the order written
    with Reader(src) as r:
        cut, by = r.start_time + round(at_s * 1e9), round(by_s * 1e9)
        split = None if split_s is None else r.start_time + round(split_s * 1e9)
        topics = [(c.topic, c.msgtype) for c in r.connections]
        for c, t, raw in sorted(r.messages(), key=lambda m: m[1] + lag.get(m[0].topic, 0)):
            if split is not None and t >= split and len(out) == 1:
                out.append([])
            if t >= cut:
                # every message here begins with a std_msgs/Header, after CDR's 4-byte
                # encapsulation: int32 sec, uint32 nanosec, little-endian
                raw = bytearray(raw)
                sec, nsec = struct.unpack_from("<iI", raw, 4)
                struct.pack_into("<iI", raw, 4, *divmod(sec * 10**9 + nsec - by, 10**9))
                t -= by
            out[-1].append(((c.topic, c.msgtype), t, bytes(raw)))
    compression = compression or ("none" if fmt == "sqlite3" else "storage")
    if len(out) == 1:
        return _write_ros2(dest, fmt, topics, out[0], compression)
    # rosbags writes one file per bag: the parts are written as bags, then their files moved
    # into one directory whose metadata.yaml lists both, in the order written
    parts = [_write_ros2(dest.with_name(f"{dest.name}_{i}"), fmt, topics, msgs, compression)
             for i, msgs in enumerate(out)]
    metas = [yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
             for p in parts]
    meta = metas[0]
    dest.mkdir()
    for p, m in zip(parts, metas, strict=True):
        for name in m["relative_file_paths"]:
            (p / name).rename(dest / name)
    meta["relative_file_paths"] = [n for m in metas for n in m["relative_file_paths"]]
    meta["files"] = [f for m in metas for f in m["files"]]
    meta["message_count"] = sum(m["message_count"] for m in metas)
    for k, tm in enumerate(meta["topics_with_message_count"]):
        tm["message_count"] = sum(m["topics_with_message_count"][k]["message_count"]
                                  for m in metas)
    end = max(m["starting_time"]["nanoseconds_since_epoch"] + m["duration"]["nanoseconds"]
              for m in metas)
    start = min(m["starting_time"]["nanoseconds_since_epoch"] for m in metas)
    meta["starting_time"]["nanoseconds_since_epoch"] = start
    meta["duration"]["nanoseconds"] = end - start
    (dest / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": meta}))
    return dest


def _write_ros2(dest: Path, fmt: str, topics: list, msgs: list, compression: str) -> Path:
    """A ROS2 bag at ``dest`` with a connection per (topic, type) of ``topics`` (all of them,
    in that order) and ``msgs``, ((topic, type), record time ns, CDR bytes), in their order."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    store = make_typestore(SIM_FORMAT[fmt])
    writer = Writer(dest, version=9, storage_plugin=StoragePlugin.SQLITE3 if fmt == "sqlite3"
                    else StoragePlugin.MCAP)
    if compression != "none":
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with writer:
        conns = {k: writer.add_connection(k[0], k[1], typestore=store) for k in topics}
        for k, t, raw in msgs:
            writer.write(conns[k], t, raw)
    return dest


@pytest.fixture(scope="module")
def ros2_bags(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    """fmt -> (clean bag, the same with the clock stepped back 10 s at 40 s): the sample's
    drive (scenario husky, seed 0, 120 s) simulated into ROS2 bags."""
    tmp = tmp_path_factory.mktemp("ros2")
    res = simulate("husky", 0, 120.0)
    out = {}
    for fmt in ROS2:
        clean, _, _ = write_bag(res, tmp / f"clean_{fmt}", SIM_FORMAT[fmt])
        out[fmt] = (clean, step_back_ros2(clean, tmp / f"step_{fmt}", fmt, STEP_AT, STEP))
    return out


def _same(a, b) -> bool:
    """Streams or measurement lists equal to the last bit (measurements hold numpy arrays,
    which ``==`` does not compare as a whole)."""
    return pickle.dumps(a) == pickle.dumps(b)


def _sorted_read(monkeypatch) -> None:
    """Bags read as before: rosbags' AnyReader, sorted by record time."""
    monkeypatch.setattr(ros2_write_order.WriteOrder, "of",
                        classmethod(lambda cls, d: (None, "sorted on purpose")))


@pytest.mark.parametrize("fmt", SQLITE_FAST)
def test_a_ros2_bag_whose_clock_stepped_back_gives_the_clean_stream_and_one_warning(
        fmt, ros2_bags):
    clean_bag, stepped = ros2_bags[fmt]
    cfg = load_config(SAMPLE_CFG)
    clean = read_stream(clean_bag, cfg)
    bs = BagStream(stepped, cfg)
    ms = list(bs)
    assert bs._msgs.write_order is not None and bs._msgs.write_order.storage == fmt
    assert len(ms) == len(clean.measurements)  # nothing dropped as late
    assert not bs.rejected
    t = np.array([m.t for m in ms])
    # the step is measured from the record times: exact to a message interval (IMU, 50 Hz)
    assert np.max(np.abs(t - [m.t for m in clean.measurements])) < 0.05
    [w] = [w for w in bs.warnings if "clock stepped back" in w]
    assert str(stepped) in w and re.search(r"stepped back by (9\.9\d|10\.0\d) s", w)
    assert abs(float(re.search(r" at t=([\d.]+) s", w).group(1)) - STEP_AT) < 0.1
    for topic in ("/odom", "/imu/data", "/fix"):
        assert topic in w


@pytest.mark.parametrize("fmt", MCAP_FAST)
def test_a_ros2_recording_split_in_two_files_is_read_file_after_file(fmt, ros2_bags, tmp_path):
    """Split at 30 s, the clock stepping back in the second file: found, and the stream is the
    clean one."""
    clean_bag, _ = ros2_bags[fmt]
    bag = step_back_ros2(clean_bag, tmp_path / "split", fmt, STEP_AT, STEP, split_s=30.0)
    assert len(ros2_write_order.WriteOrder.of(bag)[0].files) == 2
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(bag, cfg)
    t = np.array([m.t for m in bs])
    clean = read_stream(clean_bag, cfg).measurements
    assert len(t) == len(clean) and np.max(np.abs(t - [m.t for m in clean])) < 0.05
    assert [w for w in bs.warnings if "stepped back by 9.9" in w]


@pytest.mark.parametrize("fmt", ROS2)
def test_a_stepped_ros2_bag_read_sorted_interleaves_the_repeated_seconds(fmt, ros2_bags,
                                                                           monkeypatch):
    """What the write order is for: sorted by record time, the step is not seen, and the 10 s
    after it interleave with the 10 s before: the fixes jump between the two places, so the
    robot-speed screen rejects about half the fixes of those 20 s (144 of 297)."""
    _, stepped = ros2_bags[fmt]
    _sorted_read(monkeypatch)
    bs = BagStream(stepped, load_config(SAMPLE_CFG))
    list(bs)
    assert bs.clock_steps is None
    assert not [w for w in bs.warnings if "clock stepped back" in w]
    assert sum(n for (topic, _), n in bs.rejected.items() if topic == "/fix") > 50


@pytest.mark.parametrize("fmt", SQLITE_FAST)
def test_a_clean_ros2_bag_read_in_write_order_gives_the_sorted_stream(fmt, ros2_bags,
                                                                      monkeypatch):
    clean_bag, _ = ros2_bags[fmt]
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(clean_bag, cfg)
    written = read_stream(clean_bag, cfg)
    assert bs._msgs.write_order is not None
    bs.close()
    _sorted_read(monkeypatch)
    ordered = read_stream(clean_bag, cfg)
    assert _same(written, ordered)


@pytest.mark.parametrize("fmt", MCAP_FAST)
def test_a_ros2_bag_written_a_few_ms_out_of_record_order_gives_the_sorted_stream(
        fmt, ros2_bags, tmp_path, monkeypatch):
    """A recorder's threads write one topic's messages a little late (here /imu/data 8 ms,
    /fix 25 ms: under the 1 s tolerance, so no step) without changing the stream."""
    clean_bag, _ = ros2_bags[fmt]
    bag = step_back_ros2(clean_bag, tmp_path / "lag", fmt, 1e9, 0.0,
                         lag_s={"/imu/data": 0.008, "/fix": 0.025})
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(bag, cfg)
    written = list(bs)
    assert bs.clock_steps is not None and not bs.clock_steps.steps
    _sorted_read(monkeypatch)
    assert _same(written, read_stream(clean_bag, cfg).measurements)


def test_an_mcap_bag_without_the_mcap_packages_decompressors_is_read_sorted(ros2_bags,
                                                                           monkeypatch):
    """Not a damaged bag for want of zstandard (its chunks are zstd): rosbags reads it."""
    clean_bag, _ = ros2_bags["mcap"]
    monkeypatch.setitem(sys.modules, "zstandard", None)  # its import fails
    assert ros2_write_order.WriteOrder.of(clean_bag)[0] is None
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(clean_bag, cfg)
    ms = list(bs)
    assert bs.clock_steps is None and bs._msgs.stopped is None
    monkeypatch.delitem(sys.modules, "zstandard")
    assert _same(ms, read_stream(clean_bag, cfg).measurements)


def test_a_ros2_bag_compressed_per_message_is_read_sorted_as_before(ros2_bags, tmp_path):
    """Per-message (or per-file) compression: rosbags decompresses; the write order is not
    read and a step is not looked for, but the bag reads as before."""
    clean_bag, _ = ros2_bags["sqlite3"]
    bag = step_back_ros2(clean_bag, tmp_path / "zstd", "sqlite3", 1e9, 0.0,
                         compression="message")
    assert ros2_write_order.WriteOrder.of(bag) == (None, "compressed per message")
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(bag, cfg)
    ms = list(bs)
    assert bs.clock_steps is None
    assert _same(ms, read_stream(clean_bag, cfg).measurements)


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ROS2)
def test_a_stepped_ros2_run_scores_as_the_clean_one(fmt, ros2_bags, tmp_path):
    """ekf ATE of the stepped bag at most the clean bag's + SPEED x the largest re-timing error:
    every topic (truth included) shares the recording clock, so after the step all of them are
    off by the same error dt (under a message interval), and a track scored against a truth
    shifted by dt in time is off by at most the distance driven in dt."""
    clean_bag, stepped = ros2_bags[fmt]
    cfg = load_config(SAMPLE_CFG)
    t = np.array([m.t for m in read_stream(stepped, cfg).measurements])
    dt = float(np.max(np.abs(t - [m.t for m in read_stream(clean_bag, cfg).measurements])))
    clean, _ = bagedit.ekf_metrics(clean_bag, SAMPLE_CFG, tmp_path / "clean")
    ekf, warnings = bagedit.ekf_metrics(stepped, SAMPLE_CFG, tmp_path / "stepped")
    assert ekf["ate_rmse_m"] <= clean["ate_rmse_m"] + SPEED * dt
    assert any("clock stepped back" in w for w in warnings)
