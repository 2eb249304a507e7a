"""The short simulated flight of the import tests and how estimates are compared.

``three-aps`` cut to three of its circles and the close pass: 5.9 minutes, 3520 GNSS
fixes (10 Hz), 1247 ranging results, two responders that converge (AP_1F in the open,
AP_AB under vegetation).
"""

from __future__ import annotations

import dataclasses
import math

import sim
from estimator.replay import ReplayOptions, replay_logs
from tests.estimator.importers.writers import Flight, flight_from_log

MODES = ("baseline", "empirical-r", "refined")


def short_scenario():
    sc = sim.load_scenario("three-aps")
    f = sc.flight
    flight = dataclasses.replace(f, circles=(f.circles[0], f.circles[1], f.circles[6]))
    return dataclasses.replace(sc, name="three-aps-short", flight=flight)


def simulate_short(path) -> Flight:
    """Simulate the short flight (seed 0) into ``path``; its records."""
    sim.simulate(short_scenario(), 0, path)
    return flight_from_log(path)


def estimates(path, modes=MODES) -> dict:
    """{(bssid, mode): TrackResult} of a replay."""
    report = replay_logs([str(path)], ReplayOptions(modes=modes))
    return {(t.bssid, t.mode): t for t in report.tracks}


def horizontal_m(a, b) -> float:
    """Horizontal distance between two estimates (m; a local flat-earth step, exact to
    far below a millimetre at these distances)."""
    dn = (a.lat_deg - b.lat_deg) * 111_320.0
    de = (a.lon_deg - b.lon_deg) * 111_320.0 * math.cos(math.radians(a.lat_deg))
    return math.hypot(dn, de)


def largest_differences(ref: dict, got: dict) -> tuple[float, float, float]:
    """(horizontal, vertical, r95) largest differences (m) over every track, after
    checking both replays have the same tracks, statuses and estimate presence."""
    assert set(ref) == set(got)
    dh = dz = dr = 0.0
    for k, a in ref.items():
        b = got[k]
        assert (a.status, a.lat_deg is None) == (b.status, b.lat_deg is None), k
        if a.lat_deg is None:
            continue
        dh = max(dh, horizontal_m(a, b))
        dz = max(dz, abs(a.alt_m - b.alt_m))
        ra, rb = a.estimated.r95_h_m, b.estimated.r95_h_m
        assert (ra is None) == (rb is None), k
        if ra is not None:
            dr = max(dr, abs(ra - rb))
    return dh, dz, dr
