"""The one place where the environments are registered with Gymnasium."""

from __future__ import annotations

import functools

ENVS: dict[str, str] = {
    "osa/Search-v0": "envs.gym.search:SearchEnv",
    "osa/Waypoint-v0": "envs.gym.waypoint:WaypointEnv",
    "osa/Search-v1": "envs.gym.plan:PlanEnv",
    "osa/Search-v2": "envs.gym.plan:PlannedEnv",
    "osa/Search-v3": "envs.gym.plan:EffortEnv",
}
# the PettingZoo team env's name at the CLI (not a Gymnasium id: envs/gym/team.py)
TEAM_ENV_ID = "osa/Team-v0"


def register_envs() -> None:
    """Register every id of :data:`ENVS` (again is harmless: nothing changes), each with
    the batched worlds of :mod:`envs.gym.batched` as its ``vector_entry_point``."""
    import gymnasium

    for env_id, entry in ENVS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry, disable_env_checker=False,
                               vector_entry_point=functools.partial(_batched, entry))


def _batched(entry_point: str, num_envs: int, **kwargs):
    """``make_vec(..., vectorization_mode="vector_entry_point")`` of a registered id
    (imported here, not at registration: ``import envs`` stays light)."""
    from envs.gym.batched import make_batched

    return make_batched(entry_point, num_envs, **kwargs)
