"""``osa vehicle SCENARIO --connection URL [--speedup X] [--log FILE] [--seed N]``.

A simulated PX4 multicopter on MAVLink (docs/vehicle.md, docs/cli.md): the
scenario's world and sensors behind an autopilot that QGroundControl, MAVSDK,
pymavlink and ``osa upload`` talk to. Runs until SIGINT or SIGTERM, then closes the
log and exits 0. Exit 2 with one line on stderr for a bad scenario, URL or option, or a
log it may not write (an existing file without ``--force``, the scenario file itself:
envs/commands/_outputs.py); 1 if the vehicle crashed (into the terrain).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
from collections.abc import Callable
from pathlib import Path

from envs.commands._args import seed_arg
from envs.commands._outputs import OutputRefusedError, add_force_option, claim_output_file

EXIT_OK = 0
EXIT_CRASH = 1
EXIT_USAGE = 2


def speedup_value(text: str) -> float:
    """``--speedup``: a positive number, or ``max`` (as fast as the loop can)."""
    if text.strip().lower() in ("max", "inf"):
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or 'max': {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0 or 'max': {text!r}")
    return v


def param_value(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not sep or not name or not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected NAME=NUMBER, got {text!r}")
    return name.strip().upper(), v


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "vehicle",
        help="run a simulated PX4 multicopter on MAVLink (for QGroundControl, MAVSDK, "
        "osa upload)",
        description="A simulated MAVLink vehicle: the scenario's world, vehicle model and "
        "sensors behind a PX4-like autopilot. It starts landed and disarmed at the "
        "scenario's start and runs until SIGINT/SIGTERM. See docs/vehicle.md.",
    )
    p.add_argument("scenario", metavar="SCENARIO", help="scenario preset name or .toml path")
    p.add_argument("--connection", "-c", metavar="URL", action="append", required=True,
                   help="where to talk MAVLink (repeatable): udpin:127.0.0.1:14540 (listen; "
                   "ground stations use udpout:...), udpout:127.0.0.1:14550 (send to "
                   "QGroundControl's port), tcpin:HOST:PORT, tcp:HOST:PORT")
    p.add_argument("--speedup", metavar="X", type=speedup_value, default=1.0,
                   help="simulated seconds per wall second (default 1; 'max': as fast "
                   "as it can)")
    p.add_argument("--log", metavar="FILE", help="write the phone's flight log here as it "
                   "flies (with truth records, flushed line by line); an existing file "
                   "needs --force")
    p.add_argument("--seed", type=seed_arg, default=0, metavar="N",
                   help="world seed (default 0)")
    p.add_argument("--param", metavar="NAME=VALUE", type=param_value, action="append",
                   default=[], help="set an autopilot parameter at start (repeatable), "
                   "e.g. NAV_DLL_ACT=1 GF_ACTION=3; see docs/vehicle.md")
    p.add_argument("--sysid", type=int, default=1, metavar="N",
                   help="MAVLink system id (default 1)")
    p.add_argument("--lockstep", type=float, default=None, metavar="S",
                   help="never run more than S seconds of simulated time ahead of the "
                   "ground station's last acknowledgement (osa search sends one per "
                   "decision: use its --decision-period): reproducible closed loops")
    add_force_option(p)
    p.set_defaults(func=run)
    return p


def _fail(status: int, message: str) -> int:
    print(f"osa vehicle: {' '.join(str(message).split())}", file=sys.stderr)
    return status


def _inputs(scenario: str) -> list[str]:
    """The input files never to write over: the scenario's file (a preset: none)."""
    return [scenario] if Path(scenario).is_file() else []


def run(args: argparse.Namespace) -> int:
    """SIGINT and SIGTERM stop the vehicle from the moment the command starts: one that
    comes while the scenario loads (a script's ``osa vehicle ... & kill $!`` on a busy
    machine) stops it as soon as it is up, its log closed, exit status 0."""
    stop: dict[str, int | None] = {"signal": None}

    def on_signal(signum: int, frame: object) -> None:
        stop["signal"] = signum

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(args, lambda: stop["signal"] is not None)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _run(args: argparse.Namespace, stopped: Callable[[], bool]) -> int:
    from sim.scenario import ScenarioError, load_scenario

    if not 1 <= args.sysid <= 254:
        return _fail(EXIT_USAGE, f"--sysid must be in 1..254, got {args.sysid}")
    if args.lockstep is not None and not (math.isfinite(args.lockstep)
                                          and 0.05 <= args.lockstep <= 600):
        return _fail(EXIT_USAGE, f"--lockstep must be in [0.05, 600] s, got {args.lockstep}")
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        return _fail(EXIT_USAGE, str(exc))
    if scenario.agents[0].kind != "uav":
        return _fail(EXIT_USAGE, f"{scenario.name}: the first agent is not a UAV")
    if args.log is not None:
        try:
            claim_output_file(args.log, force=args.force, inputs=_inputs(args.scenario))
        except OutputRefusedError as exc:
            return _fail(EXIT_USAGE, str(exc))

    from envs.vehicle import ConnectionURLError, VirtualVehicle

    try:
        vehicle = VirtualVehicle(
            scenario, args.connection, seed=args.seed, speedup=args.speedup,
            log_path=args.log, params=dict(args.param), sysid=args.sysid,
            lockstep_s=args.lockstep,
            status=lambda message: print(f"osa vehicle: {message}", file=sys.stderr,
                                         flush=True))
    except ConnectionURLError as exc:
        return _fail(EXIT_USAGE, str(exc))
    except ValueError as exc:
        return _fail(EXIT_USAGE, str(exc))
    except OSError as exc:
        return _fail(EXIT_USAGE, f"cannot write {args.log}: {exc.strerror or exc}")
    home = vehicle.autopilot.home
    speed = "max" if math.isinf(args.speedup) else f"{args.speedup:g}x"
    print(f"osa vehicle: {scenario.name} seed {args.seed}: PX4 quadrotor, system "
          f"{args.sysid}, landed and disarmed at {home.lat_deg:.7f}, {home.lon_deg:.7f} "
          f"({home.alt_m:.1f} m); MAVLink on {', '.join(args.connection)}; speed-up {speed}"
          + (f"; lockstep {args.lockstep:g} s" if args.lockstep else "")
          + (f"; log {args.log}" if args.log else ""), flush=True)
    try:
        vehicle.run(stopped)
    finally:
        vehicle.close()
    print(f"osa vehicle: stopped at {vehicle.t_s:.1f} s simulated "
          f"({vehicle.stats.ratio:.1f}x real time)", flush=True)
    if vehicle.error is not None:
        return _fail(EXIT_CRASH, vehicle.error)
    return EXIT_OK
