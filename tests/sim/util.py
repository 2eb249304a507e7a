"""Small builders for simulator tests: a world with chosen responders and flights."""

from __future__ import annotations

import dataclasses

import numpy as np

from sim import (
    Circle,
    FtmConfig,
    HillsTerrain,
    Origin,
    Responder,
    Scenario,
    SweepsFlight,
    VehicleTrack,
    World,
)

BSSID = "a4:77:33:0f:1e:02"


def responder(
    name: str = "AP",
    bssid: str = BSSID,
    e_m: float = 0.0,
    n_m: float = 0.0,
    concealment: str = "open",
    **kw,
) -> Responder:
    return Responder(name=name, bssid=bssid, e_m=e_m, n_m=n_m, concealment=concealment, **kw)


def circles_flight(
    radii_m=(40.0, 70.0, 100.0), laps: float = 2.0, height_m: float = 45.0, center=(0.0, 0.0)
) -> SweepsFlight:
    """Concentric circles around ``center``: many ranges over a spread of distances."""
    return SweepsFlight(
        start_e_m=center[0] + radii_m[0],
        start_n_m=center[1],
        height_m=height_m,
        speed_mps=7.0,
        circles=tuple(
            Circle(center_e_m=center[0], center_n_m=center[1], radius_m=r, laps=laps)
            for r in radii_m
        ),
    )


def scenario(responders, flight=None, ftm: FtmConfig | None = None, **kw) -> Scenario:
    world = World(Origin(), HillsTerrain(), tuple(responders))
    return Scenario(
        name="test",
        world=world,
        flight=flight or circles_flight(),
        ftm=ftm or FtmConfig(),
        **kw,
    )


def hover_track(duration_s: float, enu=(0.0, 0.0, 45.0), dt_s: float = 0.05) -> VehicleTrack:
    """A vehicle standing still at ``enu`` (for sensor tests that need no motion)."""
    n = round(duration_s / dt_s) + 1
    t = np.arange(n) * dt_s
    p = np.repeat(np.asarray(enu, dtype=float)[None, :], n, axis=0)
    return VehicleTrack(t, p, np.zeros_like(p), np.zeros(n), np.zeros(n))


def with_ftm(cfg: FtmConfig, **changes) -> FtmConfig:
    return dataclasses.replace(cfg, **changes)
