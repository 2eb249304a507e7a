"""``osa train [--env ID] [--steps N] [--seed N] -o MODEL``: train a search policy with
Stable-Baselines3 (docs/cli.md, docs/rl.md).

PPO unless ``--algo`` says otherwise, on ``--envs`` copies of the env in subprocesses,
or as many worlds batched in this process with ``--vec batched`` (world seeds from the
train split), observations and rewards normalised by
``VecNormalize`` (saved with the model), checkpoints, a progress bar, evaluation on
fixed validation worlds during training (the best model kept in ``MODEL/best``), a CSV
log and TensorBoard logs when TensorBoard is installed. ``MODEL`` is a folder that
``osa search --policy ppo:MODEL`` loads (:mod:`envs.gym.trained`).
"""

from __future__ import annotations

import argparse
import math
import sys

from envs.commands._args import non_negative_int, positive_int, train_seed_arg
from envs.commands._outputs import add_force_option


def linear_schedule(start: float):
    """A learning rate falling linearly from ``start`` to 0 over the training (SB3 calls
    it with the remaining share of the training, 1 -> 0): steadier late updates."""
    def rate(remaining: float) -> float:
        return start * remaining
    return rate


PPO_DEFAULTS = dict(n_steps=256, batch_size=128, n_epochs=10, gamma=0.995, gae_lambda=0.95,
                    ent_coef=0.01, learning_rate=linear_schedule(3e-4),
                    clip_range=0.2)  # docs/rl.md


REWARD_WEIGHTS = ("time_cost_per_s", "localised_bonus", "information_weight", "detection_bonus",
                  "coverage_bonus", "leave_penalty")  # what --reward sets (docs/rl.md "Rewards")

REWARD_PRESETS = ("metric",)
# the whole search as the policy's choice
PLAN_ENVS = ("osa/Search-v1", "osa/Search-v2", "osa/Search-v3")


def preset_weights(preset: str, env_id: str) -> dict:
    """The reward weights of ``--reward-preset``. ``metric``: every term but time off, so
    an episode's return is ``-time_cost_per_s`` times the time until the estimator
    judges every expected responder localised (the episode's end), or the budget: the
    metric of the recipe's sign test (docs/rl.md)."""
    if preset != "metric":
        raise ValueError(f"unknown reward preset {preset!r}")
    out = {"information_weight": 0.0, "detection_bonus": 0.0, "coverage_bonus": 0.0,
           "leave_penalty": 0.0}
    if env_id in PLAN_ENVS:
        out["localised_bonus"] = 0.0
    return out


def reward_weights(weights: dict, env_id: str, preset: str | None = None
                   ) -> tuple[str | None, dict]:
    """``--reward-preset`` then the ``--reward NAME=X`` weights (``{NAME: X}``, X a number
    or its text; they override the preset) as env keywords: (why they cannot be, or
    None; them)."""
    from envs.gym.team import TEAM_ENV_ID

    out: dict = {}
    if preset is not None:
        if preset not in REWARD_PRESETS:
            return (f"--reward-preset: unknown preset {preset!r}; choose from "
                    f"{', '.join(REWARD_PRESETS)}"), out
        if env_id == TEAM_ENV_ID:
            return f"--reward-preset: not for {TEAM_ENV_ID}", out
        out.update(preset_weights(preset, env_id))
    for name, value in weights.items():
        if name not in REWARD_WEIGHTS:
            return (f"--reward: unknown weight {name!r}; choose from "
                    f"{', '.join(REWARD_WEIGHTS)}"), out
        if env_id == TEAM_ENV_ID:
            return f"--reward: not for {TEAM_ENV_ID}", out
        if name == "localised_bonus" and env_id not in PLAN_ENVS:
            return f"--reward: localised_bonus is osa/Search-v1's to v3's, not {env_id}'s", out
        try:
            if isinstance(value, bool):
                raise ValueError
            x = float(value)
        except (TypeError, ValueError):
            return f"--reward: expected NAME=X with X a number, got {name}={value!r}", out
        if not (math.isfinite(x) and x >= 0.0):
            return f"--reward: {name} must be a number >= 0, got {value!r}", out
        out[name] = x
    return None, out


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a search policy with Stable-Baselines3 (needs the 'rl' extra)",
        description="Train a policy on a registered search environment and save it in the "
        "folder MODEL, which osa search --policy ppo:MODEL and osa evaluate load.",
    )
    p.add_argument("--env", default="osa/Search-v0", metavar="ID",
                   help="a registered env id: osa/Search-v0 (default), osa/Search-v1, "
                   "osa/Search-v2 (v1 with adaptive's planned action), osa/Search-v3 (v2 with each "
                   "responder's recent sigma_H shrink observed) or "
                   "osa/Waypoint-v0; osa/Team-v0: a team of --uavs UAVs, one shared policy "
                   "(PettingZoo)")
    p.add_argument("--scenario", default=None, metavar="S",
                   help="the env's search scenario (preset or .toml; default the env's)")
    p.add_argument("--steps", type=positive_int, default=200_000, metavar="N",
                   help="environment steps (decisions) to train for (default 200000)")
    p.add_argument("--seed", type=train_seed_arg, default=0, metavar="N",
                   help="seed of the networks, the sampling and the envs' worlds, "
                   "0 .. 2^32 - 1 (default 0)")
    p.add_argument("-o", "--out", required=True, metavar="MODEL", help="model folder to write")
    p.add_argument("--algo", default="PPO", metavar="A",
                   help="Stable-Baselines3 algorithm: PPO (default), A2C, DQN (Search-v0), "
                   "SAC or TD3 (Waypoint-v0)")
    p.add_argument("--envs", type=positive_int, default=2, metavar="K",
                   help="env copies (default 2, one per core here), or worlds batched in "
                   "one process with --vec batched")
    p.add_argument("--vec", choices=("subproc", "batched"), default="subproc",
                   help="subproc: each copy in its own process (default); batched: K "
                   "worlds stepped in lockstep in this process (envs.gym.batched)")
    p.add_argument("--eval-every", type=non_negative_int, default=20_000, metavar="N",
                   help="evaluate on validation worlds every N steps (0: never; default 20000)")
    p.add_argument("--eval-worlds", type=positive_int, default=20, metavar="K",
                   help="validation worlds per evaluation (default 20)")
    p.add_argument("--checkpoint-every", type=non_negative_int, default=50_000, metavar="N",
                   help="save a checkpoint every N steps (0: never; default 50000)")
    p.add_argument("--curriculum", default=None, metavar="FROM:TO",
                   help="osa/Search-v1 to v3: the curriculum level (the share of the scenario's "
                   "[randomise] ranges in use, 0 to 1) rising linearly from FROM to TO over "
                   "the training (default: none, level 1)")
    p.add_argument("--imitate", type=non_negative_int, default=0, metavar="N",
                   help="osa/Search-v1 to v3: warm start by behaviour cloning of the hand-written "
                   "policy, N episodes per env before the training (default 0: none)")
    p.add_argument("--dagger", type=non_negative_int, default=0, metavar="K",
                   help="with --imitate: K DAgger rounds (the clone flies, the hand-written "
                   "policy labels its states, the clone is fitted again; default 0)")
    p.add_argument("--init", default=None, metavar="MODEL",
                   help="start from the weights (policy, value, optimiser) and the "
                   "normalisation statistics of MODEL, an osa train folder of the same env, "
                   "settings and algorithm (e.g. a DAgger clone); default: fresh weights")
    p.add_argument("--reward", action="append", default=[], metavar="NAME=X",
                   help="a reward weight of the env (repeatable): "
                   f"{', '.join(REWARD_WEIGHTS)} (localised_bonus: osa/Search-v1 to v3); "
                   "default: the env's")
    p.add_argument("--reward-preset", choices=REWARD_PRESETS, default=None,
                   help="metric: every reward term but time off (the return is minus "
                   "time_cost_per_s times the time until every expected responder is "
                   "localised); --reward items apply on top")
    p.add_argument("--imitation-coef", type=float, default=0.0, metavar="X",
                   help="PPO with --imitate: add X times the cross-entropy to the "
                   "hand-written policy's labels (the DAgger dataset) to every update, X "
                   "falling linearly to 0 over the training (default 0: none)")
    p.add_argument("--critic-warmup", type=non_negative_int, default=0, metavar="K",
                   help="PPO: the first K updates fit only the value head (the actor "
                   "frozen; default 0)")
    p.add_argument("--learning-rate", type=float, default=None, metavar="LR",
                   help="PPO: the learning rate at the start, falling linearly to 0 "
                   "(default 3e-4)")
    p.add_argument("--ent-coef", type=float, default=None, metavar="X",
                   help="PPO: the entropy bonus (default 0.01)")
    p.add_argument("--gamma", type=float, default=None, metavar="X",
                   help="PPO: the discount, in (0, 1] (default 0.995)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--uavs", type=positive_int, default=None, metavar="N",
                   help="UAVs of a team (osa/Team-v0 only; default 2)")
    p.add_argument("--sweep", default=None, metavar="FILE",
                   help="train every task of a sweep file (TOML or JSON; docs/rl.md) into "
                   "MODEL/NAME, with MODEL/sweep.csv; the other options are the tasks' "
                   "defaults")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the --sweep tasks on this Dask scheduler "
                   "(e.g. tcp://10.0.0.5:8786); default: here, one after another")
    add_force_option(p)
    p.set_defaults(func=run)


def _fail(message: object) -> int:
    print(f"osa train: {message}", file=sys.stderr)
    return 2


def check_task(task: dict) -> str | None:
    """Why a training task (the command line's or a sweep's) cannot run, or None."""
    import gymnasium

    import envs  # noqa: F401  (registers the envs)
    from envs.gym.registration import TEAM_ENV_ID
    from envs.gym.trained import ALGOS

    env, algo = task["env"], task.get("algo", "PPO").upper()
    if env != TEAM_ENV_ID and env not in gymnasium.registry:
        known = sorted(k for k in gymnasium.registry if k.startswith("osa/"))
        return f"--env: unknown env {env!r}; choose from {', '.join([*known, TEAM_ENV_ID])}"
    if algo not in ALGOS:
        return f"--algo: unknown algorithm {task.get('algo')!r}; choose from {', '.join(ALGOS)}"
    kind = "search" if env.startswith("osa/Search") else "waypoint"
    if (algo == "DQN" and kind != "search") or (algo in ("SAC", "TD3") and kind != "waypoint"):
        return f"--algo {task.get('algo')} does not fit the action space of {env}"
    if env == TEAM_ENV_ID and algo != "PPO":
        return f"--algo {task.get('algo')}: {TEAM_ENV_ID} trains with PPO (parameter sharing)"
    if env == TEAM_ENV_ID and task.get("vec", "subproc") != "subproc":
        return (f"--vec {task['vec']}: not for {TEAM_ENV_ID} (its team copies step in "
                "this process through SuperSuit)")
    if env != TEAM_ENV_ID and task.get("uavs") not in (None, 1):
        return f"--uavs: only for {TEAM_ENV_ID} ({env} flies one UAV)"
    if task.get("scenario") is not None:
        from sim.scenario import ScenarioError, search_scenario

        try:
            search_scenario(task["scenario"])
        except ScenarioError as exc:
            return f"--scenario: {exc}"
    return None


# PPO's settings of a task: (the range a value must lie in, as text; its test)
PPO_RANGES: dict[str, tuple[str, object]] = {
    "n_steps": ("an integer >= 1", lambda x: isinstance(x, int) and x >= 1),
    "batch_size": ("an integer >= 1", lambda x: isinstance(x, int) and x >= 1),
    "n_epochs": ("an integer >= 1", lambda x: isinstance(x, int) and x >= 1),
    "gamma": ("a number in (0, 1]", lambda x: 0.0 < x <= 1.0),
    "gae_lambda": ("a number in (0, 1]", lambda x: 0.0 < x <= 1.0),
    "ent_coef": ("a number in [0, 1]", lambda x: 0.0 <= x <= 1.0),
    "learning_rate": ("a number in [0, 1]", lambda x: 0.0 <= x <= 1.0),
    "clip_range": ("a number > 0", lambda x: x > 0.0),
    "vf_coef": ("a number >= 0", lambda x: x >= 0.0),
    "max_grad_norm": ("a number > 0", lambda x: x > 0.0),
}
# what a training task holds beyond check_task's keys (the options of one training)
RECIPE_KEYS = ("curriculum", "imitate", "dagger", "imitation_coef", "critic_warmup",
               "reward", "reward_preset", "init")


def option(key: str) -> str:
    """The command-line option of a task key (``imitation_coef`` -> ``--imitation-coef``)."""
    return "--" + key.replace("_", "-")


def ppo_settings(task: dict) -> tuple[str | None, dict]:
    """The algorithm's keywords of a task: PPO's defaults (:data:`PPO_DEFAULTS`) with the
    task's ``ppo`` settings over them (``learning_rate`` the start of the linear
    schedule), each checked against :data:`PPO_RANGES`: (why they cannot be, or None;
    them)."""
    ppo, algo = task.get("ppo") or {}, task.get("algo", "PPO").upper()
    if algo != "PPO":
        return (f"{option(next(iter(ppo)))}: PPO only", {}) if ppo else (None, {})
    out = dict(PPO_DEFAULTS)
    for key, value in ppo.items():
        if key not in PPO_RANGES:
            return f"ppo: unknown PPO setting {key!r}; choose from {', '.join(PPO_RANGES)}", out
        what, ok = PPO_RANGES[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and ok(value)):
            return f"{option(key)}: expected {what}, got {value!r}", out
        out[key] = linear_schedule(float(value)) if key == "learning_rate" else value
    return None, out


def recipe_options(task: dict) -> tuple[str | None, dict]:
    """A task's options of ``osa/Search-v1`` to ``v3`` training (curriculum, imitation,
    DAgger, the imitation term, the critic warm-up) and PPO's settings checked: (why
    they cannot be, or None; the :class:`envs.rl.TrainSettings` keywords they give)."""
    env, algo = task["env"], task.get("algo", "PPO").upper()
    v1 = env in PLAN_ENVS
    kw: dict = {}
    curriculum = task.get("curriculum")
    if curriculum is not None:
        if not v1:
            return f"--curriculum: {env} has no curriculum level (osa/Search-v1 to v3)", kw
        try:
            lo, hi = (float(x) for x in (curriculum.split(":") if isinstance(curriculum, str)
                                         else curriculum))
        except (TypeError, ValueError):
            return f"--curriculum: expected FROM:TO, got {curriculum!r}", kw
        if not (0.0 <= lo <= 1.0 and 0.0 <= hi <= 1.0):
            return f"--curriculum: levels must be in [0, 1], got {curriculum!r}", kw
        kw["curriculum"] = (lo, hi)
    imitate, dagger = task.get("imitate") or 0, task.get("dagger") or 0
    coef, warmup = task.get("imitation_coef") or 0.0, task.get("critic_warmup") or 0
    if imitate and not v1:
        return (f"--imitate: {env} has nothing to imitate (the hand-written policy is "
                "osa/Search-v1's to v3's)"), kw
    if dagger and not imitate:
        return "--dagger: needs --imitate N (the episodes of each round)", kw
    kw["imitate_episodes"], kw["imitate_rounds"] = imitate, dagger
    if coef:
        if not (math.isfinite(coef) and coef > 0):
            return f"--imitation-coef: expected a number >= 0, got {coef!r}", kw
        if not imitate:
            return "--imitation-coef: needs --imitate N (the dataset it keeps the policy near)", kw
    if (coef or warmup) and algo != "PPO":
        return f"{'--imitation-coef' if coef else '--critic-warmup'}: PPO only", kw
    kw["imitation_coef"], kw["critic_warmup"] = coef, warmup
    problem, kw["algo_kwargs"] = ppo_settings(task)
    return problem, kw


def task_of_args(args: argparse.Namespace) -> dict:
    """The training task of the command line (None where an option is not given): what
    :func:`task_settings` reads, and a sweep's defaults."""
    reward = {}
    for item in args.reward:
        name, _, value = item.partition("=")
        reward[name] = value
    ppo = {k: v for k, v in (("learning_rate", args.learning_rate),
                             ("ent_coef", args.ent_coef), ("gamma", args.gamma))
           if v is not None}
    return {"env": args.env, "scenario": args.scenario, "uavs": args.uavs, "steps": args.steps,
            "seed": args.seed, "algo": args.algo, "envs": args.envs, "vec": args.vec,
            "eval_every": args.eval_every, "eval_worlds": args.eval_worlds, "ppo": ppo,
            "curriculum": args.curriculum, "imitate": args.imitate or None,
            "dagger": args.dagger or None, "imitation_coef": args.imitation_coef or None,
            "critic_warmup": args.critic_warmup or None, "reward": reward or None,
            "reward_preset": args.reward_preset, "init": args.init}


def task_settings(task: dict, *, checkpoint_every: int = 0, progress: bool = False):
    """The one reading of a training task (the command line's or a sweep's): (why it
    cannot run, as one line, or None; its :class:`envs.rl.TrainSettings`)."""
    from envs.gym.registration import TEAM_ENV_ID
    from envs.rl import TrainSettings

    problem = check_task(task)
    if problem:
        return problem, None
    problem, recipe = recipe_options(task)
    if problem:
        return problem, None
    env_id, algo = task["env"], task.get("algo", "PPO").upper()
    env_kwargs: dict = {}
    if task.get("scenario") is not None:
        env_kwargs["scenario"] = task["scenario"]
    if env_id == TEAM_ENV_ID:
        env_kwargs["uavs"] = task.get("uavs") or 2
    problem, weights = reward_weights(task.get("reward") or {}, env_id,
                                      task.get("reward_preset"))
    if problem:
        return problem, None
    env_kwargs.update(weights)
    if task.get("init") is not None:
        from envs.gym.trained import model_dir
        from envs.rl import check_init

        init = model_dir(task["init"]).resolve()
        problem = check_init(init, env_id, algo, env_kwargs)
        if problem:
            return f"--init: {problem}", None
        recipe["init"] = init
    return None, TrainSettings(
        env_id=env_id, env_kwargs=env_kwargs, steps=task["steps"], seed=task["seed"],
        algo=algo, n_envs=task.get("envs") or 1, vec=task.get("vec") or "subproc",
        eval_every=task.get("eval_every") or 0, eval_worlds=task.get("eval_worlds") or 20,
        checkpoint_every=checkpoint_every, progress=progress, **recipe)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return _fail("needs the optional 'rl' extra: pip install torch==2.13.0 (or the CPU "
                     "wheel: pip install torch --index-url "
                     "https://download.pytorch.org/whl/cpu), then pip install -e '.[rl]'")
    from envs.cli import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated
    from envs.rl import train

    task = task_of_args(args)
    if args.scheduler is not None and args.sweep is None:
        return _fail("--scheduler runs the tasks of a --sweep FILE")
    if args.sweep is not None:
        return run_sweep(args, task)
    problem, settings = task_settings(task, checkpoint_every=args.checkpoint_every,
                                      progress=not args.no_progress)
    if problem:
        return _fail(problem)
    from envs.commands._outputs import OutputRefusedError, claim_output_dir

    inputs = [args.scenario] if args.scenario and Path(args.scenario).is_file() else []
    if settings.init is not None:
        inputs.append(str(settings.init))
    try:  # the one output rule (docs/cli.md "Outputs"), before any training
        out = claim_output_dir(args.out, command="train", force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(exc)
    try:
        summary = train(settings, out)
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"osa train: interrupted: {_kept(out, settings.steps)}", file=sys.stderr)
        return EXIT_INTERRUPTED if isinstance(exc, KeyboardInterrupt) else EXIT_TERMINATED
    print(summary.text())
    return 0


def _kept(out, steps: int) -> str:
    """What an interrupted training left in ``out`` (envs.rl.train saves the model so far,
    marked ``"interrupted": true``)."""
    import json

    from envs.gym.trained import META_FILE

    try:
        meta = json.loads((out / META_FILE).read_text())
    except (OSError, ValueError):
        meta = {}
    if not (isinstance(meta, dict) and meta.get("interrupted")):
        return f"no model was saved in {out}"
    return (f"the model after {meta.get('steps')} of {steps} steps is in {out}, "
            f"marked \"interrupted\": true in its {META_FILE}")


def run_sweep(args: argparse.Namespace, defaults: dict) -> int:
    """``--sweep FILE``: every task of the file, here or on ``--scheduler``'s workers."""
    from pathlib import Path

    from envs.commands._outputs import OutputRefusedError, claim_output_dir, claim_output_file
    from envs.sweep import SweepError, read_sweep
    from envs.sweep import run_sweep as sweep

    try:
        tasks = read_sweep(args.sweep, {k: v for k, v in defaults.items() if v is not None})
    except SweepError as exc:
        return _fail(exc)
    inits = []
    for t in tasks:
        problem, settings = task_settings(t)
        if problem:
            return _fail(f"--sweep {args.sweep}: task {t['name']}: {problem.lstrip('-')}")
        if settings.init is not None:
            inits.append(str(settings.init))
    inputs = [args.sweep, *inits, *{t["scenario"] for t in tasks
                                    if t.get("scenario") and Path(t["scenario"]).exists()}]
    try:
        out = claim_output_dir(args.out, command="train", force=args.force, inputs=inputs)
        claim_output_file(out / "sweep.csv", force=True, inputs=inputs)
        for t in tasks:
            claim_output_dir(out / t["name"], command="train", force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(exc)
    client = None
    if args.scheduler is not None:
        from envs.commands.evaluate import connect

        try:
            client = connect(args.scheduler, 30.0)
        except ValueError as exc:
            return _fail(exc)
    where = f"on {args.scheduler}" if client is not None else "here, one after another"
    print(f"osa train: {len(tasks)} task{'s' * (len(tasks) != 1)} {where} -> {out}",
          file=sys.stderr)

    def done(r) -> None:
        print(f"  {r.name}: {r.row['steps']} steps in {r.wall_s / 60:.1f} min", file=sys.stderr)

    try:
        results = sweep(tasks, out, client, done)
    finally:
        if client is not None:
            client.close()
    print(f"{'task':<20} {'seed':>6} {'steps':>8} {'localised':>9} {'median time':>11} "
          f"{'return':>8}")
    for r in results:
        v = r.row
        loc = "" if v["localised"] is None else f"{100 * v['localised']:.0f} %"
        med = "" if v["median_time_s"] is None else f"{v['median_time_s']:.0f} s"
        ret = "" if v["mean_return"] is None else f"{v['mean_return']:.2f}"
        print(f"{r.name:<20} {v['seed']:>6} {v['steps']:>8} {loc:>9} {med:>11} {ret:>8}")
    print(f"summary: {out / 'sweep.csv'}")
    return 0
