"""What the planner needs of the world, as protocols: a terrain and a link model.

The planner declares them; the simulator implements them (``sim.HillsTerrain``,
``sim.GridTerrain``, ``sim.FtmLink``, whose response probability between two points
knows the terrain's obstruction of the link); ``envs`` (the CLI, the closed loop) wires the
simulator's objects in, so the planner plans over the same hills and with the same
response probability as the world it is flown in. Both protocols evaluate NumPy
arrays and CasADi symbols alike (the optimal planner differentiates through them).

Two small stand-ins live here for library use without a world: :class:`FlatTerrain`
and :class:`LogisticLink` (a logistic response in slant range with an eq. (11) RSSI).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from estimator.noise import NlosConfig


def is_symbolic(x: object) -> bool:
    """Is ``x`` a CasADi expression (SX, MX or DM)?"""
    import casadi as ca

    return isinstance(x, ca.SX | ca.MX | ca.DM)


@runtime_checkable
class TerrainModel(Protocol):
    """Ground height in a local ENU frame (metres above the frame origin)."""

    def height_m(self, e_m, n_m):
        """Height at (e, n): NumPy in, NumPy out; CasADi symbols in, symbol out."""
        ...

    def sag_curvature(self) -> tuple[float, float]:
        """Bounds (concave, convex) on -h'' and +h'' along any horizontal line (1/m)."""
        ...

    # Optional: ``max_height_m(e_min, e_max, n_min, n_max) -> float``, an upper bound of
    # the height over a box, lets the simulated vehicle skip its below-the-terrain check
    # where it flies clearly above (sim.vehicle.Multirotor.advance) and the FTM radio skip
    # the terrain profile of links that clearly clear it (sim.occlusion.Occluder).


@runtime_checkable
class LinkModel(Protocol):
    """The FTM link as the planner sees it: how often a ranging attempt answers."""

    @property
    def ranging_rate_hz(self) -> float: ...

    def response_probability(self, slant_m, concealment: str = "open", loss_db=None):
        """Mean probability that one attempt at slant range d answers ``ok``, the mean
        RSSI lowered by ``loss_db`` (an obstruction's, below) when given."""
        ...

    def obstruction_loss_db(self, p_drone_enu_m, p_resp_enu_m, terrain):
        """The terrain's loss (dB) on the links from drone positions to responder
        positions (``terrain`` a :class:`TerrainModel`; None: nothing obstructs).
        NumPy: (M, 3) or (3,) positions broadcast against each other, (M,) out; CasADi:
        3 x M columns (the responder 3 x 1 or 3 x M), 1 x M out (a smooth
        approximation Ipopt can differentiate)."""
        ...

    def response_probability_between(self, p_drone_enu_m, p_resp_enu_m, terrain,
                                     concealment: str = "open"):
        """:meth:`response_probability` of those links at their slant range with the
        terrain's loss on them; with nothing in the way, P at the slant range."""
        ...

    def mean_rssi_dbm(self, slant_m, concealment: str = "open"):
        """Mean RSSI at slant range d (the q of eq. 13 comes from it)."""
        ...


@dataclass(frozen=True)
class FlatTerrain:
    """Ground at a constant height above the frame origin."""

    level_m: float = 0.0

    def height_m(self, e_m, n_m):
        if is_symbolic(e_m):
            return 0.0 * e_m + self.level_m
        return np.zeros(np.broadcast(np.asarray(e_m), np.asarray(n_m)).shape) + self.level_m

    def sag_curvature(self) -> tuple[float, float]:
        return 0.0, 0.0


_EQ11 = NlosConfig()


@dataclass(frozen=True, kw_only=True)
class LogisticLink:
    """P(d) = 1 / (1 + exp((d - reach_m) / width_m)); RSSI from eq. (11).

    A generic stand-in (50 % at 57.5 m slant, 10-90 % over 16.8-98.3 m). Wherever a
    world is known, ``osa`` passes the simulator's calibrated link (``sim.FtmLink``).
    It knows no terrain: :meth:`response_probability_between` is P at the slant range.
    """

    reach_m: float = 57.54
    width_m: float = 18.55
    rate_hz: float = 4.0  # "3-5 Hz during active ranging" (sec. Range Measurement Model)
    rssi_1m_dbm: float = _EQ11.rssi_1m_dbm
    path_loss_exponent: float = _EQ11.path_loss_exponent

    @property
    def ranging_rate_hz(self) -> float:
        return self.rate_hz

    def response_probability(self, slant_m, concealment: str = "open", loss_db=None):
        """P at slant range d; a loss of L dB acts as the slant range at which eq. (11)'s
        mean RSSI is L dB lower, d 10^(L / (10 eta))."""
        if loss_db is not None:
            slant_m = slant_m * 10.0 ** (loss_db / (10.0 * self.path_loss_exponent))
        if is_symbolic(slant_m):
            import casadi as ca

            return 0.5 * (1.0 - ca.tanh(0.5 * (slant_m - self.reach_m) / self.width_m))
        z = (np.asarray(slant_m, dtype=float) - self.reach_m) / self.width_m
        return 0.5 * (1.0 - np.tanh(0.5 * z))  # = 1 / (1 + exp(z)), overflow-free

    def obstruction_loss_db(self, p_drone_enu_m, p_resp_enu_m, terrain):
        """Nothing obstructs this stand-in (zeros)."""
        if is_symbolic(p_drone_enu_m) or is_symbolic(p_resp_enu_m):
            import casadi as ca

            b = p_drone_enu_m if is_symbolic(p_drone_enu_m) else ca.DM(p_drone_enu_m)
            a = p_resp_enu_m if is_symbolic(p_resp_enu_m) else ca.DM(p_resp_enu_m)
            return 0.0 * ca.repmat(b[0, 0] + a[0, 0], 1, max(a.shape[1], b.shape[1]))
        a, b = np.broadcast_arrays(np.asarray(p_resp_enu_m, dtype=float).reshape(-1, 3),
                                   np.asarray(p_drone_enu_m, dtype=float).reshape(-1, 3))
        return np.zeros(len(a))

    def response_probability_between(self, p_drone_enu_m, p_resp_enu_m, terrain,
                                     concealment: str = "open"):
        """P at the slant range (this stand-in knows no terrain)."""
        if is_symbolic(p_drone_enu_m) or is_symbolic(p_resp_enu_m):
            import casadi as ca

            b = p_drone_enu_m if is_symbolic(p_drone_enu_m) else ca.DM(p_drone_enu_m)
            a = p_resp_enu_m if is_symbolic(p_resp_enu_m) else ca.DM(p_resp_enu_m)
            diff = b - (ca.repmat(a, 1, b.shape[1]) if a.shape[1] == 1 else a)
            return self.response_probability(ca.sqrt(ca.sum1(diff * diff)), concealment)
        a, b = np.broadcast_arrays(np.asarray(p_resp_enu_m, dtype=float).reshape(-1, 3),
                                   np.asarray(p_drone_enu_m, dtype=float).reshape(-1, 3))
        return self.response_probability(np.sqrt(np.add.reduce((b - a) ** 2, axis=1)),
                                         concealment)

    def mean_rssi_dbm(self, slant_m, concealment: str = "open"):
        if is_symbolic(slant_m):
            import casadi as ca

            d = ca.fmax(slant_m, 1.0)
            return self.rssi_1m_dbm - 10.0 * self.path_loss_exponent * ca.log(d) / math.log(10)
        d = np.maximum(np.asarray(slant_m, dtype=float), 1.0)
        return self.rssi_1m_dbm - 10.0 * self.path_loss_exponent * np.log10(d)


def slant_at(link: LinkModel, probability: float, concealment: str = "open",
             max_m: float = 5000.0) -> float:
    """Slant range where the link's response probability falls to ``probability``
    (bisection; the probability falls with range). Raises when never reached."""
    if not 0.0 < probability < 1.0:
        raise ValueError("probability must be in (0, 1)")

    def p(d: float) -> float:
        return float(np.asarray(link.response_probability(d, concealment)))

    lo, hi = 0.0, max_m
    if p(lo) < probability:
        raise ValueError(
            f"the link never answers with probability {probability:.0%} "
            f"(at most {p(lo):.0%} at 0 m)"
        )
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if p(mid) >= probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
