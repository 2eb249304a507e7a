"""The actions of ``osa/Search-v1`` and ``osa/Search-v2``: the whole search as the
policy's choice.

:class:`PlanActions` maps a ``Discrete`` action to a :class:`planner.observation.Decision`
(as :class:`envs.gym.interface.ManoeuvreActions` does for ``osa/Search-v0``), but
nothing is forced: where to look before anything is heard (a sector of the area, or a
pattern over the whole area), which responder to work on, which manoeuvre flies about
it and when it is done are all actions. It also adds what the policy needs to know of
its own choices to the observation (:attr:`PlanActions.obs_space`): the coverage of each
sector, the responders set aside, and what is being flown.

:func:`plan_heuristic` is the hand-written policy in these actions (search the area
with the lawnmower, probe a responder heard, orbit it while its estimate is wide,
finish with the close helix, set it aside once localised): the yardstick a trained
policy is compared with and the floor a random one falls below. ``osa/Search-v2``
(``PlanActions(config, planned=True)``) adds the ``planned`` action, ``adaptive``'s
receding-horizon plan about the target, and :func:`plan_heuristic` then flies it where
v1's flies the near orbit: ``adaptive`` in v2's actions. ``osa/Search-v3``
(``PlanActions(config, planned=True, shrink=True)``) adds to the observation how much each
responder's sigma_H shrank over the last :data:`SHRINK_WINDOW_S`, so that when a
responder is done (its estimate gains nothing more from what is flown) is the policy's
judgement; :func:`plan_heuristic` then sets a target aside as soon as its close helix
gains nothing, and the estimator's plateau judgement (:class:`planner.observation.LocalisedRule`)
completes while it flies to the next.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from envs.gym.interface import discrete_action, responder_manoeuvre
from estimator.records import Trajectory
from planner.adaptive import Manoeuvres, ResponderPlanner
from planner.area import SearchArea
from planner.coverage import Sweep, search_spacing_m
from planner.observation import AgentView, Decision, Observation, SearchMission

# manoeuvres about the target responder, then the two pointer actions
TARGET_ACTIONS = ("helix", "orbit-near", "orbit-far", "close-pass")
PATTERNS = ("lawnmower", "expanding-square")
POINTER_ACTIONS = ("next", "done")
PLANNED = "planned"  # osa/Search-v2's action after v1's
SHRINK_WINDOW_S = 20.0  # osa/Search-v3's sigma_shrink: over this much of the past


class PlanActions:
    """``osa/Search-v1``: ``Discrete(sectors^2 + 8)``.

    - ``sector-i`` (``i = 0 ... sectors^2 - 1``, row-major from the south-west over the
      area's bounding box): fly the lawnmower of that sector (tracks half a sector
      apart, or the search spacing if closer), resumed where it was left, reversed at
      its end;
    - ``lawnmower``: the lawnmower over the whole area (the search spacing), resumed;
    - ``expanding-square``: the IAMSAR expanding square from the area's centroid, resumed;
    - ``helix``: about the target, the probe helix where it was heard while it has no
      estimate, the close helix (18 m, through the altitude band) once it has one;
    - ``orbit-near`` / ``orbit-far``: a level orbit of the target (25 / 60 m);
    - ``close-pass``: a straight pass over the target along its least known axis;
    - ``next``: make the next responder heard, not localised and not set aside the
      target, and fly to it;
    - ``done``: set the target aside (it is no longer the target, ``next`` skips it
      until every other responder heard is localised or set aside); the vehicle flies
      on what it flies;
    - ``planned`` (``osa/Search-v2``, ``planned=True``: ``Discrete(sectors^2 + 9)``, v1's
      actions then this one): ``adaptive``'s receding-horizon CasADi plan about the
      target's estimate (:class:`planner.adaptive.ResponderPlanner`), solved again every
      ``replan_s`` (20 s) of flight while it stays chosen, or when its segment is flown;
      the probe helix while the target has no usable estimate, or when the planner
      refuses (as ``adaptive``).

    ``shrink=True`` (``osa/Search-v3``, with ``planned=True``) adds the observation key
    ``sigma_shrink``: per slot, ``1 - sigma_H(t) / sigma_H(t - 20 s)`` (clipped to [0, 1];
    1 while the responder has no sigma_H that old: nothing is settled yet), from the
    estimates the policy has seen (:class:`planner.observation.LocalisedTracker`).

    The target (the slot feature ``target`` of the observation) is chosen by the policy
    with ``next``; when there is none and a responder heard is neither localised nor set
    aside, it is the most recently heard such responder. A localised target stays the
    target until ``next`` or ``done``. A target manoeuvre without a target (and
    ``done``) flies on what is being flown (no new segment; before the first segment:
    climb to the search height where the vehicle is and hold). Choosing what is being
    flown again keeps flying it until its segment is done, then starts it anew (a
    pattern resumes, a manoeuvre re-centres on the current estimate).
    """

    kind = "plan"

    def __init__(self, config, sectors: int = 3, planned: bool = False,
                 shrink: bool = False) -> None:
        if not 1 <= int(sectors) <= 6:
            raise ValueError("sectors must be in [1, 6]")
        self.cfg = config
        self.sectors = int(sectors)
        self.planned = bool(planned)
        self.shrink = bool(shrink)
        self.names = (*(f"sector-{i}" for i in range(self.sectors**2)), *PATTERNS,
                      *TARGET_ACTIONS, *POINTER_ACTIONS, *((PLANNED,) if planned else ()))
        # the adaptive policy's planner (built once per process and configuration)
        self.optimal = (ResponderPlanner(config.adaptive, own_warm_start=True)
                        if planned else None)
        self.space = spaces.Discrete(len(self.names))
        k = config.max_responders
        f32 = np.float32
        self.obs_space = {
            "sectors": spaces.Box(0.0, 1.0, (self.sectors**2,), f32),
            "set_aside": spaces.Box(0.0, 1.0, (k,), f32),
            "flying": spaces.Box(0.0, 1.0, (len(self.names),), f32),
        }
        if self.shrink:
            self.obs_space["sigma_shrink"] = spaces.Box(0.0, 1.0, (k,), f32)

    def index(self, name: str) -> int:
        return self.names.index(name)

    # ------------------------------------------------------------------ episode
    def reset(self, mission: SearchMission, encoder) -> None:
        self.mission = mission
        self.enc = encoder
        self.man = Manoeuvres(mission, self.cfg.adaptive)
        if self.optimal is not None:
            self.optimal.reset(mission, self.man)
        self.planned_at = -np.inf  # when the planned action last solved
        spacing = search_spacing_m(mission, self.cfg.adaptive.detect_probability)
        area = mission.area
        v = area.vertices
        lo, hi = v.min(axis=0), v.max(axis=0)
        s = self.sectors
        size = (hi - lo) / s
        self.routes: list[Sweep] = []
        for i in range(s * s):
            row, col = divmod(i, s)
            x0, y0 = lo + size * np.array([col, row])
            x1, y1 = x0 + size[0], y0 + size[1]
            sub = SearchArea(((x0, y0), (x1, y0), (x1, y1), (x0, y1)), 0.0)
            wps = sub.sweep(min(spacing, 0.5 * float(size.min())), 0.0,
                            start=mission.start_enu_m)
            inside = [area.pull_inside(np.asarray(w)) for w in wps]
            self.routes.append(Sweep.through(mission, area.join(inside)))
        self.routes.append(Sweep(mission, spacing))
        datum = area.reachable_center(mission.start_enu_m)
        self.routes.append(Sweep.through(mission, area.expanding_square(datum, spacing)))
        cells = encoder.cells
        col = np.clip(((cells[:, 0] - lo[0]) / size[0]).astype(int), 0, s - 1)
        row = np.clip(((cells[:, 1] - lo[1]) / size[1]).astype(int), 0, s - 1)
        self.cell_sector = row * s + col
        self.current: tuple[int, str | None] | None = None  # (action, target)
        self.set_aside: set[str] = set()

    # ------------------------------------------------------------------ observation
    def observe(self, obs: Observation) -> dict:
        """The extra observation keys (:attr:`obs_space`)."""
        enc = self.enc
        cov = np.asarray(enc.coverage, dtype=float).copy()
        cov[~enc.cell_inside] = np.nan
        n = self.sectors**2
        sectors = np.ones(n)
        for i in range(n):
            c = cov[self.cell_sector == i]
            c = c[np.isfinite(c)]
            if len(c):
                sectors[i] = float(c.mean())
        aside = np.zeros(self.cfg.max_responders)
        for i, b in enumerate(enc.slots[: self.cfg.max_responders]):
            aside[i] = float(b in self.set_aside)
        flying = np.zeros(len(self.names))
        if self.current is not None and self.current[0] >= 0:
            flying[self.current[0]] = 1.0
        f32 = np.float32
        out = {"sectors": np.clip(sectors, 0.0, 1.0).astype(f32), "set_aside": aside.astype(f32),
               "flying": flying.astype(f32)}
        if self.shrink:
            shrink = np.zeros(self.cfg.max_responders)
            for i, b in enumerate(enc.slots[: self.cfg.max_responders]):
                shrink[i] = sigma_shrink(enc.tracker.sigma.get(b, []), obs.t_s)
            out["sigma_shrink"] = shrink.astype(f32)
        return out

    # ------------------------------------------------------------------ decide
    def _pending(self, obs: Observation, skip: set[str]) -> list[str]:
        loc = self.enc.tracker.localised
        return [r.bssid for r in obs.responders if r.bssid not in loc and r.bssid not in skip]

    def _ensure_target(self, obs: Observation) -> None:
        views = {r.bssid for r in obs.responders}
        if self.enc.target is not None and self.enc.target in views:
            return
        pending = self._pending(obs, self.set_aside)
        if pending:
            t = {r.bssid: r.detected_at_s for r in obs.responders}
            self.enc.target = max(pending, key=lambda b: t[b])
        else:
            self.enc.target = None

    def _next(self, obs: Observation) -> None:
        pending = self._pending(obs, self.set_aside)
        if not pending:  # everything else localised or set aside: look again at those
            self.set_aside.clear()
            pending = self._pending(obs, set())
        if not pending:
            return
        t = self.enc.target
        i = pending.index(t) if t in pending else -1
        self.enc.target = pending[(i + 1) % len(pending)]

    def decide(self, action, obs: Observation) -> Decision:
        i = discrete_action(action, len(self.names))
        loc = self.enc.tracker.frozen()
        a = obs.agents[self.enc.agent]
        name = self.names[i]
        self._ensure_target(obs)
        if name == "done":
            if self.enc.target is not None:
                self.set_aside.add(self.enc.target)
                self.enc.target = None
                self._ensure_target(obs)
            return self._fly_on(a, loc)
        if name == "next":
            self._next(obs)
        target = self.enc.target
        if i < len(self.routes):
            return self._route(i, a, loc)
        if target is None:  # nothing to manoeuvre about: fly on
            return self._fly_on(a, loc)
        key = (i, target)
        if name == PLANNED:
            return self._planned(key, obs, a, loc)
        if self.current == key and not a.segment_done:
            return Decision(localised=loc)
        self.current = key
        traj = self._build(name, target, obs, a)
        return Decision(plans={self.enc.agent: traj}, localised=loc, note=f"{name} {target}")

    def _planned(self, key: tuple[int, str], obs: Observation, a: AgentView,
                 loc: frozenset[str]) -> Decision:
        """``adaptive``'s plan about the target, solved again every ``replan_s``; the
        probe while the target has no usable estimate (flown to its end)."""
        r = next(v for v in obs.responders if v.bssid == key[1])
        usable = r.tracked
        again = self.current != key or a.segment_done or (
            usable and obs.t_s - self.planned_at >= self.cfg.adaptive.replan_s)
        if not again:
            return Decision(localised=loc)
        self.current = key
        if not usable:
            self.planned_at = -np.inf
            return Decision(plans={self.enc.agent: self.man.probe(r, a)}, localised=loc,
                            note=f"planned {r.bssid}: probe")
        traj, solves = self.optimal.plan(r, a)
        self.planned_at = obs.t_s
        return Decision(plans={self.enc.agent: traj}, localised=loc, replans=solves,
                        note=f"planned {r.bssid}")

    def _fly_on(self, a: AgentView, loc: frozenset[str]) -> Decision:
        """No new segment; before the first one, climb to the search height where the
        vehicle is and hold there (the take-off)."""
        if self.current is not None:
            return Decision(localised=loc)
        m = self.mission
        e, n = (float(x) for x in a.position_enu_m[:2])
        enu = np.array([[e, n, m.height_m], [e, n, m.height_m]])
        traj = Trajectory(np.array([0.0, self.cfg.decision_period_s]), enu, m.origin,
                          "terrain", "hold")
        self.current = (-1, None)
        return Decision(plans={self.enc.agent: traj}, localised=loc, note="hold")

    def _route(self, i: int, a: AgentView, loc: frozenset[str]) -> Decision:
        route = self.routes[i]
        here = a.position_enu_m[:2]
        key = (i, None)
        if self.current == key and not a.segment_done:
            route.advance(here)
            return Decision(localised=loc)
        if self.current == key:  # the segment is flown: mark its end, reverse if over
            route.advance(here)
            if route.at_end:
                route.reverse()
        self.current = key
        return Decision(plans={self.enc.agent: route.resume(here)}, localised=loc,
                        note=self.names[i])

    def _build(self, name: str, target: str, obs: Observation, a: AgentView):
        return responder_manoeuvre(self.man, self.cfg.adaptive, name, target, obs, a, "next")


def sigma_shrink(history: list[tuple[float, float]], t_s: float,
                 window_s: float = SHRINK_WINDOW_S) -> float:
    """``1 - sigma_H(t) / sigma_H(t - window_s)`` of a responder's ``(t_s, sigma_H)``
    history (the latest sigma_H at least ``window_s`` old), in [0, 1]; 1 without one."""
    if not history:
        return 1.0
    old = None
    for t, s in reversed(history):
        if t <= t_s - window_s:
            old = s
            break
    if old is None or old <= 0.0:
        return 1.0
    return float(min(max(1.0 - history[-1][1] / old, 0.0), 1.0))


def plan_heuristic(actions: PlanActions, close_sigma_h_m: float = 3.0,
                   planned: bool | None = None, close_band: float = 2.0,
                   give_up: float | None = None, settled: float | None = None):
    """The hand-written policy in :class:`PlanActions` (observation -> action), reading
    only the observation: with a target not localised, the probe helix until it has an
    estimate, a near orbit while sigma_H > ``close_sigma_h_m``, then the close helix;
    a localised target is set aside (``done``); with no target, the lawnmower.

    ``planned`` (default: when the actions have it, ``osa/Search-v2``): ``adaptive`` in
    these actions: the ``planned`` action instead of the near orbit, and a helix being
    flown stays (re-centred) while sigma_H <= ``close_band`` x ``close_sigma_h_m`` (``adaptive``'s
    close phase stays until the target is localised; without the band a sigma_H about
    the threshold would switch segments at every decision), and a target heard first
    more than ``give_up`` of the budget ago (the slot's ``age``; 600 s of 30 minutes)
    with no usable estimate yet is set aside (``done``; ``adaptive`` gives one up after
    420 s as the target: a responder the terrain or vegetation hides could hold the
    probe to the end of the budget). ``give_up=None``: never.

    ``settled`` (default, ``osa/Search-v3``'s ``sigma_shrink``: 0.03; with ``give_up``
    then 1/3 of the budget): a target converged (with the rule's ``min_n_acc`` ranges
    accepted) whose close helix shrank its sigma_H by less than this share over the
    last 20 s is set aside (``done``): the estimator's plateau judgement of it
    (sigma_H not 5 % smaller over 90 s) completes while the drone works on the next
    responder or searches, instead of while it circles one that gains nothing."""
    from envs.gym.interface import SLOT_FEATURES

    if planned is None:
        planned = PLANNED in actions.names
    shrinks = bool(getattr(actions, "shrink", False))
    if shrinks:
        settled = 0.03 if settled is None else settled
        give_up = 1.0 / 3.0 if give_up is None else give_up
    else:
        settled = None
    f = {k: j for j, k in enumerate(SLOT_FEATURES)}
    nf = len(SLOT_FEATURES)
    helix = actions.index("helix")
    orbit = actions.index(PLANNED if planned else "orbit-near")
    done, sweep = actions.index("done"), actions.index("lawnmower")
    threshold = np.log10(close_sigma_h_m) / 2.0
    stay = np.log10(close_band * close_sigma_h_m) / 2.0
    give_up = give_up if planned else None
    min_acc = np.log1p(actions.cfg.rule.min_n_acc) / np.log(1000.0)  # log_accepted

    def act(obs: dict) -> int:
        slots = np.asarray(obs["responders"]).reshape(-1, nf)
        mask = np.asarray(obs["responder_mask"]) > 0.5
        on = [i for i, m in enumerate(mask) if m and slots[i][f["target"]] > 0.5]
        if not on and planned:  # the one the action will make the target (no decision lost)
            aside = np.asarray(obs["set_aside"]) > 0.5
            on = sorted((i for i, m in enumerate(mask)
                         if m and not aside[i] and slots[i][f["localised"]] < 0.5),
                        key=lambda i: slots[i][f["age"]])
        if not on:
            return sweep
        on_slot = on[0]
        s = slots[on_slot]
        if s[f["localised"]] > 0.5:
            return done
        if s[f["present_estimate"]] < 0.5 or s[f["status_none"]] > 0.5:
            if give_up is not None and s[f["age"]] > give_up:
                return done
            return helix
        if planned and obs["flying"][helix] > 0.5 and s[f["log_sigma_h"]] <= stay:
            if settled is not None and s[f["status_converged"]] > 0.5 and \
                    s[f["log_accepted"]] >= min_acc and s[f["log_sigma_h"]] <= threshold and \
                    obs["sigma_shrink"][on_slot] < settled:
                return done
            return helix
        return orbit if s[f["log_sigma_h"]] > threshold else helix

    return act
