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
import sys

from envs.commands._args import non_negative_int, positive_int
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


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a search policy with Stable-Baselines3 (needs the 'rl' extra)",
        description="Train a policy on a registered search environment and save it in the "
        "folder MODEL, which osa search --policy ppo:MODEL and osa evaluate load.",
    )
    p.add_argument("--env", default="osa/Search-v0", metavar="ID",
                   help="a registered env id: osa/Search-v0 (default) or osa/Waypoint-v0")
    p.add_argument("--scenario", default=None, metavar="S",
                   help="the env's search scenario (preset or .toml; default the env's)")
    p.add_argument("--steps", type=positive_int, default=200_000, metavar="N",
                   help="environment steps (decisions) to train for (default 200000)")
    p.add_argument("--seed", type=non_negative_int, default=0, metavar="N",
                   help="seed of the networks, the sampling and the envs' worlds (default 0)")
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
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_force_option(p)
    p.set_defaults(func=run)


def _fail(message: object) -> int:
    print(f"osa train: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return _fail("needs the optional 'rl' extra: pip install torch==2.13.0 (or the CPU "
                     "wheel: pip install torch --index-url "
                     "https://download.pytorch.org/whl/cpu), then pip install -e '.[rl]'")
    import gymnasium

    import envs  # noqa: F401  (registers the envs)
    from envs.gym.trained import ALGOS
    from envs.rl import TrainSettings, train

    if args.env not in gymnasium.registry:
        known = sorted(k for k in gymnasium.registry if k.startswith("osa/"))
        return _fail(f"--env: unknown env {args.env!r}; choose from {', '.join(known)}")
    if args.algo.upper() not in ALGOS:
        return _fail(f"--algo: unknown algorithm {args.algo!r}; choose from {', '.join(ALGOS)}")
    kind = "search" if args.env.startswith("osa/Search") else "waypoint"
    if (args.algo.upper() == "DQN" and kind != "search") or (
        args.algo.upper() in ("SAC", "TD3") and kind != "waypoint"
    ):
        return _fail(f"--algo {args.algo} does not fit the action space of {args.env}")
    env_kwargs = {}
    if args.scenario is not None:
        from sim.scenario import ScenarioError, search_scenario

        try:
            search_scenario(args.scenario)
        except ScenarioError as exc:
            return _fail(f"--scenario: {exc}")
        env_kwargs["scenario"] = args.scenario
    from envs.commands._outputs import OutputRefusedError, claim_output_dir

    inputs = [args.scenario] if args.scenario and Path(args.scenario).exists() else []
    try:  # the one output rule (docs/cli.md "Outputs"), before any training
        out = claim_output_dir(args.out, command="train", force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        return _fail(exc)
    settings = TrainSettings(env_id=args.env, env_kwargs=env_kwargs, steps=args.steps,
                             seed=args.seed, algo=args.algo.upper(), n_envs=args.envs,
                             vec=args.vec,
                             eval_every=args.eval_every, eval_worlds=args.eval_worlds,
                             checkpoint_every=args.checkpoint_every,
                             progress=not args.no_progress,
                             algo_kwargs=PPO_DEFAULTS if args.algo.upper() == "PPO" else {})
    summary = train(settings, out)
    print(summary.text())
    return 0
