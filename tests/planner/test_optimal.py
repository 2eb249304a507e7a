"""CasADi planner: constraints checked numerically, objective beats circles, re-solves."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from planner.optimal import (
    OptimalConfig,
    OptimalPlanner,
    _info_entries,
    _log_det_marginal,
    guidance_orbit,
    planning_objective,
)
from planner.patterns import FlightConfig, Geofence, KeepOut, densify, orbit
from planner.scoring import prior_points, score_trajectory
from tests.planner.conftest import gaussian_hills

COV = np.diag([100.0, 100.0, 4.0])
FENCE = Geofence(vertices_m=((-200.0, -200.0), (200.0, -200.0), (220.0, 150.0), (-200.0, 200.0)))
TOWER = KeepOut(east_m=40.0, north_m=30.0, radius_m=15.0)
START = np.array([-150.0, -100.0, 45.0])


@pytest.fixture(scope="module")
def planner() -> OptimalPlanner:
    return OptimalPlanner()


@pytest.fixture(scope="module")
def first(planner: OptimalPlanner):
    planner.reset_warm_start()
    return planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])


def assert_feasible(W, start, vel, dt, cfg, fence, keep_outs, band=(30.0, 80.0), terrain=None):
    """Every constraint, recomputed here (not through the planner's own check)."""
    tol = 0.01
    assert W.shape == (cfg.n_waypoints, 3) and np.all(np.isfinite(W))
    assert np.allclose(W[0], start, atol=tol)
    step = np.diff(W, axis=0)
    assert np.all(np.linalg.norm(step, axis=1) <= cfg.max_speed_m_s * dt + tol)
    assert np.all(np.abs(step[:, 2]) <= cfg.max_climb_m_s * dt + tol)
    vel_seq = np.vstack([vel, step / dt])
    assert np.all(
        np.linalg.norm(np.diff(vel_seq, axis=0), axis=1) <= cfg.max_accel_m_s2 * dt + tol / dt
    )
    ground = 0.0 if terrain is None else terrain.height_m(W[1:, 0], W[1:, 1])
    agl = W[1:, 2] - ground
    assert agl.min() >= band[0] - tol and agl.max() <= band[1] + tol
    dense = densify(W, 0.5)
    if fence is not None:
        assert fence.signed_distance_m(dense[:, :2]).max() <= tol
    for ko in keep_outs:
        assert (
            np.hypot(dense[:, 0] - ko.east_m, dense[:, 1] - ko.north_m).min() >= ko.radius_m - tol
        )


def test_plan_satisfies_every_constraint(planner: OptimalPlanner, first) -> None:
    r = first
    assert r.feasible and r.fallback is None and r.violations == ()
    assert r.dt_s == pytest.approx(planner.cfg.horizon_s / (planner.cfg.n_waypoints - 1))
    assert_feasible(r.waypoints_enu_m, START, np.zeros(3), r.dt_s, planner.cfg, FENCE, [TOWER])
    # the returned trajectory flies the waypoints
    t = r.trajectory
    assert t.duration_s == pytest.approx(planner.cfg.horizon_s)
    idx = [int(np.argmin(np.abs(t.t_s - k * r.dt_s))) for k in range(planner.cfg.n_waypoints)]
    assert np.allclose(t.t_s[idx], np.arange(planner.cfg.n_waypoints) * r.dt_s)
    assert np.allclose(t.enu_m[idx], r.waypoints_enu_m, atol=1e-9)
    assert np.diff(t.t_s).max() <= 0.5 + 1e-9
    assert (
        planner.check(r.waypoints_enu_m, START, (0, 0, 0), r.dt_s, fence=FENCE, keep_outs=[TOWER])
        == []
    )


def test_plan_beats_same_length_circles(first) -> None:
    r = first
    pts = prior_points((0.0, 0.0, 0.0), COV, 6)
    length = float(np.linalg.norm(np.diff(r.waypoints_enu_m, axis=0), axis=1).sum())
    speed = length / r.trajectory.duration_s
    best = -math.inf
    for radius in (20.0, 30.0, 45.0, 60.0, 90.0):
        for alt in (30.0, 45.0, 60.0):
            c = orbit((0.0, 0.0), radius, turns=length / (2 * math.pi * radius),
                      flight=FlightConfig(speed_m_s=speed, alt_m=alt))  # fmt: skip
            assert c.duration_s * speed == pytest.approx(length)
            Wc = np.column_stack(
                [np.interp(np.arange(40) * r.dt_s, c.t_s, c.enu_m[:, j]) for j in range(3)]
            )
            best = max(best, planning_objective(Wc, pts, r.dt_s))
            assert score_trajectory(c, (0.0, 0.0, 0.0)).log_det_fim == -math.inf
    assert r.objective > best + 1.0  # log det larger by e (x 2.7 in det) at least
    s = score_trajectory(r.trajectory, (0.0, 0.0, 0.0))
    assert math.isfinite(s.log_det_fim) and math.isfinite(s.crlb_v_m)


def test_resolve_with_changed_parameters(planner: OptimalPlanner, first) -> None:
    W0 = first.waypoints_enu_m
    start, vel = W0[1], (W0[2] - W0[1]) / first.dt_s
    towers = [TOWER, KeepOut(east_m=-60.0, north_m=-20.0, radius_m=10.0)]
    planner.reset_warm_start()
    planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])  # warm state
    r = planner.plan((25.0, -15.0, 0.0), 0.5 * COV, start, vel, fence=FENCE, keep_outs=towers)
    assert r.feasible and r.fallback is None, r.violations
    assert_feasible(r.waypoints_enu_m, start, vel, r.dt_s, planner.cfg, FENCE, towers)
    assert np.abs(r.waypoints_enu_m[1:] - W0[1:]).max() > 5.0
    r2 = planner.plan((25.0, -15.0, 0.0), 0.5 * COV, start, vel, fence=FENCE, keep_outs=towers,
                      horizon_s=90.0, agl_band_m=(35.0, 60.0))  # fmt: skip
    assert r2.feasible and r2.dt_s == pytest.approx(90.0 / 39)
    assert_feasible(
        r2.waypoints_enu_m, start, vel, r2.dt_s, planner.cfg, FENCE, towers, band=(35.0, 60.0)
    )


def test_solver_success_is_not_trusted(planner: OptimalPlanner, monkeypatch) -> None:
    """A 'successful' solver path through a tower is rejected; a feasible orbit is flown."""
    cfg = planner.cfg
    line = np.linspace(START, (200.0, 150.0, 45.0), cfg.n_waypoints)  # through TOWER
    line[1:, 2] = 20.0  # and below the altitude band

    class Lying:
        def __call__(self, *args):
            fv = np.zeros((10, cfg.n_prior_points))
            return line.T / cfg.position_scale_m, fv, np.zeros(planner._n_g), -1.0

        def stats(self) -> dict:
            return {"return_status": "Solve_Succeeded", "success": True, "iter_count": 3}

    monkeypatch.setattr(planner, "_solve_cold", Lying())
    planner.reset_warm_start()
    r = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])
    assert r.solver_success and r.status == "Solve_Succeeded"
    assert any("keep-out" in v for v in r.violations)
    assert any("height above terrain" in v for v in r.violations)
    assert r.fallback is not None and r.fallback.startswith("orbit") and r.feasible
    assert_feasible(r.waypoints_enu_m, START, np.zeros(3), r.dt_s, cfg, FENCE, [TOWER])
    planner.reset_warm_start()


def test_check_reports_each_violation(planner: OptimalPlanner) -> None:
    dt = 3.0
    W = guidance_orbit(START, (0, 0, 0), (0, 0, 0), 40.0, 45.0, 40, dt, 8.0, 2.0, 3.0)
    assert planner.check(W, START, (0, 0, 0), dt) == []
    bad = W.copy()
    bad[10, 2] = 20.0
    problems = planner.check(bad, START, (0, 0, 0), dt)
    assert any("height above terrain" in p for p in problems)
    assert any("climb" in p for p in problems) and any("acceleration" in p for p in problems)
    assert any(
        "geofence" in p
        for p in planner.check(W, START, (0, 0, 0), dt, fence=Geofence.square((0, 0), 50.0))
    )
    assert any("start" in p for p in planner.check(W, START + 1.0, (0, 0, 0), dt))


def test_symbolic_and_numpy_objective_agree() -> None:
    cfg = OptimalConfig()
    rng = np.random.default_rng(2)
    W = rng.uniform(-100, 100, (40, 3)) + np.array([0.0, 0.0, 60.0])
    s = np.array([3.0, -4.0, 0.5])
    P = ca.SX.sym("P", 3, 40)
    f = ca.Function("f", [P], [_info_entries(P, ca.DM(s), cfg, 2.5)])
    num = _info_entries(W, s, cfg, 2.5)
    assert np.allclose(np.asarray(f(W.T)).ravel(), num, rtol=1e-12)
    F = ca.SX.sym("F", 10)
    g = ca.Function("g", [F], [_log_det_marginal(F, cfg.prior_information)])
    assert float(g(num)) == pytest.approx(_log_det_marginal(num, cfg.prior_information), rel=1e-12)


def test_terrain_band_is_kept_over_a_hill() -> None:
    hill = gaussian_hills((0.0, 0.0, 25.0, 40.0))  # the AP on a 25 m hill top
    cfg = OptimalConfig(terrain=hill, n_prior_points=4, max_keep_outs=1, max_fence_edges=4)
    p = OptimalPlanner(cfg)
    r = p.plan((0.0, 0.0, 25.0), COV, (-150.0, -100.0, 45.0), fence=Geofence.square((0, 0), 200))
    assert r.feasible and r.fallback is None, r.violations
    assert_feasible(r.waypoints_enu_m, (-150.0, -100.0, 45.0), np.zeros(3), r.dt_s, cfg,
                    Geofence.square((0, 0), 200), [], terrain=hill)  # fmt: skip
    over_hill = np.hypot(r.waypoints_enu_m[:, 0], r.waypoints_enu_m[:, 1]) < 40.0
    assert np.any(over_hill) and np.all(r.waypoints_enu_m[over_hill, 2] > 30.0 + 0.6 * 25.0)


def test_bad_requests_are_refused(planner: OptimalPlanner) -> None:
    with pytest.raises(ValueError, match="outside the geofence"):
        planner.plan((0, 0, 0), COV, (500.0, 0.0, 45.0), fence=FENCE)
    with pytest.raises(ValueError, match="keep-out"):
        planner.plan((0, 0, 0), COV, (40.0, 30.0, 45.0), keep_outs=[TOWER])
    with pytest.raises(ValueError):
        planner.plan((0, 0, math.nan), COV, START)
    with pytest.raises(ValueError, match="keep-outs"):
        planner.plan(
            (0, 0, 0),
            COV,
            START,
            keep_outs=[KeepOut(east_m=900.0 + k, north_m=0.0, radius_m=1.0) for k in range(9)],
        )


TWO_HILLS = gaussian_hills((0.0, 0.0, 25.0, 25.0), (-50.0, -30.0, 20.0, 20.0))


def _dense_agl(W, terrain, step=0.25):
    d = densify(np.asarray(W)[1:], step)
    return d[:, 2] - terrain.height_m(d[:, 0], d[:, 1])


def test_check_sees_a_leg_sagging_over_a_hill_top(planner: OptimalPlanner) -> None:
    """Both ends 30 m above the ground 10 m either side of a 25 m (sigma 25 m) top: the
    straight leg passes the top 28.08 m above it."""
    p = OptimalPlanner.__new__(OptimalPlanner)  # the check needs only the config
    p.cfg = OptimalConfig(terrain=gaussian_hills((0.0, 0.0, 25.0, 25.0)))
    ground = float(p.cfg.terrain.height_m(10.0, 0.0))
    assert ground == pytest.approx(25.0 * math.exp(-0.08))
    W = np.array([[-20.0, 0.0, 30.0 + ground], [-10.0, 0.0, 30.0 + ground],
                  [10.0, 0.0, 30.0 + ground], [20.0, 0.0, 30.0 + ground]])  # fmt: skip
    problems = p.check(W, W[0], (5.0, 0.0, 0.0), 2.0, limits=(20.0, 10.0, 3.0))
    assert problems == ["height above terrain 28.08..34.92 m outside 30..80"]
    W[:, 2] += 30.0 - 28.08 + 0.01
    assert p.check(W, W[0], (5.0, 0.0, 0.0), 2.0, limits=(20.0, 10.0, 3.0)) == []


def test_hill_curvature_bounds_hold_along_lines() -> None:
    hills = gaussian_hills((0.0, 0.0, 25.0, 25.0), (300.0, 0.0, -10.0, 10.0))
    concave, convex = hills.sag_curvature()
    foot = 2.0 * math.exp(-1.5)
    assert concave == pytest.approx(25.0 / 625.0 + foot * 10.0 / 100.0)
    assert convex == pytest.approx(foot * 25.0 / 625.0 + 10.0 / 100.0)
    s = np.linspace(-150.0, 150.0, 30001)
    h = s[1] - s[0]

    def d2(cx: float, a: float) -> np.ndarray:  # T'' along the east-west line n = a
        t = hills.height_m(cx + s, np.full_like(s, a))
        return (t[2:] - 2 * t[1:-1] + t[:-2]) / h**2

    lines = [d2(0.0, 0.0), d2(0.0, 10.0), d2(300.0, 0.0), d2(300.0, 5.0)]
    assert max(-c.min() for c in lines) <= concave and max(c.max() for c in lines) <= convex
    assert -d2(0.0, 0.0).min() == pytest.approx(25.0 / 625.0, rel=1e-3)  # the hill top
    assert d2(0.0, 0.0).max() == pytest.approx(foot * 25.0 / 625.0, rel=1e-3)  # its foot
    assert d2(300.0, 0.0).max() == pytest.approx(10.0 / 100.0, rel=1e-3)  # the pit bottom
    assert -d2(300.0, 0.0).min() == pytest.approx(foot * 10.0 / 100.0, rel=1e-3)  # its rim


def test_plan_keeps_the_band_between_waypoints_over_convex_terrain() -> None:
    """Two hills (25 m, sigma 25; 20 m, sigma 20), band 30-80: the waypoint-only NLP
    returned feasible=True with the trajectory 28.4 m above ground between waypoints;
    now the band holds every 0.25 m along the returned trajectory and plan."""
    cfg = OptimalConfig(terrain=TWO_HILLS, n_prior_points=4, max_keep_outs=1, max_fence_edges=4)
    p = OptimalPlanner(cfg)
    fence = Geofence.square((0, 0), 200)
    start = (-150.0, -100.0, 45.0)
    r = p.plan((0.0, 0.0, 25.0), COV, start, fence=fence)
    assert r.feasible and r.fallback is None, r.violations
    assert _dense_agl(r.waypoints_enu_m, TWO_HILLS).min() >= 30.0 - 0.01
    t = r.trajectory.enu_m[1:]
    assert (t[:, 2] - TWO_HILLS.height_m(t[:, 0], t[:, 1])).min() >= 30.0 - 0.01
    assert_feasible(r.waypoints_enu_m, start, np.zeros(3), r.dt_s, cfg, fence, [],
                    terrain=TWO_HILLS)  # fmt: skip
    # the margin is what one half-leg can sag: kappa (v_max dt / 2)^2 / 8 = 1.70 m here
    kappa = TWO_HILLS.sag_curvature()[0]
    assert kappa * (cfg.max_speed_m_s * r.dt_s / 2) ** 2 / 8 == pytest.approx(1.70, abs=0.01)
    # a warm re-solve after a step along the plan keeps it too
    W = r.waypoints_enu_m
    r2 = p.plan((5.0, -3.0, 25.0), 0.8 * COV, W[1], (W[2] - W[1]) / r.dt_s, fence=fence)
    assert r2.feasible and r2.fallback is None, r2.violations
    assert _dense_agl(r2.waypoints_enu_m, TWO_HILLS).min() >= 30.0 - 0.01


def test_first_leg_band_starts_from_where_the_drone_is() -> None:
    p = OptimalPlanner.__new__(OptimalPlanner)
    p.cfg = OptimalConfig(terrain=TWO_HILLS)
    assert p.first_leg_band((-150.0, -100.0, 45.0), (30.0, 80.0), 8.0, 3.0) == (30.0, 80.0)
    agl0 = 45.0 - float(TWO_HILLS.height_m(0.0, 0.0))  # 19.72 m above the hill top
    lo, hi = p.first_leg_band((0.0, 0.0, 45.0), (30.0, 80.0), 8.0, 3.0)
    assert hi == 80.0 and lo == pytest.approx(agl0 - 0.09 * 12**2 / 8)  # half leg 12 m
    flat = OptimalPlanner.__new__(OptimalPlanner)
    flat.cfg = OptimalConfig()
    assert flat.first_leg_band((0.0, 0.0, 90.0), (30.0, 80.0), 8.0, 3.0) == (30.0, 90.0)


def test_a_solver_error_returns_a_labelled_fallback_and_no_warm_start(
    planner: OptimalPlanner, monkeypatch
) -> None:
    class Raising:
        def __call__(self, *args):
            raise RuntimeError("Error in Function::call for 'optimal_plan_cold'\nmore")

        def stats(self) -> dict:
            raise AssertionError("no stats after an error")

    monkeypatch.setattr(planner, "_solve_cold", Raising())
    planner.reset_warm_start()
    r = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE)  # the guess passes the check
    assert r.status.startswith("error: Error in Function::call") and not r.solver_success
    assert r.violations[0].startswith("no solver path (CasADi error")
    assert r.fallback is not None and r.fallback.startswith("initial guess: orbit r=")
    assert r.feasible and planner._warm is None
    assert_feasible(r.waypoints_enu_m, START, np.zeros(3), r.dt_s, planner.cfg, FENCE, [])
    assert len(r.violations) == 1
    # with the tower the guess (the best orbit) crosses it: the feasible-first fallback
    r = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])
    assert r.violations[0].startswith("no solver path") and "keep-out" in r.violations[1]
    assert r.fallback.startswith("orbit r=") and r.feasible and planner._warm is None
    monkeypatch.undo()
    # warm: the shifted previous plan is the guess; still a fallback, still no warm start
    good = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])
    assert good.fallback is None and planner._warm is not None
    monkeypatch.setattr(planner, "_solve_warm", Raising())
    r = planner.plan((2.0, 1.0, 0.0), COV, START, fence=FENCE, keep_outs=[TOWER])
    assert r.fallback is not None and r.feasible and not r.solver_success
    assert r.fallback == "initial guess: previous plan, shifted" or r.fallback.startswith("orbit")
    assert r.violations[0].startswith("no solver path") and planner._warm is None
    planner.reset_warm_start()


def test_a_band_the_terrains_curvature_shuts_is_not_sent_to_the_solver(capfd) -> None:
    """A DEM with a 40 m cliff between two 10 m cells (curvature 0.6 /m) and 30 m legs:
    the sag margins (41 + 41 m) exceed the 27 m band. The planner says so and falls back,
    without calling Ipopt on ill-posed bounds (CasADi refused them and printed its 300
    inputs on stderr, in every replan of a search over such a site)."""
    from sim.terrain import GridTerrain

    g = np.arange(-300.0, 301.0, 10.0)
    E, _ = np.meshgrid(g, g)
    p = OptimalPlanner(OptimalConfig(terrain=GridTerrain(40.0 * (E > 60.0), -300.0, -300.0,
                                                         10.0)))
    r = p.plan((0.0, 0.0, 0.0), np.diag([400.0, 400.0, 4.0]), (-100.0, -100.0, 45.0),
               agl_band_m=(38.0, 65.0), horizon_s=240.0)
    assert capfd.readouterr().err == ""
    assert r.status.startswith("not solved: the terrain's curvature shuts the height band")
    assert r.violations[0].startswith("no solver path (not solved: the terrain's curvature")
    assert r.fallback is not None and p._warm is None
