"""Training and evaluating policies in the search envs with Stable-Baselines3 (docs/rl.md).

:func:`train` is ``osa train``: vectorised envs in subprocesses or batched worlds in
this process (``--vec batched``, :mod:`envs.gym.batched`; world seeds of the train
split, each env seeded from ``--seed``), ``VecNormalize``, checkpoints, a
progress bar, evaluation on fixed validation worlds (:class:`ValidationCallback`, the
best model kept), a CSV log and TensorBoard logs when TensorBoard is installed.
:func:`rollout` runs one episode of any action function on a given world, the common
yardstick of the learning test and the recipe benchmark.

Needs the optional ``rl`` extra (stable-baselines3 and torch).
"""

from __future__ import annotations

import contextlib
import functools
import json
import statistics
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium
import numpy as np

import envs  # noqa: F401  (registers the envs, also in subprocesses that import this)
from envs.cli import Terminated
from envs.gym.interface import REWARD_WEIGHTS
from envs.gym.registration import TEAM_ENV_ID
from envs.gym.trained import META_FILE, MODEL_FILE, STATS_FILE, algo_class
from envs.seeds import split_seeds


@dataclass(frozen=True, kw_only=True)
class TrainSettings:
    env_id: str = "osa/Search-v0"
    env_kwargs: dict = field(default_factory=dict)
    steps: int = 200_000
    seed: int = 0
    algo: str = "PPO"
    n_envs: int = 2
    vec: str = "subproc"  # "subproc": env copies in subprocesses; "batched": envs.gym.batched
    eval_every: int = 20_000
    eval_worlds: int = 20
    checkpoint_every: int = 50_000
    progress: bool = True
    algo_kwargs: dict = field(default_factory=dict)
    policy_kwargs: dict = field(default_factory=lambda: {"net_arch": [128, 128]})
    curriculum: tuple[float, float] | None = None  # osa/Search-v1 to v3: level from, to
    imitate_episodes: int = 0  # osa/Search-v1 to v3: behaviour cloning of plan_heuristic first
    imitate_epochs: int = 30
    imitate_rounds: int = 0  # DAgger rounds after the first fit
    imitate_learning_rate: float = 3e-4  # Adam's rate while imitating (whatever PPO's)
    init: Path | None = None  # a model folder whose weights and statistics start the training
    imitation_coef: float = 0.0  # PPO: the imitation term's weight, annealed to 0 (envs.ppo)
    critic_warmup: int = 0  # PPO: updates that fit only the value head first (envs.ppo)


def curriculum_level(curriculum: tuple[float, float], progress: float) -> float:
    """The curriculum level at ``progress`` (0 to 1) of the training: linear from
    ``curriculum[0]`` to ``curriculum[1]``, rounded to 0.01 (the envs change level in
    those steps)."""
    a, b = curriculum
    return round(a + (b - a) * min(max(progress, 0.0), 1.0), 2)


@dataclass(frozen=True)
class Episode:
    """One episode's outcome (from the env's info; the truth only in ``err_h_m``)."""

    world_seed: int
    ret: float
    steps: int
    flight_time_s: float
    localised: bool  # terminated: every detected responder localised (estimator judgement)
    err_h_m: float | None


# gymnasium's note, coloured with terminal escapes, that a later version of an env id
# exists: osa/Search-v0 (osa train's default) is kept on purpose, so it is not said
OUT_OF_DATE = r".*The environment osa/.* is out of date"


def make_env(env_id: str, kwargs: dict) -> gymnasium.Env:
    """A registered env (module level: picklable for subprocess vector envs)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=OUT_OF_DATE, category=DeprecationWarning)
        return gymnasium.make(env_id, **kwargs)


def batched_vec_env(env_id: str, kwargs: dict, n_envs: int, seed: int):
    """The batched worlds of ``env_id`` (:mod:`envs.gym.batched`) as an SB3 ``VecEnv`` with
    episode statistics (``VecMonitor``), world i seeded ``seed + i`` as ``make_vec_env``
    seeds its copies."""
    from stable_baselines3.common.vec_env import VecMonitor

    from envs.gym.sb3 import SB3VecEnv

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=OUT_OF_DATE, category=DeprecationWarning)
        vec = gymnasium.make_vec(env_id, num_envs=n_envs,
                                 vectorization_mode="vector_entry_point",
                                 autoreset_mode="same_step", **kwargs)
    venv = VecMonitor(SB3VecEnv(vec))
    venv.seed(seed)
    return venv


def rollout(env: gymnasium.Env, act: Callable[[dict], object], world_seed: int) -> Episode:
    """Run ``act`` (observation -> action) for one episode on world ``world_seed``."""
    obs, info = env.reset(options={"world_seed": world_seed})
    ret, n = 0.0, 0
    while True:
        obs, r, term, trunc, info = env.step(act(obs))
        ret += float(r)
        n += 1
        if term or trunc:
            break
    errs = [v["err_h_m"] for v in info["eval"].values() if "err_h_m" in v]
    return Episode(world_seed, ret, n, float(info["flight_time_s"]), bool(term),
                   float(np.mean(errs)) if errs else None)


def summarise(episodes: list[Episode]) -> dict:
    """Success share, median flight time (censored at the budget: an episode not
    localised counts as its flight time, the budget) and mean return."""
    return {
        "worlds": len(episodes),
        "localised": sum(e.localised for e in episodes) / max(len(episodes), 1),
        "median_time_s": statistics.median(e.flight_time_s for e in episodes),
        "mean_return": statistics.fmean(e.ret for e in episodes),
    }


def model_actor(model, stats) -> Callable[[dict], object]:
    """The deterministic action of a model for one observation (normalised by ``stats``)."""
    def act(obs):
        x = stats.normalize_obs(obs) if stats is not None else obs
        return model.predict(x, deterministic=True)[0]
    return act


def evaluate(model, stats, env_id: str, env_kwargs: dict, world_seeds: list[int]
             ) -> list[Episode]:
    act = model_actor(model, stats)
    if env_id == TEAM_ENV_ID:
        from envs.gym.team import make_team_env, team_rollout  # PettingZoo: the 'rl' extra

        team = make_team_env({**env_kwargs, "seed_split": "validation"})
        return [team_rollout(team, act, s) for s in world_seeds]
    env = make_env(env_id, {**env_kwargs, "seed_split": "validation"})
    try:
        return [rollout(env, act, s) for s in world_seeds]
    finally:
        env.close()


def _callbacks(settings: TrainSettings, out: Path, venv):
    from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback

    from envs.commands._progress import QuantityProgress

    class Progress(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = QuantityProgress(f"osa train {settings.env_id}", settings.steps, "steps",
                                        enabled=settings.progress)

        def _on_step(self) -> bool:
            note = ""
            buf = self.model.ep_info_buffer
            if buf:
                note = f"episode return {np.mean([e['r'] for e in buf]):.2f}"
            self.bar.update(self.num_timesteps, note)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    class ValidationCallback(BaseCallback):
        """Every ``eval_every`` steps: the deterministic policy on the first
        ``eval_worlds`` validation worlds; the best (lowest median time to localise,
        then highest return) is saved in MODEL/best."""

        def _on_training_start(self) -> None:
            self.next = settings.eval_every
            self.seeds = split_seeds("validation", settings.eval_worlds)
            self.best: tuple | None = None
            self.history: list[dict] = []
            if (settings.imitate_episodes or settings.init is not None) and settings.eval_every:
                self.run()  # the warm start alone, before any PPO update

        def _on_step(self) -> bool:
            if settings.eval_every and self.num_timesteps >= self.next:
                self.next += settings.eval_every
                self.run()
            return True

        def run(self) -> None:
            eps = evaluate(self.model, venv, settings.env_id, settings.env_kwargs, self.seeds)
            s = summarise(eps)
            s["steps"] = int(self.num_timesteps)
            self.history.append(s)
            for k in ("localised", "median_time_s", "mean_return"):
                self.logger.record(f"validation/{k}", s[k])
            key = (-s["median_time_s"], s["mean_return"])
            if self.best is None or key > self.best:
                self.best = key
                save(self.model, venv, settings, out / "best", s)
            (out / "validation.json").write_text(json.dumps(self.history, indent=1))

    class Curriculum(BaseCallback):
        """Sets every training env's curriculum level (``set_level``, osa/Search-v1)
        from the share of the training done; it applies from each env's next episode."""

        def _on_training_start(self) -> None:
            self.level: float | None = None
            self._set()

        def _on_step(self) -> bool:
            self._set()
            return True

        def _set(self) -> None:
            assert settings.curriculum is not None
            level = curriculum_level(settings.curriculum, self.num_timesteps / settings.steps)
            if level != self.level:
                self.level = level
                venv.env_method("set_level", level)
                self.logger.record("train/curriculum_level", level)

    cbs = [Progress()]
    if settings.curriculum is not None:
        cbs.append(Curriculum())
    if settings.checkpoint_every:
        cbs.append(CheckpointCallback(max(settings.checkpoint_every // venv.num_envs, 1),
                                      str(out / "checkpoints"), name_prefix="model",
                                      save_vecnormalize=True))
    val = ValidationCallback()
    cbs.append(val)
    return cbs, val


def save(model, venv, settings: TrainSettings, folder: Path, extra: dict | None = None,
         *, interrupted: bool = False) -> None:
    """The three files ``ppo:FOLDER`` loads (``osa-model.json`` last: a save cut short
    leaves no model); ``interrupted``: the training stopped before its steps, said in
    ``osa-model.json`` (``"interrupted": true``)."""
    folder.mkdir(parents=True, exist_ok=True)
    model.save(str(folder / MODEL_FILE))
    venv.save(str(folder / STATS_FILE))
    team = settings.env_id == TEAM_ENV_ID
    if team:
        from envs.gym.team import make_team_env

        env = make_team_env(settings.env_kwargs)
    else:
        env = make_env(settings.env_id, settings.env_kwargs).unwrapped
    meta = {
        "format": 1,
        "algo": settings.algo,
        "env_id": settings.env_id,
        "kind": "team" if team else env.kind,
        **({"agents": env.roles} if team else {}),
        "env_kwargs": {k: getattr(v, "name", v) if k == "scenario" else v
                       for k, v in settings.env_kwargs.items()},
        "config": env.config.to_json(),
        "scenario": env.scenario.name,
        "seed": settings.seed,
        "steps": int(model.num_timesteps),
        **({"curriculum": list(settings.curriculum)} if settings.curriculum else {}),
        **({"init": str(settings.init)} if settings.init is not None else {}),
        **({"imitation_coef": settings.imitation_coef} if settings.imitation_coef else {}),
        **({"critic_warmup": settings.critic_warmup} if settings.critic_warmup else {}),
        **({"validation": extra} if extra else {}),
        **({"interrupted": True, "steps_asked": settings.steps} if interrupted else {}),
    }
    env.close()
    (folder / META_FILE).write_text(json.dumps(meta, indent=1))


def check_init(folder: Path, env_id: str, algo: str, env_kwargs: dict) -> str | None:
    """Why the model in ``folder`` cannot start a training of ``algo`` in ``env_id`` with
    ``env_kwargs`` (one line), or None."""
    if not (folder / MODEL_FILE).is_file() or not (folder / META_FILE).is_file():
        return f"{folder}: not a model written by osa train (no {MODEL_FILE} and {META_FILE})"
    try:
        meta = json.loads((folder / META_FILE).read_text())
    except ValueError as exc:
        return f"{folder / META_FILE}: unreadable ({exc})"
    if meta.get("env_id") != env_id or meta.get("algo", "PPO") != algo:
        return (f"{folder} is a {meta.get('algo', 'PPO')} model of {meta.get('env_id')}, not "
                f"{algo} in {env_id}")
    if env_id != TEAM_ENV_ID:
        env = make_env(env_id, env_kwargs).unwrapped
        config = env.config.to_json()
        env.close()
        if {k: v for k, v in meta.get("config", {}).items() if k not in REWARD_WEIGHTS} != \
                {k: v for k, v in config.items() if k not in REWARD_WEIGHTS}:
            return (f"{folder} was trained with other env settings (observation and "
                    "actions) than this training's")
    from envs.gym.trained import TrainedPolicy

    try:  # its files whole and of its env (one line now, not an error after the start)
        TrainedPolicy.load(folder)
    except ValueError as exc:
        return str(exc)
    return None


def load_init(model, venv, folder: Path) -> None:
    """Start ``model`` (policy, value and optimiser state) and the ``VecNormalize``
    ``venv`` (observation and return statistics) from the model in ``folder``
    (``osa train --init``); the step count and the rates are this training's."""
    import pickle

    model.set_parameters(str(folder / MODEL_FILE), exact_match=True, device="cpu")
    stats_p = folder / STATS_FILE
    if stats_p.is_file():
        with open(stats_p, "rb") as f:
            stats = pickle.load(f)
        venv.obs_rms, venv.ret_rms = stats.obs_rms, stats.ret_rms


def _fly_and_label(venv, episodes: int, teacher, actor, gamma: float):
    """``episodes`` episodes in every env of ``venv`` flown by ``actor`` (raw
    observations -> actions, batched; None: the teacher flies): the raw observations
    visited, the teacher's action at each and the discounted normalised return from
    each (only decisions of finished episodes)."""
    n = venv.num_envs
    raw: list[dict] = []
    labels: list[int] = []
    rewards: list[list[float]] = [[] for _ in range(n)]
    index: list[list[int]] = [[] for _ in range(n)]
    targets: dict[int, float] = {}
    venv.reset()
    done_eps = np.zeros(n, dtype=int)
    while done_eps.min() < episodes:
        o = venv.get_original_obs()
        per = [{k: v[i] for k, v in o.items()} for i in range(n)]
        want = np.array([teacher(x) for x in per])
        a = want if actor is None else np.asarray(actor(o))
        for i in range(n):
            index[i].append(len(raw) + i)
        raw.extend(per)
        labels.extend(int(x) for x in want)
        _, r, dones, _ = venv.step(a)
        for i in range(n):
            rewards[i].append(float(r[i]))
            if dones[i]:
                g = 0.0
                for j, rr in zip(reversed(index[i]), reversed(rewards[i]), strict=True):
                    g = rr + gamma * g
                    targets[j] = g
                index[i], rewards[i] = [], []
                done_eps[i] += 1
    keep = sorted(targets)
    return ([raw[j] for j in keep], [labels[j] for j in keep], [targets[j] for j in keep],
            int(done_eps.sum()))


def imitate(model, venv, settings: TrainSettings) -> dict:
    """Warm start (``osa/Search-v1`` to ``v3``): behaviour cloning of the hand-written policy
    (:func:`envs.gym.plan_actions.plan_heuristic`, in the env's actions) with DAgger
    rounds. The teacher flies
    ``imitate_episodes`` episodes in every training env (train worlds; the
    ``VecNormalize`` statistics learn from them as from any rollout); the network is
    fitted to its actions (maximum likelihood) and the value head to the discounted
    normalised returns, ``imitate_epochs`` passes in minibatches of 256 (Adam at
    ``imitate_learning_rate``, whatever PPO's rate is). Then, for
    ``imitate_rounds`` rounds, the clone itself flies as many episodes (its
    deterministic action), the teacher labels every state it visited, and the network
    is fitted again on everything gathered: the clone learns what to do in the states
    its own mistakes lead to (DAgger). Returns what it did and the dataset (the raw
    observations, one array per key, and the teacher's labels)."""
    import torch
    from stable_baselines3.common.utils import obs_as_tensor

    from envs.gym.plan_actions import PlanActions, plan_heuristic

    probe = make_env(settings.env_id, settings.env_kwargs).unwrapped
    if not isinstance(probe.pilot.actions, PlanActions):
        raise ValueError(f"imitation needs osa/Search-v1's to v3's actions, not "
                         f"{settings.env_id}'s")
    teacher = plan_heuristic(probe.pilot.actions)
    probe.close()
    gamma = float(getattr(model, "gamma", 0.99))
    policy = model.policy
    opt = policy.optimizer
    for group in opt.param_groups:  # its own rate (PPO sets its own again when it trains)
        group["lr"] = settings.imitate_learning_rate
    rng = np.random.default_rng(settings.seed)
    raw: list[dict] = []
    labels: list[int] = []
    returns: list[float] = []
    rounds = []

    def clone(o: dict):
        return policy.predict(venv.normalize_obs(o), deterministic=True)[0]

    for k in range(settings.imitate_rounds + 1):
        got = _fly_and_label(venv, settings.imitate_episodes, teacher,
                             None if k == 0 else clone, gamma)
        if k:  # how the clone flew before this round's fit
            rounds[-1]["clone_agreement_flying"] = float(
                np.mean([int(clone({kk: v[None] for kk, v in x.items()})[0]) == y
                         for x, y in zip(got[0], got[1], strict=True)]))
        raw += got[0]
        labels += got[1]
        returns += got[2]
        obs = venv.normalize_obs({key: np.stack([x[key] for x in raw]) for key in raw[0]})
        acts = np.array(labels)
        rets = np.array(returns)
        history = []
        for _ in range(settings.imitate_epochs):
            order = rng.permutation(len(acts))
            losses = []
            for b in range(0, len(order), 256):
                mb = order[b:b + 256]
                o_t = obs_as_tensor({key: v[mb] for key, v in obs.items()}, policy.device)
                values, log_prob, _ = policy.evaluate_actions(
                    o_t, torch.as_tensor(acts[mb], device=policy.device))
                ret = torch.as_tensor(rets[mb], dtype=torch.float32, device=policy.device)
                loss = -log_prob.mean() + 0.5 * torch.nn.functional.mse_loss(
                    values.flatten(), ret)
                opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
                opt.step()
                losses.append(float(loss.item()))
            history.append(statistics.fmean(losses))
        agree = float((policy.predict(obs, deterministic=True)[0] == acts).mean())
        rounds.append({"flown_by": "teacher" if k == 0 else "clone", "episodes": got[3],
                       "decisions": len(got[1]), "loss": history, "agreement": agree})
    first = rounds[0]
    report = {"episodes": first["episodes"], "decisions": first["decisions"],
              "epochs": len(first["loss"]), "loss": first["loss"],
              "agreement": rounds[-1]["agreement"], "rounds": rounds}
    return report, ({key: np.stack([x[key] for x in raw]) for key in raw[0]}, np.array(labels))


@dataclass
class TrainSummary:
    out: Path
    steps: int
    wall_s: float
    validation: list[dict]

    def text(self) -> str:
        lines = [f"trained {self.steps} steps in {self.wall_s / 60:.1f} min -> {self.out}"]
        for v in self.validation:
            lines.append(f"  validation at {v['steps']:>8} steps: localised "
                         f"{100 * v['localised']:.0f} %, median time {v['median_time_s']:.0f} s,"
                         f" mean return {v['mean_return']:.2f}")
        return "\n".join(lines)


def stop_vec_env(venv) -> None:
    """Close ``venv`` after an interruption or an error without waiting for its worker
    processes: SB3's ``SubprocVecEnv.close`` first reads the replies of the step in
    flight, and waits forever for one that a signal already cut short (SIGTERM's
    unwinding hung) or raises ``EOFError`` for a worker that Ctrl-C stopped; the
    workers are ours, so they are terminated."""
    inner = venv
    while getattr(inner, "processes", None) is None and getattr(inner, "venv", None) is not None:
        inner = inner.venv
    procs = getattr(inner, "processes", None)
    if procs is None:  # in this process (DummyVecEnv, batched worlds, a team's copies)
        with contextlib.suppress(Exception):
            venv.close()
        return
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=10)
    for remote in inner.remotes:
        remote.close()
    inner.closed = True


def _remove_model(folder: Path) -> None:
    """The model files of a previous training in a reused ``folder`` (and its ``best/``):
    replaced by this one, they must not stay behind as its result if it stops early."""
    for d in (folder, folder / "best"):
        for name in (META_FILE, MODEL_FILE, STATS_FILE):  # the json first: then no model
            (d / name).unlink(missing_ok=True)


def train(settings: TrainSettings, out: Path) -> TrainSummary:
    """Train and save (see the module docstring); returns what the CLI prints.

    Interrupted (Ctrl-C, SIGTERM) while training, the env workers are stopped, the
    model reached so far is saved in ``out`` with ``"interrupted": true`` in its
    ``osa-model.json``, and the interruption goes on up."""
    import torch
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.logger import configure
    from stable_baselines3.common.utils import set_random_seed
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    _remove_model(out)
    torch.set_num_threads(1)  # small networks: the envs' subprocesses want the cores
    set_random_seed(settings.seed)
    kwargs = {**settings.env_kwargs, "seed_split": "train"}
    if settings.env_id == TEAM_ENV_ID:  # parameter sharing: every UAV an entry
        from stable_baselines3.common.vec_env import VecMonitor

        from envs.gym.team import TeamVecEnv

        venv = VecMonitor(TeamVecEnv(kwargs, copies=settings.n_envs))
        venv.seed(settings.seed)
    elif settings.vec == "batched":
        venv = batched_vec_env(settings.env_id, kwargs, settings.n_envs, settings.seed)
    elif settings.vec == "subproc":
        fn = functools.partial(make_env, settings.env_id, kwargs)
        vec_cls = SubprocVecEnv if settings.n_envs > 1 else DummyVecEnv
        venv = make_vec_env(fn, n_envs=settings.n_envs, seed=settings.seed, vec_env_cls=vec_cls)
    else:
        raise ValueError(f"unknown vec {settings.vec!r} (subproc, batched)")
    algo_kw = dict(settings.algo_kwargs)
    gamma = algo_kw.get("gamma", 0.99)
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, clip_obs=10.0, gamma=gamma)
    cls = algo_class(settings.algo)
    if settings.imitation_coef or settings.critic_warmup:
        if settings.algo != "PPO":
            raise ValueError("the imitation term and the critic warm-up are PPO's")
        from envs.ppo import GuidedPPO

        cls = GuidedPPO
        algo_kw.update(imitation_coef=settings.imitation_coef,
                       critic_warmup=settings.critic_warmup, imitation_seed=settings.seed)
    model = cls("MultiInputPolicy", venv, seed=settings.seed, device="cpu", verbose=0,
                policy_kwargs=settings.policy_kwargs, **algo_kw)
    formats = ["csv"]
    try:
        import tensorboard  # noqa: F401

        formats.append("tensorboard")
    except ImportError:
        pass
    model.set_logger(configure(str(out), formats))
    if settings.init is not None:
        load_init(model, venv, Path(settings.init))
    cbs, val = _callbacks(settings, out, venv)
    t0 = time.perf_counter()
    try:
        if settings.imitate_episodes:
            imitated, data = imitate(model, venv, settings)
            (out / "imitation.json").write_text(json.dumps(imitated, indent=1))
            if settings.imitation_coef:
                model.set_imitation_data(*data, venv.normalize_obs)
        model.learn(total_timesteps=settings.steps, callback=cbs)
        if settings.eval_every and (not val.history or val.history[-1]["steps"]
                                    < model.num_timesteps - settings.eval_every // 2):
            val.run()  # the end is far from the last evaluation
    except BaseException as exc:
        stop_vec_env(venv)
        if isinstance(exc, KeyboardInterrupt | Terminated):
            bar = getattr(cbs[0], "bar", None)
            if bar is not None:
                bar.close("interrupted", line=False)  # the command says it in one line
            # the model so far, loadable and marked, rather than nothing (or the
            # previous training's model in a reused folder)
            history = getattr(val, "history", None)  # None: stopped before training
            save(model, venv, settings, out, history[-1] if history else None,
                 interrupted=True)
        raise
    venv.close()
    wall = time.perf_counter() - t0
    save(model, venv, settings, out, val.history[-1] if val.history else None)
    return TrainSummary(out, int(model.num_timesteps), wall, val.history)

