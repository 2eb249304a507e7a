"""Domain randomisation: a scenario's ``[randomise]`` ranges, drawn per world.

``[randomise]`` gives ranges ``[low, high]`` for the parts of a world a policy should
not overfit (docs/scenarios.md): the GNSS bias scale, the share of responders
concealed in vegetation, the responders' hardware range offset, GNSS dropouts and
the wind. :func:`sim.realise` draws them from the world's seed (its named child
``seed / 4``), so world seed N is the same world in ``osa search``, ``osa evaluate``
and the environments. ``level`` (0 to 1, the curriculum's knob) narrows every range
to ``[low, low + level (high - low)]``: the same world seed at a lower level is the
same draw moved towards ``low`` (each value is ``low + level u (high - low)`` with the
world's own ``u``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from sim._config import check_finite

# the order in which the uniforms are drawn (fixed: adding a range changes no other)
DRAWS = ("gnss_bias_scale", "concealed_share", "range_offset_m", "gnss_drop_prob",
         "wind_mps", "wind_direction")
CONCEALMENT_SLOTS = 20  # the concealed share is realised in steps of 1/20


@dataclass(frozen=True, kw_only=True)
class Randomise:
    """The ``[randomise]`` table: each key a range ``[low, high]`` (absent: not drawn).

    - ``gnss_bias_scale``: multiplies the GNSS receivers' bias sigmas (horizontal and
      vertical);
    - ``concealed_share``: the chance that a random responder is concealed (its
      concealment one of the scenario's non-open ``random_concealment`` kinds, else
      ``vegetation``), in steps of 1/20;
    - ``range_offset_m``: every responder's hardware range offset (m);
    - ``gnss_drop_prob``: the receivers' chance of a missed fix;
    - ``wind_mps``: a steady wind of this speed from a direction drawn uniformly;
    - ``level``: 0 to 1, the share of each range in use (the curriculum's knob).
    """

    gnss_bias_scale: tuple[float, float] | None = None
    concealed_share: tuple[float, float] | None = None
    range_offset_m: tuple[float, float] | None = None
    gnss_drop_prob: tuple[float, float] | None = None
    wind_mps: tuple[float, float] | None = None
    level: float = 1.0

    def __post_init__(self) -> None:
        bounds = {"gnss_bias_scale": (0.0, 20.0), "concealed_share": (0.0, 1.0),
                  "range_offset_m": (0.0, 20.0), "gnss_drop_prob": (0.0, 1.0),
                  "wind_mps": (0.0, 10.0)}
        for name, (lo_ok, hi_ok) in bounds.items():
            r = getattr(self, name)
            if r is None:
                continue
            if len(r) != 2:
                raise ValueError(f"{name} must be [low, high]")
            lo, hi = r
            check_finite(f"{name}[0]", lo)
            check_finite(f"{name}[1]", hi)
            if not lo_ok <= lo <= hi <= hi_ok:
                raise ValueError(f"{name} [{lo:g}, {hi:g}] is not a range within "
                                 f"[{lo_ok:g}, {hi_ok:g}]")
        check_finite("level", self.level)
        if not 0.0 <= self.level <= 1.0:
            raise ValueError(f"level {self.level:g} is not in [0, 1]")

    def draw(self, rng: np.random.Generator) -> dict[str, float]:
        """The world's values: every uniform drawn in :data:`DRAWS` order, then each
        set range's ``low + level u (high - low)`` (and the wind's direction, rad)."""
        u = dict(zip(DRAWS, rng.random(len(DRAWS)).tolist(), strict=True))
        out: dict[str, float] = {}
        for name in DRAWS[:-1]:
            r = getattr(self, name)
            if r is not None:
                out[name] = r[0] + self.level * u[name] * (r[1] - r[0])
        if "wind_mps" in out:
            out["wind_direction"] = 2.0 * math.pi * u["wind_direction"]
        return out

    def apply(self, scenario, rng: np.random.Generator):
        """``scenario`` with this draw's values in place (and no ``randomise``)."""
        v = self.draw(rng)
        sc = dataclasses.replace(scenario, randomise=None)
        gnss_kw: dict = {}
        veh_kw: dict = {}
        if "gnss_bias_scale" in v:
            k = v["gnss_bias_scale"]
            gnss_kw["scale"] = k
        if "gnss_drop_prob" in v:
            gnss_kw["drop_prob"] = v["gnss_drop_prob"]
        if "wind_mps" in v:
            w, th = v["wind_mps"], v["wind_direction"]
            veh_kw["wind_enu_mps"] = (w * math.sin(th), w * math.cos(th))

        def gnss(g):
            kw = {k: x for k, x in gnss_kw.items() if k != "scale"}
            if "scale" in gnss_kw:
                kw["bias_sigma_h_m"] = g.bias_sigma_h_m * gnss_kw["scale"]
                kw["bias_sigma_v_m"] = g.bias_sigma_v_m * gnss_kw["scale"]
            return dataclasses.replace(g, **kw) if kw else g

        def vehicle(c):
            return dataclasses.replace(c, **veh_kw) if veh_kw else c

        sc = dataclasses.replace(
            sc, gnss=gnss(sc.gnss), vehicle=vehicle(sc.vehicle),
            agents_=tuple(dataclasses.replace(a, gnss=gnss(a.gnss), vehicle=vehicle(a.vehicle))
                          for a in sc.agents_))
        if "range_offset_m" in v:
            o = v["range_offset_m"]
            sc = dataclasses.replace(sc, ftm=dataclasses.replace(sc.ftm, offset_min_m=o,
                                                                  offset_max_m=o))
        if "concealed_share" in v and sc.search is not None:
            kinds = [c for c in sc.search.random_concealment if c != "open"] or ["vegetation"]
            n = round(v["concealed_share"] * CONCEALMENT_SLOTS)
            slots = tuple(kinds[i % len(kinds)] if i < n else "open"
                          for i in range(CONCEALMENT_SLOTS))
            sc = dataclasses.replace(sc, search=dataclasses.replace(
                sc.search, random_concealment=slots))
        return sc
