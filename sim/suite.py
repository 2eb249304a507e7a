"""The benchmark suite: search presets named ``suite/r{R}-{c|h}{P}-{sa|rtk}-u{U}``.

One function (:func:`suite_table`) turns a suite name into the scenario table that
:func:`sim.scenario.load_scenario` builds and checks like any preset's, so a suite name
is accepted wherever a preset name is (``osa search``, ``osa evaluate``, the envs'
``scenario=``, ``extends``). The world of a seed (:func:`sim.realise`) places the
responders; everything else is fixed by the name:

- ``R`` in {1, 5, 10}: responders, each at a uniformly random place in the area;
- ``C`` in {0, 30, 50}: the share (%) of them concealed under dense vegetation (the
  paper's AP_AB model, ``concealment = "vegetation"``), the others in the open; the
  count is ``floor(C R / 100)`` plus one with probability the fractional part (so
  exactly 3 of 10 at 30 %, 1 or 2 of 5, and the expected share is exactly C), which
  ones drawn from the seed. Every responder, open or concealed, is on the suite's
  hilly ground with terrain occlusion on (:mod:`sim.occlusion`): a hill between drone
  and responder hides it whatever its class;
- or ``H`` in {0, 30, 50} (``h`` instead of ``c``): the share (%) hidden by terrain
  from the take-off point, on the same hills with a :data:`RIDGE` across the north of
  the area (``[search] hidden_share``, :func:`sim.realisation.random_responders`):
  that many (counted as for ``C``) are placed where the ground blocks the line of sight
  from the take-off point at the search height (knife-edge nu >= ``HIDDEN_NU``), the
  others where it does not (nu <= 0); every responder is in the open. The
  ``c`` names' terrain and worlds are those without the ridge;
- ``sa`` (standalone dual-frequency GNSS) or ``rtk`` (RTK fixes), ``sim.gnss`` presets;
- ``U`` in {1, 2, 4}: UAVs taking off side by side (:data:`UAV_SPACING_M` apart
  eastwards from the take-off point), each with its own GNSS receiver and phone, one
  fused estimate (``[[agents]]``).

The battery: every UAV flies at most :data:`BUDGET_S` (15 minutes, a small
multirotor's endurance with a landing reserve) at :data:`SPEED_MPS` (8 m/s); the search
ends when that is spent (``[search] budget_s``). Chosen so that the hand-written
``adaptive`` localises most of five responders and uniform random actions fewer
(docs/rl.md, "The benchmark suite"); given more time, random manoeuvres catch up.
The area is an :data:`AREA_SIDE_M` square (500 m) on the
presets' hills (``sim.terrain.HillsTerrain`` defaults), the take-off point 10 m inside
its southern edge; the policies are told how many responders to expect
(``expected_responders = R``).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

from sim.terrain import DEFAULT_HILLS, Hill

PREFIX = "suite/"
RESPONDERS = (1, 5, 10)
CONCEALED_PCT = (0, 30, 50)
HIDDEN_PCT = (0, 30, 50)
GNSS = {"sa": "standalone", "rtk": "rtk"}
UAVS = (1, 2, 4)
AREA_SIDE_M = 500.0
BUDGET_S = 900.0  # the battery: flight time per UAV (15 min)
SPEED_MPS = 8.0
HEIGHT_M = 45.0
UAV_SPACING_M = 30.0
_NAME = re.compile(r"^suite/r(\d+)-([ch])(\d+)-(sa|rtk)-u(\d+)$")
# The h names' ridge: nine 8 m Gaussian hills 35 m apart along n = 60 m (a crest some
# 20 m above the presets' hills from e = -140 to 140 m, slopes up to 25 degrees). From
# the take-off point at 45 m it hides some 18 % of the area (nu >= 1), 0 % without it.
RIDGE: tuple[Hill, ...] = tuple(
    Hill(e_m=35.0 * k, n_m=60.0, height_m=8.0, sigma_m=35.0) for k in range(-4, 5))


@dataclass(frozen=True)
class SuiteSpec:
    """What a suite name says."""

    responders: int
    concealed_pct: int
    gnss: str  # "sa" | "rtk"
    uavs: int
    hidden_pct: int | None = None  # an h name (hidden by terrain; concealed_pct is 0)

    @property
    def name(self) -> str:
        share = f"c{self.concealed_pct}" if self.hidden_pct is None else f"h{self.hidden_pct}"
        return f"{PREFIX}r{self.responders}-{share}-{self.gnss}-u{self.uavs}"


def is_suite_name(name: str) -> bool:
    return isinstance(name, str) and name.startswith(PREFIX)


def suite_names(hidden: bool = False) -> list[str]:
    """The 54 suite presets' names with a concealed share (``c``), or with
    ``hidden=True`` the 54 with a share hidden by terrain (``h``)."""
    if hidden:
        return [SuiteSpec(r, 0, g, u, hidden_pct=h).name for r in RESPONDERS
                for h in HIDDEN_PCT for g in GNSS for u in UAVS]
    return [SuiteSpec(r, c, g, u).name for r in RESPONDERS for c in CONCEALED_PCT
            for g in GNSS for u in UAVS]


GRAMMAR = "suite/r{1,5,10}-{c,h}{0,30,50}-{sa,rtk}-u{1,2,4}"


def parse_suite_name(name: str) -> SuiteSpec:
    """The :class:`SuiteSpec` of ``name`` (ValueError with the grammar otherwise)."""
    m = _NAME.match(name)
    if m is None:
        raise ValueError(f"unknown suite preset {name!r} (names: {GRAMMAR}, e.g. "
                         "suite/r5-c30-sa-u1)")
    r, hidden, p, g, u = int(m[1]), m[2] == "h", int(m[3]), m[4], int(m[5])
    share = ("hidden h", p, HIDDEN_PCT) if hidden else ("concealed c", p, CONCEALED_PCT)
    for what, v, allowed in (("responders r", r, RESPONDERS), share, ("UAVs u", u, UAVS)):
        if v not in allowed:
            raise ValueError(f"suite preset {name!r}: {what}{v} is not one of "
                             f"{', '.join(map(str, allowed))} ({GRAMMAR})")
    if hidden:
        return SuiteSpec(r, 0, g, u, hidden_pct=p)
    return SuiteSpec(r, p, g, u)


def suite_table(name: str) -> dict:
    """The scenario table of the suite preset ``name`` (see the module docstring)."""
    s = parse_suite_name(name)
    half = AREA_SIDE_M / 2.0
    start = (0.0, -half + 10.0)
    share = (f"{s.concealed_pct} % under vegetation" if s.hidden_pct is None else
             f"{s.hidden_pct} % hidden by terrain behind a ridge from the take-off point")
    table: dict = {
        "name": s.name,
        "description": (
            f"Suite: {s.responders} responder"
            f"{'s at random places' if s.responders > 1 else ' at a random place'} in a "
            f"{AREA_SIDE_M:.0f} m square on hills, {share}, {GNSS[s.gnss]} GNSS, "
            f"{s.uavs} UAV{'s' if s.uavs > 1 else ''}, "
            f"{BUDGET_S / 60:.0f} min battery each"),
        "log": {"agent": "uav-1", "start_utc": "2025-06-12T10:12:00Z"},
        "world": {"origin": {"lat_deg": 36.715, "lon_deg": -4.478, "h_m": 140.0},
                  "terrain": {"kind": "hills"}},
        "search": {
            "area_enu_m": [[-half, -half], [half, -half], [half, half], [-half, half]],
            "start_e_m": start[0], "start_n_m": start[1], "budget_s": BUDGET_S,
            "height_m": HEIGHT_M, "speed_mps": SPEED_MPS,
            "random_responders": s.responders,
            "random_concealment": ["vegetation"],
            "concealed_share": s.concealed_pct / 100.0,
            "expected_responders": s.responders,
        },
        "gnss": {"preset": GNSS[s.gnss]},
    }
    if s.hidden_pct is not None:  # the c names' tables stay as they were
        table["world"]["terrain"]["hills"] = [dataclasses.asdict(h)
                                              for h in (*DEFAULT_HILLS, *RIDGE)]
        table["search"]["hidden_share"] = s.hidden_pct / 100.0
    if s.uavs > 1:
        table["agents"] = [
            {"name": f"uav-{i + 1}", "start_e_m": start[0] + UAV_SPACING_M * i,
             "start_n_m": start[1]} for i in range(s.uavs)]
    return table


def concealed_count(share: float, n: int, u: float) -> int:
    """How many of ``n`` responders are concealed for a uniform draw ``u`` in [0, 1):
    ``floor(share n)`` plus one when ``u`` falls below the fractional part."""
    x = share * n
    k = math.floor(x + 1e-9)
    return min(n, k + (1 if u < x - k - 1e-9 else 0))
