"""``osa run``: the main job. Simulate a scenario, replay it in every mode, show the result.

Writes into the output folder: the flight log (``flight.jsonl``), the JSON report
(``report.json``, the ``osa replay --json`` shape), ``trajectory.png`` (the paper's
trajectory figure) and ``convergence.png`` (the paper's convergence figure), and
prints the paper-style table against the simulator's truth.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

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
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--out", default="osa-run", help="output folder (default ./osa-run)")
    p.add_argument("--mode", default="all",
                   help="modes to replay: all (the paper's six, default), all+robust, or a list")
    p.add_argument("--rerun", metavar="RRD", default=None,
                   help="also write a rerun recording (.rrd) of the flight and estimates")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    import sim
    from envs.plots import plot_convergence, plot_trajectory
    from estimator.replay import ReplayOptions, format_table, parse_modes, replay_logs

    mode_text = args.mode
    try:
        if mode_text == "all+robust":
            modes = (*parse_modes("all"), "robust")
        else:
            modes = parse_modes(mode_text)
    except ValueError as exc:
        print(f"osa run: {exc}", file=sys.stderr)
        return 2
    try:
        scenario = sim.load_scenario(args.scenario)
    except (KeyError, ValueError, OSError) as exc:
        msg = exc.args[0] if exc.args else exc
        print(f"osa run: {msg}", file=sys.stderr)
        return 2
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"osa run: cannot create {out}: {exc.strerror}", file=sys.stderr)
        return 2
    log_path = out / "flight.jsonl"
    steps = ["simulate", "replay", "figures"] + (["rerun"] if args.rerun else [])
    bar = tqdm(total=len(steps), desc="osa run", unit="step", disable=args.no_progress,
               file=sys.stderr, bar_format="{desc}: {n}/{total} {postfix}")
    bar.set_postfix_str(f"simulating {args.scenario} (seed {args.seed})")
    sim.simulate(scenario, args.seed, log_path)
    bar.update()
    bar.set_postfix_str(f"replaying {len(modes)} modes")
    report = replay_logs([log_path], ReplayOptions(modes=modes))
    (out / "report.json").write_text(json.dumps(report.to_json(), indent=1, allow_nan=False))
    bar.update()
    bar.set_postfix_str("drawing figures")
    title = f"{args.scenario}, seed {args.seed}"
    traj = plot_trajectory(report, [log_path], out / "trajectory.png", title=title)
    conv = plot_convergence(report, out / "convergence.png")
    bar.update()
    if args.rerun:
        from envs.viz import record_replay

        bar.set_postfix_str("writing rerun recording")
        record_replay(report, [log_path], args.rerun)
        bar.update()
    bar.set_postfix_str("done")
    bar.close()
    print(f"scenario {args.scenario}, seed {args.seed}\n")
    print(format_table(report))
    print(f"\nwrote {log_path}, {out / 'report.json'}, {traj}, {conv}"
          + (f", {args.rerun}" if args.rerun else ""))
    return 0
