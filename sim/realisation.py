"""One draw of a scenario's world: everything that does not depend on what is flown.

``realise(scenario, seed)`` fixes, for that scenario and seed, the responders (drawn
uniformly in the search area when the scenario asks for random ones), their hardware
range offsets, one shadowing field per responder over the whole plane, and the seeds
of every agent's own processes (GNSS error as a function of time, phone clock,
tracking wander, ranging noise, log writer). Two plans flown on the same seed meet the
same world: common random numbers, the standard way to compare policies.

Seeds may be an int, a ``numpy.random.SeedSequence`` or a ``numpy.random.Generator``.
Streams are named children of the seed (:func:`sim._random.child_seed`), not spawned
by count, so adding an agent does not change the others' draws::

    seed / 0        responders (random placement, concealment, hiding by terrain)
    seed / 1        hardware range offsets
    seed / 2        shadowing fields
    seed / 3 / i    agent i: / 0 GNSS, / 1 clock, / 2 wander, / 3 radio, / 4 log writer
    seed / 4        the scenario's [randomise] draw (sim.randomise), applied first
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from estimator.geometry import point_in_polygon
from estimator.records import TruthRecord
from sim._random import Seed, as_seed_sequence, child_rng, child_seed
from sim.ftm import draw_offsets, draw_shadowing
from sim.occlusion import link_obstruction
from sim.scenario import Scenario
from sim.suite import concealed_count
from sim.world import Responder, World

AGENT_GNSS, AGENT_CLOCK, AGENT_WANDER, AGENT_RADIO, AGENT_WRITER = range(5)
# ``[search] hidden_share``: a responder is hidden by terrain when the knife-edge nu of
# its link to the take-off point at the search height is at least HIDDEN_NU (the ground
# rises above the straight line; J(1) = 13.9 dB, beyond vegetation_debris' 12 dB), in
# view when nu <= 0 (the straight line clears the ground)
HIDDEN_NU = 1.0
HIDE_BLOCK = 64  # candidate places drawn at a time
HIDE_MAX_CANDIDATES = 4096  # per world; then the rest keep their uniform place (counted)


@dataclass(frozen=True)
class TerrainHiding:
    """How a world met ``[search] hidden_share``: ``wanted`` responders to hide, the
    names of those hidden from the take-off point (nu >= :data:`HIDDEN_NU`),
    ``misplaced`` responders for which no place of their kind (hidden or in view) was
    found among ``candidates`` drawn places (they keep their uniform place)."""

    wanted: int
    hidden: tuple[str, ...]
    misplaced: int
    candidates: int

    @property
    def note(self) -> str:
        s = f"hidden by terrain from the take-off point: {len(self.hidden)} (wanted {self.wanted})"
        if self.misplaced:
            s += (f"; {self.misplaced} responder(s) found no place of their kind in "
                  f"{self.candidates} candidates and kept a uniform one")
        return s


@dataclass(frozen=True, eq=False)
class Realisation:
    """A scenario's world for one seed (see the module docstring)."""

    scenario: Scenario
    seed: np.random.SeedSequence
    world: World
    offsets_m: np.ndarray
    shadowing: tuple
    hiding: TerrainHiding | None = None  # with [search] hidden_share

    @property
    def notes(self) -> tuple[str, ...]:
        """One-line remarks on how the world was drawn (the hiding by terrain)."""
        return () if self.hiding is None else (self.hiding.note,)

    def agent_seed(self, index: int, stream: int) -> np.random.SeedSequence:
        return child_seed(self.seed, 3, index, stream)

    def responder_enu_m(self) -> np.ndarray:
        return self.world.responder_enu_m()

    def truth_records(self) -> tuple[TruthRecord, ...]:
        return self.world.truth_records()

    @property
    def bssids(self) -> tuple[str, ...]:
        return tuple(r.bssid for r in self.world.responders)


def takeoff_nu(scenario: Scenario, e_m: np.ndarray, n_m: np.ndarray,
               antenna_height_m: float = 0.5) -> np.ndarray:
    """The knife-edge nu (:mod:`sim.occlusion`) of the links from responders at
    (e, n), antennas ``antenna_height_m`` above the ground, to the search's take-off
    point at the search height above the ground: > 0 where the terrain rises above the
    straight line."""
    search = scenario.search
    assert search is not None
    terrain, ftm = scenario.world.terrain, scenario.ftm
    e, n = np.asarray(e_m, dtype=float), np.asarray(n_m, dtype=float)
    a = np.column_stack([e, n, terrain.height_m(e, n) + antenna_height_m])
    s = np.array([search.start_e_m]), np.array([search.start_n_m])
    b = np.array([s[0][0], s[1][0], float(terrain.height_m(*s)[0]) + search.height_m])
    return link_obstruction(a, np.broadcast_to(b, a.shape), terrain, ftm.frequency_hz,
                            ftm.occlusion_step_m).nu


def _hide_by_terrain(scenario: Scenario, out: list[Responder], rng: np.random.Generator,
                     poly: np.ndarray) -> tuple[list[Responder], TerrainHiding]:
    """``hidden_share``: :func:`sim.suite.concealed_count` responders, chosen at random,
    moved to places hidden from the take-off point and the others to places in its
    view, each that is not there already, by rejection sampling over uniform places
    in the area (:data:`HIDE_BLOCK` at a time, :data:`HIDE_MAX_CANDIDATES` at most)."""
    search = scenario.search
    assert search is not None and search.hidden_share is not None
    k = concealed_count(search.hidden_share, len(out), float(rng.random()))
    want = np.zeros(len(out), dtype=bool)
    want[rng.permutation(len(out))[:k]] = True
    if not out:
        return out, TerrainHiding(0, (), 0, 0)
    ant = out[0].antenna_height_m  # the drawn responders share it
    place = np.array([(r.e_m, r.n_m) for r in out], dtype=float).reshape(-1, 2)
    nu = takeoff_nu(scenario, place[:, 0], place[:, 1], ant)
    ok = np.where(want, nu >= HIDDEN_NU, nu <= 0.0)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    drawn = 0
    while not ok.all() and drawn < HIDE_MAX_CANDIDATES:
        cand = np.array([[round(float(x), 3) for x in p]
                         for p in rng.uniform(lo, hi, (HIDE_BLOCK, 2))])
        drawn += HIDE_BLOCK
        inside = point_in_polygon(poly, cand)
        cnu = takeoff_nu(scenario, cand[:, 0], cand[:, 1], ant)
        pools = {True: list(np.flatnonzero(inside & (cnu >= HIDDEN_NU))),
                 False: list(np.flatnonzero(inside & (cnu <= 0.0)))}
        for i in np.flatnonzero(~ok):
            pool = pools[bool(want[i])]
            if pool:
                place[i] = cand[pool.pop(0)]
                ok[i] = True
    out = [dataclasses.replace(r, e_m=float(p[0]), n_m=float(p[1]))
           for r, p in zip(out, place, strict=True)]
    nu = takeoff_nu(scenario, place[:, 0], place[:, 1], ant)
    hidden = tuple(r.name for r, v in zip(out, nu, strict=True) if v >= HIDDEN_NU)
    return out, TerrainHiding(k, hidden, int((~ok).sum()), drawn)


def random_responders(scenario: Scenario, rng: np.random.Generator) -> tuple[Responder, ...]:
    """The ``[search] random_responders`` responders: uniform in the area polygon,
    concealment uniform over ``random_concealment`` (or, with ``concealed_share``, that
    share concealed: :func:`sim.suite.concealed_count` of them, chosen at random, each
    of a kind uniform over ``random_concealment``, the others open), locally
    administered BSSIDs; with ``hidden_share``, that share hidden by terrain from the
    take-off point and the others in its view (:func:`draw_responders`)."""
    return draw_responders(scenario, rng)[0]


def draw_responders(scenario: Scenario, rng: np.random.Generator
                    ) -> tuple[tuple[Responder, ...], TerrainHiding | None]:
    """:func:`random_responders` and, with ``hidden_share``, how the hiding went."""
    search = scenario.search
    assert search is not None
    poly = np.asarray(search.area_enu_m, dtype=float)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    out: list[Responder] = []
    used = {r.bssid for r in scenario.world.responders}
    while len(out) < search.random_responders:
        p = rng.uniform(lo, hi)
        conc = search.random_concealment[int(rng.integers(len(search.random_concealment)))]
        octets = rng.integers(0, 256, 6)
        octets[0] = (int(octets[0]) & 0xFC) | 0x02  # locally administered, unicast
        bssid = ":".join(f"{int(o):02x}" for o in octets)
        if not point_in_polygon(poly, p[None, :])[0] or bssid in used:
            continue
        used.add(bssid)
        out.append(Responder(name=f"R{len(out) + 1}", bssid=bssid, e_m=round(float(p[0]), 3),
                             n_m=round(float(p[1]), 3), concealment=conc))
    if search.concealed_share is not None:  # after the places: their draws stay the same
        k = concealed_count(search.concealed_share, len(out), float(rng.random()))
        hidden = set(rng.permutation(len(out))[:k].tolist())
        kinds = search.random_concealment
        out = [dataclasses.replace(
            r, concealment=kinds[int(rng.integers(len(kinds)))] if i in hidden else "open")
            for i, r in enumerate(out)]
    hiding = None
    if search.hidden_share is not None:  # after everything else: those draws stay the same
        out, hiding = _hide_by_terrain(scenario, out, rng, poly)
    return tuple(out), hiding


def realise(scenario: Scenario, seed: Seed = 0) -> Realisation:
    """Draw the world of ``scenario`` for ``seed`` (see the module docstring)."""
    seq = as_seed_sequence(seed)
    if scenario.randomise is not None:  # this world's GNSS, concealment, offsets, wind
        scenario = scenario.randomise.apply(scenario, child_rng(seq, 4))
    world = scenario.world
    hiding = None
    if scenario.search is not None and scenario.search.random_responders > 0:
        drawn, hiding = draw_responders(scenario, child_rng(seq, 0))
        world = dataclasses.replace(world, responders=drawn)
    offsets = draw_offsets(world, scenario.ftm, child_rng(seq, 1))
    shadowing = draw_shadowing(world, scenario.ftm, child_rng(seq, 2))
    return Realisation(scenario, seq, world, offsets, shadowing, hiding)
