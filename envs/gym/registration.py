"""The one place where the environments are registered with Gymnasium."""

from __future__ import annotations

ENVS: dict[str, str] = {
    "osa/Search-v0": "envs.gym.search:SearchEnv",
    "osa/Waypoint-v0": "envs.gym.waypoint:WaypointEnv",
    "osa/Search-v1": "envs.gym.plan:PlanEnv",
}


def register_envs() -> None:
    """Register every id of :data:`ENVS` (again is harmless: nothing changes)."""
    import gymnasium

    for env_id, entry in ENVS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry, disable_env_checker=False)
