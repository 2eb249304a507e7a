"""The closed loop over MAVLink (``osa search --connection``) against ``osa vehicle``.

The same plan flown in process and over MAVLink on the same scenario and seed ends
with final estimates within :data:`SAME_PLAN_TOLERANCE_M` of each other (timing
differs, the world is the same; with the loop's estimator mode measured 0.17-0.22 m
with RTK GNSS and 0.2-1.1 m with standalone GNSS, seeds 0-4); new plans are uploaded,
read back and switched to without stopping; the loop's log replays to its report; a
lost vehicle ends the loop with one line.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from envs.cli import main as osa_main
from envs.loop import run_search
from envs.mavlink_loop import (
    LinkLoopConfig,
    MavlinkLoop,
    VehicleLinkError,
    run_search_mavlink,
)
from estimator.replay import ReplayOptions, replay_logs
from planner.coverage import polyline_trajectory
from planner.observation import Decision
from sim import load_scenario
from tests.envs.vehicle.helpers import SEARCH_SCENARIO
from tests.vehicles import running_vehicle

DATA = Path(__file__).parent / "vehicle" / "data"
SHORT = str(DATA / "search-ap1f-short.toml")
# horizontal distance between the two final estimates, by GNSS preset
SAME_PLAN_TOLERANCE_M = {"rtk": 0.5, "standalone": 2.5}
RTK_SCENARIO = str(DATA / "search-ap1f-rtk.toml")


class TwoOrbits:
    """A fixed plan: a circle about a prior point, a smaller one from ``switch_s``
    (sent mid-flight), the end at ``end_s`` (whatever the estimator says), or once the
    second circle is flown (``end_when_flown``)."""

    name = "two-orbits"

    def __init__(self, center: tuple[float, float], switch_s: float = 90.0,
                 end_s: float = 160.0, laps: float = 2.0, end_when_flown: bool = False) -> None:
        self.center = center
        self.switch_s, self.end_s, self.laps = switch_s, end_s, laps
        self.end_when_flown = end_when_flown

    def reset(self, mission, rng) -> None:
        self.mission = mission
        self.sent = 0

    def _circle(self, radius: float, laps: float, a0: float = 0.0) -> object:
        a = a0 + np.linspace(0.0, 2 * math.pi * laps, int(36 * laps) + 1)
        pts = np.column_stack([self.center[0] + radius * np.cos(a),
                               self.center[1] + radius * np.sin(a)])
        return polyline_trajectory(pts, 40.0, 6.0, self.mission.origin, f"orbit-{radius:g}")

    def decide(self, obs) -> Decision:
        if self.sent == 0:
            self.sent = 1
            return Decision(plans={0: self._circle(50.0, self.laps)})
        if self.sent == 1 and obs.t_s >= self.switch_s:
            self.sent = 2  # the inner circle from 40 degrees ahead of the vehicle
            x, y = obs.agent.position_enu_m[:2]
            a0 = math.atan2(y - self.center[1], x - self.center[0]) + math.radians(40.0)
            return Decision(plans={0: self._circle(35.0, self.laps, a0)}, replans=1)
        if obs.t_s >= self.end_s if not self.end_when_flown else (
                self.sent == 2 and obs.agent.segment_done):
            return Decision(done=True, localised=frozenset(
                r.bssid for r in obs.responders if r.status == "converged"))
        return Decision()


def _horizontal_m(a: dict, b: dict) -> float:
    dn = (a["lat"] - b["lat"]) * 111_320.0
    de = (a["lon"] - b["lon"]) * 111_320.0 * math.cos(math.radians(a["lat"]))
    return math.hypot(de, dn)


@pytest.mark.parametrize("gnss", ["rtk", pytest.param("standalone", marks=pytest.mark.slow)])
def test_same_plan_in_process_and_over_mavlink(tmp_path: Path, gnss: str) -> None:
    scenario = RTK_SCENARIO if gnss == "rtk" else SEARCH_SCENARIO
    tol = SAME_PLAN_TOLERANCE_M[gnss]
    sc = load_scenario(scenario)
    ap1f = sc.world.responder("AP_1F")
    prior = (ap1f.e_m + 8.0, ap1f.n_m - 5.0)
    in_proc = run_search(sc, TwoOrbits(prior), 0)
    vlog, own = tmp_path / "vehicle.jsonl", tmp_path / "flight.jsonl"
    with running_vehicle(scenario, speedup=30.0, log_path=vlog) as rv:
        over = run_search_mavlink(sc, TwoOrbits(prior), rv.pymavlink_url, vlog, 0,
                                  log_paths=[own])
        ap = rv.autopilot
        uploads = rv.vehicle.protocol.commits[0]
        assert ap.mode.label == "AUTO.RTL"  # sent home at the end
        t_switch = ap.mission_set_at[-1]
        trk = ap.vehicle.track()
    assert (in_proc.ended, over.ended) == ("localised", "localised")
    assert over.flight_time_s == pytest.approx(160.0, abs=5.0)
    assert uploads == 2 and over.replans == 1
    a = {r["bssid"]: r for r in in_proc.responders}[ap1f.bssid]
    b = {r["bssid"]: r for r in over.responders}[ap1f.bssid]
    assert a["status"] == b["status"] == "converged"
    assert _horizontal_m(a, b) < tol, _horizontal_m(a, b)
    assert abs(a["err_h_m"] - b["err_h_m"]) < tol
    # the second plan was switched to without stopping (the vehicle's own 20 Hz track)
    at = (trk.t_s >= t_switch - 2.0) & (trk.t_s <= t_switch + 5.0)
    speed = np.hypot(trk.vel_enu_mps[at, 0], trk.vel_enu_mps[at, 1])
    assert speed.min() > 3.0
    # the loop's own log replays to its report
    rep = replay_logs([str(own)], ReplayOptions(modes=(over.mode,), keep_history=False))
    tr = {t.bssid: t for t in rep.tracks}[ap1f.bssid]
    assert (round(tr.lat_deg, 8), round(tr.lon_deg, 8)) == (b["lat"], b["lon"])


def test_loop_over_a_lossy_link(tmp_path: Path) -> None:
    """10 % of the datagrams lost both ways: telemetry gaps, resent commands and items;
    the plans still get through, verified, and the search ends as planned."""
    from tests.net import LossyUdpProxy

    sc = load_scenario(SEARCH_SCENARIO)
    ap1f = sc.world.responder("AP_1F")
    vlog = tmp_path / "vehicle.jsonl"
    with running_vehicle(SEARCH_SCENARIO, speedup=40.0, log_path=vlog) as rv, \
            LossyUdpProxy(rv.port, drop=0.1, seed=3) as proxy:
        link = LinkLoopConfig(message_timeout_s=0.08, retries=12, command_timeout_s=0.3,
                              command_attempts=8)
        policy = TwoOrbits((ap1f.e_m, ap1f.n_m), 35.0, laps=1.0, end_when_flown=True)
        over = run_search_mavlink(sc, policy, f"udpout:127.0.0.1:{proxy.port}", vlog, 0,
                                  link=link)
        ap = rv.autopilot
        assert rv.vehicle.protocol.commits[0] == 2
        # the second plan was flown to its end (the loop saw it done through the link)
        second = [seq for seq, t, _ in ap.reached_log if t > ap.mission_set_at[-1]]
        assert second[-3:] == list(range(len(ap.mission.items) - 3, len(ap.mission.items)))
        assert min(proxy.dropped) > 1
    assert over.ended == "localised" and 35.0 < over.flight_time_s < 200.0
    b = {r["bssid"]: r for r in over.responders}[ap1f.bssid]
    assert b["detected_at_s"] < 10.0  # the phone's ranges reached the estimator


def test_osa_search_over_mavlink(tmp_path: Path, capsys) -> None:
    vlog = tmp_path / "vehicle.jsonl"
    out = tmp_path / "out"
    with running_vehicle(SHORT, speedup=40.0, log_path=vlog) as rv:
        status = osa_main(["search", SHORT, "--policy", "lawnmower", "--connection",
                           rv.pymavlink_url, "--vehicle-log", str(vlog), "-o", str(out),
                           "--json", "--no-figures", "--no-progress"])
        o, err = capsys.readouterr()
        assert (status, err) == (0, ""), err
    report = json.loads(o)
    assert report["ended"] == "budget" and report["flight_time_s"] == pytest.approx(120.0)
    assert report["log"] == str(out / "flight.jsonl")
    assert json.loads((out / "report.json").read_text()) == report
    rep = json.loads(_replay_json(out / "flight.jsonl", report["mode"], capsys))
    got = {e["bssid"]: e for e in rep["estimates"]}
    for r in report["responders"]:
        if "lat" in r:
            assert (got[r["bssid"]]["lat"], got[r["bssid"]]["status"]) == (r["lat"], r["status"])


def _replay_json(path: Path, mode: str, capsys) -> str:
    assert osa_main(["replay", str(path), "--mode", mode, "--json"]) == 0
    return capsys.readouterr().out


def test_osa_search_over_mavlink_refusals(tmp_path: Path, capsys) -> None:
    cases = [
        (["--connection", "udpout:127.0.0.1:1"], 2, "--connection needs --vehicle-log"),
        (["--vehicle-log", "x.jsonl"], 2, "--vehicle-log needs --connection"),
        (["--connection", "", "--vehicle-log", "x.jsonl"], 2, "--connection: empty"),
        (["--connection", "udpout:127.0.0.1:1", "--vehicle-log", "x.jsonl.gz"], 2, "gzip"),
    ]
    for extra, code, text in cases:
        status = osa_main(["search", SHORT, "-o", str(tmp_path / "o"), "--no-progress",
                           *extra])
        err = capsys.readouterr().err
        assert status == code and err.count("\n") == 1 and text in err, err
    # a vehicle of another world (seed) is refused before it flies
    vlog = tmp_path / "vehicle.jsonl"
    with running_vehicle(SHORT, seed=1, speedup=20.0, log_path=vlog) as rv:
        status = osa_main(["search", SHORT, "--seed", "0", "--connection", rv.pymavlink_url,
                           "--vehicle-log", str(vlog), "-o", str(tmp_path / "o"),
                           "--no-progress", "--no-figures"])
        err = capsys.readouterr().err
        assert not rv.autopilot.armed
    assert status == 1 and err.count("\n") == 1
    assert err.startswith("osa search: VehicleLinkError: the vehicle flies another world "
                          "than search-ap1f-short seed 0")


def test_a_lost_vehicle_ends_the_loop_in_bounded_time(tmp_path: Path) -> None:
    sc = load_scenario(SHORT)
    vlog = tmp_path / "vehicle.jsonl"
    with running_vehicle(SHORT, speedup=20.0, log_path=vlog) as rv:
        loop = MavlinkLoop(sc, 0, rv.pymavlink_url, vlog,
                           link=LinkLoopConfig(telemetry_timeout_s=1.0))
        loop.start()
        loop.advance(2.0)
        rv.vehicle.stop()  # the vehicle (or the radio) is gone
        t0 = time.monotonic()
        with pytest.raises(VehicleLinkError, match="no telemetry from the vehicle for 1 s"):
            loop.advance(60.0)
        assert time.monotonic() - t0 < 3.0
        loop.link_config = LinkLoopConfig(telemetry_timeout_s=0.2, return_at_end=False)
        loop.finish()


@pytest.mark.slow
def test_adaptive_search_over_mavlink_ends_like_in_process(tmp_path: Path) -> None:
    """The adaptive policy (CasADi re-plans while the vehicle flies on) over MAVLink:
    both runs localise the responder; their decisions differ, so the estimates agree
    within the estimator's scatter (bench_vehicle, RTK, seeds 0-2: 0.25-0.77 m)."""
    from envs.policies import load_policy

    sc = load_scenario("search-random-los-rtk")
    in_proc = run_search(sc, load_policy("adaptive"), 0)
    vlog = tmp_path / "vehicle.jsonl"
    with running_vehicle("search-random-los-rtk", speedup=30.0, log_path=vlog) as rv:
        over = run_search_mavlink(sc, load_policy("adaptive"), rv.pymavlink_url, vlog, 0,
                                  log_paths=[tmp_path / "flight.jsonl"])
        assert rv.vehicle.protocol.commits[0] >= 3  # the sweep, a probe, CasADi plans
    assert in_proc.ended == over.ended == "localised"
    a, b = in_proc.responders[0], over.responders[0]
    assert a["status"] == b["status"] == "converged"
    assert _horizontal_m(a, b) < 2.0 and b["err_h_m"] < 2.0
