"""estimates.mcap: every run's tracks, ground truth and GPS fixes as ROS 2 messages in MCAP,
read back with rosbags and with the mcap reader (mcap-ros2-support), written whole or not at
all."""

from __future__ import annotations

import errno
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.estimate_msgs import fix_of, odometry_of, transform_of
from ddfuse.estimation.estimator import Estimate
from ddfuse.evaluation import atomic_files
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.estimates_mcap import (
    ESTIMATES_FILE,
    GPS_TOPIC,
    GPS_WITHHELD_TOPIC,
    TF_TOPIC,
    TRUTH_TOPIC,
    write_estimates,
)
from ddfuse.evaluation.ros_messages import navsatfix_msg, odometry_msg, tf_msg, typestore
from ddfuse.evaluation.run_files import INCOMPLETE

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"


@pytest.fixture(scope="module")
def sample_run(sample_husky, tmp_path_factory):
    """The sample bag run with the EKF and the smoother, every 5th fix withheld, written by
    ``write_outputs`` (what ``node -o`` calls): (cfg, result, estimates.mcap)."""
    from ddfuse.estimation.runner import run
    from ddfuse.evaluation.estimators import build
    from ddfuse.evaluation.pipeline import score, write_outputs

    cfg, stream = sample_husky
    result = run(stream, build(cfg, stream, ["ekf", "smoother"]), holdout="every:5")
    out = tmp_path_factory.mktemp("run")
    write_outputs(result, out, score(result), cfg=cfg)
    return cfg, result, out / ESTIMATES_FILE


def _rosbags_read(path: Path) -> tuple[dict[str, list], dict[str, str]]:
    """topic -> [(log time ns, message)], topic -> type, with rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader

    msgs: dict[str, list] = defaultdict(list)
    with AnyReader([path]) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        for con, ns, raw in r.messages():
            msgs[con.topic].append((ns, r.deserialize(raw, con.msgtype)))
    return msgs, types


def _tracks(result) -> dict:
    return {n: r.trajectory for n, r in result.runs.items() if len(r.trajectory)}


def _stamp(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def _yaw(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def _wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def test_topics_and_counts_match_the_tracks(sample_run):
    cfg, result, path = sample_run
    msgs, types = _rosbags_read(path)
    tracks = _tracks(result)
    assert set(tracks) == {"ekf", "smoother", "smoother_lagged"}
    want = {TF_TOPIC: ("tf2_msgs/msg/TFMessage", len(tracks["smoother"])),
            TRUTH_TOPIC: ("nav_msgs/msg/Odometry", len(result.truth)),
            GPS_TOPIC: ("sensor_msgs/msg/NavSatFix", int((~result.gps.withheld).sum())),
            GPS_WITHHELD_TOPIC: ("sensor_msgs/msg/NavSatFix", int(result.gps.withheld.sum()))}
    for name, tr in tracks.items():
        want[f"/ddfuse/{name}/odom"] = ("nav_msgs/msg/Odometry", len(tr))
        want[f"/ddfuse/{name}/fix"] = ("sensor_msgs/msg/NavSatFix", len(tr))
    assert {t: (types[t], len(m)) for t, m in msgs.items()} == want
    # the smoother's pose is on /tf (the node's rule), local -> base frame
    tf = msgs[TF_TOPIC][-1][1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == (cfg.local_frame, cfg.base_frame)
    assert tf.transform.translation.x == tracks["smoother"].pose[-1, 0]


def test_header_stamps_and_log_times_are_the_estimates_times(sample_run):
    _, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    for name, tr in _tracks(result).items():
        got = msgs[f"/ddfuse/{name}/odom"]
        stamps = np.array([_stamp(m.header) for _, m in got])
        assert np.abs(stamps - tr.t).max() < 1e-6
        assert [ns for ns, _ in got] == [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                         for _, m in got]
    # the file is in log-time order: rosbag play and streaming readers need no sort
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert times == sorted(times)


def test_the_final_pose_of_each_estimator_is_its_tracks_last_row(sample_run):
    _, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    for name, tr in _tracks(result).items():
        o = msgs[f"/ddfuse/{name}/odom"][-1][1]
        p = o.pose.pose
        assert abs(p.position.x - tr.pose[-1, 0]) < 1e-9
        assert abs(p.position.y - tr.pose[-1, 1]) < 1e-9
        assert abs(_wrap(_yaw(p.orientation) - tr.pose[-1, 2])) < 1e-9
        c = o.pose.covariance.reshape(6, 6)
        assert np.abs(c[np.ix_((0, 1, 5), (0, 1, 5))] - tr.cov[-1]).max() < 1e-12


@pytest.mark.slow
def test_the_mcap_reader_decodes_the_same_messages(sample_run):
    """Foxglove's own reader and ROS 2 decoder (mcap-ros2-support): profile ros2, ros2msg
    schemas, cdr messages; every message decodes and the poses are the tracks'."""
    mcap_ros2 = pytest.importorskip("mcap_ros2.decoder")
    from mcap.reader import make_reader

    _, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    counts: dict[str, int] = defaultdict(int)
    last = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[mcap_ros2.DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for _, channel, _, decoded in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            last[channel.topic] = decoded
    assert dict(counts) == {t: len(m) for t, m in msgs.items()}
    for name, tr in _tracks(result).items():
        p = last[f"/ddfuse/{name}/odom"].pose.pose.position
        assert (p.x, p.y) == (tr.pose[-1, 0], tr.pose[-1, 1])


def test_each_message_is_the_estimate_msgs_fields_serialised_by_rosbags(sample_run):
    """The encoded bytes equal rosbags' serialize_cdr of odometry_of / fix_of / transform_of's
    fields, estimate by estimate: one derivation, whatever the fast path does."""
    cfg, result, path = sample_run
    from mcap.reader import make_reader

    raw: dict[str, list[bytes]] = defaultdict(list)
    with open(path, "rb") as f:
        for _, channel, m in make_reader(f).iter_messages():
            raw[channel.topic].append(m.data)
    ts, datum = typestore(), result.stream.datum
    local, base = cfg.local_frame, cfg.base_frame
    for name, tr in _tracks(result).items():
        for i in [*range(0, len(tr), 97), len(tr) - 1]:
            e = Estimate(float(tr.t[i]), tuple(tr.pose[i]), tr.cov[i])
            assert raw[f"/ddfuse/{name}/odom"][i] == ts.serialize_cdr(
                odometry_msg(odometry_of(e, local, base)), "nav_msgs/msg/Odometry")
            assert raw[f"/ddfuse/{name}/fix"][i] == ts.serialize_cdr(
                navsatfix_msg(fix_of(e, datum, base)), "sensor_msgs/msg/NavSatFix")
            if name == "smoother":
                assert raw[TF_TOPIC][i] == ts.serialize_cdr(
                    tf_msg([transform_of(e, local, base)]), "tf2_msgs/msg/TFMessage")


def test_the_fixes_convert_back_to_the_enu_positions(sample_run):
    _, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    datum = result.stream.datum
    for name, tr in _tracks(result).items():
        fixes = [m for _, m in msgs[f"/ddfuse/{name}/fix"]]
        lat, lon, alt = (np.array([getattr(m, k) for m in fixes])
                         for k in ("latitude", "longitude", "altitude"))
        e, n, _ = geodesy.geodetic_to_enu(lat, lon, alt, *datum)
        assert np.abs(np.column_stack([e, n]) - tr.pose[:, :2]).max() < 1e-6


def test_covariances_are_symmetric_positive_definite(sample_run):
    _, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    for name in _tracks(result):
        for kind, k in (("odom", 6), ("fix", 3)):
            cov = np.array([m.pose.covariance if kind == "odom" else m.position_covariance
                            for _, m in msgs[f"/ddfuse/{name}/{kind}"]]).reshape(-1, k, k)
            assert np.array_equal(cov, np.swapaxes(cov, 1, 2)), (name, kind)
            assert np.linalg.eigvalsh(cov).min() > 0, (name, kind)
        twist = np.array([m.twist.covariance for _, m in msgs[f"/ddfuse/{name}/odom"]])
        assert np.linalg.eigvalsh(twist.reshape(-1, 6, 6)).min() > 0


def test_the_gps_fixes_are_the_bags(sample_run):
    """One message per fix: the bag's header stamp, lat/lon/alt, and the covariance the
    estimators were given (here the config's noise); the withheld fixes (every 5th) on their
    own topic."""
    from rosbags.highlevel import AnyReader

    cfg, result, path = sample_run
    msgs, _ = _rosbags_read(path)
    gps = next(s for s in cfg.sensors if s.kind == "gps")
    with AnyReader([SAMPLE]) as r:
        bag = [r.deserialize(raw, c.msgtype)
               for c, _, raw in r.messages([c for c in r.connections if c.topic == gps.topic])]
    assert len(bag) == len(result.gps)
    got = sorted(msgs[GPS_TOPIC] + msgs[GPS_WITHHELD_TOPIC], key=lambda x: x[0])
    assert [(m.latitude, m.longitude, m.altitude) for _, m in got] == [
        (b.latitude, b.longitude, b.altitude) for b in bag]
    stamps = np.array([_stamp(m.header) for _, m in got])
    assert np.abs(stamps - np.array([_stamp(b.header) for b in bag])).max() < 1e-6
    cov = np.array([m.position_covariance for _, m in got]).reshape(-1, 3, 3)
    assert np.array_equal(cov, result.gps.enu_cov)
    held = [m.latitude for _, m in msgs[GPS_WITHHELD_TOPIC]]
    assert held == [b.latitude for b in bag[4::5]]


def test_ddfuse_run_writes_it_in_the_configs_frames_tf_from_the_first_without_smoother(
        tmp_path):
    """``ddfuse run`` (``--no-report``: the report is not where the estimates are) writes
    estimates.mcap; frame.local/base name the frames; without a smoother /tf carries the first
    estimator's pose."""
    text = (ROOT / "data" / "sample_husky.yaml").read_text()
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text.replace("frame:\n", "frame:\n  local: odom\n  base: base_footprint\n"))
    out = tmp_path / "out"
    assert main(["run", str(SAMPLE), "-c", str(cfg), "-o", str(out), "--estimators",
                 "dr,ekf", "--no-report"]) == 0
    msgs, _ = _rosbags_read(out / ESTIMATES_FILE)
    o = msgs["/ddfuse/dr/odom"][0][1]
    assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_footprint")
    assert msgs["/ddfuse/dr/fix"][0][1].header.frame_id == "base_footprint"
    tf = [m.transforms[0].transform.translation.x for _, m in msgs[TF_TOPIC]]
    dr = [m.pose.pose.position.x for _, m in msgs["/ddfuse/dr/odom"]]
    assert tf == dr
    assert not (out / INCOMPLETE).exists()


def _partials(d: Path) -> list[Path]:
    return sorted(d.rglob(f"*{atomic_files.PARTIAL}*"))


@pytest.mark.slow
def test_a_run_killed_while_writing_it_leaves_no_truncated_file(tmp_path):
    """SIGKILL half way through estimates.mcap: the previous run's is gone (removed first, it
    would not match the new tracks), the new one is only a .partial- file, the directory is
    marked incomplete; the next run completes it."""
    out = tmp_path / "out"
    args = ["run", "-o", str(out), "--estimators", "dr", "--no-report"]
    assert main(args) == 0 and (out / ESTIMATES_FILE).is_file()
    script = textwrap.dedent(f"""
        import os, signal
        from mcap.writer import Writer
        real, n = Writer.add_message, [0]
        def add_then_die(self, *a, **k):
            n[0] += 1
            if n[0] == 2000:
                os.kill(os.getpid(), signal.SIGKILL)
            return real(self, *a, **k)
        Writer.add_message = add_then_die
        from ddfuse.evaluation.cli import main
        main({args!r})
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert not (out / ESTIMATES_FILE).exists()
    assert [p.name.split(atomic_files.PARTIAL)[0] for p in _partials(out)] == [
        f".{ESTIMATES_FILE}"]
    assert (out / INCOMPLETE).read_text().splitlines()[-1] == "ground_truth.csv"
    assert main(args) == 0
    assert not _partials(out) and not (out / INCOMPLETE).exists()
    _rosbags_read(out / ESTIMATES_FILE)


def test_a_file_size_limit_names_estimates_mcap_and_leaves_the_old_one(sample_run, tmp_path):
    """A write the system refuses (RLIMIT_FSIZE: EFBIG, as a full disk gives ENOSPC): one line
    naming the file, the previous estimates.mcap untouched, no partial file."""
    _, _, path = sample_run
    target = tmp_path / ESTIMATES_FILE
    shutil.copy(path, target)
    before = target.read_bytes()
    script = textwrap.dedent(f"""
        import resource, signal
        from ddfuse.estimation.bags import read_stream
        from ddfuse.estimation.config import load_config
        from ddfuse.estimation.runner import run
        from ddfuse.evaluation.estimators import build
        from ddfuse.evaluation.estimates_mcap import write_estimates
        from ddfuse.evaluation.atomic_files import OutputError
        cfg = load_config({str(ROOT / "data" / "sample_husky.yaml")!r})
        stream = read_stream({str(SAMPLE)!r}, cfg)
        result = run(stream, build(cfg, stream, ["dr"]))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, resource.RLIM_INFINITY))
        try:
            write_estimates({str(target)!r}, result)
        except OutputError as e:
            print(e)
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=300)
    assert r.stdout.strip() == f"cannot write {target}: {os.strerror(errno.EFBIG)}", r.stderr
    assert target.read_bytes() == before and not _partials(tmp_path)


@pytest.mark.integration
def test_converted_to_a_ros1_bag_rosbag_reads_it(sample_run, tmp_path):
    """The RViz path on ROS 1: rosbags-convert to a .bag, which ROS 1's own rosbag (the Debian
    python3-rosbag, as ``rosbag play`` uses) reads: every topic, its ROS 1 type and count."""
    python = Path("/usr/bin/python3")
    if not python.is_file() or subprocess.run(
            [str(python), "-c", "import rosbag"], capture_output=True).returncode != 0:
        pytest.skip("ROS 1's rosbag (python3-rosbag) is not installed")
    _, _, path = sample_run
    bag = tmp_path / "estimates.bag"
    convert = Path(sys.executable).with_name("rosbags-convert")
    subprocess.run([str(convert), "--src", str(path), "--dst", str(bag), "--dst-typestore",
                    "ros1_noetic"], check=True, capture_output=True, timeout=300)
    r = subprocess.run([str(python), "-c", textwrap.dedent(f"""
        import rosbag
        info = rosbag.Bag({str(bag)!r}).get_type_and_topic_info().topics
        for t, v in sorted(info.items()):
            print(t, v.msg_type, v.message_count)
    """)], capture_output=True, text=True, timeout=300, check=True)
    msgs, types = _rosbags_read(path)
    want = sorted(f"{t} {types[t].replace('/msg/', '/')} {len(m)}" for t, m in msgs.items())
    assert r.stdout.splitlines() == want


def test_the_writer_takes_an_empty_run(tmp_path):
    """No tracks, no truth, no fixes (a run stopped before any estimate): a valid, empty file."""
    from ddfuse.estimation.measurements import Stream
    from ddfuse.estimation.runner import run

    result = run(Stream([]), {})
    msgs, _ = _rosbags_read(write_estimates(tmp_path / ESTIMATES_FILE, result))
    assert not msgs


def test_the_file_is_the_same_whatever_the_encoding_block(sample_run, tmp_path, monkeypatch):
    """A long run is encoded a block of messages at a time (bounded memory): blocks that cut
    through every topic give the same file, byte for byte, as one block."""
    from ddfuse.evaluation import estimates_mcap

    cfg, result, path = sample_run
    monkeypatch.setattr(estimates_mcap, "_BLOCK", 777)
    small = write_estimates(tmp_path / ESTIMATES_FILE, result, local_frame=cfg.local_frame,
                            base_frame=cfg.base_frame)
    assert len(result.truth) > 777 and small.read_bytes() == path.read_bytes()


def test_a_run_without_a_datum_has_no_fix_topics(tmp_path):
    """seed002's sample: wheels and landmarks, no GPS, so no datum: the poses (odom, /tf,
    truth) only, in the landmark map's frame."""
    out = tmp_path / "out"
    assert main(["run", str(ROOT / "data" / "sample_seed002.bag"), "-c",
                 str(ROOT / "data" / "sample_seed002.yaml"), "-o", str(out), "--estimators",
                 "dr", "--no-report"]) == 0
    msgs, _ = _rosbags_read(out / ESTIMATES_FILE)
    assert set(msgs) == {"/ddfuse/dr/odom", TF_TOPIC, TRUTH_TOPIC}
