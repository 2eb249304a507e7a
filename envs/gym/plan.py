"""``osa/Search-v1``: the whole search is the policy's choice; ``osa/Search-v2``: the
same with ``adaptive``'s receding-horizon plan as one more action; ``osa/Search-v3``: v2
with how much each responder's sigma_H shrank lately in the observation."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

from envs.gym.base import DEFAULT_SCENARIO, SearchEnvBase
from envs.gym.interface import PLAN_KINDS, Pilot
from envs.gym.plan_actions import PlanActions
from envs.loop import DEFAULT_MODE
from sim.scenario import Scenario


class PlanEnv(SearchEnvBase):
    """
    ## Description

    The search of ``osa/Search-v0`` (a drone ranging to WiFi responders, the online
    estimator turning ranges from GNSS-known poses into estimates), with nothing forced:
    where to look before anything is heard (a sector of the area or a pattern over all
    of it), which responder to work on, which manoeuvre flies about it and when it is
    done are the policy's choices (:class:`envs.gym.plan_actions.PlanActions`). The
    scenario's ``[randomise]`` ranges (domain randomisation, drawn from the world's
    seed) are scaled by a curriculum level: :meth:`set_level` or
    ``reset(options={"level": x})``.

    ## Action Space

    ``Discrete(sectors^2 + 8)`` (17 with the default 3 x 3 sectors): ``sector-i``
    (the lawnmower of sector i, row-major from the south-west), ``lawnmower`` and
    ``expanding-square`` over the whole area (resumed where they were left), ``helix``
    (probe helix before an estimate, close helix after), ``orbit-near``, ``orbit-far``,
    ``close-pass`` about the target, ``next`` (the next responder heard and not
    localised becomes the target: fly to it), ``done`` (set the target aside). See
    :class:`envs.gym.plan_actions.PlanActions`.

    ## Observation Space

    The ``Dict`` of ``osa/Search-v0`` (``agent``, ``responders`` slots with estimate,
    sigmas, status, heard, localised, target; ``responder_mask``; ``coverage`` map),
    from the autopilot and the estimator only, plus ``sectors`` (the mean coverage of
    each sector), ``set_aside`` (per slot: set aside with ``done``) and ``flying`` (a
    one-hot of the action whose segment is being flown).

    ## Rewards

    As ``osa/Search-v0`` (information gained, detection bonus, coverage of the area,
    minus time, minus leaving the area) plus ``localised_bonus`` per responder newly
    localised by the estimator's judgement.

    ## Starting State, Episode End

    As ``osa/Search-v0``: on the ground at the take-off point; terminated when every
    responder heard (at least one, as many as the scenario expects) is localised,
    truncated at the budget; ``info["eval"]`` has the truth for evaluation only, and
    ``info["level"]`` the curriculum level.

    ## Arguments

    ```python
    gymnasium.make("osa/Search-v1", scenario="search-random-los", seed_split="train",
                   actions=None, sectors=3, level=1.0, localised_bonus=5.0,
                   decision_period_s=5.0, max_responders=5, coverage_cells=6,
                   information_weight=1.0, detection_bonus=1.0, coverage_bonus=5.0,
                   time_cost_per_s=0.01, leave_penalty=1.0, mode="robust", render_mode=None,
                   rerun_path=None)
    ```

    ``actions``: a :class:`PlanActions` (else one with ``sectors``); ``level``: the
    curriculum level in [0, 1] (the share of each ``[randomise]`` range in use).
    """

    kind = "plan"

    def __init__(self, scenario: str | Path | Scenario = DEFAULT_SCENARIO, *,
                 actions: PlanActions | None = None, sectors: int = 3, level: float = 1.0,
                 localised_bonus: float = 5.0, max_responders: int = 5,
                 coverage_cells: int = 6, mode: str = DEFAULT_MODE, **kwargs) -> None:
        self._actions_arg = actions
        self._sectors = sectors
        super().__init__(scenario, max_responders=max_responders,
                         coverage_cells=coverage_cells, mode=mode, **kwargs)
        if not (math.isfinite(localised_bonus) and localised_bonus >= 0):
            raise ValueError("localised_bonus must be >= 0")
        self.localised_bonus = float(localised_bonus)
        self.level = 1.0
        self.set_level(level)

    def _make_pilot(self) -> Pilot:
        # the given actions are a setting: each env flies its own copy (one object given
        # to make_vec or to several makes was every world's: their state is per episode)
        actions = (copy.deepcopy(self._actions_arg) if self._actions_arg is not None
                   else PlanActions(self.config, self._sectors, **PLAN_KINDS[self.kind]))
        k, n = actions.cfg.max_responders, self.config.max_responders
        if k != n:  # set_aside (and sigma_shrink) per responder slot of the observation
            raise ValueError(f"actions observe {k} responder slots, the env {n} "
                             "(max_responders): give both the same")
        return Pilot(self.kind, self.config, actions=actions)

    # ------------------------------------------------------------------ curriculum
    def set_level(self, level: float) -> None:
        """The curriculum level in [0, 1] from the next episode on: the share of each
        ``[randomise]`` range in use (0: every world at the ranges' low ends)."""
        level = float(level)
        if not (math.isfinite(level) and 0.0 <= level <= 1.0):
            raise ValueError(f"level {level!r} is not in [0, 1]")
        self.level = level

    def _episode_scenario(self, options: dict | None) -> Scenario:
        if options and options.get("level") is not None:
            self.set_level(options["level"])
        rnd = self.scenario.randomise
        if rnd is None or rnd.level == self.level:
            return self.scenario
        return dataclasses.replace(self.scenario,
                                   randomise=dataclasses.replace(rnd, level=self.level))

    # ------------------------------------------------------------------ hooks
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        out = super().reset(seed=seed, options=options)
        self._n_localised = 0
        return out

    def _compute_reward(self, changes: dict) -> float:
        reward = super()._compute_reward(changes)
        n = len(self.pilot.localised)
        new = n - self._n_localised
        self._n_localised = n
        self._last_terms["localised"] = self.localised_bonus * new
        return reward + self.localised_bonus * new

    def _info(self) -> dict:
        info = super()._info()
        info["level"] = self.level
        return info


class PlannedEnv(PlanEnv):
    """``osa/Search-v2``: ``osa/Search-v1`` (its observation, rewards, episode end and
    arguments) with one more action after v1's, ``planned``: ``adaptive``'s
    receding-horizon CasADi plan about the target's estimate, solved again every 20 s
    of flight while it stays chosen (the probe helix while the target has no usable
    estimate); ``Discrete(sectors^2 + 9)``, 18 by default. See
    :class:`envs.gym.plan_actions.PlanActions` (``planned=True``)."""

    kind = "plan-v2"


class EffortEnv(PlannedEnv):
    """``osa/Search-v3``: ``osa/Search-v2`` (its actions, rewards, episode end and
    arguments) with one more observation key, ``sigma_shrink``: per responder slot, how
    much its sigma_H shrank over the last 20 s of flight (``1 - now / then``, in [0, 1]; 1
    before it has a sigma_H that old). When a responder is done, that is, when what is
    flown about it no longer improves its estimate, becomes the policy's judgement
    (``done`` sets it aside and the estimator's plateau judgement completes meanwhile):
    how to split the effort between responders. See
    :class:`envs.gym.plan_actions.PlanActions` (``shrink=True``)."""

    kind = "plan-v3"
