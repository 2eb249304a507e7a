"""Write the small example flight log shipped in examples/ (seeded, a few lines of numpy).

A drone circles a line-of-sight responder at 45 m above ground for four minutes on
three orbits of different radii and centres, then passes close by. GNSS at 10 Hz with
a slowly drifting bias, FTM ranges at ~4 Hz with the paper's Empirical-R noise and a
few multipath outliers. Run:  python examples/make_example_log.py examples/example_flight.jsonl
"""

from __future__ import annotations

import argparse

import numpy as np

from estimator.geodesy import ExactENU
from estimator.logio import LogWriter
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord

ORIGIN = (36.7151, -4.4783, 100.0)  # lat, lon, ellipsoidal height of the ground (m)
BSSID = "a4:77:33:0f:1e:02"
AP_ENU = np.array([20.0, -15.0, 0.5])  # responder 0.5 m above flat ground
AGL_M = 45.0


def drone_path(t: np.ndarray) -> np.ndarray:
    """Three orbits (60 m, 35 m, 80 m) around shifted centres, then a close pass."""
    seg = np.minimum((t // 60).astype(int), 3)
    centres = np.array([[0.0, 0.0], [40.0, -10.0], [10.0, -30.0], [20.0, -15.0]])
    radii = np.array([60.0, 35.0, 80.0, 8.0])
    omega = 2 * np.pi / 60.0
    ang = omega * t
    xy = centres[seg] + radii[seg, None] * np.column_stack((np.cos(ang), np.sin(ang)))
    z = np.full_like(t, AGL_M) + 3.0 * np.sin(2 * np.pi * t / 97.0)
    return np.column_stack((xy, z))


def main(path: str, seed: int = 7) -> None:
    rng = np.random.default_rng(seed)
    frame = ExactENU(*ORIGIN)
    t0_ns = 81_234_000_000_000
    t_gnss = np.arange(0.0, 240.0, 0.1)
    bias = np.cumsum(rng.normal(0.0, 0.02, (len(t_gnss), 3)), axis=0) + np.array([0.8, -0.5, 0.3])
    pos = drone_path(t_gnss) + bias + rng.normal(0.0, 0.05, (len(t_gnss), 3))
    lat, lon, alt = frame.to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    t_rtt = np.sort(rng.uniform(0.0, 240.0, 960))
    true = drone_path(t_rtt)
    d = np.linalg.norm(true - AP_ENU, axis=1)
    rssi = np.round(-35.0 - 22.0 * np.log10(d) + rng.normal(0.0, 2.0, len(d)))
    sigma = np.sqrt(0.3**2 + 4e-4 * d**2 + 3e-3 * np.maximum(0.0, -rssi - 40.0) ** 2)
    meas = d + 0.4 + sigma * rng.standard_normal(len(d))
    outlier = rng.random(len(d)) < 0.03
    meas[outlier] += rng.exponential(8.0, outlier.sum())
    alat, alon, aalt = frame.to_geodetic(*AP_ENU)
    header = LogHeader(agent="uav-1", start_utc="2026-05-08T10:12:00Z", agl_m=AGL_M,
                       range_offset_m=0.0)
    with LogWriter(path, header) as w:
        w.write(TruthRecord(bssid=BSSID, lat_deg=round(alat, 9), lon_deg=round(alon, 9),
                            alt_m=round(aalt, 3), concealment="open"))
        recs = []
        for k, t in enumerate(t_gnss):
            recs.append(GnssFix(t_ns=t0_ns + round(t * 1e9), lat_deg=round(float(lat[k]), 9),
                                lon_deg=round(float(lon[k]), 9), alt_m=round(float(alt[k]), 3),
                                acc_m=0.9, vacc_m=1.5, fix="3d", sats=21))
        for k, t in enumerate(t_rtt):
            recs.append(RangeSample(t_ns=t0_ns + round(t * 1e9), bssid=BSSID, status="ok",
                                    range_m=round(float(meas[k]), 3),
                                    range_std_m=round(float(sigma[k]), 3),
                                    rssi_dbm=float(rssi[k]), attempted=8, successful=7))
        recs.sort(key=lambda r: r.t_ns)
        w.write_all(recs)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", nargs="?", default="examples/example_flight.jsonl",
                    help="log to write (.jsonl, or .jsonl.gz; default %(default)s)")
    ap.add_argument("--seed", type=int, default=7, help="random seed (default %(default)s)")
    a = ap.parse_args()
    main(a.path, a.seed)
