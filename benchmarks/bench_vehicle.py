"""Benchmark ``osa vehicle``: mission transfers, a 20-minute mission at speed, the loop.

Each part runs ``osa vehicle`` as its own process on 127.0.0.1 (as a user would; a
vehicle thread in the benchmark's process would share its interpreter lock):

1. upload + read-back of ``--items`` mission items (pymavlink and MAVSDK paths),
   ``--runs`` times, median and spread in ms;
2. a lawnmower mission of about 20 simulated minutes flown at ``--speedup 50`` (the
   issue's criterion: well under a minute of wall time) and at ``--speedup max``:
   wall time from MISSION_START to the disarm after landing, simulated time (from
   the vehicle's time_boot_ms), and the simulated/real ratio;
3. the closed loop (``osa search``, adaptive on search-random-los-rtk, seeds 0-2) in
   process and over MAVLink against ``osa vehicle --speedup 50 --lockstep 5`` on the
   same scenario and seed (the phone's records relayed on the link): how each ended,
   when the responder was localised, wall time, final horizontal error, distance
   between the two estimates against the sum of their 95 % radii.

    python benchmarks/bench_vehicle.py [--items 100] [--runs 20] [--skip-loop | --loop-only]
        [--loop-scenario S] [--loop-policy P] [--loop-seeds N] [--loop-speedup X]

Prints medians and ratios; never asserts timings.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

os.environ["MAVLINK20"] = "1"

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "tests" / "envs" / "vehicle" / "data" / "search-ap1f.toml")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def vehicle_process(*args: str, scenario: str = SCENARIO) -> Iterator[int]:
    """``osa vehicle SCENARIO`` listening on a free port (yields the port)."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "envs.cli", "vehicle", scenario,
                             "--connection", f"udpin:127.0.0.1:{port}", *args],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        line = proc.stdout.readline()
        if not line.startswith("osa vehicle:"):
            raise SystemExit(f"osa vehicle did not start: {proc.stderr.read()}")
        yield port
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        if err.strip():
            print(f"    (osa vehicle said: {err.strip()})")


def bench_upload(n_items: int, runs: int) -> None:
    from planner.mavlink import MAV_MISSION_TYPE_MISSION, TransferConfig, connected
    from planner.mavlink_wire import compare_wire, mission_to_wire
    from planner.mission import Mission, MissionItem

    lat0, lon0 = 36.7140, -4.4785
    items = tuple(MissionItem(lat_deg=lat0 + 1e-4 * (i % 10), lon_deg=lon0 + 1e-4 * (i // 10),
                              alt_m=45.0 + 0.1 * i) for i in range(n_items))
    wire = mission_to_wire(Mission(items=items, home=(lat0, lon0, 140.0)))
    print(f"1. upload + read-back of {n_items} items to osa vehicle, {runs} runs")
    with vehicle_process() as port:
        for backend, url in (("pymavlink", f"udpout:127.0.0.1:{port}"),
                             ("mavsdk", f"udpout://127.0.0.1:{port}")):
            times = []
            with connected(url, TransferConfig(connect_timeout_s=5.0)) as link:
                for k in range(runs + 3):
                    t0 = time.perf_counter()
                    link.upload(wire, MAV_MISSION_TYPE_MISSION)
                    held = link.download(MAV_MISSION_TYPE_MISSION)
                    dt = time.perf_counter() - t0
                    if compare_wire(wire, held):
                        raise SystemExit(f"read-back differs on run {k}")
                    if k >= 3:
                        times.append(dt)
            print(f"   {backend:9s} median {statistics.median(times) * 1e3:6.1f} ms  "
                  f"(min {min(times) * 1e3:.1f}, max {max(times) * 1e3:.1f})")


def lawnmower(home, frame, minutes: float, speed: float, alt: float):
    """A lawnmower from home lasting about ``minutes`` at ``speed`` (plus climb, turns)."""
    from planner.mission import (
        MAV_CMD_NAV_RETURN_TO_LAUNCH,
        MAV_CMD_NAV_TAKEOFF,
        Mission,
        MissionItem,
    )

    leg, spacing = 400.0, 40.0
    n_legs = max(2, int(minutes * 60.0 * speed / (leg + spacing)))
    items = [MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=home.lat_deg,
                         lon_deg=home.lon_deg, alt_m=alt)]
    e0, n0 = home.enu[0] - leg / 2, home.enu[1]
    for k in range(n_legs):
        n = n0 + spacing * (k % 10)  # back and forth over a 400 m x 360 m block
        xs = (e0, e0 + leg) if k % 2 == 0 else (e0 + leg, e0)
        for e in xs:
            lat, lon, _ = frame.to_geodetic(e, n, home.enu[2])
            items.append(MissionItem(lat_deg=float(lat), lon_deg=float(lon), alt_m=alt))
    items.append(MissionItem(command=MAV_CMD_NAV_RETURN_TO_LAUNCH))
    return Mission(items=tuple(items), home=(home.lat_deg, home.lon_deg, home.alt_m))


def fly_mission(speedup: str, minutes: float) -> tuple[float, float]:
    """(wall s, simulated s) from MISSION_START to the disarm after landing."""
    from envs.vehicle.autopilot import Autopilot
    from planner.mavlink import TransferConfig, mavutil, upload_mission
    from sim import Stepper, load_scenario, realise

    sc = load_scenario(SCENARIO)
    ap = Autopilot(Stepper(realise(sc, 0), agents=sc.agents[:1]))  # the same home and frame
    mission = lawnmower(ap.home, ap.frame, minutes, sc.search.speed_mps, 40.0)
    with vehicle_process("--speedup", speedup) as port:
        upload_mission(mission, f"udpout:127.0.0.1:{port}",
                       config=TransferConfig(connect_timeout_s=5.0))
        c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255,
                                       source_component=190)
        try:
            def command(cmd: int, *p: float) -> int:
                c.mav.command_long_send(1, 1, cmd, 0, *p, *([0.0] * (7 - len(p))))
                end = time.monotonic() + 5.0
                while time.monotonic() < end:
                    m = c.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5)
                    if m is not None and m.command == cmd:
                        return int(m.result)
                raise SystemExit(f"no COMMAND_ACK for {cmd}")

            c.mav.heartbeat_send(6, 8, 0, 0, 0)
            c.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
            assert command(400, 1.0) == 0 and command(300, 0.0, 0.0) == 0
            t0 = time.perf_counter()
            boot0 = None
            last_hb = 0.0
            armed_seen = True
            deadline = time.monotonic() + 3600.0
            while time.monotonic() < deadline:
                if time.monotonic() - last_hb > 0.5:
                    c.mav.heartbeat_send(6, 8, 0, 0, 0)
                    last_hb = time.monotonic()
                m = c.recv_match(type=["GLOBAL_POSITION_INT", "HEARTBEAT"], blocking=True,
                                 timeout=0.5)
                if m is None:
                    continue
                if m.get_type() == "GLOBAL_POSITION_INT":
                    boot0 = m.time_boot_ms if boot0 is None else boot0
                    boot1 = m.time_boot_ms
                elif m.get_srcSystem() == 1:
                    armed_seen = bool(m.base_mode & 128)
                    if not armed_seen:
                        break
            wall = time.perf_counter() - t0
        finally:
            c.close()
    return wall, (boot1 - boot0) / 1000.0


def bench_fly(minutes: float) -> None:
    print(f"2. a lawnmower of ~{minutes:g} simulated minutes (8 m/s, 40 m), start to disarm")
    for speedup in ("50", "max"):
        wall, sim_s = fly_mission(speedup, minutes)
        print(f"   --speedup {speedup:>3s}: {sim_s / 60:5.1f} simulated min in {wall:6.1f} s "
              f"wall, simulated/real {sim_s / wall:6.1f}x")


def _search(args: list[str]) -> tuple[dict, float]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "envs.cli", "search", *args, "--json",
                           "--no-figures", "--no-progress"], cwd=ROOT, capture_output=True,
                          text=True, timeout=3600)
    if proc.returncode:
        raise SystemExit(f"osa search failed: {proc.stderr.strip()}")
    return json.loads(proc.stdout), time.perf_counter() - t0


def _distance_m(a: dict, b: dict) -> float:
    dn = (a["lat"] - b["lat"]) * 111_320.0
    de = (a["lon"] - b["lon"]) * 111_320.0 * math.cos(math.radians(a["lat"]))
    return math.hypot(de, dn)


def bench_loop(scenario: str, policy: str, seeds: int, speedup: str) -> None:
    print(f"3. closed loop {policy} on {scenario}: in process vs over MAVLink "
          f"(osa vehicle --speedup {speedup} --lockstep 5)")
    walls: dict[str, list[float]] = {"in": [], "mav": []}
    for seed in range(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            inp, w_in = _search([scenario, "--policy", policy, "--seed", str(seed), "-o",
                                 f"{tmp}/in"])
            with vehicle_process("--speedup", speedup, "--seed", str(seed), "--lockstep",
                                 "5", scenario=scenario) as port:
                mav, w_mav = _search([scenario, "--policy", policy, "--seed", str(seed),
                                      "-o", f"{tmp}/mav", "--connection",
                                      f"udpout:127.0.0.1:{port}"])
        walls["in"].append(w_in)
        walls["mav"].append(w_mav)
        for a, b in zip(inp["responders"], mav["responders"], strict=True):
            d = f"{_distance_m(a, b):5.2f} m" if "lat" in a and "lat" in b else "  -    "
            nan = float("nan")
            print(f"   seed {seed}: in process {inp['ended']:>9s} {inp['flight_time_s']:6.0f} s "
                  f"loc {a.get('localised_at_s', nan):5.0f} s {a['status']:>13s} err "
                  f"{a.get('err_h_m', nan):5.2f} m, wall {w_in:5.1f} s | MAVLink "
                  f"{mav['ended']:>9s} {mav['flight_time_s']:6.0f} s loc "
                  f"{b.get('localised_at_s', nan):5.0f} s {b['status']:>13s} err "
                  f"{b.get('err_h_m', nan):5.2f} m, wall {w_mav:5.1f} s, lost "
                  f"{mav['phone']['lost']} | estimates {d} apart (r95 sum "
                  f"{a.get('r95_h_m', nan) + b.get('r95_h_m', nan):.2f} m)")
    m_in, m_mav = statistics.median(walls["in"]), statistics.median(walls["mav"])
    print(f"   median wall: in process {m_in:.1f} s, over MAVLink {m_mav:.1f} s "
          f"(ratio {m_mav / m_in:.1f})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=100)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--skip-loop", action="store_true")
    parser.add_argument("--loop-only", action="store_true", help="only part 3")
    parser.add_argument("--loop-scenario", default="search-random-los-rtk")
    parser.add_argument("--loop-policy", default="adaptive")
    parser.add_argument("--loop-seeds", type=int, default=3)
    parser.add_argument("--loop-speedup", default="50")
    args = parser.parse_args(argv)
    if not args.loop_only:
        bench_upload(args.items, args.runs)
        bench_fly(args.minutes)
    if not args.skip_loop:
        bench_loop(args.loop_scenario, args.loop_policy, args.loop_seeds, args.loop_speedup)
    return 0


if __name__ == "__main__":
    sys.exit(main())
