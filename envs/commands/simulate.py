"""``osa simulate SCENARIO -o LOG [--seed N]`` and ``osa simulate --list`` (docs/cli.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from envs.commands._args import seed_arg
from envs.commands._outputs import add_force_option


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="write a simulated flight log for a scenario preset",
        description=(
            "Simulate a flight over a scenario (a preset name or a TOML file) and write its "
            "log (.jsonl or .jsonl.gz) with truth records. The same scenario and seed give "
            "a byte-identical file."
        ),
    )
    p.add_argument("scenario", nargs="?", metavar="SCENARIO", help="preset name or .toml path")
    p.add_argument("-o", "--output", "--out", metavar="LOG",
                   help="log file to write (.jsonl, .jsonl.gz)")
    p.add_argument("--seed", type=seed_arg, default=0, metavar="N",
                   help="random seed, 0 .. 2^63 - 1 (default 0)")
    p.add_argument("--list", action="store_true", help="list the scenario presets and exit")
    add_force_option(p)
    p.set_defaults(func=run)
    return p


def _fail(message: str) -> int:
    print(f"osa simulate: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from envs.commands._outputs import OutputRefusedError, claim_output_file, written_whole
    from sim.scenario import ScenarioError, list_scenarios, load_scenario, scenario_description

    if args.list:
        names = list_scenarios()
        width = max((len(n) for n in names), default=0) + 2  # `name  description`
        for name in names:
            print(f"{name:<{width}}{scenario_description(name)}")
        return 0
    if not args.scenario:
        return _fail("a SCENARIO is required (see osa simulate --list)")
    if not args.output:
        return _fail("-o LOG is required")
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        return _fail(str(exc))
    if scenario.flight is None:
        return _fail(f"{args.scenario} is a search (no [flight]): fly it with osa search")
    if len(scenario.agents) > 1:  # one log: said, not silently one agent of several
        print(f"osa simulate: {scenario.name} has {len(scenario.agents)} agents; the first, "
              f"{scenario.agents[0].name}, flies the flight (one log)", file=sys.stderr)
    inputs = [args.scenario] if Path(args.scenario).is_file() else []  # a preset: none
    try:  # before the simulation: a refused output costs nothing
        out = claim_output_file(args.output, force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(str(exc))

    from sim.simulate import run_scenario, write_log
    from sim.vehicle import FlightError

    try:
        result = run_scenario(scenario, args.seed)
    except FlightError as exc:  # the scenario's path cannot be flown (below the ground...)
        return _fail(f"{args.scenario}: {exc}")
    try:
        with written_whole(out) as tmp:
            write_log(result, tmp)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        return _fail(f"cannot write {args.output}: {reason}")
    print(f"{result.summary()} -> {out}")
    return 0
