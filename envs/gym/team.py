"""``osa/Team-v0``: the PettingZoo env (:class:`envs.gym.multi.SearchParallelEnv`) as
a Stable-Baselines3 vector env for parameter-shared training (docs/rl.md, Teams).

Parameter sharing: every UAV of every team copy is one entry of one vector env, so one
network learns from every UAV's experience and every UAV runs it (its own observation,
with the others' positions, gives each its own decisions). The conversion is
SuperSuit's: ``pettingzoo_env_to_vec_env_v1`` makes the agents of one team the entries
of a Gymnasium vector env, ``concat_vec_envs_v1`` joins ``copies`` teams. SuperSuit's
own Stable-Baselines3 adapter (``base_class="stable_baselines3"``) is not used: it has
no ``seed`` (SB3 >= 2 seeds every vector env before training: AttributeError), and it
reports a time limit as a termination (PPO would not bootstrap the value at the
budget). :class:`TeamVecEnv` is that adapter, seeded, with ``TimeLimit.truncated``
(not :class:`envs.gym.sb3.SB3VecEnv`: SuperSuit's vector envs give a list of infos,
one per entry, the last observation already in them, not Gymnasium's batched infos).
The copies step in this process (SuperSuit's subprocess pool forks, which the
simulator's compiled loops and CasADi do not survive).

``osa/Team-v0`` is a name for ``osa train --env`` and the model's metadata, not a
Gymnasium registration (a PettingZoo env is not a ``gymnasium.Env``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from envs.gym.multi import SearchParallelEnv
from envs.gym.registration import TEAM_ENV_ID  # noqa: F401  (its name here too)


def make_team_env(kwargs: dict) -> SearchParallelEnv:
    """The PettingZoo env of ``osa/Team-v0`` (``uavs``, ``ground``, the env's arguments)."""
    return SearchParallelEnv(**kwargs)


def _vec_base():
    from stable_baselines3.common.vec_env import VecEnv

    return VecEnv


class TeamVecEnv(_vec_base()):
    """Stable-Baselines3's ``VecEnv`` over SuperSuit's vector env of ``copies`` teams:
    ``num_envs`` = copies x agents, entry ``k * agents + i`` is agent ``i`` of copy ``k``.
    Copy ``k`` is seeded ``seed + k`` at the first reset (SB3's ``seed``), then draws
    its worlds from its own generator; a team's episode ends for all its agents at once
    (auto-reset), the last observation in ``info["terminal_observation"]``."""

    def __init__(self, env_kwargs: dict, copies: int = 1) -> None:
        import supersuit as ss

        par = make_team_env(env_kwargs)
        self.agents = list(par.possible_agents)
        markov = ss.pettingzoo_env_to_vec_env_v1(par)
        self.venv = ss.concat_vec_envs_v1(markov, copies, num_cpus=0, base_class="gymnasium")
        super().__init__(self.venv.num_envs, self.venv.observation_space,
                         self.venv.action_space)
        self.render_mode = None
        self._actions: Any = None

    def reset(self):
        seed = self._seeds[0] if self._seeds and self._seeds[0] is not None else None
        obs, infos = self.venv.reset(seed=seed)
        self._reset_seeds()
        self.reset_infos = list(infos)
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, rewards, terms, truncs, infos = self.venv.step(self._actions)
        dones = np.logical_or(terms, truncs)
        infos = [dict(i) for i in infos]
        for k in np.flatnonzero(dones):
            infos[k]["TimeLimit.truncated"] = bool(truncs[k] and not terms[k])
        return obs, np.asarray(rewards, dtype=np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices=None) -> list:
        return [getattr(self, attr_name, None)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value, indices=None) -> None:
        raise AttributeError(f"TeamVecEnv: cannot set {attr_name}")

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list:
        raise AttributeError(f"TeamVecEnv: no per-entry method {method_name}")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))


def team_rollout(env: SearchParallelEnv, act: Callable[[dict], object], world_seed: int):
    """One episode of the team env on world ``world_seed``, every agent choosing its own
    action with ``act`` (observation -> action); an :class:`envs.rl.Episode` whose
    return is the team's (the mean over agents of each agent's return)."""
    from envs.rl import Episode

    obs, infos = env.reset(options={"world_seed": world_seed})
    ret, n = 0.0, 0
    term = False
    while env.agents:
        actions = {a: act(obs[a]) for a in env.agents}
        obs, rewards, terms, _truncs, infos = env.step(actions)
        ret += float(np.mean(list(rewards.values())))
        n += 1
        term = all(terms.values())
    info = next(iter(infos.values()))
    errs = [v["err_h_m"] for v in info["eval"].values() if "err_h_m" in v]
    return Episode(world_seed, ret, n, float(info["flight_time_s"]), bool(term),
                   float(np.mean(errs)) if errs else None)
