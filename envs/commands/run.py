"""``osa run``: the main job. Simulate a scenario, replay it in every mode, show the result.

Writes into the output folder: the flight log (``flight.jsonl``), the JSON report
(``report.json``, the ``osa replay --json`` shape), ``trajectory.png`` (the paper's
trajectory figure) and ``convergence.png`` (the paper's convergence figure), and
prints the paper-style table against the simulator's truth.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TextIO

from envs.commands._args import seed_arg
from envs.commands._outputs import add_force_option

DEFAULT_SCENARIO = "three-aps"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="simulate a scenario, replay it in all modes, print the table, write figures",
        description="The main job: simulate SCENARIO (default: three-aps), replay the log "
        "in all six paper modes, print the paper-style table against truth and write the "
        "log, report.json, trajectory.png and convergence.png into --out.",
    )
    p.add_argument("scenario", nargs="?", default=DEFAULT_SCENARIO,
                   help=f"scenario preset or TOML file (default: {DEFAULT_SCENARIO})")
    p.add_argument("--seed", type=seed_arg, default=0, metavar="N",
                   help="random seed, 0 .. 2^63 - 1 (default 0)")
    p.add_argument("-o", "--out", default="osa-run", help="output folder (default ./osa-run)")
    p.add_argument("--mode", default="all",
                   help="modes to replay: all (the paper's six, default), all+robust, or a list")
    p.add_argument("--rerun", metavar="RRD", default=None,
                   help="also write a rerun recording (.rrd) of the flight and estimates")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_force_option(p)
    p.set_defaults(func=run)


class StepProgress:
    """Progress over a few named steps on ``stream``: a tqdm bar on a terminal, one
    plain line per step otherwise (a file or a pipe gets no carriage returns)."""

    def __init__(self, desc: str, total: int, *, enabled: bool = True,
                 stream: TextIO | None = None) -> None:
        self.desc, self.total, self.n = desc, total, 0
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.bar = None
        if enabled and self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="step", file=self.stream,
                            bar_format="{desc}: {n}/{total}{postfix}")

    def step(self, text: str) -> None:
        """Start the next step."""
        if self.n:
            self._advance()
        self.n += 1
        if self.bar is not None:
            self.bar.set_postfix_str(text)
        elif self.enabled:
            print(f"{self.desc}: {self.n}/{self.total} {text}", file=self.stream, flush=True)

    def _advance(self) -> None:
        if self.bar is not None:
            self.bar.update()

    def close(self) -> None:
        """All steps done."""
        if self.n:
            self._advance()
        if self.bar is not None:
            self.bar.set_postfix_str("done")
            self.bar.close()
        elif self.enabled:
            print(f"{self.desc}: done", file=self.stream, flush=True)


def _fail(message: object) -> int:
    print(f"osa run: {message}", file=sys.stderr)
    return 2


def writable_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be written (checked before a long job), or None."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        return f"cannot write {p}: is a directory"
    if not parent.is_dir():
        return f"cannot write {p}: no such directory {parent}"
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        return f"cannot write {p}: permission denied"
    return None


def run(args: argparse.Namespace) -> int:
    import sim
    from envs.plots import plot_convergence, plot_trajectory
    from estimator.replay import ReplayOptions, format_table, parse_modes, replay_logs

    # everything a user can get wrong is checked before the output folder exists
    try:
        modes = parse_modes(args.mode)
    except ValueError as exc:
        return _fail(exc)
    try:
        scenario = sim.load_scenario(args.scenario)
    except (KeyError, ValueError, OSError) as exc:
        return _fail(exc.args[0] if exc.args else exc)
    if scenario.flight is None:
        return _fail(f"{args.scenario} is a search (no [flight]): fly it with osa search")
    from envs.commands._outputs import (
        OutputRefusedError,
        claim_output_dir,
        claim_output_file,
        json_text,
        written_whole,
    )

    inputs = [args.scenario] if Path(args.scenario).is_file() else []  # a preset: none
    if args.rerun and (problem := writable_file_problem(args.rerun)):
        return _fail(problem)  # its folder must exist: a typo creates no folder tree
    try:  # the one output rule (docs/cli.md "Outputs"), before anything is simulated
        if args.rerun:
            claim_output_file(args.rerun, force=args.force, inputs=inputs)
        out = claim_output_dir(args.out, command="run", force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(exc)
    log_path = out / "flight.jsonl"
    steps = 3 + bool(args.rerun)
    progress = StepProgress("osa run", steps, enabled=not args.no_progress)
    progress.step(f"simulating {args.scenario} (seed {args.seed})")
    from sim.simulate import write_log
    from sim.vehicle import FlightError

    try:
        result = sim.simulate(scenario, args.seed)
    except FlightError as exc:  # the scenario's path cannot be flown (below the ground...)
        progress.close()
        return _fail(f"{args.scenario}: {exc}")
    with written_whole(log_path) as tmp:  # an interrupted write keeps the previous log
        write_log(result, tmp)
    progress.step(f"replaying {len(modes)} modes")
    report = replay_logs([log_path], ReplayOptions(modes=modes))
    with written_whole(out / "report.json") as tmp:
        tmp.write_text(json_text(report.to_json(), indent=1))
    progress.step("drawing figures")
    title = f"{args.scenario}, seed {args.seed}"
    world = sim.realise(scenario, args.seed).world  # the ground under the map
    traj = plot_trajectory(report, [log_path], out / "trajectory.png", title=title,
                           terrain=world.terrain, terrain_frame=world.frame)
    conv = plot_convergence(report, out / "convergence.png")
    if args.rerun:
        from envs.viz import record_replay

        progress.step("writing rerun recording")
        with written_whole(args.rerun) as tmp:  # never half a recording over the last
            record_replay(report, [log_path], tmp)
    progress.close()
    print(f"scenario {args.scenario}, seed {args.seed}\n")
    print(format_table(report))
    print(f"\nwrote {log_path}, {out / 'report.json'}, {traj}, {conv}"
          + (f", {args.rerun}" if args.rerun else ""))
    return 0
