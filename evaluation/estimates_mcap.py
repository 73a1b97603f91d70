"""A run's estimates as ROS 2 messages in one MCAP file, ``OUTDIR/estimates.mcap``: what
Foxglove, PlotJuggler, rosbags and (converted to a ROS 1 bag) ``rosbag play`` into RViz show
without ddfuse (docs/design/estimates_out.md: why ROS 2 CDR in a bare .mcap, the cost).

Topics (header stamps and log times are the estimates' times: the bag's header-stamp clock):

* ``/ddfuse/<track>/odom`` ``nav_msgs/msg/Odometry``: every sample of every track (the
  lagged smoother's and the batch's too), ``header.frame_id`` the local frame,
  ``child_frame_id`` the base frame. A track holds t, pose and pose_cov
  (``estimation.runner.TrackBuilder``), not the twist: the twist is 0 with
  ``UNKNOWN_TWIST_COVARIANCE``.
* ``/ddfuse/<track>/fix`` ``sensor_msgs/msg/NavSatFix``: the same samples in lat/lon, when
  the run has a datum.
* ``/tf`` ``tf2_msgs/msg/TFMessage``: local -> base for one track
  (``estimate_msgs.tf_source``: ``tf``, the config's ``node.tf``, else the smoother, else the
  first).
* ``/ddfuse/ground_truth/odom``: the ground truth, when the run has it (covariance NaN: none).
* ``/ddfuse/gps/fix`` and ``/ddfuse/gps/fix_withheld``: the GPS fixes the estimators were
  given and those ``--gps-holdout`` withheld, one message per fix: its header stamp,
  lat/lon/alt and status, and the ENU covariance the estimators used.

Every field comes from ``ddfuse.estimation.estimate_msgs`` (``pose_columns``,
``fix_columns``: the columns ``odometry_of``/``fix_of``/``transform_of`` give one by one).
Messages are encoded ``_BLOCK`` at a time, as numpy columns: each type's CDR bytes are rosbags' own
serialisation of one message built by ``evaluation.ros_messages`` (the template), whose stamp
and float64 block are overwritten row by row with numpy (``CdrLayout``); tests pin the bytes to
``serialize_cdr`` of ``odometry_of``/``fix_of``/``transform_of``'s messages.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from ddfuse.estimation.estimate_msgs import (
    UNKNOWN_TWIST_COVARIANCE,
    FixOut,
    OdometryOut,
    TransformOut,
    fix_columns,
    pose_columns,
    tf_source,
)
from ddfuse.evaluation.atomic_files import replacing
from ddfuse.evaluation.ros_messages import (
    navsatfix_msg,
    odometry_msg,
    stamp_ns,
    tf_msg,
    typestore,
)

__all__ = ["ESTIMATES_FILE", "GPS_TOPIC", "GPS_WITHHELD_TOPIC", "TF_TOPIC", "TRUTH_TOPIC",
           "CdrLayout", "layout", "topic_of", "write_estimates"]

ESTIMATES_FILE = "estimates.mcap"
TF_TOPIC = "/tf"
GPS_TOPIC = "/ddfuse/gps/fix"
GPS_WITHHELD_TOPIC = "/ddfuse/gps/fix_withheld"
TRUTH_TOPIC = "/ddfuse/ground_truth/odom"
ODOMETRY = "nav_msgs/msg/Odometry"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
_FIX_KNOWN = 3  # sensor_msgs/NavSatFix COVARIANCE_TYPE_KNOWN
_CHUNK = 4 << 20  # bytes per MCAP chunk: fewer, better compressed chunks than the 1 MB default
_BLOCK = 5_000  # messages encoded at a time (~2.5 MB of CDR, and its bytes copy)


def topic_of(track: str, kind: str) -> str:
    """``/ddfuse/<track>/<kind>`` (kind 'odom' or 'fix')."""
    return f"/ddfuse/{track}/{kind}"


@dataclass(frozen=True)
class CdrLayout:
    """One message type's CDR bytes with fixed frame ids: ``template`` (K, L) uint8, rosbags'
    serialisation of K messages (``evaluation.ros_messages``; the variants, e.g. one per
    NavSatStatus, differ outside the stamp and the float block), where their header stamp
    (``stamp_at``: int32 sec, uint32 nanosec) and their one block of ``n_float`` float64
    (``float_at``) are."""

    typename: str
    template: np.ndarray
    stamp_at: int
    float_at: int
    n_float: int

    def encode(self, t: np.ndarray, floats: np.ndarray,
               variant: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(log times ns (N,) int64, messages (N, L) uint8) for stamps ``t`` (N,) s and the
        float64 block ``floats`` (N, n_float); ``variant`` (N,) the template of each."""
        sec, nsec, ns = stamp_ns(t)
        rows = self.template[np.zeros(len(ns), np.intp) if variant is None else variant]
        stamp = np.empty(len(ns), dtype=[("s", "<i4"), ("n", "<u4")])
        stamp["s"], stamp["n"] = sec, nsec
        rows[:, self.stamp_at:self.stamp_at + 8] = stamp.view(np.uint8).reshape(-1, 8)
        block = np.ascontiguousarray(floats, dtype="<f8").reshape(len(ns), self.n_float)
        rows[:, self.float_at:self.float_at + 8 * self.n_float] = block.view(np.uint8)
        return ns, rows


_MARK_T = 123456789.25  # a marker stamp, exact in binary: 123456789 s + 250000000 ns


def _locate(typename: str, messages: list, marks: list[float]) -> CdrLayout:
    """The layout of ``messages`` (built with stamp _MARK_T and the float block ``marks``):
    where the marker bytes are in their CDR."""
    raws = [bytes(typestore().serialize_cdr(m, typename)) for m in messages]
    sec, nsec, _ = stamp_ns(_MARK_T)
    stamp_at = raws[0].index(struct.pack("<iI", int(sec[0]), int(nsec[0])))
    float_at = raws[0].index(struct.pack(f"<{len(marks)}d", *marks))
    return CdrLayout(typename, np.array([np.frombuffer(r, np.uint8) for r in raws]),
                     stamp_at, float_at, len(marks))


@cache
def layout(typename: str, frame_id: str, child_frame_id: str = "") -> CdrLayout:
    """The ``CdrLayout`` of ``typename`` with these frames. Float blocks: Odometry 85
    (position, orientation, pose covariance, linear, angular, twist covariance); NavSatFix 12
    (latitude, longitude, altitude, position covariance; one variant per NavSatStatus.status
    -1..2 at index status + 1, covariance type KNOWN); TFMessage of one transform 7
    (translation, rotation)."""
    m = [1000.0 + i + 0.123 for i in range(85)]
    if typename == ODOMETRY:
        msgs = [odometry_msg(OdometryOut(_MARK_T, frame_id, child_frame_id, m[0:3], m[3:7],
                                         m[7:43], m[43:46], m[46:49], m[49:85]))]
        return _locate(typename, msgs, m)
    if typename == NAVSATFIX:
        f = FixOut(_MARK_T, frame_id, m[0], m[1], m[2], m[3:12])
        return _locate(typename, [navsatfix_msg(f, s) for s in (-1, 0, 1, 2)], m[:12])
    if typename == TFMESSAGE:
        x = TransformOut(_MARK_T, frame_id, child_frame_id, m[0:3], m[3:7])
        return _locate(typename, [tf_msg([x])], m[:7])
    raise ValueError(f"no CDR layout for {typename}")


@dataclass(frozen=True)
class _Source:
    """One topic's messages, encoded a block at a time: ``t`` (N,) s their stamps (sorted),
    ``encode(i0, i1)`` -> (log times ns, CDR rows) of messages i0..i1-1."""

    topic: str
    typename: str
    t: np.ndarray
    encode: Callable[[int, int], tuple[np.ndarray, np.ndarray]]


def _odometry(track, local: str, base: str) -> Callable:
    def encode(i0: int, i1: int):
        p = pose_columns(track.t[i0:i1], track.pose[i0:i1], track.cov_at(slice(i0, i1)))
        n = i1 - i0
        floats = np.hstack([p.position, p.orientation, p.pose_covariance, np.zeros((n, 6)),
                            np.broadcast_to(UNKNOWN_TWIST_COVARIANCE, (n, 36))])
        return layout(ODOMETRY, local, base).encode(p.stamp, floats)
    return encode


def _transforms(track, local: str, base: str) -> Callable:
    def encode(i0: int, i1: int):
        p = pose_columns(track.t[i0:i1], track.pose[i0:i1], track.cov_at(slice(i0, i1)))
        return layout(TFMESSAGE, local, base).encode(
            p.stamp, np.hstack([p.position, p.orientation]))
    return encode


def _fixes(track, datum, base: str) -> Callable:
    def encode(i0: int, i1: int):
        f = fix_columns(track.t[i0:i1], track.pose[i0:i1], track.cov_at(slice(i0, i1)), datum)
        floats = np.column_stack([f.latitude, f.longitude, f.altitude, f.position_covariance])
        return layout(NAVSATFIX, base).encode(f.stamp, floats, np.ones(i1 - i0, np.intp))
    return encode


def _gps(gps, keep: np.ndarray, base: str) -> Callable:
    """The fixes ``keep`` (indices) selects, as the estimators were given them."""
    def encode(i0: int, i1: int):
        k = keep[i0:i1]
        floats = np.column_stack([gps.lla[k], gps.enu_cov[k].reshape(-1, 9)])
        status = np.clip(gps.status[k].astype(np.intp), -1, 2) + 1
        return layout(NAVSATFIX, base).encode(gps.t[k], floats, status)
    return encode


def _sources(result, local: str, base: str, tf: str | None) -> list[_Source]:
    """Every topic ``result`` has data for (module docstring)."""
    tracks = {n: r.trajectory for n, r in result.runs.items() if len(r.trajectory)}
    datum = getattr(result.stream, "datum", None)
    out = []
    for name, tr in tracks.items():
        out.append(_Source(topic_of(name, "odom"), ODOMETRY, tr.t, _odometry(tr, local, base)))
        if datum is not None:
            out.append(_Source(topic_of(name, "fix"), NAVSATFIX, tr.t, _fixes(tr, datum, base)))
    if (tf := tf_source(tracks, tf)) is not None:
        out.append(_Source(TF_TOPIC, TFMESSAGE, tracks[tf].t,
                           _transforms(tracks[tf], local, base)))
    if result.truth is not None and len(result.truth):
        out.append(_Source(TRUTH_TOPIC, ODOMETRY, result.truth.t,
                           _odometry(result.truth, local, base)))
    gps = result.gps
    if len(gps) and gps.lla is not None:
        held = np.asarray(gps.withheld, bool)
        for topic, keep in ((GPS_TOPIC, np.flatnonzero(~held)),
                            (GPS_WITHHELD_TOPIC, np.flatnonzero(held))):
            if len(keep):
                out.append(_Source(topic, NAVSATFIX, gps.t[keep], _gps(gps, keep, base)))
    return out


def write_estimates(path: str | Path, result, *, local_frame: str = "map",
                    base_frame: str = "base_link", tf: str | None = None) -> Path:
    """Write ``result``'s (a ``RunResult``) estimates, ground truth and GPS fixes to ``path``
    as the module docstring says: ROS 2 CDR in MCAP (profile ros2, ros2msg schemas, zstd
    chunks), messages in log-time order; whole or not at all (``atomic_files.replacing``:
    OutputError naming the path). Encoded ``_BLOCK`` messages at a time: memory stays a few
    MB however long the run. Returns the path."""
    from mcap.writer import CompressionType, Writer

    sources = _sources(result, local_frame, base_frame, tf)
    ts = typestore()
    stamps = np.sort(np.concatenate([s.t for s in sources] or [np.zeros(0)]))
    edges = [*stamps[::_BLOCK][1:].tolist(), math.inf]
    path = Path(path)
    with replacing(path, "wb") as f:
        # no CRCs: they cost a third of the writer's time per message, and the file is written
        # whole or not at all (replacing), so it cannot be truncated
        w = Writer(f, chunk_size=_CHUNK, compression=CompressionType.ZSTD, enable_crcs=False)
        w.start(profile="ros2", library="ddfuse")
        schemas: dict[str, int] = {}
        ids = []
        for s in sources:
            if s.typename not in schemas:
                text = ts.generate_msgdef(s.typename, ros_version=2)[0]
                schemas[s.typename] = w.register_schema(s.typename, "ros2msg", text.encode())
            ids.append(w.register_channel(s.topic, "cdr", schemas[s.typename]))
        start = [0] * len(sources)
        tracks = [r.trajectory for r in result.runs.values()]
        for edge in edges:
            _write_block(w, ids, sources, start, edge)
            for tr in tracks:  # a spilled track's pages of this block (Trajectory.release)
                tr.release()
        w.finish()
    return path


def _write_block(w, ids: list[int], sources: list[_Source], start: list[int],
                 edge: float) -> None:
    """Add every message stamped before ``edge`` from ``start`` on (updated), in log-time
    order (a stable sort: equal stamps keep the sources' order)."""
    blocks = []
    for c, s in enumerate(sources):
        i0, i1 = start[c], int(np.searchsorted(s.t, edge, side="left"))
        if i1 > i0:
            ns, rows = s.encode(i0, i1)
            blocks.append((c, i0, ns, rows.tobytes(), rows.shape[1]))
        start[c] = i1
    if not blocks:
        return
    log_ns = np.concatenate([b[2] for b in blocks])
    which = np.concatenate([np.full(len(b[2]), k) for k, b in enumerate(blocks)])
    index = np.concatenate([np.arange(len(b[2])) for b in blocks])
    order = np.argsort(log_ns, kind="stable")
    add = w.add_message
    for ns, k, i in zip(log_ns[order].tolist(), which[order].tolist(), index[order].tolist(),
                        strict=True):
        c, i0, _, data, size = blocks[k]
        a = i * size
        add(ids[c], ns, data[a:a + size], ns, i0 + i + 1)
