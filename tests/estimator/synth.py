"""A seeded synthetic flight, a few lines of numpy (no simulator needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator.geodesy import ExactENU
from estimator.logio import LogWriter
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord

ORIGIN = (36.7151, -4.4783, 100.0)
BSSID = "a4:77:33:0f:1e:02"


def write_flight(
    path: Path,
    *,
    seed: int = 0,
    ap_enu=(25.0, -10.0, 0.5),
    path_fn=None,
    duration_s: float = 180.0,
    t0_ns: int = 5_000_000_000_000,
    agent: str = "uav-1",
    start_utc: str | None = "2026-05-08T10:12:00Z",
    sigma_m: float = 0.5,
    bssid: str = BSSID,
    rtt_rate_hz: float = 4.0,
    extra_lines: tuple[str, ...] = (),
) -> Path:
    """Orbit(s) at 45 m AGL around an AP on flat ground; GNSS 10 Hz, FTM ~4 Hz."""
    rng = np.random.default_rng(seed)
    frame = ExactENU(*ORIGIN)
    ap = np.asarray(ap_enu, float)
    if path_fn is None:
        def path_fn(t):
            a = 2 * np.pi * t / 60.0
            r = 50.0 + 15.0 * np.sin(2 * np.pi * t / 90.0)
            return np.column_stack((r * np.cos(a), r * np.sin(a), 45.0 + 0 * t))
    tg = np.arange(0.0, duration_s, 0.1)
    pos = path_fn(tg) + rng.normal(0, 0.05, (tg.size, 3))
    lat, lon, alt = frame.to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    tr = np.sort(rng.uniform(0, duration_s, int(rtt_rate_hz * duration_s)))
    d = np.linalg.norm(path_fn(tr) - ap, axis=1) + 0.3 + rng.normal(0, sigma_m, tr.size)
    rssi = np.round(-35 - 20 * np.log10(d))
    alat, alon, aalt = frame.to_geodetic(*ap)
    hdr = LogHeader(agent=agent, start_utc=start_utc, agl_m=45.0, range_offset_m=0.0)
    recs = [GnssFix(t_ns=t0_ns + int(t * 1e9), lat_deg=float(a), lon_deg=float(b),
                    alt_m=float(c), acc_m=0.9, fix="3d")
            for t, a, b, c in zip(tg, lat, lon, alt, strict=True)]
    recs += [RangeSample(t_ns=t0_ns + int(t * 1e9), bssid=bssid, status="ok",
                         range_m=float(x), rssi_dbm=float(s))
             for t, x, s in zip(tr, d, rssi, strict=True)]
    recs.sort(key=lambda r: r.t_ns)
    with LogWriter(path, hdr) as w:
        w.write(TruthRecord(bssid=bssid, lat_deg=float(alat), lon_deg=float(alon),
                            alt_m=float(aalt), concealment="open"))
        w.write_all(recs)
    if extra_lines:
        with open(path, "a", encoding="utf-8") as fh:
            for line in extra_lines:
                fh.write(line + "\n")
    return path
