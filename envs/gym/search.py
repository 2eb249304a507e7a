"""``osa/Search-v0``: choose a manoeuvre every few seconds of a search flight."""

from __future__ import annotations

from envs.gym.base import SearchEnvBase


class SearchEnv(SearchEnvBase):
    """
    ## Description

    A drone searches an area for people carrying WiFi access points (FTM responders).
    Every ranging result from a GNSS-known pose is a virtual anchor for the online
    estimator (multilateration); the agent chooses, every ``decision_period_s`` seconds
    of simulated flight, which manoeuvre the drone flies next. Built on the closed loop
    of ``osa search`` (``envs.loop.ClosedLoop``): simulator -> estimator -> policy ->
    vehicle, so a trained agent is an ``osa search --policy ppo:MODEL`` policy.

    ## Action Space

    ``Discrete(7)``, the manoeuvres of ``planner.adaptive.Manoeuvres``:

    | action | manoeuvre |
    | --- | --- |
    | 0 | `sweep`: continue the search sweep (the lawnmower, resumed where it was left) |
    | 1 | `orbit-near`: level orbit of the target's estimate, 25 m radius |
    | 2 | `orbit-far`: level orbit of the target's estimate, 60 m radius |
    | 3 | `helix`: close helix about the estimate (the probe helix without one) |
    | 4 | `close-pass`: straight pass over the estimate along its least known axis |
    | 5 | `next-responder`: target the next detected responder not yet localised and fly to it |
    | 6 | `return`: fly back to the take-off point and hold |

    The close helix has an 18 m radius and climbs from 15 m below to 20 m above the
    search height; the probe helix climbs 20 m at about the range heard. The target is
    the most recently detected responder not yet localised (until `next-responder`
    changes it); orbits and passes use where it was heard while it has no estimate;
    without a target (nothing heard yet, or all localised) every action continues the
    sweep. Choosing the manoeuvre being
    flown again keeps flying it until its segment ends.

    ## Observation Space

    A flat ``Dict`` of normalised ``float32`` vectors, from the vehicle's autopilot and
    the estimator only (never the truth):

    - ``agent`` (10): position about the area's centre / half its extent (east, north),
      height above the terrain / search height - 1, velocity / cruise speed (3), flight
      time and time left / budget, distance inside the area's edge / half extent,
      whether the current segment has been flown;
    - ``responders`` (``max_responders`` x 17, slots in order of detection): has an
      estimate, estimate minus drone position (3), log10 sigma_H / 2, log10 sigma_z / 2,
      status one-hot (no estimate yet, tracking, converged, diverged), log counts of
      ranges heard and accepted, localised (``LocalisedRule``), where it was heard
      minus drone position (2), time since detection / budget, is the target;
    - ``responder_mask`` (``max_responders``): 1 for a filled slot;
    - ``coverage`` (``coverage_cells``^2, row-major from the south-west): the chance
      that a responder in that cell would have been heard by now (the simulator's
      link model as the planner knows it); 1 outside the area.

    ## Rewards

    Per decision: the information gained, i.e. the increase of ``sum_b 0.5 (log det P0 -
    log det P_b)`` over the detected responders (P_b the estimate's 3 x 3 position
    covariance, P0 = diag(100, 100, 30)^2 m^2 before an estimate: the reduction of 1/2
    log det of the covariance, the D-optimal objective of the CasADi planner);
    ``detection_bonus`` per responder heard for the first time; ``coverage_bonus`` times
    the share of the area newly covered (the mean of the coverage map: what the search
    learns before anything is heard, where the responder is not; 1 for the whole area);
    minus ``time_cost_per_s`` per second flown; minus ``leave_penalty`` per segment the
    loop refused because it left the area and per decision that ends with the vehicle
    outside it (a turn swung wide). ``info["reward_terms"]`` has the parts.

    ## Starting State

    On the ground at the scenario's take-off point, at rest, nothing heard. The world
    (responders at random places in the area, sensor noise) is drawn from the env's
    ``np_random``: a world seed of the ``seed_split`` split (``envs.seeds``), or
    ``reset(options={"world_seed": N})``.

    ## Episode End

    Terminated when every detected responder (at least one) is localised by the
    estimator's own judgement (``planner.observation.LocalisedRule``) and, when the scenario
    says how many to expect, that many are. Truncated when the flight-time budget is
    spent. ``info["eval"]`` carries the truth for evaluation only (per BSSID
    ``detected`` and ``err_h_m`` when an estimate exists), with ``info["flight_time_s"]``
    and ``info["world_seed"]``.

    ## Arguments

    ```python
    gymnasium.make("osa/Search-v0", scenario="search-random-los", seed_split="train",
                   decision_period_s=5.0, max_responders=3, coverage_cells=8,
                   information_weight=1.0, detection_bonus=1.0, coverage_bonus=5.0,
                   time_cost_per_s=0.01, leave_penalty=1.0,
                   mode="robust", render_mode=None, rerun_path=None)
    ```

    ``scenario``: a search preset name, a TOML path or a ``sim.Scenario`` (one agent);
    ``render_mode``: ``"rgb_array"`` (a map of the area, track, estimates and coverage)
    or ``"human"`` (a rerun recording: the ``.rrd`` file ``rerun_path``, which
    ``rerun FILE`` opens, else kept in memory as ``env.unwrapped.rerun_memory``);
    ``mode``: the estimator mode.
    """

    kind = "search"
