"""Batched worlds: N search worlds stepped in lockstep as one Gymnasium vector env.

``gymnasium.make_vec(ID, num_envs=N, vectorization_mode="vector_entry_point")`` of
every id of :data:`envs.gym.registration.ENVS` returns a :class:`BatchedSearchEnv`
(docs/rl.md, "Batched worlds"). It holds N worlds of the env class of that id (each its
own :class:`envs.loop.ClosedLoop` and :class:`envs.gym.interface.Pilot`: the action
mapping is the env's object, so a new env id joins by being registered), takes one
batched action, and returns the observations as one ``(N, ...)`` array per key, the
rewards, terminations and truncations as arrays and the infos in Gymnasium's vector
form (``info[key]`` an array over the worlds, ``info["_" + key]`` its mask).

Equal to N single envs seed for seed: ``reset(seed=s)`` seeds world i with ``s + i``
(as ``SyncVectorEnv``), and each world runs exactly the single env's
:meth:`envs.gym.base.SearchEnvBase.step`, so observations, rewards, terminations and
infos are those of N ``gymnasium.make(ID)`` envs bit for bit
(tests/envs/gym/test_batched.py).

Autoreset (Gymnasium 1.x, ``metadata["autoreset_mode"]``): ``next_step`` (the default,
as ``SyncVectorEnv``: the step after a world's episode ends resets it and returns its
first observation with reward 0) or ``same_step`` (the world resets within the step
that ends it; ``info["final_obs"]`` and ``info["final_info"]`` carry the last
observation and info: what SB3's ``VecEnv`` expects, :mod:`envs.gym.sb3`).

What is batched, and why not more: the observation, reward and flag buffers are filled
in place over the world axis and the wrappers' per-step checks of N single envs are
not paid; the simulator (vehicle, GNSS, FTM radio, phone records), the estimator and
the action mapping stay per world (each world's state is its own objects; their inner
loops are compiled already, ``sim/_kernels.py``). The profile in docs/rl.md shows that
no one part dominates a decision, which is why the batched env is not much faster per
CPU-second than one env (``python benchmarks/bench_batch.py``).
"""

from __future__ import annotations

import copy
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, iterate

from envs.gym.base import SearchEnvBase

AUTORESET_MODES = {"next_step": AutoresetMode.NEXT_STEP, "same_step": AutoresetMode.SAME_STEP}


def parse_autoreset(mode: str | AutoresetMode) -> AutoresetMode:
    """``"next_step"`` / ``"same_step"`` (or Gymnasium's ``AutoresetMode`` and its values
    ``"NextStep"`` / ``"SameStep"``)."""
    for name, m in AUTORESET_MODES.items():
        if mode in (name, m, m.value):
            return m
    raise ValueError(f"autoreset_mode must be one of {list(AUTORESET_MODES)}, not {mode!r}")


def load_env_class(entry_point: str | type[SearchEnvBase]) -> type[SearchEnvBase]:
    """The single-world env class of an entry point (``"module:Class"`` or the class)."""
    cls = gymnasium.envs.registration.load_env_creator(entry_point) \
        if isinstance(entry_point, str) else entry_point
    if not (isinstance(cls, type) and issubclass(cls, SearchEnvBase)):
        raise ValueError(f"{entry_point!r} is not a search env class (SearchEnvBase)")
    return cls


class BatchedSearchEnv(VectorEnv):
    """N worlds of one search env class stepped in lockstep (see the module docstring).

    ``env_class``: the single-world class (or its ``"module:Class"`` entry point);
    ``autoreset_mode``: ``"next_step"`` (default) or ``"same_step"``;
    ``max_episode_steps``: truncate each world's episode after this many decisions (as
    ``gymnasium.make(ID, max_episode_steps=K)``); every other keyword goes to each
    world (``scenario``, ``seed_split``, ``decision_period_s``, ...).
    """

    def __init__(self, num_envs: int, *, env_class: str | type[SearchEnvBase],
                 autoreset_mode: str | AutoresetMode = "next_step",
                 max_episode_steps: int | None = None, **env_kwargs: Any) -> None:
        if not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, not {num_envs!r}")
        mode = parse_autoreset(autoreset_mode)
        if max_episode_steps is not None and max_episode_steps < 1:
            raise ValueError("max_episode_steps must be >= 1")
        if env_kwargs.get("render_mode") is not None:
            raise ValueError("the batched env does not render; render a single env")
        cls = load_env_class(env_class)
        self.worlds: list[SearchEnvBase] = [cls(**env_kwargs) for _ in range(int(num_envs))]
        self.num_envs = len(self.worlds)
        self.autoreset_mode = mode
        self.max_episode_steps = max_episode_steps
        self.metadata = {**cls.metadata, "render_modes": [], "autoreset_mode": mode}
        self.render_mode = None
        first = self.worlds[0]
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        # batch_space seeds the space it is given from the OS when it is not seeded yet:
        # given copies, the single spaces stay unseeded (as a single env's), so what is
        # saved with them (SB3's VecNormalize) does not depend on the machine's entropy
        self.observation_space = batch_space(copy.deepcopy(self.single_observation_space),
                                             self.num_envs)
        self.action_space = batch_space(copy.deepcopy(self.single_action_space), self.num_envs)
        self._keys = list(self.single_observation_space.spaces)
        self._autoreset = np.zeros(self.num_envs, dtype=np.bool_)
        self._elapsed = np.zeros(self.num_envs, dtype=np.int64)
        self._ready = False

    # ------------------------------------------------------------------ buffers
    def _buffers(self):
        n = self.num_envs
        obs = {k: np.empty((n, *s.shape), dtype=s.dtype)
               for k, s in self.single_observation_space.spaces.items()}
        return obs, np.zeros(n), np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)

    def _put(self, obs: dict, i: int, enc: dict) -> None:
        for k in self._keys:
            obs[k][i] = enc[k]

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict | None = None):
        """Reset every world (world i seeded ``seed + i``), or those of
        ``options["reset_mask"]``; ``options`` goes to each world's reset."""
        n = self.num_envs
        if seed is None:
            seeds: list = [None] * n
        elif isinstance(seed, int | np.integer):
            super().reset(seed=int(seed))
            seeds = [int(seed) + i for i in range(n)]
        else:
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"{len(seeds)} seeds for {n} worlds")
        options = dict(options) if options else {}
        mask = options.pop("reset_mask", None)
        if mask is None:
            mask = np.ones(n, dtype=np.bool_)
        elif not self._ready:
            raise ValueError("the first reset resets every world: no reset_mask")
        else:
            mask = np.asarray(mask, dtype=np.bool_).reshape(n)
        obs, _, _, _ = self._buffers()
        if self._ready:
            for k in self._keys:
                obs[k][:] = self._obs[k]
        infos: dict = {}
        for i in np.flatnonzero(mask):
            enc, info = self.worlds[i].reset(seed=seeds[i], options=options or None)
            self._put(obs, i, enc)
            infos = self._add_info(infos, info, i)
        self._autoreset[mask] = False
        self._elapsed[mask] = 0
        self._obs, self._ready = obs, True
        return self._copy(obs), infos

    def step(self, actions):
        """One decision in every world (in lockstep); see the module docstring for the
        autoreset."""
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        acts = list(iterate(self.action_space, actions))  # any action space, as SyncVectorEnv
        if len(acts) != self.num_envs:
            raise ValueError(f"{len(acts)} actions for {self.num_envs} worlds")
        obs, rew, term, trunc = self._buffers()
        infos: dict = {}
        same = self.autoreset_mode == AutoresetMode.SAME_STEP
        for i, w in enumerate(self.worlds):
            if self._autoreset[i]:  # next-step autoreset: this step resets the world
                enc, info = w.reset()
                self._elapsed[i] = 0
            else:
                enc, r, te, tr, info = w.step(acts[i])
                self._elapsed[i] += 1
                limit = self.max_episode_steps
                if limit is not None and self._elapsed[i] >= limit:
                    tr = True  # as gymnasium's TimeLimit
                rew[i], term[i], trunc[i] = r, te, tr
                if same and (te or tr):
                    infos = self._add_info(infos, {"final_obs": enc, "final_info": info}, i)
                    enc, info = w.reset()
                    self._elapsed[i] = 0
            self._put(obs, i, enc)
            infos = self._add_info(infos, info, i)
        self._autoreset = (term | trunc) if not same else np.zeros(self.num_envs, np.bool_)
        self._obs = obs
        return self._copy(obs), rew, term, trunc, infos

    @staticmethod
    def _copy(obs: dict) -> dict:
        return {k: v.copy() for k, v in obs.items()}

    # ------------------------------------------------------------------ the worlds
    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """``name`` of every world (called with the arguments when it is a method)."""
        out = []
        for w in self.worlds:
            v = getattr(w, name)
            out.append(v(*args, **kwargs) if callable(v) else v)
        return tuple(out)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        return tuple(getattr(w, name) for w in self.worlds)

    def set_attr(self, name: str, values: list[Any] | tuple[Any, ...] | Any) -> None:
        if not isinstance(values, list | tuple):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"{len(values)} values for {self.num_envs} worlds")
        for w, v in zip(self.worlds, values, strict=True):
            setattr(w, name, v)

    def close_extras(self, **kwargs: Any) -> None:
        for w in self.worlds:
            w.close()


def make_batched(entry_point: str, num_envs: int, **kwargs: Any) -> BatchedSearchEnv:
    """The ``vector_entry_point`` of a registered search env (bound to its entry point
    by :func:`envs.gym.registration.register_envs`)."""
    return BatchedSearchEnv(num_envs, env_class=entry_point, **kwargs)
