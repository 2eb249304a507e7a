"""Accuracy and honesty of every mode over seeded worlds (issue 8).

    python benchmarks/accuracy_best.py [--seeds 40] [--first-seed 0] [--worlds all]

Worlds (tests/estimator/worlds.py, independent of sim/): ``los-standalone`` (one UAV,
hilly ground, standalone GNSS with a 1.5 m/axis bias correlated over 20 min, 3 %
gross outliers), ``los-rtk`` (the same with RTK fixes), ``vegetation-pass`` (an
AP_AB-like 28 m straight pass, NLoS) and ``three-agents`` (two UAVs and a walking
ground agent with worse GNSS, each on its own clock and range offset).

Per world and mode: the median and 90th percentile of the final horizontal error;
its ratio to the plain batch robust fit of the same logs in the same ENU frame (scipy
least_squares, [x, y, z, b], soft-L1, multi-start; ``/batch`` the ratio of the
medians, ``paired`` the median of the per-world ratios) and to the CRLB (the median
radial error an efficient estimator would have: the 50 % circle of the Cramer-Rao
covariance with the true range noise and GNSS error, so 1.0 is the information
limit); the 95 % coverage (truth inside the circle of the reported covariance,
computed for every mode); the confidently wrong answers (``wrong``: converged, and the
truth outside the 95 % circle or more than 5 m off; ``>5m``: converged and more than
5 m off); the statuses; the median cost per update (the track alone on the associated
ranges). For ``vegetation-pass``: also the error of the nearest candidate. For
``three-agents``: each agent alone, the best single agent, and UAV 1 with the walker.
Medians and ratios only: nothing here is asserted.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.batch import r_circle_m  # noqa: E402
from estimator.geodesy import ExactENU  # noqa: E402
from estimator.modes import MODES, resolve_mode  # noqa: E402
from estimator.pipeline import SharedFront, make_track  # noqa: E402
from estimator.replay import ReplayOptions, replay_logs  # noqa: E402
from tests.estimator import worlds as W  # noqa: E402, N812

ALL_WORLDS = ("los-standalone", "los-rtk", "vegetation-pass", "three-agents")


def horizontal_error_m(world: W.World, lat: float, lon: float, alt: float) -> float:
    e, n, _ = ExactENU(*W.ORIGIN).to_enu(lat, lon, alt)
    return math.hypot(e - world.ap_enu_m[0], n - world.ap_enu_m[1])


def cost_per_update_us(paths, modes) -> dict[str, float]:
    """Each mode's track alone (own front) over the associated ranges, per range."""
    ms, _ = W.associated_ranges(paths)
    out = {}
    for mode in modes:
        tr = make_track(W.BSSID, resolve_mode(mode), front=SharedFront(), keep_history=False)
        t0 = time.perf_counter()
        for m in ms:
            tr.process(m)
        fin = getattr(tr, "finalize", None)
        if fin is not None:
            fin()
        out[mode] = (time.perf_counter() - t0) / max(len(ms), 1) * 1e6
    return out


class Row:
    def __init__(self) -> None:
        self.err: list[float] = []
        self.ref: list[float] = []
        self.crlb: list[float] = []
        self.covered: list[bool] = []
        self.wrong = 0
        self.far = 0  # converged and more than 5 m off
        self.status: Counter = Counter()
        self.cost: list[float] = []
        self.cand: list[float] = []

    def add(self, t, world: W.World, ref_err: float, crlb50: float) -> None:
        self.status[t.status] += 1
        self.ref.append(ref_err)
        self.crlb.append(crlb50)
        e = t.estimate
        if e is None or t.err_h_m is None:
            self.err.append(math.inf)
            return
        self.err.append(t.err_h_m)
        C = np.array(e.cov_m2)[:2, :2]
        r95 = e.r95_h_m if e.r95_h_m is not None else r_circle_m(C, 0.95)
        inside = t.err_h_m <= r95
        self.covered.append(inside)
        if t.status == "converged" and (not inside or t.err_h_m > 5.0):
            self.wrong += 1
        if t.status == "converged" and t.err_h_m > 5.0:
            self.far += 1
        cands = t.estimated.candidates if t.estimated is not None else ()
        if cands:
            self.cand.append(min(horizontal_error_m(world, c.lat_deg, c.lon_deg, c.alt_m)
                                 for c in cands))
        else:
            self.cand.append(t.err_h_m)


def fmt_row(name: str, r: Row, n: int, extra: str = "") -> str:
    err = np.array(r.err)
    med = float(np.median(err))
    p90 = float(np.percentile(err, 90))
    ratio_ref = med / float(np.median(r.ref))
    ratio_crlb = med / float(np.median(r.crlb))
    paired = float(np.median(err / np.array(r.ref)))
    cov = f"{np.mean(r.covered):.0%}" if r.covered else "-"
    cost = f"{np.median(r.cost):.0f}" if r.cost else "-"
    st = ",".join(f"{k}:{v}" for k, v in sorted(r.status.items()))
    return (f"  {name:<16}{med:>8.2f}{p90:>8.2f}{ratio_ref:>8.2f}{paired:>8.2f}"
            f"{ratio_crlb:>8.2f}{cov:>7}"
            f"{r.wrong:>6}/{n:<4}{r.far:>5}{cost:>7}  {st}{extra}")


HEAD = (f"  {'mode':<16}{'median':>8}{'p90':>8}{'/batch':>8}{'paired':>8}{'/CRLB':>8}"
        f"{'cov95':>7}{'wrong':>11}{'>5m':>5}{'us/upd':>7}  statuses")


def run_world(kind: str, seeds, modes, tmp: Path, timing_seeds: int, projection: str
              ) -> None:
    rows = {m: Row() for m in modes}
    ref_row: list[float] = []
    crlb_row: list[float] = []
    singles: dict[str, list[float]] = {}
    pair: list[float] = []
    for k, seed in enumerate(tqdm(seeds, desc=kind, unit="world", file=sys.stderr)):
        d = tmp / f"{kind}-{seed}"
        d.mkdir()
        world = W.WORLDS[kind](seed, d)
        rep = replay_logs(world.paths, ReplayOptions(modes=modes, keep_history=False,
                                                     projection=projection))
        ref_err = W.reference_error_m(world, projection)
        crlb50 = r_circle_m(W.crlb_cov_h(world), 0.5)
        ref_row.append(ref_err)
        crlb_row.append(crlb50)
        for m in modes:
            rows[m].add(rep.get(W.BSSID, m), world, ref_err, crlb50)
        if k < timing_seeds:
            for m, us in cost_per_update_us(world.paths, modes).items():
                rows[m].cost.append(us)
        if kind == "three-agents":
            for a in world.agents:
                t = replay_logs([a.path], ReplayOptions(modes=("refined",), keep_history=False,
                                                        projection=projection))
                e = t.get(W.BSSID, "refined").err_h_m
                singles.setdefault(a.name, []).append(math.inf if e is None else e)
            t = replay_logs([world.agents[0].path, world.agents[2].path],
                            ReplayOptions(modes=("refined",), keep_history=False,
                                          projection=projection))
            e = t.get(W.BSSID, "refined").err_h_m
            pair.append(math.inf if e is None else e)
    n = len(seeds)
    print(f"\n{kind}: {n} worlds (seeds {seeds[0]}..{seeds[-1]}), {projection} ENU; "
          "final horizontal error [m]")
    print(HEAD)
    for m in modes:
        extra = ""
        if kind == "vegetation-pass" and m == "refined":
            extra = f"  nearest candidate: median {np.median(rows[m].cand):.2f} m"
        print(fmt_row(m, rows[m], n, extra))
    ref = np.array(ref_row)
    print(f"  {'batch fit':<16}{np.median(ref):>8.2f}{np.percentile(ref, 90):>8.2f}"
          f"{1.0:>8.2f}{1.0:>8.2f}{np.median(ref) / np.median(crlb_row):>8.2f}")
    print(f"  {'CRLB (50 %)':<16}{np.median(crlb_row):>8.2f}{np.percentile(crlb_row, 90):>8.2f}")
    if singles:
        fused = np.array(rows["refined"].err)
        best = min(singles, key=lambda a: np.median(singles[a]))
        for a, errs in singles.items():
            print(f"  refined, {a + ' alone':<22} median {np.median(errs):.2f}  "
                  f"p90 {np.percentile(errs, 90):.2f}")
        b = np.array(singles[best])
        print(f"  fused / best single agent ({best}): median {np.median(fused):.2f} / "
              f"{np.median(b):.2f} = {np.median(fused) / np.median(b):.2f}; worlds where "
              f"fused > 1.2 x that agent: {int(np.sum(fused > 1.2 * b))}/{n}")
        u1 = np.array(singles[world.agents[0].name])
        pr = np.array(pair)
        print(f"  uav-1 + walker / uav-1 alone: median {np.median(pr):.2f} / "
              f"{np.median(u1):.2f} = {np.median(pr) / np.median(u1):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--worlds", default="all", help="comma-separated, or all")
    ap.add_argument("--modes", default="all", help="comma-separated, or all (every mode)")
    ap.add_argument("--timing-seeds", type=int, default=5,
                    help="worlds per kind on which the cost per update is measured")
    ap.add_argument("--projection", choices=("tangent", "wgs84"), default="tangent",
                    help="replay frame: eq. (1) tangent plane (osa replay's default) or exact")
    a = ap.parse_args()
    kinds = ALL_WORLDS if a.worlds == "all" else tuple(a.worlds.split(","))
    modes = tuple(MODES) if a.modes == "all" else tuple(a.modes.split(","))
    if "refined" not in modes:
        modes = (*modes, "refined")
    seeds = list(range(a.first_seed, a.first_seed + a.seeds))
    with tempfile.TemporaryDirectory(prefix="osa-best-") as tmp:
        for kind in kinds:
            run_world(kind, seeds, modes, Path(tmp), a.timing_seeds, a.projection)


if __name__ == "__main__":
    main()
