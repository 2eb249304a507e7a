"""Gymnasium and PettingZoo environments of the search (docs/rl.md).

- ``osa/Search-v0`` (:class:`envs.gym.search.SearchEnv`): a discrete choice of
  manoeuvre per decision;
- ``osa/Waypoint-v0`` (:class:`envs.gym.waypoint.WaypointEnv`): a continuous
  ``Box(-1, 1)`` next waypoint;
- ``osa/Search-v1`` (:class:`envs.gym.plan.PlanEnv`): the whole search as the
  policy's choice (:class:`envs.gym.plan_actions.PlanActions`), domain randomisation
  from ``[randomise]`` and a curriculum level;
- ``osa/Search-v2`` (:class:`envs.gym.plan.PlannedEnv`): v1 with ``adaptive``'s
  receding-horizon plan about the target as one more action, ``planned``;
- ``osa/Search-v3`` (:class:`envs.gym.plan.EffortEnv`): v2 with how much each
  responder's sigma_H shrank over the last 20 s in the observation (when a responder
  is done is the policy's judgement);
- :class:`envs.gym.multi.SearchParallelEnv`: N agents (UAVs, optionally a ground
  agent) sharing one fused estimate (PettingZoo ``ParallelEnv``);
- :class:`envs.gym.trained.TrainedPolicy`: a model trained by ``osa train`` as a
  search policy (``ppo:PATH``).
"""

from __future__ import annotations

from envs.gym.registration import ENVS, register_envs

register_envs()

__all__ = ["ENVS", "register_envs"]
