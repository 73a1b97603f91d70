"""A compiled EKF's innovation buffer moved into the estimator's InnovationLog as columns
(``InnovationLog.extend_small``) holds what moving it record by record held."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.estimator import InnovationLog
from ddfuse.evaluation.estimators import build

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def buffered():
    """A compiled unicycle EKF over the sample's first 4000 messages, its buffer not drained,
    with a record its Python path logged ahead of the buffer's rows."""
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    ekf = build(cfg, stream, ["ekf"])["ekf"]  # started as ``ddfuse run`` starts it
    assert ekf.compiled
    for m in stream.measurements[:4000]:
        ekf.process(m)
    kf = ekf.kf
    n = int(kf.ip[kf.kj.IP_LOGN])
    assert n > 1000 and {int(v) for v in kf.lg[:n, 10]} == {1, 2}  # both dimensions in it
    return kf, kf.lg[:n].copy(), n


def _drain(kf, rows, n, store):
    kf.lg[:n] = rows
    kf.ip[kf.kj.IP_LOGN] = n
    kf.drain_log(store)
    assert kf.ip[kf.kj.IP_LOGN] == 0


def _first(log: InnovationLog):
    log.add(0.5, "first", "gyro", [0.1, 0.2, 0.3], np.eye(3), 1.5, accepted=False)


@pytest.mark.parametrize("keep", [InnovationLog.KEEP, 300])
def test_columns_moved_at_once_equal_records_moved_one_by_one(buffered, keep):
    kf, rows, n = buffered
    bulk, records = InnovationLog(keep), []
    _first(bulk)
    _drain(kf, rows, n, bulk)
    _drain(kf, rows, n, records)  # a list: the record-by-record path
    one_by_one = InnovationLog(keep)
    _first(one_by_one)
    one_by_one.extend(records)
    one_by_one.compact()
    assert len(bulk) == len(one_by_one) == n + 1
    assert bulk.folded_by_group().keys() == one_by_one.folded_by_group().keys()
    for key, a in bulk.folded_by_group().items():
        assert a == pytest.approx(one_by_one.folded_by_group()[key], rel=1e-12)
    if keep == InnovationLog.KEEP:  # nothing folded: every column equal, bit for bit
        for name in ("_t", "_nis", "_g", "_acc", "_roff", "_coff", "_res", "_cov"):
            assert getattr(bulk, name) == getattr(one_by_one, name), name
        assert bulk._groups == one_by_one._groups
        a, b = bulk.held_log_det(), one_by_one.held_log_det()
        assert np.array_equal(a["log_det"], b["log_det"], equal_nan=True)
        view = bulk[n]
        assert view.residual.shape == (int(rows[-1, 10]),) and view.t == rows[-1, 0]
    else:
        assert bulk._n_folded > 0


def test_a_dimension_other_than_one_or_two_is_refused():
    log = InnovationLog()
    with pytest.raises(ValueError, match="dimensions 1 or 2"):
        log.extend_small(np.zeros(1), np.zeros(1), np.zeros(1, int), [("gps", "gps", 3)],
                         np.zeros((1, 2)), np.zeros((1, 4)), np.ones(1, bool))
