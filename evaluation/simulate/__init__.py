"""Differential-drive robot simulator with ground truth, writing ROS1 / ROS2 / MCAP bags.

``simulate(scenario, seed)`` drives a differential-drive robot along a named scenario's path
and samples its sensors; ``write_bag(result, path, fmt)`` writes the bag plus, next to it, the
ddfuse config (and the landmark map) that describe it. The command ``ddfuse simulate`` is
``evaluation/cli/simulate.py``.

Everything is SI; time in seconds since the start of the run (``SimResult.t0`` adds the absolute
epoch that goes into the header stamps); the local frame is ENU about the scenario's datum.
Deterministic per seed, each sensor with its own random stream. One module per job:

* ``scenarios``: the named scenarios (robot geometry, trajectory, sensor specifications);
* ``motion``: the truth drive (commands along the path, exact SE(2) integration);
* ``sensors``: wheel encoders, IMU, magnetometer, landmark sightings, ground truth; ``gps``: the
  GPS fixes and their white or Gauss-Markov errors;
* ``simulator``: ``simulate`` and its ``SimResult``;
* ``sidecars``: the config and landmark map written beside a bag;
* ``bag_writer``: the messages and the bag (ROS1 file, ROS 2 directory with sqlite3 or MCAP).

The sample bags in data/ are its output (data/README.md says how to regenerate them).
"""

from ddfuse.evaluation.simulate.bag_writer import (
    FORMATS,
    LANDMARK_MSGDEF,
    LANDMARK_MSGTYPE,
    SUFFIXES,
    UNUSED_VAR,
    check_bag_path,
    make_typestore,
    storage_file,
    write_bag,
)
from ddfuse.evaluation.simulate.gps import GpsData
from ddfuse.evaluation.simulate.motion import Truth, integrate_truth, se2_step, wrap
from ddfuse.evaluation.simulate.scenarios import (
    OUTDOOR_DATUM,
    SCENARIOS,
    EncoderSpec,
    Geometry,
    GpsSpec,
    ImuSpec,
    LandmarkSpec,
    MagnetometerSpec,
    Scenario,
    TrajectorySpec,
    get_scenario,
    with_duration,
)
from ddfuse.evaluation.simulate.sensors import (
    EncoderData,
    G,
    GroundTruthData,
    ImuData,
    LandmarkData,
    MagnetometerData,
)
from ddfuse.evaluation.simulate.sidecars import (
    SMOOTHER_LAG,
    sidecar_paths,
    sim_config,
    write_sidecars,
)

# _rng: Monte Carlo draws each seed's true geometry from a stream of the same family
from ddfuse.evaluation.simulate.simulator import SimResult, _rng, simulate

__all__ = [
    "FORMATS", "G", "LANDMARK_MSGDEF", "LANDMARK_MSGTYPE", "OUTDOOR_DATUM", "SCENARIOS",
    "SMOOTHER_LAG", "SUFFIXES", "UNUSED_VAR", "EncoderData", "EncoderSpec", "Geometry",
    "GpsData", "GpsSpec", "GroundTruthData", "ImuData", "ImuSpec", "LandmarkData",
    "LandmarkSpec", "MagnetometerData", "MagnetometerSpec", "Scenario", "SimResult",
    "TrajectorySpec", "Truth", "_rng",
    "check_bag_path", "get_scenario", "integrate_truth", "make_typestore", "se2_step",
    "sidecar_paths", "sim_config", "simulate", "storage_file", "with_duration", "wrap",
    "write_bag", "write_sidecars",
]
