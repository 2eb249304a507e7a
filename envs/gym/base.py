"""The base of the search environments: the closed loop behind ``reset`` and ``step``.

:class:`SearchEnvBase` owns one :class:`envs.loop.ClosedLoop` per episode and a
:class:`envs.gym.interface.Pilot` (observation, action and reward mapping); its
``step`` is ``decide -> apply -> advance(decision period) -> observe`` with hooks
(``_compute_reward``, ``_info``) that subclasses may override, as gym-pybullet-drones'
base env does. The world of an episode is drawn from ``self.np_random`` (a world seed
of the ``seed_split`` split of :mod:`envs.seeds`), or given with
``reset(options={"world_seed": N})``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from envs.gym.interface import EnvConfig, Pilot
from envs.loop import DEFAULT_MODE, ClosedLoop, LoopConfig
from envs.seeds import SPLITS, check_seed
from sim.scenario import Scenario, search_scenario

DEFAULT_SCENARIO = "search-random-los"  # one open responder at a random place


def env_settings(render_mode: str | None, render_modes: list[str], seed_split: str,
                 mode: str, **env: Any) -> tuple[EnvConfig, LoopConfig]:
    """Check the arguments every search env takes; its :class:`EnvConfig` (``env``: the
    reward and observation settings) and the closed loop's :class:`LoopConfig`."""
    if render_mode is not None and render_mode not in render_modes:
        raise ValueError(f"render_mode must be one of {render_modes}")
    if seed_split not in SPLITS:
        raise ValueError(f"unknown seed split {seed_split!r}; choose from {list(SPLITS)}")
    config = EnvConfig(**env)
    return config, LoopConfig(mode=mode, decision_period_s=config.decision_period_s)


def warn_unobserved(scenario: Scenario, max_responders: int) -> None:
    """Gymnasium's warning when the scenario may hold more responders than the
    observation has slots: the first ``max_responders`` detected fill the slots, the
    others are flown and judged (episode end, ``info["eval"]``) but not observed."""
    s = scenario.search
    assert s is not None
    n = max(s.random_responders or len(scenario.world.responders),
            s.expected_responders or 0)
    if n > max_responders:
        gym.logger.warn(
            f"{scenario.name} has {n} responders and the observation {max_responders} "
            f"responder slots (max_responders): responders detected after the first "
            f"{max_responders} are not observed")


def draw_world_seed(options: dict | None, rng: np.random.Generator, seed_split: str) -> int:
    """The world of an episode: ``options["world_seed"]``, else one of ``seed_split``'s
    seeds drawn from the env's generator."""
    world_seed = (options or {}).get("world_seed")
    if world_seed is None:
        lo, hi = SPLITS[seed_split]
        world_seed = rng.integers(lo, hi)
    if isinstance(world_seed, np.integer):
        world_seed = int(world_seed)
    # a world seed as every command takes it (not 2.7 flown as world 2)
    return check_seed(world_seed)


def free_sibling(path: Path) -> Path:
    """The first of ``NAME-2.rrd``, ``NAME-3.rrd``, ... beside ``path`` not there yet."""
    k = 2
    while (p := path.with_name(f"{path.stem}-{k}{path.suffix}")).exists():
        k += 1
    return p


def outside_area(loop: ClosedLoop, obs, agent: int) -> float:
    """1 when the agent's autopilot position is outside the search area, else 0."""
    p = np.asarray(obs.agents[agent].position_enu_m[:2], dtype=float)[None, :]
    return 0.0 if loop.mission.area.contains(p, 0.0)[0] else 1.0


def loop_eval(loop: ClosedLoop) -> dict[str, dict]:
    """The truth, for evaluation only: per responder BSSID ``detected`` and, when an
    estimate exists, ``err_h_m`` (horizontal error against the truth, m)."""
    out: dict[str, dict] = {}
    for b in loop.truth:
        d: dict[str, Any] = {"detected": loop.detected_at(b) is not None}
        series = loop.series.get(b)
        if series and series[-1].err_h_m is not None:
            d["err_h_m"] = float(series[-1].err_h_m)
        out[b] = d
    return out


class SearchEnvBase(gym.Env):
    """Shared by ``osa/Search-v0`` and ``osa/Waypoint-v0`` (see their docstrings)."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array", "human"], "render_fps": 4}
    kind = "search"

    def __init__(
        self,
        scenario: str | Path | Scenario = DEFAULT_SCENARIO,
        *,
        render_mode: str | None = None,
        seed_split: str = "train",
        decision_period_s: float = 5.0,
        max_responders: int = 3,
        coverage_cells: int = 8,
        information_weight: float = 1.0,
        detection_bonus: float = 1.0,
        coverage_bonus: float = 5.0,
        time_cost_per_s: float = 0.01,
        leave_penalty: float = 1.0,
        mode: str = DEFAULT_MODE,
        rerun_path: str | None = None,
    ) -> None:
        self.config, self.loop_config = env_settings(
            render_mode, self.metadata["render_modes"], seed_split, mode,
            decision_period_s=decision_period_s, max_responders=max_responders,
            coverage_cells=coverage_cells, information_weight=information_weight,
            detection_bonus=detection_bonus,
            coverage_bonus=coverage_bonus, time_cost_per_s=time_cost_per_s,
            leave_penalty=leave_penalty)
        self.scenario = search_scenario(scenario)
        if len(self.scenario.agents) != 1:
            raise ValueError(f"{self.scenario.name} has {len(self.scenario.agents)} agents: "
                             "use envs.gym.multi.SearchParallelEnv")
        warn_unobserved(self.scenario, max_responders)
        self.render_mode = render_mode
        self.seed_split = seed_split
        self.pilot = self._make_pilot()
        self.observation_space = self.pilot.observation_space
        self.action_space = self.pilot.action_space
        self.rerun_path = rerun_path
        self.rerun_file: str | None = None  # the .rrd this env writes (human, rerun_path)
        self._rrd_taken = False  # rerun_path opened by this env or the one it copies
        self.loop: ClosedLoop | None = None
        self.world_seed: int | None = None
        self._rr = None

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.world_seed = draw_world_seed(options, self.np_random, self.seed_split)
        self.loop = ClosedLoop(self._episode_scenario(options), self.world_seed,
                               config=self.loop_config)
        self.pilot.reset(self.loop.mission)
        self._obs = self.loop.observe()
        enc, _ = self.pilot.observe(self._obs)
        self._last_terms: dict[str, float] = {}
        if self.render_mode == "human":
            self.render()
        return enc, self._info()

    def step(self, action):
        if self.loop is None:
            raise RuntimeError("call reset() before step()")
        loop = self.loop
        t0, refused0 = loop.t_s, loop.refused_plans
        decision = self.pilot.act(action, self._obs)
        loop.apply(decision)
        loop.advance(self.config.decision_period_s)
        self._obs = loop.observe()
        enc, changes = self.pilot.observe(self._obs)
        changes["dt_s"] = loop.t_s - t0
        changes["refused"] = loop.refused_plans - refused0
        changes["outside"] = self.pilot.area_penalty() + outside_area(loop, self._obs, 0)
        reward = self._compute_reward(changes)
        terminated = self.pilot.done(self._obs)
        truncated = not terminated and loop.budget_spent
        if self.render_mode == "human":
            self.render()
        return enc, reward, terminated, truncated, self._info()

    # ------------------------------------------------------------------ hooks
    def _make_pilot(self) -> Pilot:
        """The observation and action mapping (``osa/Search-v1`` passes its own actions)."""
        return Pilot(self.kind, self.config)

    def _episode_scenario(self, options: dict | None) -> Scenario:
        """The scenario of the next episode (``osa/Search-v1`` sets its curriculum level)."""
        return self.scenario

    def _compute_reward(self, changes: dict) -> float:
        c = self.config
        terms = {
            "information": c.information_weight * float(changes["information"]),
            "detection": c.detection_bonus * changes["detected"],
            "coverage": c.coverage_bonus * changes["covered"],
            "time": -c.time_cost_per_s * changes["dt_s"],
            "area": -c.leave_penalty * (changes["refused"] + changes["outside"]),
        }
        self._last_terms = terms
        return float(sum(terms.values()))

    def _info(self) -> dict:
        loop = self.loop
        assert loop is not None
        return {
            "flight_time_s": float(loop.t_s),
            "world_seed": self.world_seed,
            "localised": len(self.pilot.localised),
            "reward_terms": dict(self._last_terms),
            "eval": loop_eval(loop),
        }

    # ------------------------------------------------------------------ render
    def render(self):
        if self.render_mode is None or self.loop is None:
            return None
        from envs.gym.render import log_rerun, map_image

        if self.render_mode == "rgb_array":
            return map_image(self.loop, self.pilot)
        if self._rr is None:
            import rerun as rr

            self._rr = rr.RecordingStream("osa-testbed", recording_id="osa-env",
                                          send_properties=False)
            self._rr.set_log_time_enabled(False)
            # a file, else kept in memory (``self.rerun_memory``, e.g. for a notebook):
            # never a spawned viewer, which would open a network port
            if self.rerun_path:
                path = Path(self.rerun_path)
                if self._rrd_taken:  # a copy (or reopened): the file is another's
                    path = free_sibling(path)
                self._rr.save(str(path))
                self.rerun_file, self._rrd_taken = str(path), True
            else:
                self.rerun_memory = self._rr.memory_recording()
        log_rerun(self._rr, self.loop, self.pilot)
        return None

    def close(self) -> None:
        if self._rr is not None:
            self._rr.flush()
            self._rr = None
        super().close()

    @property
    def flight_time_s(self) -> float:
        return float(self.loop.t_s) if self.loop is not None else math.nan

    def __getstate__(self) -> dict:
        d = self.__dict__.copy()
        d["_rr"] = None  # a rerun stream does not pickle; it reopens on the next render
        d.pop("rerun_memory", None)
        return d

