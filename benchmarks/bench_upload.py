"""Benchmark: upload 100 mission items and read them back on loopback.

Target (issue 4): median <= 50 ms for upload + download of 100 items, for both the
pymavlink and the MAVSDK path, against ``osa vehicle``'s autopilot
(:class:`envs.vehicle.VirtualVehicle`, landed, speed-up 1) on 127.0.0.1. The
connection (heartbeat discovery, up to 1 s) is made once and not timed. Every run's
read-back is compared with what was sent.

    python benchmarks/bench_upload.py [--items 100] [--runs 30]

Exit status 1 if a median misses the target.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import time

from planner.mavlink import MAV_MISSION_TYPE_MISSION, TransferConfig, connected
from planner.mavlink_wire import compare_wire, mission_to_wire
from planner.mission import Mission, MissionItem
from sim import load_scenario

TARGET_S = 0.050


def make_mission(n_items: int) -> Mission:
    lat0, lon0 = 36.7149123, -4.4781234
    items = tuple(
        MissionItem(lat_deg=lat0 + 1e-4 * (i % 10), lon_deg=lon0 + 1e-4 * (i // 10),
                    alt_m=45.0 + 0.1 * i)
        for i in range(n_items))
    return Mission(items=items, home=(lat0, lon0, 108.0))


def bench(url: str, n_items: int, runs: int, warmup: int = 3) -> list[float]:
    """Seconds per upload + download round trip, one entry per timed run."""
    wire = mission_to_wire(make_mission(n_items))
    times = []
    with connected(url, TransferConfig(connect_timeout_s=5.0)) as link:
        for k in range(warmup + runs):
            t0 = time.perf_counter()
            link.upload(wire, MAV_MISSION_TYPE_MISSION)
            held = link.download(MAV_MISSION_TYPE_MISSION)
            dt = time.perf_counter() - t0
            diffs = compare_wire(wire, held)
            if diffs:
                raise SystemExit(f"read-back differs on run {k}: {diffs[0]}")
            if k >= warmup:
                times.append(dt)
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=100)
    parser.add_argument("--runs", type=int, default=30)
    args = parser.parse_args(argv)
    if args.runs < 10:
        parser.error("--runs must be >= 10")
    ok = True
    from envs.vehicle import VirtualVehicle

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    with VirtualVehicle(load_scenario("three-aps"), [f"udpin:127.0.0.1:{port}"]):
        print(f"upload + read-back of {args.items} items to osa vehicle on loopback, "
              f"{args.runs} runs, target median {TARGET_S * 1e3:.0f} ms")
        for backend, url in (("pymavlink", f"udpout:127.0.0.1:{port}"),
                             ("mavsdk", f"udpout://127.0.0.1:{port}")):
            times = bench(url, args.items, args.runs)
            med = statistics.median(times)
            ok &= med <= TARGET_S
            print(f"  {backend:9s} median {med * 1e3:6.1f} ms  (min {min(times) * 1e3:.1f}, "
                  f"max {max(times) * 1e3:.1f})  ratio to target {med / TARGET_S:.2f}  "
                  f"{'OK' if med <= TARGET_S else 'MISS'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
