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

    seed / 0        responders (random placement and concealment)
    seed / 1        hardware range offsets
    seed / 2        shadowing fields
    seed / 3 / i    agent i: / 0 GNSS, / 1 clock, / 2 wander, / 3 radio, / 4 log writer
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from estimator.geometry import point_in_polygon
from estimator.records import TruthRecord
from sim._random import Seed, as_seed_sequence, child_rng, child_seed
from sim.ftm import draw_offsets, draw_shadowing
from sim.scenario import Scenario
from sim.suite import concealed_count
from sim.world import Responder, World

AGENT_GNSS, AGENT_CLOCK, AGENT_WANDER, AGENT_RADIO, AGENT_WRITER = range(5)


@dataclass(frozen=True, eq=False)
class Realisation:
    """A scenario's world for one seed (see the module docstring)."""

    scenario: Scenario
    seed: np.random.SeedSequence
    world: World
    offsets_m: np.ndarray
    shadowing: tuple

    def agent_seed(self, index: int, stream: int) -> np.random.SeedSequence:
        return child_seed(self.seed, 3, index, stream)

    def responder_enu_m(self) -> np.ndarray:
        return self.world.responder_enu_m()

    def truth_records(self) -> tuple[TruthRecord, ...]:
        return self.world.truth_records()

    @property
    def bssids(self) -> tuple[str, ...]:
        return tuple(r.bssid for r in self.world.responders)


def random_responders(scenario: Scenario, rng: np.random.Generator) -> tuple[Responder, ...]:
    """The ``[search] random_responders`` responders: uniform in the area polygon,
    concealment uniform over ``random_concealment`` (or, with ``concealed_share``, that
    share concealed: :func:`sim.suite.concealed_count` of them, chosen at random, each
    of a kind uniform over ``random_concealment``, the others open), locally
    administered BSSIDs."""
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
    return tuple(out)


def realise(scenario: Scenario, seed: Seed = 0) -> Realisation:
    """Draw the world of ``scenario`` for ``seed`` (see the module docstring)."""
    seq = as_seed_sequence(seed)
    world = scenario.world
    if scenario.search is not None and scenario.search.random_responders > 0:
        drawn = random_responders(scenario, child_rng(seq, 0))
        world = dataclasses.replace(world, responders=drawn)
    offsets = draw_offsets(world, scenario.ftm, child_rng(seq, 1))
    shadowing = draw_shadowing(world, scenario.ftm, child_rng(seq, 2))
    return Realisation(scenario, seq, world, offsets, shadowing)
