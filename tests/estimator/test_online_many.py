"""OnlineEstimator.push_many is push() record after record: the same publications and
the same final estimates, for several agents interleaved in chunks."""

from __future__ import annotations

import numpy as np

from estimator.logio import read_log
from estimator.online import EstimatorOptions, OnlineEstimator
from tests.estimator import worlds as W  # noqa: N812


def _streams(tmp_path):
    w = W.three_agent_world(2, tmp_path, duration_s=90.0)
    logs = [read_log(p) for p in w.paths]
    return w, logs


def _run(logs, many: bool, chunk_s: float = 4.0):
    est = OnlineEstimator(EstimatorOptions(modes=("refined", "baseline")))
    for lg in logs:
        est.add_agent(lg.header.agent, header=lg.header)
    recs = [sorted(lg.gnss + lg.rtt, key=lambda r: r.t_ns) for lg in logs]
    t0 = min(r[0].t_ns for r in recs)
    t_end = max(r[-1].t_ns for r in recs)
    pubs = []
    edge = t0
    while edge <= t_end:  # each agent delivers its next chunk_s of records in turn
        edge += int(chunk_s * 1e9)
        for i, rs in enumerate(recs):
            part = [r for r in rs if edge - chunk_s * 1e9 <= r.t_ns < edge]
            got = est.push_many(part, i) if many else [p for r in part for p in est.push(r, i)]
            pubs.append(("push", got))  # what the chunk's records published, in order
            if part:
                pubs.append(("mark", est.mark_time(i, part[-1].t_ns)))
    pubs.append(("finish", est.finish()))
    return pubs, est


def test_push_many_equals_push_one_by_one(tmp_path):
    _, logs = _streams(tmp_path)
    (p1, e1), (p2, e2) = _run(logs, False), _run(logs, True)
    assert sum(len(x) for _, x in p1 if _ == "push") > 100 and p1 == p2
    for mode in ("refined", "baseline"):
        a, b = e1.estimate(W.BSSID, mode), e2.estimate(W.BSSID, mode)
        assert a.mean_enu_m == b.mean_enu_m and np.array_equal(a.cov_m2, b.cov_m2)
