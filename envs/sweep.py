"""Training sweeps (``osa train --sweep FILE [--scheduler ADDRESS]``, docs/rl.md).

A sweep file (TOML or JSON) lists training tasks: its top-level keys are every task's
defaults (over the command line's options), each ``[[task]]`` overrides them::

    env = "osa/Team-v0"
    steps = 4096
    [[task]]
    name = "lr3e-4-s0"
    seed = 0
    [task.ppo]
    learning_rate = 3e-4

Keys (:data:`TASK_KEYS`): ``name`` (the task's folder, unique), ``env``, ``scenario``,
``uavs``, ``steps``, ``seed``, ``algo``, ``envs``, ``vec``, ``eval_every``,
``eval_worlds``, the recipe's (:data:`envs.commands.train.RECIPE_KEYS`:
``curriculum``, ``imitate``, ``dagger``, ``imitation_coef``, ``critic_warmup``,
``reward`` (a table ``NAME = X``), ``reward_preset``, ``init``), and ``ppo`` (a table of
PPO settings over the defaults of ``envs.commands.train``; a ``learning_rate`` is the
start of the linear schedule). A task is read as a command line is
(:func:`envs.commands.train.task_settings`).

Each task is one :func:`envs.rl.train` on a worker (a Dask worker of the scheduler at
``ADDRESS``; without one, here, one after another). A task's outcome depends only on
the task: torch, NumPy and Python seeded from its seed, one torch thread, and one
training at a time per process (:data:`_ONE_TRAINING`; torch's generator is the
process's), so a task on a cluster gives the model it gives here. The worker trains
into a temporary folder and sends the model's files back; they are written here, under
``OUT/NAME``, with ``OUT/sweep.csv``, one row per task (the final validation).
"""

from __future__ import annotations

import csv
import io
import json
import math
import tempfile
import threading
import time
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from envs.commands._outputs import MARKER
from envs.commands.train import PPO_RANGES, RECIPE_KEYS, task_settings
from envs.seeds import TRAIN_SEED_BITS, check_seed

TASK_KEYS = ("name", "env", "scenario", "uavs", "steps", "seed", "algo", "envs", "vec",
             "eval_every", "eval_worlds", "ppo", *RECIPE_KEYS)
SUMMARY_COLUMNS = ("name", "env", "scenario", "uavs", "seed", "steps", "algo", "ppo",
                   "localised", "median_time_s", "mean_return", "recipe")
TABLES = ("ppo", "reward")  # merged key by key: the command line's, the top level's, the task's
SUMMARY_FILE = "sweep.csv"  # OUT/sweep.csv: one row per task
_ONE_TRAINING = threading.Lock()  # torch's random generator is one per process


class SweepError(ValueError):
    """A sweep file that cannot be run (one line)."""


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _check_value(key: str, v, where: str) -> None:
    """The type of a task's value (its range is :func:`task_settings`' to check)."""
    ints = {"uavs": 1, "steps": 1, "envs": 1, "eval_every": 0, "eval_worlds": 1,
            "imitate": 0, "dagger": 0, "critic_warmup": 0}
    if key == "seed":
        try:
            check_seed(v, TRAIN_SEED_BITS)
        except ValueError as exc:
            raise SweepError(f"{where}: seed: {exc}") from None
    elif key in ints:
        if isinstance(v, bool) or not isinstance(v, int) or v < ints[key]:
            raise SweepError(f"{where}: {key} must be an integer >= {ints[key]}, not {v!r}")
    elif key in TABLES:
        if not isinstance(v, dict):
            raise SweepError(f"{where}: {key} must be a table of "
                             f"{'PPO settings' if key == 'ppo' else 'reward weights'}")
        for k, x in v.items():
            if key == "ppo" and k not in PPO_RANGES:
                raise SweepError(f"{where}: unknown PPO setting {k!r}; choose from "
                                 f"{', '.join(PPO_RANGES)}")
            if not _number(x):
                raise SweepError(f"{where}: {key}.{k} must be a number, not {x!r}")
    elif key == "imitation_coef":
        if not _number(v) or v < 0:
            raise SweepError(f"{where}: imitation_coef must be a number >= 0, not {v!r}")
    elif key == "curriculum":
        if not (isinstance(v, str) or (isinstance(v, list) and len(v) == 2
                                       and all(_number(x) for x in v))):
            raise SweepError(f"{where}: curriculum must be \"FROM:TO\" or [FROM, TO], not {v!r}")
    elif key == "vec" and v not in ("subproc", "batched"):
        raise SweepError(f"{where}: vec must be 'subproc' or 'batched', not {v!r}")
    elif not isinstance(v, str) or not v:
        raise SweepError(f"{where}: {key} must be a non-empty string, not {v!r}")


def read_sweep(path: str | Path, defaults: dict) -> list[dict]:
    """The tasks of a sweep file over ``defaults`` (the command line's); SweepError
    with one line for an unreadable file, an unknown key, a bad value, a repeated name."""
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SweepError(f"--sweep {p}: cannot read ({exc})") from None
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise SweepError(f"--sweep {p}: not valid {'JSON' if p.suffix == '.json' else 'TOML'}"
                         f" ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise SweepError(f"--sweep {p}: expected a table with [[task]] entries")
    tasks = data.get("task")
    if not isinstance(tasks, list) or not tasks or not all(isinstance(t, dict) for t in tasks):
        raise SweepError(f"--sweep {p}: no [[task]] entries")
    top = {k: v for k, v in data.items() if k != "task"}
    out, names = [], set()
    for i, t in enumerate([top, *tasks]):
        where = f"--sweep {p}: " + ("top level" if i == 0 else f"task {i}")
        for k, v in t.items():
            if k not in TASK_KEYS:
                raise SweepError(f"{where}: unknown key {k!r}; choose from {', '.join(TASK_KEYS)}")
            _check_value(k, v, where)
    for i, t in enumerate(tasks, 1):
        task = {**defaults, **top, **t}
        for k in TABLES:
            task[k] = {**(defaults.get(k) or {}), **top.get(k, {}), **t.get(k, {})}
        task.setdefault("name", f"task-{i}")
        if "/" in task["name"] or task["name"] in (".", ".."):
            raise SweepError(f"--sweep {p}: task {i}: name {task['name']!r} is not a folder name")
        if task["name"] in (SUMMARY_FILE, MARKER):  # its folder would take the file's place
            raise SweepError(f"--sweep {p}: task {i}: name {task['name']!r} is a file of the "
                             "sweep's output folder")
        if task["name"] in names:
            raise SweepError(f"--sweep {p}: task name {task['name']!r} repeated")
        names.add(task["name"])
        out.append(task)
    return out


def settings_of(task: dict):
    """The :class:`envs.rl.TrainSettings` of a task, read as a command line is
    (:func:`envs.commands.train.task_settings`; no checkpoints, no progress bar)."""
    problem, settings = task_settings(task)
    if problem:
        raise SweepError(f"task {task.get('name')}: {problem.lstrip('-')}")
    return settings


def recipe_of(task: dict) -> str:
    """The recipe options a task sets (not left at their defaults), as JSON."""
    return json.dumps({k: task[k] for k in RECIPE_KEYS if task.get(k) not in (None, 0, {})},
                      sort_keys=True)


@dataclass(frozen=True)
class TaskResult:
    """A finished task: its model folder's files (relative path -> bytes), its summary
    row and the wall time it took (not in the row: the row is deterministic)."""

    name: str
    files: dict[str, bytes]
    row: dict
    wall_s: float


def run_task(task: dict) -> TaskResult:
    """Train one task in a temporary folder (on whichever machine runs it) and return
    its files: the unit of work a Dask worker runs."""
    from envs.rl import train

    settings = settings_of(task)
    with _ONE_TRAINING, tempfile.TemporaryDirectory(prefix="osa-sweep-") as tmp:
        t0 = time.perf_counter()
        summary = train(settings, Path(tmp) / "model")
        wall = time.perf_counter() - t0
        root = Path(tmp) / "model"
        files = {str(f.relative_to(root)): f.read_bytes()
                 for f in sorted(root.rglob("*")) if f.is_file()}
    last = summary.validation[-1] if summary.validation else {}
    row = {"name": task["name"], "env": settings.env_id, "scenario": task.get("scenario"),
           "uavs": settings.env_kwargs.get("uavs"), "seed": settings.seed,
           "steps": summary.steps, "algo": settings.algo,
           "ppo": json.dumps(task.get("ppo", {}), sort_keys=True),
           "localised": last.get("localised"), "median_time_s": last.get("median_time_s"),
           "mean_return": last.get("mean_return"), "recipe": recipe_of(task)}
    return TaskResult(task["name"], files, row, wall)


def write_result(result: TaskResult, out: Path) -> Path:
    """The task's model folder ``OUT/NAME`` (written here, wherever it trained)."""
    folder = out / result.name
    for rel, data in result.files.items():
        f = folder / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(data)
    return folder


def summary_csv(rows: Sequence[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r[k] for k in SUMMARY_COLUMNS})
    return buf.getvalue()


def run_sweep(tasks: Sequence[dict], out: Path, client=None,
              done: Callable[[TaskResult], None] | None = None) -> list[TaskResult]:
    """Every task, on ``client``'s cluster (``Client.map``, results as they finish) or
    here one after another; each result written under ``out`` as it arrives, then
    ``out/sweep.csv`` in the file's task order. Returns the results in that order."""
    results: dict[str, TaskResult] = {}

    def finished(r: TaskResult) -> None:
        write_result(r, out)
        results[r.name] = r
        if done is not None:
            done(r)

    if client is None:
        for t in tasks:
            finished(run_task(t))
    else:
        from distributed import as_completed

        futures = client.map(run_task, list(tasks), key=[f"osa-train-{t['name']}-{i}"
                                                         for i, t in enumerate(tasks)],
                             pure=False)
        with client.as_current():  # our client, not a process-wide default
            for fut in as_completed(futures):
                finished(fut.result())
    ordered = [results[t["name"]] for t in tasks]
    (out / SUMMARY_FILE).write_text(summary_csv([r.row for r in ordered]))
    return ordered
