"""Every compiled kernel (numba: sim._kernels, and the loops given to
estimator._jit.compiled: the WGS84 conversion's, the FTM radio's and its terrain
occlusion's) gives the interpreted source's values bit for bit, so a flight is the
same flight with and without numba's compiler."""

from __future__ import annotations

import ast
import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from estimator.geodesy import ExactENU
from sim import _kernels as kn
from sim._random import BlockedGaussMarkov
from sim.clock import ClockConfig
from sim.ftm import FtmConfig, simulate_ftm
from sim.terrain import GridTerrain, HillsTerrain
from sim.vehicle import (
    WALKER,
    HoldGuidance,
    Multirotor,
    PathGuidance,
    VehicleConfig,
    VehicleState,
    VehicleTrack,
)
from sim.world import Origin, Responder, World

WORLD = World(Origin(), HillsTerrain(), ())
ROOT = Path(__file__).parents[2]


def test_hypot_rounds_as_cpython_does() -> None:
    rng = np.random.default_rng(11)
    for scale in (1e-300, 1e-3, 1.0, 37.0, 1e5, 1e300):
        a = rng.normal(size=20000) * scale
        b = rng.normal(size=20000) * scale
        b[::5] = 0.0
        a[::7] = b[::7]
        want = [math.hypot(x, y) for x, y in zip(a.tolist(), b.tolist(), strict=True)]
        got = [kn.hypot(x, y) for x, y in zip(a.tolist(), b.tolist(), strict=True)]
        assert got == want
    assert math.isinf(kn.hypot(math.inf, math.nan)) and math.isnan(kn.hypot(1.0, math.nan))
    assert kn.hypot(0.0, -0.0) == 0.0 and kn.hypot(5e-324, 5e-324) == math.hypot(5e-324, 5e-324)


def _random_path(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    k = int(rng.integers(2, 7))
    p = np.cumsum(rng.normal(0.0, 25.0, (k, 3)), axis=0)
    p[:, 2] = 30.0 + 0.2 * np.abs(p[:, 2])
    if k > 2 and rng.random() < 0.4:
        p[2] = p[1]  # a hover
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(1.0, 15.0, k - 1))])
    return t, p


def flights_digest() -> str:
    """SHA-256 of paths built and flown (path, hold, wind, a terrain-referenced path,
    navigation errors) on seeded random references: the same in any process."""
    rng = np.random.default_rng(5)
    h = hashlib.sha256()
    cfgs = (VehicleConfig(), VehicleConfig(wind_enu_mps=(3.0, -2.0)),
            VehicleConfig(max_speed_mps=6.0, sharp_turn_deg=40.0))
    for j in range(18):
        cfg = cfgs[j % 3]
        t, p = _random_path(rng)
        kw = {}
        if j % 4 == 3:
            kw = {"terrain_height": WORLD.ground_m, "height_above_terrain_m": p[:, 2] - 10.0}
        g = PathGuidance(t, p, cfg, start_speed_mps=float(rng.uniform(0.0, 6.0)),
                         arrive_m=0.5, **kw)
        off = rng.normal(0.0, 1.0, 3)
        v = Multirotor(cfg, WORLD, VehicleState(0.0, g.start_m, (0.5, -0.3, 0.0)),
                       nav_error=lambda tt, off=off: np.sin(tt)[:, None] * off)
        v.set_guidance(g)
        v.advance(37.35)
        v.set_guidance(HoldGuidance(tuple(p[0]), cfg))
        v.advance(60.0)
        at = v.position_at(rng.uniform(-5.0, 65.0, 50))  # the logged grid, interpolated
        for a in (g._path, g._dwell, g._stop_after, g._gs, v.state_log.view, at):
            h.update(np.ascontiguousarray(a).tobytes())
    # a blocked Gauss-Markov process (the GNSS and wander errors), interpolated
    gm = BlockedGaussMarkov(np.random.SeedSequence(3), 0.1, (1.5, 1.5, 2.5), 60.0, order=2)
    h.update(gm.at(np.sort(rng.uniform(0.0, 300.0, 400))).tobytes())
    # the GNSS records' geodesy (estimator.geodesy's compiled pymap3d path) and terrain
    frame = ExactENU(36.72, -4.48, 60.0)
    for _ in range(20):
        e, n, u = rng.normal(0.0, 10.0 ** rng.uniform(0, 5), (3, 200))
        for a in (*frame.to_geodetic(e, n, u), WORLD.ground_m(e, n)):
            h.update(np.ascontiguousarray(a).tobytes())
    # the FTM radio (its reach bound, time warp and request scan): a 2-minute pass by
    # 16 responders, some out of reach, up to 6 ranged per request
    resp = tuple(Responder(name=f"R{k}", bssid=f"02:00:00:00:00:{k:02x}", e_m=float(e),
                           n_m=float(n), concealment=("open", "vegetation")[k % 2])
                 for k, (e, n) in enumerate(rng.uniform((-350, -150), (350, 150), (16, 2))))
    world = World(Origin(), HillsTerrain(), resp)
    t = np.arange(0.0, 120.0, 0.05)
    p = np.column_stack([-300.0 + 5.0 * t, 40.0 * np.sin(t / 9.0), 45.0 + 10.0 * np.sin(t / 20.0)])
    track = VehicleTrack(t, p, np.gradient(p, t, axis=0), np.zeros(len(t)),
                         world.ground_m(p[:, 0], p[:, 1]))
    f = simulate_ftm(track, world, FtmConfig(), ClockConfig(), 4)
    for name in ("t_s", "request", "responder", "status", "range_m", "rssi_dbm", "request_peers",
                 "occlusion_loss_db", "occlusion_excess_m"):
        h.update(np.ascontiguousarray(getattr(f, name)).tobytes())
    # the radio's terrain occlusion (its clearance test, profile sampling and nu)
    h.update(occlusion_digest().encode())
    return h.hexdigest()


def compiled_kernels() -> set[tuple[str, str]]:
    """(file, function) of every compiled kernel in the packages: functions decorated
    with numba's ``njit`` / ``jit`` and functions given to ``estimator._jit.compiled``
    (``compiled(f)`` or ``map(compiled, (f, g, ...))``)."""
    out = set()
    for pkg in ("estimator", "sim", "planner", "envs"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.FunctionDef):
                    for d in node.decorator_list:
                        t = d.func if isinstance(d, ast.Call) else d
                        if getattr(t, "id", getattr(t, "attr", None)) in ("njit", "jit"):
                            out.add((rel, node.name))
                elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                    args = node.args
                    if node.func.id == "map" and args and getattr(args[0], "id", "") == "compiled":
                        args = getattr(args[1], "elts", []) if len(args) > 1 else []
                    elif node.func.id != "compiled":
                        continue
                    out |= {(rel, a.id) for a in args if isinstance(a, ast.Name)}
    return out


_INTERPRETED = """
import json, sys
from tests.sim.test_kernels import flights_digest
ran = set()
def seen(frame, event, arg):
    if event == "call":
        ran.add((frame.f_code.co_filename, frame.f_code.co_name))
sys.setprofile(seen)
digest = flights_digest()
sys.setprofile(None)
print(json.dumps({"digest": digest, "ran": sorted(ran)}))
"""


def test_compiled_flights_equal_the_interpreted_source_bit_for_bit() -> None:
    """The same flights, geodesy, terrain and FTM ranging with numba's compiler and with
    NUMBA_DISABLE_JIT=1 (the source run by the interpreter, CPython's math.hypot
    included): the same bytes; and the interpreted run went through every kernel."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    out = subprocess.run([sys.executable, "-c", _INTERPRETED], env=env, capture_output=True,
                         text=True, timeout=300, cwd=ROOT, check=True)
    got = json.loads(out.stdout)
    assert got["digest"] == flights_digest()
    ran = set()
    for file, name in got["ran"]:
        p = Path(file)
        if p.is_relative_to(ROOT):
            ran.add((p.relative_to(ROOT).as_posix(), name))
    kernels = compiled_kernels()
    assert {("sim/ftm.py", k) for k in ("_warp", "_scan", "_maybe_reached")} <= kernels
    assert {("sim/occlusion.py", k) for k in ("_profile_samples", "_profile_max_nu",
                                               "_cleared_annuli")} <= kernels
    assert len(kernels) >= 21 and not kernels - ran, f"not exercised: {sorted(kernels - ran)}"


def test_walker_and_generic_guidance_tick_by_tick_equal_the_compiled_run() -> None:
    """A guidance object the kernel does not know flies tick by tick through the same
    dynamics: wrapping a path guidance's command gives the compiled flight's track."""
    world = WORLD
    cfg = VehicleConfig()
    t, p = np.array([0.0, 20.0, 40.0]), np.array([[0.0, 0.0, 60.0], [90.0, 10.0, 70.0],
                                                   [120.0, 80.0, 65.0]])

    class Wrapped:
        name = "wrapped"

        def __init__(self, g: PathGuidance) -> None:
            self.g = g

        @property
        def done(self) -> bool:
            return self.g.done

        def command(self, px: float, py: float, pz: float, dt: float):
            return self.g.command(px, py, pz, dt)

    tracks = []
    for wrap in (False, True):
        g = PathGuidance(t, p, cfg)
        v = Multirotor(cfg, world, VehicleState(0.0, tuple(p[0]), (0.0, 0.0, 0.0)),
                       nav_error=lambda tt: np.column_stack([np.sin(tt), np.cos(tt), 0 * tt]))
        v.set_guidance(Wrapped(g) if wrap else g)
        for t_end in (7.3, 19.0, 61.0):
            v.advance(t_end, until_done=True)
        tracks.append(v.state_log.view.copy())
    assert np.array_equal(tracks[0], tracks[1]) and len(tracks[0]) > 500
    # a walker's height follows the ground, 1.5 m above it
    v = Multirotor(WALKER, world, VehicleState(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    v.set_guidance(HoldGuidance((20.0, 5.0, 0.0), WALKER))
    v.advance(30.0)
    st = v.state_log.view
    assert np.allclose(st[:, 3], world.ground_m(st[:, 1], st[:, 2]) + 1.5)
    assert math.dist(st[-1, 1:3], (20.0, 5.0)) < 0.5


def occlusion_digest() -> str:
    """SHA-256 of the FTM occlusion profiles (sim.occlusion's compiled sampling and nu
    loops) of seeded random links over hills and a grid, with and without the
    clearance tables' cleared annuli."""
    from sim.occlusion import Occluder, profile_nu

    rng = np.random.default_rng(9)
    h = hashlib.sha256()
    grid = GridTerrain(rng.normal(0.0, 2.0, (81, 81)).cumsum(0) * 0.3, -200.0, -200.0, 5.0)
    for terrain in (HillsTerrain(), grid):
        resp = np.column_stack([rng.uniform(-150, 150, (3, 2)), np.zeros(3)])
        resp[:, 2] = terrain.height_m(resp[:, 0], resp[:, 1]) + 0.5
        k = rng.integers(0, 3, 400)
        p = resp[k] + np.column_stack([rng.uniform(-250, 250, (400, 2)),
                                       rng.uniform(-5.0, 60.0, 400)])
        occ = Occluder(terrain, resp, 5.18e9, 2.0)
        ob = occ.obstruction(k, p)
        for a in (profile_nu(resp[k], p, terrain, 0.0579, 3.0), ob.nu, ob.loss_db, ob.excess_m):
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()
