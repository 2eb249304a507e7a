"""FTM terrain occlusion's cost (sim.occlusion).

Run ``python benchmarks/bench_occlusion.py [--runs N]``. Prints

1. per link: the whole terrain profile against the radio's path through the clearance
   tables, on the default hills and on a rough grid (20 000 links of 150 m, the drone
   45 m above the ground), and the share of links whose profile is sampled;
2. per flight: the CPU time of the FTM radio (``FtmRadio.range_until``, reach grid and
   results) with ``[ftm] occlusion`` on and off, median over N seeds, for paper-ap1f and
   three-aps, and the links it checked.
3. with ``--planner`` (instead of 1 and 2): the CasADi planner's two stages over a
   grid ridge (20 m high, 40 m wide, 5 m cells, 15 m north of the estimate; the case
   of tests/planner/test_link_occlusion.py) at 24 and 40 waypoints: the build and the
   plan's CPU time blind to the ridge (the first stage alone) and aware of it (both
   stages), the share of the aware plan in view of the estimate, the CPU time per call
   of the constraints' Jacobian and of the Lagrangian's Hessian in each stage; then the
   adaptive policy's planner build on ``site-valley`` and ``search-random-los``.

CPU time (``time.process_time``), so a busy machine shifts the figures less.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np


def per_link() -> None:
    from sim import GridTerrain, HillsTerrain
    from sim.occlusion import Occluder, profile_nu, wavelength_m

    rng = np.random.default_rng(0)
    grid = GridTerrain(rng.normal(0, 2, (161, 161)).cumsum(0).cumsum(1) * 0.02,
                       -400.0, -400.0, 5.0)
    lam = wavelength_m(5.18e9)
    for name, t in (("hills", HillsTerrain()), ("grid", grid)):
        ap = rng.uniform(-200, 200, (3, 2))
        resp = np.column_stack([ap, t.height_m(ap[:, 0], ap[:, 1]) + 0.5])
        n = 20_000
        k = rng.integers(0, 3, n)
        ang = rng.uniform(0, 2 * np.pi, n)
        e, nn = resp[k, 0] + 150.0 * np.cos(ang), resp[k, 1] + 150.0 * np.sin(ang)
        p = np.column_stack([e, nn, t.height_m(e, nn) + 45.0])
        profile_nu(resp[k[:5]], p[:5], t, lam, 2.0)  # compile
        Occluder(t, resp, 5.18e9, 2.0).obstruction(k[:5], p[:5])
        t0 = time.process_time()
        profile_nu(resp[k], p, t, lam, 2.0)
        t1 = time.process_time()
        occ = Occluder(t, resp, 5.18e9, 2.0)
        occ.obstruction(k, p)
        t2 = time.process_time()
        occ.obstruction(k, p)
        t3 = time.process_time()
        print(f"{name}: whole profile (74 samples) {1e6 * (t1 - t0) / n:.1f} us/link; "
              f"through the tables {1e6 * (t2 - t1) / n:.2f} us/link (bounding the sectors), "
              f"{1e6 * (t3 - t2) / n:.2f} us/link after; sampled "
              f"{occ.n_profiled / occ.n_links:.0%} of the links")


def per_flight(runs: int) -> None:
    import sim
    from sim.ftm import FtmRadio
    from sim.occlusion import Occluder

    spent = [0.0]
    checked = [0, 0]
    range_until, obstruction = FtmRadio.range_until, Occluder.obstruction

    def timed(self, *a, **kw):
        t0 = time.process_time()
        try:
            return range_until(self, *a, **kw)
        finally:
            spent[0] += time.process_time() - t0

    def counted(self, k, p):
        out = obstruction(self, k, p)
        checked[0] += len(out.nu)
        checked[1] += int(np.count_nonzero(out.loss_db))
        return out

    FtmRadio.range_until, Occluder.obstruction = timed, counted
    for name in ("paper-ap1f", "three-aps"):
        sc = sim.load_scenario(name)
        for occ in (False, True):
            s = dataclasses.replace(sc, ftm=dataclasses.replace(sc.ftm, occlusion=occ))
            sim.run_scenario(s, 0)
            per, checked[:] = [], [0, 0]
            for seed in range(runs):
                spent[0] = 0.0
                sim.run_scenario(s, seed)
                per.append(spent[0])
            extra = (f"; {checked[0] // runs} links checked per flight, {checked[1]} with a loss"
                     if occ else "")
            print(f"{name}, occlusion {'on ' if occ else 'off'}: radio "
                  f"{1e3 * statistics.median(per):.1f} ms CPU per flight (median of {runs})"
                  f"{extra}")


def _ridge():
    from sim import GridTerrain

    x = np.arange(-300.0, 301.0, 5.0)
    d = x - 15.0
    prof = np.where(np.abs(d) < 20.0, 20.0 * np.cos(np.pi * d / 40.0) ** 2, 0.0)
    return GridTerrain(np.tile(prof[:, None], (1, len(x))), -300.0, -300.0, 5.0)


def _per_call_ms(fn) -> tuple[float, float]:
    st = fn.stats()
    return (1e3 * st["t_proc_nlp_jac_g"] / max(st["n_call_nlp_jac_g"], 1),
            1e3 * st["t_proc_nlp_hess_l"] / max(st["n_call_nlp_hess_l"], 1))


def planner_stages() -> None:
    import sim
    from envs.loop import mission_of
    from planner.adaptive import AdaptivePolicy, ResponderPlanner
    from planner.optimal import OptimalConfig, OptimalPlanner
    from planner.scoring import ScoringConfig
    from sim import FtmConfig, FtmLink

    link = FtmLink(FtmConfig())
    g = _ridge()
    mean = np.array([0.0, 0.0, float(g.height_m(0.0, 0.0)) + 0.5])
    cov = np.diag([100.0, 100.0, 9.0])
    for n_w, horizon, k in ((24, 60.0, 4), (40, 120.0, 6)):
        kw = dict(n_waypoints=n_w, horizon_s=horizon, n_prior_points=k, terrain=g,
                  agl_min_m=10.0, agl_max_m=40.0)
        for aware in (False, True):
            t0 = time.process_time()
            planner = OptimalPlanner(OptimalConfig(
                **kw, scoring=ScoringConfig(link=link, terrain=g if aware else None)))
            build = time.process_time() - t0
            for start in ((30.0, -30.0), (-40.0, 0.0)):
                st = np.array([*start, float(g.height_m(*start)) + 25.0])
                planner.reset_warm_start()
                t0 = time.process_time()
                res = planner.plan(mean, cov, st)
                cpu = time.process_time() - t0
                view = float(np.mean(link.obstruction_loss_db(res.trajectory.enu_m, mean, g)
                                     == 0.0))
                jac1, hess1 = _per_call_ms(planner._solve_cold)
                line = (f"ridge, {n_w} waypoints, {'aware' if aware else 'blind'}: build "
                        f"{build:.2f} s, plan from {start} {cpu:.2f} s CPU, "
                        f"{res.iterations} iterations, {view:.0%} in view "
                        f"({res.occlusion or 'blind'}); first stage: Jacobian {jac1:.2f} ms, "
                        f"Hessian {hess1:.2f} ms per call")
                if aware and res.occlusion != "in view":
                    jac2, hess2 = _per_call_ms(planner._solve_occluded)
                    line += f"; second: {jac2:.2f} ms, {hess2:.2f} ms"
                print(line)
    for name in ("site-valley", "search-random-los"):
        mission = mission_of(sim.load_scenario(name))
        ResponderPlanner._planners.clear()
        t0 = time.process_time()
        AdaptivePolicy().reset(mission, np.random.default_rng(0))
        print(f"{name}: the adaptive policy's planner built in "
              f"{time.process_time() - t0:.2f} s CPU")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--planner", action="store_true",
                    help="the CasADi planner's two stages instead (see the docstring)")
    args = ap.parse_args(argv)
    if args.planner:
        planner_stages()
        return 0
    per_link()
    per_flight(args.runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
