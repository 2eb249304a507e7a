"""``osa/Waypoint-v0``: set the next waypoint every few seconds of a search flight."""

from __future__ import annotations

from envs.gym.base import SearchEnvBase


class WaypointEnv(SearchEnvBase):
    """
    ## Description

    The search of ``osa/Search-v0`` (a drone ranging to WiFi responders, the online
    estimator turning ranges from GNSS-known poses into position estimates), flown
    waypoint by waypoint: every ``decision_period_s`` seconds of simulated flight the
    agent sets where the drone goes next.

    ## Action Space

    ``Box(-1, 1, (3,), float32)``: the next waypoint relative to the drone. East and
    north times the reach of one decision (cruise speed x decision period, 40 m by
    default); the height above the terrain changed by up to 10 m, within the altitude
    band (20 m below to 25 m above the search height, at least 10 m). A waypoint beyond
    the area's margin plus the drone's braking distance at cruise speed (26 m at 8 m/s)
    moves to the nearest point inside it (the drone slides along the edge); the drone
    flies to it at cruise speed and on along the same line (no braking at each
    waypoint), routed inside a concave area; a request shorter than 1 m holds.

    ## Observation Space

    As ``osa/Search-v0``: a flat ``Dict`` of normalised ``float32`` vectors ``agent``
    (10), ``responders`` (``max_responders`` x 17), ``responder_mask``
    (``max_responders``), ``coverage`` (``coverage_cells``^2), from the autopilot and
    the estimator only (see ``envs.gym.search.SearchEnv`` and docs/rl.md).

    ## Rewards

    As ``osa/Search-v0`` (information gained as the reduction of 1/2 log det of the
    estimates' covariance, detection bonus, coverage of the area, minus time, minus
    ``leave_penalty`` per decision ending outside the area), the area term adding
    ``-leave_penalty`` times the share of the reach by which the requested waypoint lay
    outside the area less its margin and the braking distance (where it is moved to).

    ## Starting State

    On the ground at the scenario's take-off point, at rest; the world drawn from the
    env's ``np_random`` (a world seed of the ``seed_split`` split) or
    ``reset(options={"world_seed": N})``.

    ## Episode End

    Terminated when every detected responder (at least one, and as many as the scenario
    expects when it says) is localised by the estimator's own judgement; truncated at
    the flight-time budget. ``info["eval"]`` (truth, per BSSID ``detected`` and
    ``err_h_m``) and ``info["flight_time_s"]`` for evaluation.

    ## Arguments

    ```python
    gymnasium.make("osa/Waypoint-v0", scenario="search-random-los", seed_split="train",
                   decision_period_s=5.0, max_responders=3, coverage_cells=8,
                   information_weight=1.0, detection_bonus=1.0, coverage_bonus=5.0,
                   time_cost_per_s=0.01, leave_penalty=1.0,
                   mode="robust", render_mode=None, rerun_path=None)
    ```

    The same arguments as ``osa/Search-v0``.
    """

    kind = "waypoint"
