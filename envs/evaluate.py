"""Monte Carlo evaluation of search policies (``osa evaluate``, docs/evaluate.md).

Every policy flies every seed of one search scenario: the world of (scenario, seed) is
the same whatever flies it (common random numbers), and
:func:`envs.loop.run_search` is deterministic per (scenario, policy, seed), so the
rows depend on nothing but those three. Episodes are grouped into tasks of several
episodes each (scheduler overhead stays small next to the work) and run

* serially in this process (``workers=1``),
* in ``workers`` local processes (``spawn`` start method: CasADi, OpenBLAS and the
  threads they start do not survive ``fork``), or
* on any pre-configured ``dask.distributed.Client`` (a laptop's ``LocalCluster`` or
  a cluster's scheduler), through ``Client.map``.

Results are put back in a fixed order (policy as given, then seed, then the
scenario's responders), so the same seeds give the same rows wherever they ran.
Every wait is bounded: if no task finishes within ``task_timeout_s`` the evaluation
stops with :class:`EvaluationTimeoutError`.

Rows (one per policy, seed and responder) carry the ``osa search`` report's fields
(truth errors included: evaluation only) plus a few of our own; see :data:`COLUMNS`.

Nothing finished is lost: each episode, as it finishes, is appended to a journal
(:class:`EpisodeJournal`, JSON Lines beside the rows file, flushed and synced), so an
interrupted run (Ctrl-C, SIGTERM, a failed episode, a lost machine) keeps its finished
episodes and ``evaluate(..., done=journal.episodes)`` runs only the others: the rows of
an interrupted and resumed run equal those of an uninterrupted one.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import dataclasses
import json
import math
import multiprocessing
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from envs.loop import LoopConfig, SearchResult, run_search
from envs.metrics import (
    CHALLENGE_TIMES_S,
    SUCCESS_RADII_M,
    all_localised_at_s,
    episode_error_m,
    error_at_flight_s,
    median,
    quantile,
    time_within_s,
    within,
)
from envs.policies import load_policy
from envs.seeds import split_of
from estimator.tables import Column, text_table
from sim.scenario import Scenario

# (name, type) of every column, in order. The first eleven are the spec's
# (shared/spec/cli.md, `osa evaluate`); the rest are added fields. None (an empty CSV
# cell, a Parquet null) where the `osa search` report has no such field.
COLUMNS: tuple[tuple[str, type], ...] = (
    ("policy", str),
    ("seed", int),
    ("bssid", str),
    ("ended", str),  # "localised" (the policy's own judgement) or "budget"
    ("flight_time_s", float),
    ("detected_at_s", float),  # first heard (None: never)
    ("localised_at_s", float),  # judged localised by the policy (None: never)
    ("status", str),  # the estimator's status at the end
    ("sigma_h_m", float),  # the estimator's horizontal sigma at the end
    ("err_h_m", float),  # truth: horizontal error of the final estimate
    ("err_3d_m", float),  # truth: 3-D error of the final estimate
    # added fields
    ("scenario", str),
    ("split", str),  # train / validation / test (envs/seeds.py), None outside them
    ("mode", str),  # the estimator mode the loop ran
    ("concealment", str),  # the responder's concealment class (truth)
    ("r95_h_m", float),  # the estimator's 95 % horizontal radius at the end
    ("time_within_1m_s", float),  # truth: from when the error stays <= 1 m (None: never)
    ("budget_s", float),
    ("path_length_m", float),
    ("replans", int),
    # the timed search challenge (envs/metrics.py; truth: evaluation only)
    ("err_h_3min_m", float),  # horizontal error of the estimate held at 3 min (None: none)
    ("err_h_10min_m", float),  # ... at 10 min (a search that ended keeps its estimate)
    ("within_2m", int),  # 1 if the final estimate is within 2 m horizontally, else 0
    ("within_5m", int),  # ... within 5 m
    ("all_localised_at_s", float),  # per episode: the last responder judged localised
    # (None: not every responder was by the end; censored at the budget)
)
SPEC_COLUMNS = tuple(name for name, _ in COLUMNS[:11])
COLUMN_TYPES = dict(COLUMNS)

DEFAULT_TASK_TIMEOUT_S = 3600.0  # no task finished for this long: stop (bounded waits)
MAX_TASK_EPISODES = 16  # the largest automatic task (coarser tasks balance worse)


class EvaluationTimeoutError(TimeoutError):
    """No task finished within the allowed time."""


class EpisodeError(RuntimeError):
    """An episode raised; the message names the policy and the seed."""


@dataclass(frozen=True)
class EpisodeResult:
    """One episode's rows and what the figures need (small: it crosses processes)."""

    policy: str
    seed: int
    rows: list[dict]
    # per responder: (k, 4) float array of t_s, err_h_m, sigma_h_m, r95_h_m (NaN: none)
    series: dict[str, np.ndarray] = field(repr=False)
    # only for the example seeds (trajectory figure): per agent (k, 2) east, north
    track_enu_m: list[np.ndarray] | None = field(default=None, repr=False)
    truth_enu_m: dict[str, tuple[float, float, float]] = field(default_factory=dict, repr=False)
    estimates_enu_m: dict[str, tuple[float, float, float]] = field(default_factory=dict,
                                                                   repr=False)


@dataclass
class Evaluation:
    """The outcome of :func:`evaluate`: rows in their fixed order, and the episodes."""

    scenario: str
    policies: tuple[str, ...]
    seeds: tuple[int, ...]
    budget_s: float
    area_enu_m: tuple
    episodes: list[EpisodeResult]
    example_seeds: tuple[int, ...] = ()
    decision_period_s: float = 5.0

    @property
    def rows(self) -> list[dict]:
        return [r for e in self.episodes for r in e.rows]


# ---------------------------------------------------------------------- one episode
def _rounded(v: float | None) -> float | None:
    return None if v is None else round(float(v), 3)


def rows_of(result: SearchResult, policy: str, seed: int, budget_s: float) -> list[dict]:
    """The table rows of one search (one per responder, the scenario's order)."""
    rows = []
    t3, t10 = CHALLENGE_TIMES_S
    r2, r5 = SUCCESS_RADII_M
    t_all = all_localised_at_s([r.get("localised_at_s") for r in result.responders])
    for r in result.responders:
        b = r["bssid"]
        series = result.series.get(b, [])
        err = r.get("err_h_m")
        row = {
            "policy": policy,
            "seed": int(seed),
            "bssid": b,
            "ended": result.ended,
            "flight_time_s": round(float(result.flight_time_s), 3),
            "detected_at_s": r.get("detected_at_s"),
            "localised_at_s": r.get("localised_at_s"),
            "status": r["status"],
            "sigma_h_m": r.get("sigma_h_m"),
            "err_h_m": r.get("err_h_m"),
            "err_3d_m": r.get("err_3d_m"),
            "scenario": result.scenario,
            "split": split_of(int(seed)),
            "mode": result.mode,
            "concealment": r.get("concealment"),
            "r95_h_m": r.get("r95_h_m"),
            "time_within_1m_s": _rounded(time_within_s(result.series.get(b, []), 1.0)),
            "budget_s": float(budget_s),
            "path_length_m": round(float(result.path_length_m), 2),
            "replans": int(result.replans),
            "err_h_3min_m": error_at_flight_s(series, t3, result.flight_time_s, err),
            "err_h_10min_m": error_at_flight_s(series, t10, result.flight_time_s, err),
            "within_2m": within(err, r2),
            "within_5m": within(err, r5),
            "all_localised_at_s": t_all,
        }
        rows.append({k: _typed(k, v) for k, v in row.items()})
    return rows


def _typed(name: str, v: Any) -> Any:
    if v is None:
        return None
    t = COLUMN_TYPES[name]
    return t(v)


def _series_array(points) -> np.ndarray:
    def f(v):
        return math.nan if v is None else float(v)

    return np.array([(p.t_s, f(p.err_h_m), f(p.sigma_h_m), f(p.r95_h_m)) for p in points],
                    dtype=float).reshape(-1, 4)


def run_episode(scenario: Scenario, policy: str, seed: int, config: LoopConfig = LoopConfig(),
                *, keep_track: bool = False) -> EpisodeResult:
    """Fly one (policy, seed) with a freshly loaded policy."""
    try:
        result = run_search(scenario, load_policy(policy, scenario), seed, config=config)
    except Exception as exc:
        raise EpisodeError(f"policy {policy}, seed {seed}: {type(exc).__name__}: {exc}") from exc
    track = None
    if keep_track:
        track = [np.asarray(t, dtype=float).reshape(-1, 4)[:, 1:3] for t in result.nav_track]
    return EpisodeResult(
        policy=policy, seed=int(seed),
        rows=rows_of(result, policy, seed, scenario.search.budget_s),
        series={b: _series_array(pts) for b, pts in result.series.items()},
        track_enu_m=track,
        truth_enu_m=dict(result.truth_enu_m) if keep_track else {},
        estimates_enu_m=dict(result.estimates_enu_m) if keep_track else {},
    )


def run_episodes(episodes: Sequence[tuple[str, int]], scenario: Scenario,
                 config: LoopConfig = LoopConfig(),
                 track_seeds: frozenset[int] = frozenset()) -> list[EpisodeResult]:
    """One task: several episodes, one after another (the unit sent to a worker)."""
    return [run_episode(scenario, p, s, config, keep_track=s in track_seeds)
            for p, s in episodes]


# ---------------------------------------------------------------------- many
def episode_list(policies: Sequence[str], seeds: Sequence[int]) -> list[tuple[str, int]]:
    """Every (policy, seed), seed-major so that a task mixes fast and slow policies."""
    return [(p, int(s)) for s in seeds for p in policies]


def chunks(items: Sequence, size: int) -> list[list]:
    return [list(items[i:i + size]) for i in range(0, len(items), size)]


def auto_task_size(n_episodes: int, slots: int) -> int:
    """Episodes per task: about four tasks per worker slot (load balance), at most
    :data:`MAX_TASK_EPISODES` (progress and balance), at least one."""
    return max(1, min(MAX_TASK_EPISODES, math.ceil(n_episodes / (4 * max(1, slots)))))


def local_workers() -> int:
    """The CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def dask_slots(client) -> int:
    """Worker threads a Dask client's cluster offers (1 if it reports none yet)."""
    info = client.scheduler_info()
    return max(1, sum(int(w.get("nthreads", 1)) for w in info.get("workers", {}).values()))


def _is_dask(client) -> bool:
    return type(client).__module__.startswith("distributed")


def _wait_first(pending: set, timeout_s: float, client) -> tuple[set, set]:
    """Wait (at most ``timeout_s``) until one of ``pending`` is done."""
    if client is not None:
        from distributed import wait

        try:
            with client.as_current():  # our client, not a process-wide default
                done, not_done = wait(list(pending), timeout=timeout_s,
                                      return_when="FIRST_COMPLETED")
        except TimeoutError:
            return set(), pending
        except (cf.CancelledError, OSError) as exc:
            raise _cluster_lost(exc) from exc
        return set(done), set(not_done)
    done, not_done = cf.wait(pending, timeout=timeout_s, return_when=cf.FIRST_COMPLETED)
    return set(done), set(not_done)


# what Dask's nanny sets for its workers: one BLAS/OpenMP thread per worker process
# (N processes with a spinning OpenBLAS pool each oversubscribe the cores)
SINGLE_THREADED = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _single_threaded_children():
    """Spawned children start with one BLAS thread unless the user chose otherwise."""
    added = [k for k in SINGLE_THREADED if k not in os.environ]
    for k in added:
        os.environ[k] = "1"
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _stop_pool(pool: cf.ProcessPoolExecutor) -> None:
    """Stop a local pool now (after a timeout or an error): its workers are ours."""
    terminate = getattr(pool, "terminate_workers", None)  # Python >= 3.14
    if terminate is not None:
        terminate()
        return
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=10)


def _cluster_lost(exc: BaseException) -> EpisodeError:
    """What Dask raises when the scheduler goes away (its tasks cancelled, ``Futures
    cancelled ... scheduler-connection-lost``; a closed connection), as one line."""
    reason = " ".join(str(exc).split())[:160]
    return EpisodeError(f"the Dask scheduler was lost or cancelled the tasks "
                        f"({type(exc).__name__}{': ' + reason if reason else ''})")


def _result(future, timeout_s: float, dask: bool) -> list[EpisodeResult]:
    """A finished task's episodes; a worker that died is an :class:`EpisodeError`."""
    try:
        return future.result(timeout=timeout_s) if dask else future.result()
    except cf.BrokenExecutor as exc:  # BrokenProcessPool
        raise EpisodeError(f"a local worker process died ({exc})") from exc
    except cf.CancelledError as exc:
        if dask:
            raise _cluster_lost(exc) from exc
        raise
    except Exception as exc:
        if type(exc).__name__ == "KilledWorker":  # distributed.KilledWorker
            raise EpisodeError(f"Dask workers died running a task ({exc})") from exc
        raise


def evaluate(
    scenario: Scenario,
    policies: Sequence[str],
    seeds: Iterable[int],
    *,
    config: LoopConfig = LoopConfig(),
    workers: int = 1,
    client=None,
    task_size: int | None = None,
    example_seeds: Sequence[int] = (),
    progress: Callable[[int, str], None] | None = None,
    task_timeout_s: float = DEFAULT_TASK_TIMEOUT_S,
    done: Sequence[EpisodeResult] = (),
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> Evaluation:
    """Fly every policy on every seed of ``scenario``.

    ``client``: a pre-configured ``dask.distributed.Client`` (or any
    ``concurrent.futures.Executor``) to run on; otherwise ``workers`` local processes
    (1, or a single task: serially, in this process, one episode at a time).
    ``progress(episodes_done, note)`` is called as tasks finish, ``on_episode(result)``
    for every finished episode (the journal). ``done``: episodes finished before (a
    resumed run), not flown again. ``example_seeds`` keep their tracks (trajectory
    figure). Raises :class:`EpisodeError` if an episode fails,
    :class:`EvaluationTimeoutError` if no task finishes within ``task_timeout_s``.
    """
    if scenario.search is None:
        raise ValueError(f"scenario {scenario.name} has no [search] table")
    policies = tuple(policies)
    if not policies or len(set(policies)) != len(policies):
        raise ValueError("policies must be given, each once")
    seeds = tuple(int(s) for s in seeds)
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError("seeds must be given, each once, all >= 0")
    if workers < 1:
        raise ValueError("workers must be >= 1")
    if not (task_timeout_s > 0):
        raise ValueError("task_timeout_s must be > 0")
    examples = frozenset(int(s) for s in example_seeds) & frozenset(seeds)
    every = episode_list(policies, seeds)
    have = {(e.policy, e.seed) for e in done}
    if not have <= set(every) or len(have) != len(done):
        raise ValueError("done episodes must be distinct episodes of these policies and seeds")
    todo = [ep for ep in every if ep not in have]
    dask = client is not None and _is_dask(client)
    slots = dask_slots(client) if dask else workers
    size = task_size if task_size is not None else auto_task_size(len(todo), slots)
    if size < 1:
        raise ValueError("task_size must be >= 1")
    tasks = chunks(todo, size)
    done_results: list[EpisodeResult] = list(done)

    def finished(batch: list[EpisodeResult]) -> None:
        for e in batch:
            done_results.append(e)
            if on_episode is not None:
                on_episode(e)
        if progress is not None and batch:
            progress(len(done_results), f"{batch[-1].policy} seed {batch[-1].seed}")

    if client is None and (workers == 1 or len(tasks) == 1):  # no pool for one task
        for p, s in todo:  # one at a time: each is kept as soon as it is flown
            finished([run_episode(scenario, p, s, config, keep_track=s in examples)])
    else:
        own_pool = None
        if client is None:
            own_pool = cf.ProcessPoolExecutor(
                max_workers=min(workers, len(tasks)),
                mp_context=multiprocessing.get_context("spawn"))
            runner = own_pool
        else:
            runner = client
        futures: list = []
        try:
            if dask:
                futures = client.map(run_episodes, tasks, scenario=scenario, config=config,
                                     track_seeds=examples, pure=False)
            else:  # a spawning pool starts its processes as tasks are submitted
                with (_single_threaded_children() if own_pool is not None
                      else contextlib.nullcontext()):
                    futures = [runner.submit(run_episodes, t, scenario, config, examples)
                               for t in tasks]
            pending = set(futures)
            while pending:
                done, pending = _wait_first(pending, task_timeout_s, client if dask else None)
                if not done:
                    raise EvaluationTimeoutError(
                        f"no task of {len(tasks)} finished within {task_timeout_s:g} s "
                        f"({len(done_results)} of {len(todo)} episodes done)")
                for f in done:
                    finished(_result(f, task_timeout_s, dask))
        except BaseException:
            if dask:
                client.cancel(futures)
            if own_pool is not None:
                _stop_pool(own_pool)
                own_pool = None
            raise
        finally:
            if own_pool is not None:
                own_pool.shutdown(wait=True)
    order = {p: i for i, p in enumerate(policies)}
    done_results.sort(key=lambda e: (order[e.policy], e.seed))
    return Evaluation(
        scenario=scenario.name, policies=policies, seeds=seeds,
        budget_s=float(scenario.search.budget_s),
        area_enu_m=tuple(tuple(v) for v in scenario.search.area_enu_m),
        episodes=done_results, example_seeds=tuple(s for s in seeds if s in examples),
        decision_period_s=config.decision_period_s,
    )


# ---------------------------------------------------------------------- journal
JOURNAL_SUFFIX = ".partial.jsonl"
JOURNAL_FORMAT = "osa-evaluate-journal"


def journal_path(rows_path: str | Path) -> Path:
    """Where the episodes of a run writing ``rows_path`` are kept as they finish."""
    p = Path(rows_path)
    return p.with_name(p.name + JOURNAL_SUFFIX)


def episode_to_json(e: EpisodeResult) -> dict:
    """One journal line: everything the rows and the figures need, exactly (floats
    are written as their shortest repr, NaN as ``NaN``, and read back as the same)."""
    return {
        "policy": e.policy, "seed": e.seed, "rows": e.rows,
        "series": {b: a.tolist() for b, a in e.series.items()},
        "track_enu_m": None if e.track_enu_m is None else [t.tolist() for t in e.track_enu_m],
        "truth_enu_m": {b: list(v) for b, v in e.truth_enu_m.items()},
        "estimates_enu_m": {b: list(v) for b, v in e.estimates_enu_m.items()},
    }


def episode_from_json(d: dict) -> EpisodeResult:
    track = d["track_enu_m"]
    return EpisodeResult(
        policy=d["policy"], seed=int(d["seed"]), rows=d["rows"],
        series={b: np.array(a, dtype=float).reshape(-1, 4) for b, a in d["series"].items()},
        track_enu_m=None if track is None else [np.array(t, dtype=float).reshape(-1, 2)
                                                for t in track],
        truth_enu_m={b: tuple(v) for b, v in d["truth_enu_m"].items()},
        estimates_enu_m={b: tuple(v) for b, v in d["estimates_enu_m"].items()},
    )


class JournalError(ValueError):
    """A journal that cannot be resumed (another run's, unreadable): one line."""


class EpisodeJournal:
    """The finished episodes of one run, one JSON line each after a header line that
    names the run (``key``: scenario, policies, seeds, loop settings); appended, flushed
    and synced as each episode finishes. A run is resumed only with the same key; a
    last line cut short (the process killed while writing it) is ignored."""

    def __init__(self, path: str | Path, key: dict, *, resume: bool = False) -> None:
        self.path = Path(path)
        self.key = json.loads(json.dumps({"format": JOURNAL_FORMAT, **key}))  # as read back
        self.episodes: list[EpisodeResult] = []
        if resume:
            self._read()
            self._fh = self.path.open("a", encoding="utf-8")
        else:
            self._fh = self.path.open("x", encoding="utf-8")  # never over another run's
            try:
                self._write(self.key)
            except OSError:  # no journal rather than one without its header
                self.close()
                self.path.unlink(missing_ok=True)
                raise

    def _read(self) -> None:
        try:
            with self.path.open(encoding="utf-8") as fh:
                lines = fh.read().split("\n")
        except (OSError, UnicodeDecodeError) as exc:
            raise JournalError(f"cannot read {self.path}: {exc}") from None
        try:
            head = json.loads(lines[0])
        except ValueError:
            head = None
        if head != self.key:
            raise JournalError(f"{self.path} belongs to another run (scenario, policies or "
                               "their trained models, seeds or loop options differ): resume "
                               "with the same command, or start again with --force")
        seen = set()
        for line in lines[1:]:
            try:
                e = episode_from_json(json.loads(line))
            except (ValueError, KeyError, TypeError):
                continue  # the line being written when the run stopped
            if (e.policy, e.seed) not in seen:
                seen.add((e.policy, e.seed))
                self.episodes.append(e)
        if lines[-1]:  # a cut line: end it so the next episode starts on its own line
            with self.path.open("a", encoding="utf-8") as fh:
                fh.write("\n")

    def _write(self, obj: dict) -> None:
        self._fh.write(json.dumps(obj, separators=(",", ":")) + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def append(self, e: EpisodeResult) -> None:
        """Keep ``e`` (:class:`JournalError` if it cannot be written: a full disk)."""
        try:
            self._write(episode_to_json(e))
        except OSError as exc:
            raise JournalError(f"cannot write {self.path}: {exc.strerror or exc}") from exc
        self.episodes.append(e)  # only once it is on disk

    def close(self) -> None:
        with contextlib.suppress(OSError):  # what a full disk refused stays refused
            self._fh.close()

    def remove(self) -> None:
        self.close()
        self.path.unlink(missing_ok=True)


# ---------------------------------------------------------------------- summary
@dataclass(frozen=True)
class PolicySummary:
    """Per policy, over every (seed, responder) row.

    ``success_rate``: the share of responders the policy judged localised
    (``localised_at_s`` set). Times are censored at the budget: a responder never
    localised counts as the budget, and a quantile that reaches a censored value is a
    lower bound (``*_censored``). Errors are over the rows that have an estimate.
    The timed search challenge (added fields): the median error at 3 and 10 minutes
    (no estimate counting as infinite), the final estimates within 2 m and 5 m, and per
    episode the time until every responder was judged localised (censored).
    """

    policy: str
    episodes: int
    responders: int
    localised: int
    success_rate: float
    localised_at_s_median: float
    localised_at_s_p90: float
    localised_at_s_median_censored: bool
    localised_at_s_p90_censored: bool
    with_estimate: int
    err_h_m_median: float
    err_h_m_p90: float
    within_1m: int
    time_within_1m_s_median: float
    time_within_1m_s_median_censored: bool
    # the timed search challenge (added; defaults for summaries made before it)
    err_h_3min_m_median: float = math.nan  # over the rows, no estimate counting as inf
    err_h_10min_m_median: float = math.nan
    within_2m: int = 0
    within_5m: int = 0
    all_localised: int = 0  # episodes in which every responder was judged localised
    all_localised_at_s_median: float = math.nan  # censored at the budget
    all_localised_at_s_median_censored: bool = False
    all_localised_at_s_p90: float = math.nan
    all_localised_at_s_p90_censored: bool = False


def censored_quantile(values: Sequence[float | None], q: float,
                      budget_s: float) -> tuple[float, bool]:
    """Quantile ``q`` with None counted as the budget; True if it is a lower bound
    (the interpolation reached a censored value)."""
    v = sorted(budget_s if x is None else float(x) for x in values)
    if not v:
        return math.nan, False
    n_cens = sum(x is None for x in values)
    pos = q * (len(v) - 1)
    hi = min(math.floor(pos) + (pos > math.floor(pos)), len(v) - 1)
    return quantile(v, q), n_cens > 0 and hi >= len(v) - n_cens


def summarise(rows: Sequence[dict], policies: Sequence[str] | None = None,
              budget_s: float | None = None) -> list[PolicySummary]:
    """One :class:`PolicySummary` per policy (in the given order, else first seen)."""
    if policies is None:
        policies = list(dict.fromkeys(r["policy"] for r in rows))
    out = []
    for p in policies:
        mine = [r for r in rows if r["policy"] == p]
        budget = budget_s if budget_s is not None else max(
            (r.get("budget_s") or r["flight_time_s"] for r in mine), default=math.nan)
        loc = [r["localised_at_s"] for r in mine]
        m, m_c = censored_quantile(loc, 0.5, budget)
        p90, p90_c = censored_quantile(loc, 0.9, budget)
        errs = [r["err_h_m"] for r in mine if r["err_h_m"] is not None]
        t1 = [r.get("time_within_1m_s") for r in mine]
        t1m, t1m_c = censored_quantile(t1, 0.5, budget)
        n_loc = sum(x is not None for x in loc)
        t_all = [e["all_localised_at_s"] for e in _episodes(mine).values()]
        a_m, a_m_c = censored_quantile(t_all, 0.5, budget)
        a_90, a_90_c = censored_quantile(t_all, 0.9, budget)
        out.append(PolicySummary(
            policy=p, episodes=len({r["seed"] for r in mine}), responders=len(mine),
            localised=n_loc, success_rate=n_loc / len(mine) if mine else math.nan,
            localised_at_s_median=m, localised_at_s_p90=p90,
            localised_at_s_median_censored=m_c, localised_at_s_p90_censored=p90_c,
            with_estimate=len(errs), err_h_m_median=median(errs),
            err_h_m_p90=quantile(errs, 0.9),
            within_1m=sum(x is not None for x in t1),
            time_within_1m_s_median=t1m, time_within_1m_s_median_censored=t1m_c,
            err_h_3min_m_median=_median_none_inf([r.get("err_h_3min_m") for r in mine]),
            err_h_10min_m_median=_median_none_inf([r.get("err_h_10min_m") for r in mine]),
            within_2m=sum(int(r.get("within_2m") or 0) for r in mine),
            within_5m=sum(int(r.get("within_5m") or 0) for r in mine),
            all_localised=sum(x is not None for x in t_all),
            all_localised_at_s_median=a_m, all_localised_at_s_median_censored=a_m_c,
            all_localised_at_s_p90=a_90, all_localised_at_s_p90_censored=a_90_c,
        ))
    return out


def _median_none_inf(values: Sequence[float | None]) -> float:
    """The median with None (no estimate) counted as an infinite error."""
    return median([math.inf if v is None else float(v) for v in values])


def _episodes(rows: Sequence[dict]) -> dict[int, dict]:
    """Per seed of one policy's rows: ``all_localised_at_s`` and ``error_m``
    (:func:`envs.metrics.episode_error_m` of its responders' final errors)."""
    by_seed: dict[int, list[dict]] = {}
    for r in rows:
        by_seed.setdefault(int(r["seed"]), []).append(r)
    return {s: {"all_localised_at_s": all_localised_at_s([r["localised_at_s"] for r in rs]),
                "error_m": episode_error_m([r["err_h_m"] for r in rs])}
            for s, rs in by_seed.items()}


# ---------------------------------------------------------------------- paired
PAIRED_METRICS = ("all_localised_at_s", "error_m")


@dataclass(frozen=True)
class PairedComparison:
    """Policy ``a`` against ``b`` on the seeds both flew, one value per episode of
    ``metric`` (lower is better): ``all_localised_at_s`` (censored at the budget: an
    episode not localised counts as the budget) or ``error_m`` (the mean capped final
    error, :func:`envs.metrics.episode_error_m`). ``wins``: episodes where ``a`` is
    lower; ``losses``: where ``b`` is; ``ties``: equal. ``sign_p``: the two-sided exact
    sign test on wins against losses (ties dropped); ``wilcoxon_p``: the two-sided
    Wilcoxon signed-rank test of the differences (zeros dropped; exact for small
    samples, scipy's choice); NaN when no episode differs."""

    a: str
    b: str
    metric: str
    seeds: int
    wins: int
    losses: int
    ties: int
    median_a: float
    median_b: float
    sign_p: float
    wilcoxon_p: float


def paired_tests(a_values: Sequence[float], b_values: Sequence[float]
                 ) -> tuple[int, int, int, float, float]:
    """(wins of a, losses, ties, two-sided sign-test p, two-sided Wilcoxon p) of paired
    values, lower being better (see :class:`PairedComparison`)."""
    from scipy import stats

    d = np.asarray(a_values, dtype=float) - np.asarray(b_values, dtype=float)
    if d.shape != (len(b_values),) or not np.all(np.isfinite(d)):
        raise ValueError("paired values must be finite and of one length")
    wins, losses = int(np.sum(d < 0)), int(np.sum(d > 0))
    ties = len(d) - wins - losses
    if wins + losses == 0:
        return wins, losses, ties, math.nan, math.nan
    sign_p = float(stats.binomtest(wins, wins + losses, 0.5).pvalue)
    wil_p = float(stats.wilcoxon(d[d != 0], zero_method="wilcox").pvalue)
    return wins, losses, ties, sign_p, wil_p


def _censored(v: float | None, budget_s: float) -> float:
    return float(budget_s) if v is None else float(v)


def compare_pairs(rows: Sequence[dict], policies: Sequence[str] | None = None,
                  budget_s: float | None = None) -> list[PairedComparison]:
    """Every pair of ``policies`` (in order: the first against the later ones) on both
    :data:`PAIRED_METRICS`, over the seeds both flew."""
    if policies is None:
        policies = list(dict.fromkeys(r["policy"] for r in rows))
    per = {p: _episodes([r for r in rows if r["policy"] == p]) for p in policies}
    if budget_s is None:
        budget_s = max((r.get("budget_s") or r["flight_time_s"] for r in rows),
                       default=math.nan)
    out = []
    for i, a in enumerate(policies):
        for b in policies[i + 1:]:
            seeds = sorted(set(per[a]) & set(per[b]))
            for metric in PAIRED_METRICS:
                if not seeds:
                    continue
                va = [_censored(per[a][s][metric], budget_s) for s in seeds]
                vb = [_censored(per[b][s][metric], budget_s) for s in seeds]
                w, lo, t, sp, wp = paired_tests(va, vb)
                out.append(PairedComparison(a, b, metric, len(seeds), w, lo, t,
                                            median(va), median(vb), sp, wp))
    return out


def _minutes(v: float, censored: bool) -> str:
    if not math.isfinite(v):
        return "-"
    return (">=" if censored else "") + f"{v / 60:.1f}"


def _metres(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.2f}"


SUMMARY_COLUMNS = (
    Column("policy", "<", 20), Column("seeds", ">", 6), Column("localised", ">", 14),
    Column("t_loc med", ">", 11), Column("t_loc p90", ">", 11), Column("err med", ">", 9),
    Column("err p90", ">", 9), Column("<=1 m", ">", 7), Column("t_1m med", ">", 10),
)


def format_summary(summaries: Sequence[PolicySummary]) -> str:
    """The per-policy table ``osa evaluate`` prints (times in minutes, errors in m)."""
    rows = [
        (s.policy, str(s.episodes), f"{s.localised}/{s.responders} {s.success_rate:4.0%}",
         _minutes(s.localised_at_s_median, s.localised_at_s_median_censored),
         _minutes(s.localised_at_s_p90, s.localised_at_s_p90_censored),
         _metres(s.err_h_m_median), _metres(s.err_h_m_p90), str(s.within_1m),
         _minutes(s.time_within_1m_s_median, s.time_within_1m_s_median_censored))
        for s in summaries
    ]
    return "\n".join(text_table(SUMMARY_COLUMNS, rows, rule="-"))


CHALLENGE_COLUMNS = (
    Column("policy", "<", 20), Column("seeds", ">", 6), Column("all loc", ">", 8),
    Column("t_all med", ">", 10), Column("t_all p90", ">", 10), Column("err@3min", ">", 9),
    Column("err@10min", ">", 10), Column("<=2 m", ">", 11), Column("<=5 m", ">", 11),
)


def format_challenge(summaries: Sequence[PolicySummary]) -> str:
    """The timed search challenge per policy: episodes with every responder localised,
    the time until then (min; censored), the median error at 3 and 10 min (m; "-": more
    than half without an estimate), the responders whose final estimate is within 2 m
    and 5 m."""
    rows = [
        (s.policy, str(s.episodes), f"{s.all_localised}/{s.episodes}",
         _minutes(s.all_localised_at_s_median, s.all_localised_at_s_median_censored),
         _minutes(s.all_localised_at_s_p90, s.all_localised_at_s_p90_censored),
         _metres(s.err_h_3min_m_median), _metres(s.err_h_10min_m_median),
         f"{s.within_2m}/{s.responders}", f"{s.within_5m}/{s.responders}")
        for s in summaries
    ]
    return "\n".join(text_table(CHALLENGE_COLUMNS, rows, rule="-"))


PAIRED_COLUMNS = (
    Column("A vs B", "<", 36), Column("metric", "<", 10), Column("seeds", ">", 6),
    Column("A wins", ">", 7), Column("B wins", ">", 7), Column("ties", ">", 5),
    Column("med A", ">", 7), Column("med B", ">", 7), Column("sign p", ">", 8),
    Column("Wilcoxon p", ">", 11),
)
_METRIC_LABEL = {"all_localised_at_s": "t_all min", "error_m": "error m"}


def _p(v: float) -> str:
    return "-" if not math.isfinite(v) else (f"{v:.2g}" if v < 0.01 else f"{v:.3f}")


def format_paired(comparisons: Sequence[PairedComparison]) -> str:
    """The paired comparisons (times in minutes, errors in m, two-sided p values)."""
    rows = []
    for c in comparisons:
        scale = 60.0 if c.metric == "all_localised_at_s" else 1.0
        rows.append((f"{c.a} vs {c.b}", _METRIC_LABEL[c.metric], str(c.seeds), str(c.wins),
                     str(c.losses), str(c.ties), f"{c.median_a / scale:.2f}",
                     f"{c.median_b / scale:.2f}", _p(c.sign_p), _p(c.wilcoxon_p)))
    return "\n".join(text_table(PAIRED_COLUMNS, rows, rule="-"))


def summary_json(rows: Sequence[dict], policies: Sequence[str] | None = None,
                 budget_s: float | None = None) -> dict:
    """The summary, the timed challenge and the paired comparisons as one JSON object
    (``osa evaluate --summary-json``); non-finite numbers become None."""
    def clean(d: dict) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in d.items()}

    return {
        "policies": [clean(dataclasses.asdict(s)) for s in summarise(rows, policies, budget_s)],
        "paired": [clean(dataclasses.asdict(c)) for c in compare_pairs(rows, policies,
                                                                       budget_s)],
    }


# ---------------------------------------------------------------------- files
def write_rows(rows: Sequence[dict], path: str | Path) -> Path:
    """Write the rows as ``.csv`` (standard library) or ``.parquet`` (pyarrow), typed
    by :data:`COLUMNS`; None is an empty CSV cell or a Parquet null."""
    p = Path(path)
    suffix = p.suffix.lower()
    names = [n for n, _ in COLUMNS]
    if suffix == ".csv":
        with p.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(names)
            for r in rows:  # floats as repr: the shortest text that reads back exactly
                w.writerow(["" if r.get(n) is None else r[n] for n in names])
        return p
    if suffix == ".parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        pa_type = {str: pa.string(), int: pa.int64(), float: pa.float64()}
        schema = pa.schema([(n, pa_type[t]) for n, t in COLUMNS])
        table = pa.Table.from_pylist([{n: r.get(n) for n in names} for r in rows],
                                     schema=schema)
        pq.write_table(table, p)
        return p
    raise ValueError(f"{p}: the rows are written as .csv or .parquet, not {suffix or 'no suffix'}")


def read_rows(path: str | Path) -> list[dict]:
    """Read rows written by :func:`write_rows` back (the same values and types)."""
    p = Path(path)
    if p.suffix.lower() == ".parquet":
        import pyarrow.parquet as pq

        return pq.read_table(p).to_pylist()
    with p.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        return [{n: (None if v == "" else COLUMN_TYPES.get(n, str)(v)) for n, v in r.items()}
                for r in reader]
