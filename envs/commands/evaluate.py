"""``osa evaluate SCENARIO --policies P[,P...] --seeds N``: a Monte Carlo of search
policies (docs/cli.md, docs/evaluate.md).

Every policy flies the same seeds (the same worlds), serially, in local processes or on
a Dask scheduler; one row per policy, seed and responder goes to ``-o FILE`` (``.csv``
or ``.parquet``), a summary per policy, the timed search challenge and the paired
comparisons to stdout (``--json``: the rows instead; ``--summary-json FILE``: those
tables as JSON), and the figures (time to localise, error and sigma against flight time, example
trajectories) into ``--figures DIR``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

from envs.commands._args import non_negative_int, positive_float, positive_int, seed_arg
from envs.commands._outputs import add_force_option
from envs.seeds import MAX_SEED, SPLITS

DEFAULT_OUT = "osa-evaluate/rows.csv"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="Monte Carlo of search policies over seeds (local processes or Dask)",
        description="Fly every policy of --policies on the same N seeds (worlds) of the "
        "search SCENARIO; write one row per policy, seed and responder to -o FILE (.csv or "
        ".parquet), print a summary per policy and draw figures.",
    )
    p.add_argument("scenario", metavar="SCENARIO",
                   help="a search preset (osa simulate --list), a suite preset "
                   "suite/r{1,5,10}-{c,h}{0,30,50}-{sa,rtk}-u{1,2,4}, or a .toml with a [search] "
                   "table")
    p.add_argument("--policies", required=True, metavar="P[,P...]",
                   help="comma-separated: lawnmower, expanding-square, adaptive, random, "
                   "random:waypoint, ppo:PATH, team:POLICY")
    p.add_argument("--seeds", required=True, type=positive_int, metavar="N",
                   help="number of seeds (worlds)")
    p.add_argument("--first-seed", type=seed_arg, default=None, metavar="K",
                   help="first seed (default 0, or the start of --split)")
    p.add_argument("--split", choices=tuple(SPLITS), default=None,
                   help="take the seeds from this documented seed split (envs/seeds.py); "
                   "compare policies on test")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=positive_int, default=None, metavar="N",
                       help="local processes (default: the CPUs available; 1: in this process)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run on an existing Dask scheduler, e.g. tcp://127.0.0.1:8786")
    p.add_argument("--connect-timeout", type=positive_float, default=10.0, metavar="S",
                   help="seconds to wait for the scheduler (default 10)")
    p.add_argument("--task-timeout", type=positive_float, default=3600.0, metavar="S",
                   help="stop if no task finishes for this many seconds (default 3600)")
    p.add_argument("--task-size", type=positive_int, default=None, metavar="N",
                   help="episodes per task (default: about four tasks per worker, at most 16)")
    p.add_argument("-o", "--out", default=DEFAULT_OUT, metavar="FILE",
                   help=f"rows as .csv or .parquet (default {DEFAULT_OUT})")
    p.add_argument("--figures", default=None, metavar="DIR",
                   help="folder for the figures (default: the folder of -o FILE)")
    p.add_argument("--examples", type=non_negative_int, default=3, metavar="K",
                   help="example seeds drawn in trajectories.png (default 3)")
    p.add_argument("--no-figures", action="store_true", help="do not draw the figures")
    p.add_argument("--mode", default=None, metavar="M",
                   help="estimator mode the loop runs (default: the project's recommended mode)")
    p.add_argument("--decision-period", type=float, default=5.0, metavar="S",
                   help="seconds of flight between two decisions of the policy (default 5)")
    p.add_argument("--json", action="store_true",
                   help="print the rows as a JSON array on stdout instead of the summary")
    p.add_argument("--summary-json", default=None, metavar="FILE",
                   help="also write the summary, the timed challenge and the paired "
                   "comparisons as one JSON object to FILE")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run of the same command: the episodes kept "
                   "in FILE.partial.jsonl are not flown again")
    add_force_option(p)
    p.set_defaults(func=run)


def _fail(message: object) -> int:
    print(f"osa evaluate: {message}", file=sys.stderr)
    return 2


def seeds_of(n: int, first: int | None, split: str | None) -> list[int]:
    """The seeds to fly (raises ValueError with a one-line reason)."""
    if split is None:
        k = 0 if first is None else first
        if k + n - 1 > MAX_SEED:
            raise ValueError(f"seeds {k}..{k + n - 1} pass the largest seed {MAX_SEED}")
        return list(range(k, k + n))
    lo, hi = SPLITS[split]
    k = lo if first is None else first
    if not (lo <= k and k + n <= hi):
        raise ValueError(f"seeds {k}..{k + n - 1} are not all in the {split} split "
                         f"({lo}..{hi - 1})")
    return list(range(k, k + n))


def parse_policies(text: str) -> list[str]:
    names = [p.strip() for p in text.split(",")]
    if not text.strip() or any(not p for p in names):
        raise ValueError(f"--policies: empty policy name in {text!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"--policies: a policy is named twice in {text!r}")
    return names


def _check_policy(spec: str, scenario) -> str | None:
    from envs.policies import load_policy

    try:
        load_policy(spec, scenario)
    except ValueError as exc:
        return str(exc)
    except ModuleNotFoundError as exc:
        return (f"{spec}: trained policies need {exc.name}, which is not available here "
                "(install the 'rl' extra)")
    except (OSError, ImportError) as exc:
        return f"{spec}: cannot load: {exc}"
    return None


def connect(address: str, timeout_s: float):
    """A Dask client of the scheduler at ``address`` (ValueError if unreachable)."""
    if "://" not in address:  # a malformed address is said whether Dask is installed or not
        raise ValueError(f"--scheduler: {address!r} is not an address like "
                         "tcp://127.0.0.1:8786")
    try:
        from distributed import Client
    except ModuleNotFoundError:
        raise ValueError("--scheduler needs Dask distributed: pip install "
                         "'osa-testbed[dist]'") from None
    import logging

    # Dask logs a lost scheduler with its tracebacks on stderr; the command says it in
    # one line (envs.evaluate turns it into an EpisodeError)
    for name in ("distributed", "distributed.client", "distributed.comm"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        return Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"cannot reach the Dask scheduler at {address} within "
                         f"{timeout_s:g} s ({reason})") from None
    except ValueError as exc:
        raise ValueError(f"--scheduler: {exc}") from None


def claim_outputs(args: argparse.Namespace, out: Path, fig_dir: Path, inputs: list[str]) -> None:
    """Check every file the run will write, before any episode (raises ValueError with
    one line): the rows (.csv or .parquet), the figures, the journal of a run to resume
    or to replace (the one output rule: an existing file needs --force)."""
    from envs.commands._outputs import claim_output_file
    from envs.evaluate import journal_path
    from envs.evaluate_plots import FIGURES

    if out.suffix.lower() not in (".csv", ".parquet"):
        raise ValueError(f"-o {out}: write .csv or .parquet, not "
                         f"{out.suffix or 'a name without a suffix'}")
    if out.suffix.lower() == ".parquet":
        try:
            import pyarrow.parquet  # noqa: F401
        except ModuleNotFoundError:
            raise ValueError(f"-o {out}: Parquet needs pyarrow (pip install pyarrow), or "
                             "write .csv") from None
    journal = journal_path(out)
    if args.resume and not journal.is_file():
        raise ValueError(f"--resume: nothing to resume ({journal} does not exist)")
    if journal.exists() and not args.resume:
        if not args.force:
            raise ValueError(f"{journal} holds the episodes of an interrupted run: continue "
                             "it with --resume, or start again with --force")
        journal.unlink()
    claim_output_file(out, force=args.force, inputs=inputs)
    if args.summary_json is not None:
        if Path(args.summary_json).resolve() == out.resolve():
            raise ValueError("--summary-json and -o name the same file")
        if Path(args.summary_json).resolve() == journal.resolve():
            raise ValueError(f"--summary-json names the journal of -o ({journal}), which is "
                             "removed at the end")
        claim_output_file(Path(args.summary_json), force=args.force, inputs=inputs)
    if not args.no_figures:
        for name in FIGURES:
            claim_output_file(fig_dir / name, force=args.force, inputs=inputs)


def run(args: argparse.Namespace) -> int:
    from envs.cli import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated
    from envs.commands._progress import QuantityProgress
    from envs.evaluate import (
        EpisodeError,
        EpisodeJournal,
        EvaluationTimeoutError,
        JournalError,
        evaluate,
        journal_path,
        local_workers,
    )
    from envs.loop import DEFAULT_MODE, LoopConfig
    from sim.scenario import ScenarioError, search_scenario

    # every mistake is reported before any work starts
    try:
        scenario = search_scenario(args.scenario)
    except ScenarioError as exc:
        return _fail(exc)
    try:
        policies = parse_policies(args.policies)
        seeds = seeds_of(args.seeds, args.first_seed, args.split)
    except ValueError as exc:
        return _fail(exc)
    for spec in policies:
        if problem := _check_policy(spec, scenario):
            return _fail(f"--policies: {problem}")
    if not (math.isfinite(args.decision_period) and 0.5 <= args.decision_period <= 600):
        return _fail(f"--decision-period must be in [0.5, 600] s, got {args.decision_period}")
    try:
        config = LoopConfig(mode=args.mode or DEFAULT_MODE,
                            decision_period_s=args.decision_period)
    except ValueError as exc:
        return _fail(f"--mode: {exc}")
    out = Path(args.out)
    fig_dir = Path(args.figures) if args.figures else out.parent
    inputs = [args.scenario] if Path(args.scenario).is_file() else []  # a preset: none
    try:
        claim_outputs(args, out, fig_dir, inputs)
    except ValueError as exc:  # OutputRefusedError too
        return _fail(exc)
    train = SPLITS["train"]
    if any("ppo:" in p for p in policies) and seeds[0] < train[1]:  # team:ppo: too
        print("osa evaluate: note: seeds below 1000000 are training seeds (envs/seeds.py); "
              "score trained policies with --split test", file=sys.stderr)

    client = None
    if args.scheduler is not None:
        try:
            client = connect(args.scheduler, args.connect_timeout)
        except ValueError as exc:
            return _fail(exc)
    workers = args.workers if args.workers is not None else local_workers()
    n = len(policies) * len(seeds)
    key = {"scenario": scenario.name, "source": args.scenario,
           "scenario_sha256": _file_sha256(args.scenario), "policies": policies,
           "seeds": [seeds[0], seeds[-1]], "mode": config.mode,
           "decision_period_s": config.decision_period_s, "examples": args.examples}
    if models := _model_digests(policies):  # a model trained on meanwhile is another run
        key["models"] = models
    try:
        journal = EpisodeJournal(journal_path(out), key, resume=args.resume)
    except (JournalError, OSError) as exc:
        if client is not None:
            client.close(timeout=args.connect_timeout)
        return _fail(exc)
    bar = QuantityProgress("osa evaluate", n, "episodes", enabled=not args.no_progress,
                           every=max(1.0, n / 10))
    kept = f"kept in {journal.path}; run the same command with --resume to finish"
    try:
        bar.update(len(journal.episodes), "resumed" if journal.episodes else "")
        ev = evaluate(scenario, policies, seeds, config=config, workers=workers,
                      client=client, task_size=args.task_size,
                      example_seeds=seeds[:args.examples], task_timeout_s=args.task_timeout,
                      progress=lambda k, note: bar.update(k, note),
                      done=list(journal.episodes), on_episode=journal.append)
    except (EpisodeError, EvaluationTimeoutError, JournalError) as exc:
        bar.close("failed", line=False)  # the reason is the one line
        journal.close()
        print(f"osa evaluate: {exc} ({len(journal.episodes)} of {n} episodes {kept})",
              file=sys.stderr)
        return 1
    except (KeyboardInterrupt, Terminated) as exc:
        bar.close("interrupted", line=False)
        journal.close()
        print(f"osa evaluate: interrupted: {len(journal.episodes)} of {n} episodes {kept}",
              file=sys.stderr)
        return EXIT_INTERRUPTED if isinstance(exc, KeyboardInterrupt) else EXIT_TERMINATED
    finally:
        if client is not None:
            client.close(timeout=args.connect_timeout)
    bar.close()
    from sim import realise

    # the ground under the example worlds (the same terrain for every seed)
    try:
        status = _report(args, ev, out, fig_dir, realise(scenario, seeds[0]).world.terrain)
    except _WriteError as exc:  # a full disk, a folder made read-only meanwhile
        journal.close()
        again = "--resume --force" if out.exists() else "--resume"
        print(f"osa evaluate: {exc} (all {n} episodes kept in {journal.path}; run the same "
              f"command with {again} to write them)", file=sys.stderr)
        return 1
    journal.remove()  # every row is in FILE now
    return status


class _WriteError(Exception):
    """A result file that could not be written (one line: the file and why)."""


@contextlib.contextmanager
def _writing(path: Path):
    """Say which result ``path`` could not be written, and why."""
    try:
        yield
    except OSError as exc:
        raise _WriteError(f"cannot write {path}: {exc.strerror or exc}") from exc


def _model_digests(policies: list[str]) -> dict[str, str]:
    """Per trained policy (``ppo:PATH``, ``team:ppo:PATH``): one digest of its model
    folder's files, so that a journal resumes only with the same models."""
    import hashlib

    from envs.gym.trained import META_FILE, MODEL_FILE, STATS_FILE, model_dir

    out = {}
    for spec in policies:
        _, ppo, path = spec.partition("ppo:")
        if not ppo:
            continue
        h = hashlib.sha256()
        for name in (MODEL_FILE, STATS_FILE, META_FILE):
            h.update((_file_sha256(str(model_dir(path) / name)) or "-").encode())
        out[spec] = h.hexdigest()
    return out


def _file_sha256(path: str) -> str | None:
    """The scenario file's digest (a journal resumes only the same scenario), None for
    a preset name."""
    import hashlib

    p = Path(path)
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None


def _report(args: argparse.Namespace, ev, out: Path, fig_dir: Path, terrain=None) -> int:
    from envs.commands._outputs import json_text, written_whole
    from envs.evaluate import (
        compare_pairs,
        format_challenge,
        format_paired,
        format_summary,
        summarise,
        summary_json,
        write_rows,
    )

    rows = ev.rows
    with _writing(out), written_whole(out) as tmp:
        write_rows(rows, tmp)
    if args.summary_json is not None:
        with _writing(Path(args.summary_json)), written_whole(Path(args.summary_json)) as tmp:
            Path(tmp).write_text(json_text(summary_json(rows, ev.policies, ev.budget_s)) + "\n",
                                 encoding="utf-8")
    figures: list[Path] = []
    if not args.no_figures:
        from envs.evaluate_plots import plot_evaluation

        with _writing(fig_dir):
            figures = plot_evaluation(ev, fig_dir, terrain=terrain)
    if args.json:
        print(json_text(rows))
        return 0
    s = ev.seeds
    print(f"{ev.scenario}: {len(ev.policies)} polic{'ies' if len(ev.policies) > 1 else 'y'} "
          f"x {len(s)} seeds ({s[0]}..{s[-1]}), budget {ev.budget_s / 60:.1f} min; times in "
          "min (>= : censored at the budget), errors in m")
    summaries = summarise(rows, ev.policies, ev.budget_s)
    print(format_summary(summaries))
    print("\nTimed search challenge (t_all: every responder judged localised; err@T: the "
          "median error of the estimate held at T; <=2 m, <=5 m: final estimates)")
    print(format_challenge(summaries))
    if len(ev.policies) > 1:
        print("\nPaired on the same seeds (A wins: A lower; two-sided p)")
        print(format_paired(compare_pairs(rows, ev.policies, ev.budget_s)))
    extra = [Path(args.summary_json)] if args.summary_json is not None else []
    print("wrote " + ", ".join(str(p) for p in (out, *extra, *figures)))
    return 0
