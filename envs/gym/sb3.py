"""A Gymnasium vector env as a Stable-Baselines3 ``VecEnv`` (``osa train --vec batched``).

:class:`SB3VecEnv` adapts any ``gymnasium.vector.VectorEnv`` whose autoreset mode is
``same_step`` (the batched worlds of :mod:`envs.gym.batched` made with
``autoreset_mode="same_step"``) to SB3's interface, as SB3's ``DummyVecEnv`` presents
N single envs: ``dones = terminated | truncated``, one info dict per env with
``"TimeLimit.truncated"`` and, at an episode's end, ``"terminal_observation"`` (the
info being the last step's, the reset's in ``reset_infos``); ``seed()`` and
``set_options()`` apply at the next ``reset()``. ``VecMonitor``, ``VecNormalize`` and
the rest of SB3's wrappers go on top (tests/envs/gym/test_batched_train.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv


def unbatch_info(infos: dict, i: int) -> dict:
    """Env ``i``'s info from Gymnasium's vector form (``info[key]`` over the envs with its
    mask ``info["_" + key]``, nested dicts alike)."""
    out: dict = {}
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get("_" + key)
        if mask is not None and not mask[i]:
            continue
        out[key] = unbatch_info(value, i) if isinstance(value, dict) else value[i]
    return out


def _plain(v: Any) -> Any:
    """A NumPy scalar of an unbatched info as the Python value a single env gave."""
    return v.item() if isinstance(v, np.generic) else v


class SB3VecEnv(VecEnv):
    """SB3 ``VecEnv`` over a same-step Gymnasium vector env (see the module docstring)."""

    def __init__(self, venv: VectorEnv) -> None:
        if venv.metadata.get("autoreset_mode") != AutoresetMode.SAME_STEP:
            raise ValueError("SB3VecEnv needs a vector env with autoreset_mode='same_step'")
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space,
                         venv.single_action_space)
        self._actions: np.ndarray | None = None

    # ------------------------------------------------------------------ stepping
    def reset(self):
        opts = self._options
        if any(o != opts[0] for o in opts):
            raise ValueError("the batched worlds take one set of reset options for all")
        obs, infos = self.venv.reset(seed=list(self._seeds), options=opts[0] or None)
        self.reset_infos = [self._info(infos, i) for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, rew, term, trunc, infos = self.venv.step(self._actions)
        dones = term | trunc
        out = []
        final_info = infos.get("final_info")
        for i in range(self.num_envs):
            if dones[i]:
                info = {k: _plain(v) for k, v in unbatch_info(final_info, i).items()}
                info["terminal_observation"] = {k: v[i] for k, v in infos["final_obs"].items()} \
                    if isinstance(infos["final_obs"], dict) else infos["final_obs"][i]
                self.reset_infos[i] = self._info(infos, i)
            else:
                info = self._info(infos, i)
            info["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
            out.append(info)
        return obs, rew, dones, out

    def _info(self, infos: dict, i: int) -> dict:
        return {k: _plain(v) for k, v in unbatch_info(infos, i).items()
                if k not in ("final_obs", "final_info")}

    def close(self) -> None:
        self.venv.close()

    # ------------------------------------------------------------------ the envs
    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        values = self.venv.get_attr(attr_name)
        return [values[i] for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        values = list(self.venv.get_attr(attr_name))
        for i in self._get_indices(indices):
            values[i] = value
        self.venv.set_attr(attr_name, values)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs
                   ) -> list[Any]:
        worlds = getattr(self.venv, "worlds", None)
        if worlds is None:
            raise AttributeError(f"{type(self.venv).__name__} does not expose its envs")
        return [getattr(worlds[i], method_name)(*method_args, **method_kwargs)
                for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]  # the worlds are bare envs
