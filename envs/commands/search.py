"""``osa search SCENARIO``: a search flown in closed loop, in simulated time (docs/cli.md).

Simulator -> estimator -> policy -> vehicle until the policy judges every responder it
heard localised (from the estimator alone) or the budget is spent. Writes into the
output folder the flight log (``flight.jsonl``; one more per extra agent), the report
(``report.json``, the ``--json`` object), ``trajectory.png`` and ``errors.png``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from envs.commands._args import seed_arg
from envs.commands._outputs import add_force_option
from estimator.tables import Column, text_table

POLICY_HELP = ("lawnmower (the QGroundControl-style survey), expanding-square, adaptive "
               "(default: search until heard, then plan around the estimate), random (uniform "
               "actions of osa/Search-v0: the floor; random:waypoint), ppo:PATH "
               "(a policy trained by osa train) or team:POLICY (every UAV its own copy)")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "search",
        help="fly a search in closed loop (simulator -> estimator -> policy -> vehicle)",
        description="Fly the [search] of SCENARIO in closed loop in simulated time, until "
        "the policy judges every responder it heard localised or the budget is spent; "
        "write the flight log, report.json and figures into -o DIR.",
    )
    p.add_argument("scenario", metavar="SCENARIO",
                   help="a search preset (osa simulate --list) or a .toml with a [search] table")
    p.add_argument("--policy", default="adaptive", metavar="P", help=POLICY_HELP)
    p.add_argument("--seed", type=seed_arg, default=0, metavar="N",
                   help="world seed (default 0): the same seed, the same world for every policy")
    p.add_argument("-o", "--out", default="osa-search", metavar="DIR",
                   help="output folder (default ./osa-search)")
    p.add_argument("--json", action="store_true", help="print the JSON report on stdout only")
    p.add_argument("--mode", default=None, metavar="M",
                   help="estimator mode the loop runs (default: the project's recommended mode)")
    p.add_argument("--decision-period", type=float, default=5.0, metavar="S",
                   help="seconds of flight between two decisions of the policy (default 5)")
    p.add_argument("--rerun", metavar="RRD", default=None,
                   help="also write a rerun recording (.rrd) of the loop")
    p.add_argument("--no-figures", action="store_true", help="do not draw the figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--connection", "-c", metavar="URL", default=None,
                   help="fly a MAVLink vehicle instead of the in-process simulator, e.g. "
                   "osa vehicle on the same scenario and seed (udpout:127.0.0.1:14540); "
                   "the phone's records come on the same link (the vehicle relays them)")
    p.add_argument("--phone", metavar="URL", default=None,
                   help="with --connection: take the phone's records as JSON-line datagrams "
                   "from a phone app listening here (udpin://0.0.0.0:14600) instead")
    p.add_argument("--vehicle-log", metavar="FILE", default=None,
                   help="with --connection: take the phone's records from the log the "
                   "vehicle writes on this machine (osa vehicle --log FILE) instead")
    add_force_option(p)
    p.set_defaults(func=run)


def _fail(message: object) -> int:
    print(f"osa search: {' '.join(str(message).split())}", file=sys.stderr)
    return 2


class _Stop:
    """SIGINT (Ctrl-C) and SIGTERM end the search at its next decision: the report says
    ``interrupted``, what was heard is delivered and the log closed. A second Ctrl-C
    stops at once."""

    def __init__(self) -> None:
        self.signal: int | None = None
        self.previous: dict = {}

    def __enter__(self) -> _Stop:
        if threading.current_thread() is threading.main_thread():  # signals: main only
            for s in (signal.SIGINT, signal.SIGTERM):
                self.previous[s] = signal.signal(s, self._on_signal)
        return self

    def _on_signal(self, signum: int, frame: object) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum

    def __call__(self) -> bool:
        return self.signal is not None

    def __exit__(self, *exc: object) -> None:
        for s, h in self.previous.items():
            signal.signal(s, h)


def run(args: argparse.Namespace) -> int:
    import math

    from envs.commands._outputs import (
        OutputRefusedError,
        claim_output_dir,
        claim_output_file,
        files_written_before,
        record_files,
        remove_stale,
        written_whole,
    )
    from envs.commands._progress import QuantityProgress
    from envs.loop import DEFAULT_MODE, ClosedLoop, LoopConfig, fly
    from envs.policies import load_policy
    from sim.realisation import realise
    from sim.scenario import ScenarioError, search_scenario

    try:
        scenario = search_scenario(args.scenario)
    except ScenarioError as exc:
        return _fail(exc)
    if not (math.isfinite(args.decision_period) and 0.5 <= args.decision_period <= 600):
        return _fail(f"--decision-period must be in [0.5, 600] s, got {args.decision_period}")
    try:
        config = LoopConfig(mode=args.mode or DEFAULT_MODE,
                            decision_period_s=args.decision_period)
    except ValueError as exc:
        return _fail(f"--mode: {exc}")
    try:
        policy = load_policy(args.policy, scenario)
    except ValueError as exc:
        return _fail(f"--policy: {exc}")
    if args.connection is not None or args.vehicle_log is not None or args.phone is not None:
        problem = _link_problem(args, scenario)
        if problem:
            return _fail(problem)
    # every output is checked before the flight (docs/cli.md, "Outputs")
    inputs = [p for p in (args.scenario, args.vehicle_log) if p and Path(p).is_file()]
    names = ["flight.jsonl" if i == 0 else f"flight-{a.name}.jsonl"
             for i, a in enumerate(scenario.agents)]
    previous = files_written_before(args.out, "search")
    try:
        out = claim_output_dir(args.out, command="search", force=args.force, inputs=inputs)
        if args.rerun:
            claim_output_file(args.rerun, force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(exc)
    figure_names = [] if args.no_figures else ["trajectory.png", "errors.png"]
    # the previous search's files that this one does not write go (only those)
    remove_stale(out, [n for n in previous
                       if n not in (*names, "report.json", *figure_names)])
    record_files(out, "search", [*names, "report.json", *figure_names])
    logs = [out / name for name in names]
    budget = scenario.search.budget_s
    bar = QuantityProgress(f"osa search {policy.name}", budget, "s",
                           enabled=not args.no_progress, every=60.0)
    try:
        with _Stop() as stop:
            if args.connection is not None:
                from envs.mavlink_vehicle import VehicleLinkError
                from planner.mavlink_wire import UploadError

                try:
                    vehicle = _mavlink_vehicle(args, scenario, realise(scenario, args.seed),
                                               logs[0])
                    loop = ClosedLoop(scenario, args.seed, config=config, vehicle=vehicle,
                                      realisation=vehicle.realisation)
                    result = fly(loop, policy, progress=bar.update, should_stop=stop)
                except (VehicleLinkError, UploadError, OSError) as exc:
                    bar.close("failed", line=False)  # the reason is the one line
                    print(f"osa search: {type(exc).__name__}: {' '.join(str(exc).split())}",
                          file=sys.stderr)
                    return 1
            else:
                loop = ClosedLoop(scenario, args.seed, config=config, log_paths=logs)
                result = fly(loop, policy, progress=bar.update, should_stop=stop)
    except KeyboardInterrupt:  # a second Ctrl-C: stop at once
        bar.close("interrupted")
        return 130
    bar.close("interrupted" if result.ended == "interrupted" else "done")
    report = result.to_json()
    with written_whole(out / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=1, allow_nan=False))
    figures: list[Path] = []
    if not args.no_figures:
        from envs.search_plots import plot_search
        from sim import realise

        figures = list(plot_search(result, out,
                                   terrain=realise(scenario, args.seed).world.terrain))
    if args.rerun:
        from envs.viz import record_search

        with written_whole(args.rerun) as tmp:  # never half a recording over the last
            record_search(result, tmp)
    if args.json:
        print(json.dumps(report, allow_nan=False))
    else:
        print(summary(result))
        wrote = [str(p) for p in (*result.logs, out / "report.json", *figures)]
        if args.rerun:
            wrote.append(args.rerun)
        print("wrote " + ", ".join(wrote))
    if result.ended != "interrupted":
        return 0
    return 143 if stop.signal == signal.SIGTERM else 130  # docs/cli.md, Conventions


def _mavlink_vehicle(args: argparse.Namespace, scenario, realisation, log: Path):
    """The vehicle of ``--connection``, its phone's records from the relay, ``--phone``
    or ``--vehicle-log``."""
    from envs.mavlink_vehicle import MavlinkVehicle, VehicleLinkError
    from envs.phone import FileRecords, UdpRecords

    source = None
    try:
        if args.phone is not None:
            source = UdpRecords(args.phone)
        elif args.vehicle_log is not None:
            source = FileRecords(args.vehicle_log)
    except (OSError, ValueError) as exc:
        raise VehicleLinkError(str(exc)) from None
    try:
        return MavlinkVehicle(scenario, realisation, args.connection, phone=source,
                              log_path=log, seed=args.seed)
    except BaseException:
        if source is not None:
            source.close()
        raise


def _link_problem(args: argparse.Namespace, scenario) -> str | None:
    """Why ``--connection`` / ``--phone`` / ``--vehicle-log`` cannot be used (None: they
    can)."""
    from envs.mavlink_vehicle import pymavlink_url
    from envs.phone import udp_listen_address
    from planner.mavlink import check_connection_url
    from planner.mavlink_wire import InvalidConnectionError

    if args.connection is None:
        what = "--phone" if args.phone is not None else "--vehicle-log"
        return f"{what} needs --connection"
    if args.phone is not None and args.vehicle_log is not None:
        return "--phone and --vehicle-log are two sources of the same records: give one"
    if len(scenario.agents) != 1:
        return (f"{scenario.name} has {len(scenario.agents)} agents: --connection flies one "
                "vehicle")
    try:
        check_connection_url(pymavlink_url(args.connection))
    except InvalidConnectionError as exc:
        return f"--connection: {exc}"
    if args.phone is not None:
        try:
            udp_listen_address(args.phone)
        except ValueError as exc:
            return f"--phone: {exc}"
    if args.vehicle_log is not None and str(args.vehicle_log).endswith(".gz"):
        return "--vehicle-log: a gzip log cannot be read while it is written"
    return None


SUMMARY_COLUMNS = (
    Column("responder", "<", 18), Column("class", "<", 19), Column("heard", ">", 8),
    Column("localised", ">", 11), Column("status", ">", 15), Column("sigma_H", ">", 9),
    Column("err_2D", ">", 8),
)


def summary(result) -> str:
    """A readable report: how the search ended, then one line per responder."""

    def t(v):
        return "-" if v is None else f"{v / 60:.1f} min"

    def m(v):
        return "-" if v is None else f"{v:.2f}"

    rows = [(r["bssid"], r.get("concealment", "-"), t(r.get("detected_at_s")),
             t(r.get("localised_at_s")), r["status"], m(r.get("sigma_h_m")),
             m(r.get("err_h_m"))) for r in result.responders]
    phone = getattr(result, "phone", None)
    return "\n".join([
        f"{result.scenario}, seed {result.seed}: {result.policy} ({result.mode}) ended "
        f"{result.ended} after {result.flight_time_s / 60:.1f} min, "
        f"{result.path_length_m / 1000:.2f} km, {result.replans} re-plans",
        *([phone_line(phone)] if phone is not None else []),
        *text_table(SUMMARY_COLUMNS, rows, indent="  "),
    ])


def phone_line(phone: dict) -> str:
    """The record path's counts (the report's ``phone`` entry) in one line: what a
    network lost or a phone app sent wrong is seen without --json."""
    what = [f"{phone.get('released', 0)} records fed", f"{phone.get('late', 0)} late",
            f"{phone.get('lost', 0)} lost"]
    if rejected := phone.get("rejected_lines"):
        what.append("rejected lines " + ", ".join(f"{k}={v}" for k, v in rejected.items()))
    if n := phone.get("other_sender"):
        what.append(f"{n} datagram{'s' * (n != 1)} of another phone ignored")
    if n := phone.get("clock_jumps"):
        what.append(f"{n} clock jump{'s' * (n != 1)} (a reboot)")
    return f"  phone ({phone.get('source', '?')}): " + ", ".join(what)
