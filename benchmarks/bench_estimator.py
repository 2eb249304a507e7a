"""Estimator speed: filter updates against filterpy, and the six-mode replay.

    python benchmarks/bench_estimator.py [--repeat N]

Prints medians measured in this run and the ratios to the targets of issue 2:
IEKF update <= 0.2 x filterpy's ExtendedKalmanFilter, UKF update <= 0.2 x filterpy's
UnscentedKalmanFilter (same state, same measurement, same Joseph / Merwe maths), and
a replay of up to 455 measurements (a paper-ap1f flight's: 426 on seed 1) in all six
modes < 50 ms, and the same replay in mode
``refined`` (``best``: front, periodic and final batch refinement) < 50 ms (the
pipeline from associated ranges; log parsing and association are timed separately).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimator.filters import IEKF3D, UKF3D, IekfConfig, UkfConfig
from estimator.modes import MODES, PAPER_MODES
from estimator.pipeline import SharedFront, Track
from estimator.refined import RefinedTrack

ANCHORS = [(40.0 * math.cos(a), 40.0 * math.sin(a), 45.0) for a in np.linspace(0, 6.28, 64)]
AP = (5.0, -3.0, 0.0)
RANGES = [math.dist(u, AP) + 0.3 for u in ANCHORS]


def per_call_us(fn, n: int, repeat: int) -> float:
    """Median over ``repeat`` runs of the mean time per call (microseconds)."""
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn(n)
        runs.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(runs)


def bench_iekf(n: int, iterations: int):
    f = IEKF3D((4.0, -2.0, 1.0), IekfConfig(iterations=iterations))

    def run(k):
        for i in range(k):
            j = i & 63
            f.P = [[25.0, 0, 0, 0], [0, 25.0, 0, 0], [0, 0, 100.0, 0], [0, 0, 0, 4.0]]
            f.predict()
            f.update(ANCHORS[j], RANGES[j], 0.5)

    return run


def bench_filterpy_ekf(n: int):
    from filterpy.kalman import ExtendedKalmanFilter

    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=1)
    ekf.x = np.array([[4.0], [-2.0], [1.0], [0.0]])
    ekf.Q = np.diag([0.01, 0.01, 0.04, 1e-4])
    ekf.R = np.array([[0.5]])
    u_box = [ANCHORS[0]]

    def hx(x):
        u = u_box[0]
        return np.array([[math.dist(x[:3, 0], u) + x[3, 0]]])

    def jac(x):
        u = u_box[0]
        d = x[:3, 0] - np.asarray(u)
        r = np.linalg.norm(d)
        return np.array([[d[0] / r, d[1] / r, d[2] / r, 1.0]])

    P0 = np.diag([25.0, 25.0, 100.0, 4.0])

    def run(k):
        for i in range(k):
            j = i & 63
            u_box[0] = ANCHORS[j]
            ekf.P = P0.copy()
            ekf.predict()
            ekf.update(np.array([[RANGES[j]]]), jac, hx)

    return run


def bench_ukf(n: int):
    f = UKF3D((4.0, -2.0, 1.0), UkfConfig())

    def run(k):
        for i in range(k):
            j = i & 63
            f.P = [[25.0, 0, 0], [0, 25.0, 0], [0, 0, 100.0]]
            f.predict()
            f.update(ANCHORS[j], RANGES[j] - 0.3, 0.5)

    return run


def bench_filterpy_ukf(n: int):
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    u_box = [ANCHORS[0]]
    pts = MerweScaledSigmaPoints(3, alpha=1e-3, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=3, dim_z=1, dt=1.0, points=pts,
                                fx=lambda x, dt: x,
                                hx=lambda x: np.array([math.dist(x, u_box[0])]))
    ukf.x = np.array([4.0, -2.0, 1.0])
    ukf.Q = np.diag([0.01, 0.01, 0.04])
    ukf.R = np.array([[0.5]])
    P0 = np.diag([25.0, 25.0, 100.0])

    def run(k):
        for i in range(k):
            j = i & 63
            u_box[0] = ANCHORS[j]
            ukf.P = P0.copy()
            ukf.predict()
            ukf.update(np.array([RANGES[j] - 0.3]))

    return run


def make_replay_input(n_meas: int = 455, seed: int = 1):
    """Associated ranges of a simulated paper-ap1f flight (first ``n_meas`` to AP_1F)."""
    from estimator.association import Associator
    from estimator.geodesy import TangentPlaneENU
    from estimator.logio import read_log
    from estimator.records import AssociatedRange

    tmp = Path(tempfile.mkdtemp(prefix="osa-bench-")) / "ap1f.jsonl"
    try:
        import sim

        sim.simulate(sim.load_scenario("paper-ap1f"), seed, tmp)
        source = "sim paper-ap1f"
    except Exception as exc:
        print(f"(simulator unavailable: {exc}; using the example log)")
        tmp = Path(__file__).resolve().parents[1] / "examples" / "example_flight.jsonl"
        source = "examples/example_flight.jsonl"
    t0 = time.perf_counter()
    log = read_log(tmp)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    geo = list(Associator().run(sorted(log.gnss + log.rtt, key=lambda r: r.t_ns)))
    t_assoc = time.perf_counter() - t0
    counts: dict[str, int] = {}
    for g in geo:
        counts[g.bssid] = counts.get(g.bssid, 0) + 1
    bssid = max(counts, key=counts.get)
    geo = [g for g in geo if g.bssid == bssid][:n_meas]
    fr = TangentPlaneENU(geo[0].lat_deg, geo[0].lon_deg, geo[0].alt_m)
    ms = [
        AssociatedRange(t_s=g.t_ns * 1e-9, bssid=g.bssid, range_m=g.range_m,
                        rssi_dbm=g.rssi_dbm, anchor_enu_m=fr.to_enu(g.lat_deg, g.lon_deg, g.alt_m),
                        anchor_acc_m=g.acc_m, anchor_vacc_m=g.vacc_m,
                        agl_m=log.header.agl_m or 45.0, anchor_fix=g.fix, agent="uav-1")
        for g in geo
    ]
    return ms, source, len(log.gnss) + len(log.rtt), t_read, t_assoc


def six_modes(ms) -> list[Track]:
    front = SharedFront()
    tracks = [Track(ms[0].bssid, MODES[m], front=front, keep_history=False) for m in PAPER_MODES]
    for m in ms:
        for t in tracks:
            t.process(m)
    return tracks


def refined_mode(ms) -> RefinedTrack:
    """Mode refined alone: front, periodic refinements, the final one (its own front)."""
    tr = RefinedTrack(ms[0].bssid, front=SharedFront(), keep_history=False)
    for m in ms:
        tr.process(m)
    tr.finalize()
    tr.reported()  # the 95 % circle of the final estimate
    return tr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--n", type=int, default=4000, help="updates per timing run")
    a = ap.parse_args()
    n, rep = a.n, a.repeat
    rows = []
    iekf3 = per_call_us(bench_iekf(n, 3), n, rep)
    iekf1 = per_call_us(bench_iekf(n, 1), n, rep)
    fp_ekf = per_call_us(bench_filterpy_ekf(n), n, rep)
    ukf = per_call_us(bench_ukf(n), n, rep)
    fp_ukf = per_call_us(bench_filterpy_ukf(n), n, rep)
    rows.append(("IEKF3D predict+update, M=3 (us)", iekf3, fp_ekf, iekf3 / fp_ekf, 0.2))
    rows.append(("IEKF3D predict+update, M=1 (us)", iekf1, fp_ekf, iekf1 / fp_ekf, 0.2))
    rows.append(("UKF3D predict+update (us)", ukf, fp_ukf, ukf / fp_ukf, 0.2))
    print(f"{'benchmark':<36}{'ours':>10}{'filterpy':>10}{'ratio':>8}{'target':>8}")
    for name, ours, ref, ratio, target in rows:
        ok = "ok" if ratio <= target else "MISS"
        print(f"{name:<36}{ours:>10.2f}{ref:>10.2f}{ratio:>8.3f}{'<=' + str(target):>8} {ok}")

    ms, source, n_lines, t_read, t_assoc = make_replay_input()
    times = []
    for _ in range(rep):
        t0 = time.perf_counter()
        tracks = six_modes(ms)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times) * 1e3
    print(f"\nsix-mode replay of {len(ms)} measurements ({source}): median {med:.1f} ms "
          f"(min {min(times) * 1e3:.1f}); target < 50 ms: {'ok' if med < 50 else 'MISS'}")
    print("  statuses: " + ", ".join(f"{t.spec.name}={t.status}" for t in tracks))
    refined_mode(ms)  # warm-up: scipy.special is imported on the first 95 % circle
    times = []
    for _ in range(rep):
        t0 = time.perf_counter()
        tr = refined_mode(ms)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times) * 1e3
    print(f"refined-mode replay of {len(ms)} measurements: median {med:.1f} ms "
          f"(min {min(times) * 1e3:.1f}; {tr.n_refinements} refinements); target < 50 ms: "
          f"{'ok' if med < 50 else 'MISS'}; status {tr.status}")
    print(f"  log read ({n_lines} records): {t_read * 1e3:.0f} ms, association "
          f"{t_assoc * 1e3:.0f} ms (once per log, shared by all modes)")


if __name__ == "__main__":
    main()
