"""Bad landmark input: maps that name no landmark or one id twice, sightings of ids not in the
map (counted at the reader under one reason, a warning naming the topic, map and ids when they
cost a topic more than 10 %), a range of 0. Each ends in one line naming the file, key, topic."""

from __future__ import annotations

import math
import re
from pathlib import Path

import bagwriter as bw
import pytest
from ddfuse.estimation.bags import BagStream, read_stream
from ddfuse.estimation.config import (
    LANDMARK_NOT_IN_MAP,
    landmark_maps,
    load_landmark_map,
    parse_config,
)
from ddfuse.estimation.errors import BagError, ConfigError
from ddfuse.estimation.live import LiveConverter
from ddfuse.estimation.measurements import LandmarkObservation

T0 = 1_600_000_000.0
PATHS = pytest.mark.parametrize("fmt", ["ros1", "mcap"])  # fast ROS1 decoder, rosbags objects
BAD_RANGE = "range not finite or not positive"


def _write_map(tmp_path: Path, text: str, name: str = "m.landmarks.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _cfg(*maps: Path):
    return parse_config({"sensors": {"landmarks": [
        {"topic": f"/lm{i or ''}", "map": str(m)} for i, m in enumerate(maps)]}})


MAP = "landmarks:\n  '7': [1.5, -2.0]\n  L2: [0.0, 3.25]\n"


# --- the map ---------------------------------------------------------------------------------

def test_the_reason_string_is_the_one_every_estimator_is_to_use():
    assert LANDMARK_NOT_IN_MAP == "landmark id not in the map"


def test_an_empty_map_is_an_error_naming_the_file(tmp_path):
    p = _write_map(tmp_path, "landmarks: {}\n")
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    assert str(e.value).startswith(f"{p}: landmarks: empty")
    with pytest.raises(ConfigError, match="landmarks: empty"):
        landmark_maps(_cfg(p))


@pytest.mark.parametrize("text", [
    "landmarks:\n  '1': [999.0, 999.0]\n  '1': [5.0, 6.0]\n  '2': [0.0, 0.0]\n",
    "landmarks:\n  1: [999.0, 999.0]\n  2: [0.0, 0.0]\n  1: [5.0, 6.0]\n",
    "landmarks: {1: [999.0, 999.0], 1: [5.0, 6.0]}\n",
])
def test_a_yaml_key_given_twice_is_a_duplicate_id(tmp_path, text):
    """PyYAML keeps the last of two equal keys without a word."""
    p = _write_map(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    assert str(e.value).startswith(f"{p}: landmarks.1: duplicate id")


def test_an_int_and_a_string_key_that_are_one_id_are_a_duplicate(tmp_path):
    """``1:`` and ``"1":`` are two keys to YAML but one id after str(): the last won."""
    p = _write_map(tmp_path, "landmarks:\n  \"1\": [5.0, 6.0]\n  1: [999.0, 999.0]\n")
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: landmarks.1: duplicate id")
    assert "'1' and 1" in msg


def test_the_map_files_top_level_key_given_twice_is_an_error(tmp_path):
    p = _write_map(tmp_path, "landmarks: {'1': [0, 0]}\nlandmarks: {'2': [1, 1]}\n")
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    assert str(e.value).startswith(f"{p}: landmarks: given twice (lines 1 and 2)")


def test_one_id_at_two_positions_in_two_sensors_maps_is_an_error(tmp_path):
    a = _write_map(tmp_path, "landmarks:\n  '7': [1.5, -2.0]\n  L2: [0.0, 3.25]\n", "a.yaml")
    b = _write_map(tmp_path, "landmarks:\n  '8': [4.0, 4.0]\n  '7': [1.5, -2.5]\n", "b.yaml")
    with pytest.raises(ConfigError) as e:
        landmark_maps(_cfg(a, b))
    msg = str(e.value)
    assert msg.startswith(f"{b}: landmarks.7: duplicate id")
    assert str(a) in msg


def test_one_id_at_the_same_position_in_two_maps_is_fine(tmp_path):
    a = _write_map(tmp_path, "landmarks:\n  '7': [1.5, -2.0]\n  L2: [0.0, 3.25]\n", "a.yaml")
    b = _write_map(tmp_path, "landmarks:\n  '8': [4.0, 4.0]\n  7: [1.5, -2.0]\n", "b.yaml")
    assert landmark_maps(_cfg(a, b)) == {"7": (1.5, -2.0), "L2": (0.0, 3.25), "8": (4.0, 4.0)}


# --- sightings at the reader ------------------------------------------------------------------

def _bag(tmp_path: Path, fmt: str, sightings: list[tuple[str, float]]) -> Path:
    recs = [("/lm", bw.landmark(T0 + 0.1 * i, lid, rng, 0.1)) for i, (lid, rng) in
            enumerate(sightings)]
    return bw.write_bag(bw.bag_path(tmp_path, "b", fmt), fmt, recs)


@PATHS
def test_sightings_not_in_the_map_are_dropped_counted_and_warned_about(tmp_path, fmt):
    ids = ["7", "L2", "Q1", "7", "Q2", "L2", "Q1", "7", "L2", "7"]  # 3 of 10 not in the map
    bag = _bag(tmp_path, fmt, [(i, 2.0) for i in ids])
    m = _write_map(tmp_path, MAP)
    s = read_stream(bag, _cfg(m))
    assert [o.landmark_id for o in s.measurements if isinstance(o, LandmarkObservation)] == \
        [i for i in ids if not i.startswith("Q")]
    assert s.rejected == {("/lm", LANDMARK_NOT_IN_MAP): 3}
    bs = BagStream(bag, _cfg(m))
    list(bs)
    assert len(bs.warnings) == 1
    w = bs.warnings[0]
    assert w.startswith(f"{bag}: topic /lm: 3 of 10 messages (30 %) rejected")
    assert LANDMARK_NOT_IN_MAP in w
    assert f"map {m} has ids '7', 'L2'" in w
    assert "not in it: 'Q1', 'Q2'" in w  # the most frequent first


@PATHS
def test_a_few_sightings_not_in_the_map_are_counted_without_a_warning(tmp_path, fmt):
    bag = _bag(tmp_path, fmt, [("Q1" if i == 5 else "7", 2.0) for i in range(20)])  # 5 %
    bs = BagStream(bag, _cfg(_write_map(tmp_path, MAP)))
    assert sum(1 for _ in bs) == 19
    assert bs.rejected == {("/lm", LANDMARK_NOT_IN_MAP): 1}
    assert bs.warnings == []


@PATHS
def test_a_map_for_another_run_is_an_error_naming_topic_map_and_ids(tmp_path, fmt):
    """Every sighting rejected: the reader's rule for a topic that lost all its messages."""
    bag = _bag(tmp_path, fmt, [(str(5 + i % 3), 2.0) for i in range(12)])
    m = _write_map(tmp_path, "landmarks:\n" + "".join(f"  X{i}: [{i}, 0]\n" for i in range(9)))
    with pytest.raises(BagError) as e:
        read_stream(bag, _cfg(m))
    msg = str(e.value)
    assert msg.startswith(f"{bag}: topic /lm (sensors.landmarks[0]): all 12 messages rejected: "
                          f"{LANDMARK_NOT_IN_MAP}; map {m} has ids 'X0', 'X1', 'X2', 'X3', "
                          "'X4' ... (9 in all)")
    assert "not in it: '5', '6', '7'" in msg


@PATHS
def test_a_range_of_zero_is_dropped_as_a_bad_range(tmp_path, fmt):
    """0 is a range finder's "no return": counted with the negative and NaN ranges."""
    ranges = [2.0, 0.0, 3.0, -1.0, math.nan, 4.0, 0.0, 5.0]
    bag = _bag(tmp_path, fmt, [("7", r) for r in ranges])
    s = read_stream(bag, _cfg(_write_map(tmp_path, MAP)))
    got = [o.range for o in s.measurements if isinstance(o, LandmarkObservation)]
    assert got == [r for r in ranges if r > 0.0]
    assert s.rejected == {("/lm", BAD_RANGE): 4}


# --- the live converter applies the reader's checks ---------------------------------------------

def test_the_live_converter_drops_what_the_reader_drops(tmp_path):
    conv = LiveConverter(_cfg(_write_map(tmp_path, MAP)))
    store = bw.typestore("ros2")

    def sight(i: int, lid: str, rng: float) -> list:
        t = T0 + 0.1 * i
        return conv.convert("/lm", bw.landmark(t, lid, rng, 0.1).build(store), received=t)

    assert [o.landmark_id for o in sight(0, "7", 2.0)] == ["7"]
    assert sight(1, "Q1", 2.0) == []
    assert sight(2, "L2", 0.0) == []
    assert [o.landmark_id for o in sight(3, "L2", 2.5)] == ["L2"]
    assert conv.rejected == {("/lm", LANDMARK_NOT_IN_MAP): 1, ("/lm", BAD_RANGE): 1}
    assert conv.stream().landmarks == {"7": (1.5, -2.0), "L2": (0.0, 3.25)}


def test_the_live_converter_refuses_an_empty_map(tmp_path):
    p = _write_map(tmp_path, "landmarks: {}\n")
    with pytest.raises(ConfigError, match=f"^{re.escape(str(p))}: landmarks: empty"):
        LiveConverter(_cfg(p))
