"""A model trained by ``osa train`` as a search policy (``--policy ppo:PATH``).

``osa train -o MODEL`` writes a folder::

    MODEL/model.zip          the Stable-Baselines3 model (PPO unless --algo said otherwise)
    MODEL/vecnormalize.pkl   its VecNormalize statistics (observation normalisation)
    MODEL/osa-model.json     the env id, its settings and the algorithm
    MODEL/best/              the same three files for the best model on validation seeds
    MODEL/checkpoints/       periodic checkpoints (model and statistics)
    MODEL/progress.csv       the training log (TensorBoard event files beside it, if installed)
    MODEL/validation.json    the evaluations on validation worlds during training

:class:`TrainedPolicy` wraps the model, its statistics and the env's observation and
action mapping (:class:`envs.gym.interface.Pilot`) into a
:class:`planner.observation.Policy`: each ``decide`` encodes the observation exactly as the
env did in training, normalises it with the saved statistics, asks the network for its
deterministic action and turns it into a flight with the env's mapping. So a policy
trained in the env flies ``osa search`` and ``osa evaluate`` as it flew in training.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np

from envs.gym.interface import PLAN_KINDS, EnvConfig, Pilot
from planner.observation import Decision, Observation, SearchMission

MODEL_FILE, STATS_FILE, META_FILE = "model.zip", "vecnormalize.pkl", "osa-model.json"
ALGOS = ("PPO", "A2C", "DQN", "SAC", "TD3")


def model_dir(path: str | Path) -> Path:
    """The model folder of ``path`` (the folder itself, or its ``model.zip``)."""
    p = Path(path)
    return p.parent if p.name == MODEL_FILE else p


def _reason(exc: BaseException) -> str:
    """An exception as a short one-line reason."""
    text = " ".join(str(exc).split())[:200]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def algo_class(name: str):
    """A Stable-Baselines3 algorithm class by name (PPO, A2C, DQN, SAC, TD3)."""
    import stable_baselines3 as sb3

    key = name.upper()
    if key not in ALGOS:
        raise ValueError(f"unknown algorithm {name!r}; choose from {', '.join(ALGOS)}")
    return getattr(sb3, key)


class TrainedPolicy:
    """A policy trained in ``osa/Search-v0`` or ``osa/Waypoint-v0`` (see the module);
    :meth:`load` gives a :class:`TrainedTeamPolicy` for a model of ``osa/Team-v0``."""

    def __init__(self, model, stats, meta: dict, path: Path) -> None:
        self.model = model
        self.stats = stats
        self.meta = meta
        self.path = path
        self.name = f"ppo:{path}"
        cfg = dict(meta.get("config", {}))
        self.config = EnvConfig(**cfg)
        self.kind = meta["kind"]

    @classmethod
    def load(cls, path: str | Path) -> TrainedPolicy:
        """Load ``MODEL`` written by ``osa train`` (ValueError with the reason if not)."""
        d = model_dir(path)
        meta_p = d / META_FILE
        if not (d / MODEL_FILE).is_file() or not meta_p.is_file():
            raise ValueError(f"{path}: not a model written by osa train (no {MODEL_FILE} "
                             f"and {META_FILE} there)")
        try:
            meta = json.loads(meta_p.read_text())
            kind = meta["kind"]
            algo = meta.get("algo", "PPO")
        except (ValueError, KeyError) as exc:
            raise ValueError(f"{meta_p}: unreadable ({exc})") from None
        if kind not in ("search", "waypoint", *PLAN_KINDS, "team"):
            raise ValueError(f"{meta_p}: unknown env kind {kind!r}")
        try:
            import torch

            cls_ = algo_class(algo)
        except ImportError:
            raise ValueError("ppo:PATH needs the optional 'rl' extra (stable-baselines3, "
                             "torch): pip install -e '.[rl]'") from None
        if torch.get_num_threads() > 1:  # one decision at a time: threads only contend
            torch.set_num_threads(1)
        # a file cut short, another version's or garbage fails in many ways (BadZipFile,
        # EOFError, UnpicklingError, TypeError of an unknown setting): one line each
        try:
            model = cls_.load(str(d / MODEL_FILE), device="cpu")
        except Exception as exc:
            raise ValueError(f"{d / MODEL_FILE}: unreadable ({_reason(exc)})") from None
        stats = None
        if (d / STATS_FILE).is_file():
            try:
                with open(d / STATS_FILE, "rb") as f:
                    stats = pickle.load(f)  # a VecNormalize without its env
                stats.training = False
            except Exception as exc:
                raise ValueError(f"{d / STATS_FILE}: unreadable ({_reason(exc)})") from None
        if kind == "team":
            cls = TrainedTeamPolicy
        try:
            policy = cls(model, stats, meta, d)
            pilots = policy._pilots()
        except (TypeError, ValueError, KeyError) as exc:
            raise ValueError(f"{meta_p}: settings this version cannot fly "
                             f"({_reason(exc)})") from None
        # the network must take the observations and give the actions of the env that
        # osa-model.json names (not another env's, e.g. a json copied from elsewhere)
        for pilot in pilots[:1]:
            if (model.observation_space != pilot.observation_space
                    or model.action_space != pilot.action_space):
                raise ValueError(f"{d}: {MODEL_FILE} was not trained in the env of its "
                                 f"{META_FILE} ({meta.get('env_id', kind)}): its observation "
                                 "or action space differs")
            # the normalisation of another env or observation version (a copied file)
            # broke the first decision ("operands could not be broadcast")
            if (stats is not None
                    and getattr(stats, "observation_space", None) != pilot.observation_space):
                raise ValueError(f"{d / STATS_FILE}: statistics of another observation than "
                                 f"{MODEL_FILE}'s ({meta.get('env_id', kind)})")
        return policy

    def _pilots(self) -> list[Pilot]:
        """Fresh pilots of the env the model was trained in (its spaces)."""
        return [Pilot(self.kind, self.config)]

    def __reduce__(self):  # pickles as its path (to worker processes): loaded there again
        return (TrainedPolicy.load, (str(self.path),))

    # ------------------------------------------------------------------ Policy
    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        if mission.n_agents != 1:
            raise ValueError(f"{self.name} flies one agent; the mission has {mission.n_agents}")
        self.pilot = Pilot(self.kind, self.config)
        self.pilot.reset(mission)

    def decide(self, obs: Observation) -> Decision:
        enc, _ = self.pilot.observe(obs)
        if self.pilot.done(obs):
            return Decision(localised=self.pilot.localised, done=True,
                            note="every detected responder localised")
        return self.pilot.act(self.action(enc), obs)

    def action(self, encoded: dict):
        """The network's deterministic action for one encoded observation."""
        x = self.stats.normalize_obs(encoded) if self.stats is not None else encoded
        action, _ = self.model.predict(x, deterministic=True)
        return action


class TrainedTeamPolicy(TrainedPolicy):
    """A team policy trained in ``osa/Team-v0`` (``osa train --env osa/Team-v0``): every
    agent of the team runs the one shared network on its own observation (its own
    position first, the others' in ``others``), as in the env
    (:class:`envs.gym.multi.SearchParallelEnv`): each decision encodes every agent's
    observation, ends the search when the shared estimate is localised, else gives
    each agent its own waypoint. The mission must have the team's number of agents."""

    @property
    def team_size(self) -> int:
        return len(self.meta["agents"])

    def _pilots(self) -> list[Pilot]:
        from envs.gym.multi import team_pilots

        return team_pilots(self.meta["agents"], self.config)

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        from envs.gym.multi import team_pilots

        roles = self.meta["agents"]
        if mission.n_agents != len(roles):
            raise ValueError(f"{self.name} flies a team of {len(roles)}; the mission has "
                             f"{mission.n_agents} agents")
        self.pilots = team_pilots(roles, self.config)
        for i, p in enumerate(self.pilots):
            p.reset(mission, agent=i)

    def decide(self, obs: Observation) -> Decision:
        n = len(self.pilots)
        encoded = [p.observe(obs, tuple(a for j, a in enumerate(obs.agents) if j != i))[0]
                   for i, p in enumerate(self.pilots)]
        first = self.pilots[0]
        if first.done(obs):
            return Decision(localised=first.localised, done=True,
                            note="every detected responder localised")
        plans = {}
        for i in range(n):
            plans.update(self.pilots[i].act(self.action(encoded[i]), obs).plans)
        return Decision(plans=plans, localised=first.localised)
