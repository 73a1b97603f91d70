"""``inspect`` (estimation.baginfo) on the bad bags of audit 13: a bag damaged mid-file, unset
header stamps, fixes the reader drops, an empty bag."""

from __future__ import annotations

import math
from pathlib import Path

import bagwriter as bw
import pytest
from ddfuse.estimation.baginfo import bag_info, fix_scatter, suggest_config
from ddfuse.estimation.errors import BagError

T0 = 1_600_000_000.0


def topic(info, name):
    return next(t for t in info.topics if t.topic == name)


def _imu(t: float, i: int):
    return bw.imu(t, angvel=(0, 0, 0.01 * i), wcov=bw.diag(1, 1, 1))


def test_a_bag_damaged_mid_file_shows_what_was_read(tmp_path):
    """An LZ4 chunk garbled mid-file, the index intact: inspect said only 'damaged'."""
    from rosbags.rosbag1 import Reader

    recs = [("/imu", _imu(T0 + 0.01 * i, i)) for i in range(3000)]
    bag = bw.write_bag(tmp_path / "b.bag", "ros1", recs, compression="lz4",
                       chunk_bytes=200_000)  # 6 chunks of 5.5 s
    with Reader(bag) as r:
        third = r.chunk_infos[2].pos
    data = bytearray(bag.read_bytes())
    for k in range(400, 2400):  # inside the third chunk's compressed data, past its header
        data[third + k] ^= 0x5A
    bag.write_bytes(bytes(data))
    info = bag_info(bag)
    imu = topic(info, "/imu")
    assert imu.count == 3000  # the index's
    assert 100.0 * 0.9 < imu.rate_hz < 100.0 * 1.1  # of what was read
    assert T0 + 5.0 < imu.t1 < T0 + 11.0  # the first two chunks, not the end
    assert info.error is not None and str(bag) in info.error and "damaged" in info.error
    assert any("past the damage" in n for n in imu.notes)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_unset_stamps_are_left_out_of_rates_and_spans(tmp_path, fmt):
    """One zero stamp among a 100 Hz IMU's made its rate 3.6e12 Hz and the bag's span 50
    years; a topic of only zero stamps is not suggested."""
    recs = [("/imu", _imu(0.0 if i in (0, 7) else T0 + 0.01 * i, i), T0 + 0.01 * i)
            for i in range(300)]
    recs += [("/odom", bw.odometry(0.0, 1.0, 0.0), T0 + 0.1 * i) for i in range(30)]
    recs += [("/odom2", bw.odometry(T0 + 0.1 * i, 1.0, 0.0), T0 + 0.1 * i) for i in range(30)]
    recs.sort(key=lambda r: r[2])
    info = bag_info(bw.write_bag(bw.bag_path(tmp_path, "b", fmt), fmt, recs))
    imu = topic(info, "/imu")
    assert imu.rate_hz == pytest.approx(100.0, rel=0.01)
    assert imu.t0 == pytest.approx(T0 + 0.01, abs=1e-6)
    assert info.t0 > T0 - 1.0 and info.duration < 3.0
    assert any(n.startswith("2 message(s) with a zero") for n in imu.notes)
    odom = topic(info, "/odom")
    assert math.isnan(odom.rate_hz) and any("unusable" in n for n in odom.notes)
    assert [s["topic"] for s in suggest_config(info)["sensors"]["odometry"]] == ["/odom2"]


def _fix(i: int, lat: float, lon: float, status: int = 0):
    return (T0 + 0.5 * i, status, lat, lon, 10.0, (1.0, 0, 0, 0, 1.0, 0, 0, 0, 4.0), 2)


def test_the_gps_scatter_leaves_out_fixes_the_reader_drops():
    """Three fixes at latitude 95, longitude 200 and (0, 0) with a valid status made the
    scatter 388 km against 1.2 m."""
    recs = [_fix(i, 42.0 + 1e-6 * i, -71.0) for i in range(40)]
    clean = fix_scatter(recs)
    recs[10] = _fix(10, 95.0, -71.0)
    recs[20] = _fix(20, 42.0, 200.0)
    recs[30] = _fix(30, 0.0, 0.0)
    recs[25] = _fix(25, 0.0, 0.0, status=-1)
    dirty = fix_scatter(recs)
    # a straight track sampled evenly: its neighbours predict each fix to the cm
    assert clean.rms < 0.01 and dirty.rms < 0.01, dirty
    assert (clean.n, dirty.n) == (40, 36)


def test_a_garbled_index_is_read_from_the_front(tmp_path):
    """rosbags asserts on a damaged IndexData record: an AssertionError came out of inspect
    (and any command opening the bag with rosbags) instead of what could be read."""
    recs = [("/imu", _imu(T0 + 0.01 * i, i)) for i in range(3000)]
    bag = bw.write_bag(tmp_path / "b.bag", "ros1", recs, compression="lz4",
                       chunk_bytes=20_000)
    data = bytearray(bag.read_bytes())
    for k in range(2000):  # over a chunk's IndexData and the next chunk's start
        data[len(data) // 2 + k] ^= 0x5A
    bag.write_bytes(bytes(data))
    info = bag_info(bag)
    assert 0 < topic(info, "/imu").count < 3000
    assert info.error is not None and str(bag) in info.error


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_an_empty_bag_says_it_has_no_messages(tmp_path, fmt):
    """It suggested a config with 'sensors: {}'."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    path = bw.bag_path(tmp_path, "b", fmt)
    store = bw.typestore(fmt)
    writer = Writer1(path) if fmt == "ros1" else Writer2(path, version=9,
                                                          storage_plugin=StoragePlugin.MCAP)
    with writer:
        writer.add_connection("/imu", bw.IMU, typestore=store)
    with pytest.raises(BagError) as e:
        bag_info(Path(path))
    assert str(path) in str(e.value) and "no messages" in str(e.value) and "/imu" in str(e.value)
