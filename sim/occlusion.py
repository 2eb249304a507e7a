"""Terrain occlusion of the FTM link: Fresnel-zone clearance and the knife-edge
diffraction loss over the dominant obstacle of the terrain profile, in the manner of
ITU-R P.526 (sec. 2.1 Fresnel ellipsoids, sec. 4.1 single knife edge).

Geometry. A link joins the responder's antenna A and the drone's antenna B, s = |AB|
apart. A point P lies on the Fresnel ellipsoid of (fractional) order n when its excess
path is Delta(P) = |AP| + |PB| - s = n lambda / 2. An edge at P has the diffraction
parameter

    nu = +-2 sqrt(Delta(P) / lambda)     (+ when P is above the straight line AB),

which is P.526's nu = h sqrt(2 / lambda (1/d1 + 1/d2)) (h the edge's height above the
line, d1 and d2 the distances to the ends) to second order in h, and keeps its meaning
(nu^2 / 2 = the ellipsoid's order) on steep links, where the vertical h overstates the
clearance across the line. nu = -0.78 is 0.55 of the first Fresnel radius below the line.

Profile. The terrain under AB is sampled at ``n = ceil(X / step_m) - 1`` interior points
evenly spaced in horizontal distance (X the link's horizontal length, ``step_m`` the
largest spacing, 2 m by default), at most :data:`MAX_SAMPLES` per link (beyond
2 km the spacing grows; such links are far out of reach). At each sample the ground
point directly below (or above) the line, P = (e, n, terrain(e, n)), gives a nu; the
dominant obstacle is the sample of largest nu. A link shorter horizontally than one
step has no sample (the drone is overhead) and is clear.

Loss. J(nu) = 6.9 + 20 log10(sqrt((nu - 0.1)^2 + 1) + nu - 0.1) dB for nu > -0.78,
else 0 (P.526 sec. 4.1). Range. When nu > 0 the direct path is blocked and the
first path to arrive runs over the edge, longer by Delta = lambda nu^2 / 4;
:class:`sim.ftm.FtmConfig` adds an NLoS-like exponential excess growing with the loss
beyond grazing.

Cheap first (:class:`Occluder`): when the terrain has the optional
``max_height_m(e_min, e_max, n_min, n_max)`` upper bound, each responder gets a table
of that bound over annular sectors about it (16 sectors; annuli doubling from half a
step out to 1 km; a sector is bounded when a link first lies in it). A ray from the
responder stays in one sector, so a link is provably clear when, in every annulus it
crosses, the line minus the vertical clearance that keeps a point outside the
nu = -0.78 ellipsoid stays above the bound; in the annuli where that holds no sample
can have a loss. The profile is sampled only in the other annuli (not at all when
every annulus clears), and the loss and excess are exactly those of the whole profile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator._jit import compiled

SPEED_OF_LIGHT_MPS = 299_792_458.0
NU_CLEAR = -0.78  # J(nu) = 0 at and below this (P.526 sec. 4.1)
MAX_SAMPLES = 1024  # profile samples per link at most (2 km at the default 2 m step)
SECTORS = 16
TABLE_RANGE_M = 1024.0  # the clearance tables reach this far; longer links are profiled
_MARGIN_M = 1e-6  # covers the rounding of the clearance test


def wavelength_m(frequency_hz: float) -> float:
    return SPEED_OF_LIGHT_MPS / frequency_hz


def knife_edge_loss_db(nu):
    """ITU-R P.526 single knife-edge loss J(nu) in dB (0 for nu <= -0.78)."""
    nu = np.asarray(nu, dtype=float)
    x = np.where(nu > NU_CLEAR, nu, 0.0) - 0.1
    j = 6.9 + 20.0 * np.log10(np.sqrt(x * x + 1.0) + x)
    return np.where(nu > NU_CLEAR, j, 0.0)


J_GRAZING_DB = float(knife_edge_loss_db(0.0))  # the loss at grazing incidence, ~6.03 dB


@dataclass(frozen=True, eq=False)
class Obstruction:
    """The dominant obstacle of each link: ``nu`` (-inf when the profile has no sample),
    the loss J(nu) in dB and the geometric range excess (the path over the edge minus
    the direct path; 0 unless nu > 0)."""

    nu: np.ndarray
    loss_db: np.ndarray
    excess_m: np.ndarray

    @classmethod
    def clear(cls, n: int) -> Obstruction:
        return cls(np.full(n, -np.inf), np.zeros(n), np.zeros(n))

    @classmethod
    def of_nu(cls, nu: np.ndarray, lam_m: float) -> Obstruction:
        nu = np.asarray(nu, dtype=float)
        return cls(nu, knife_edge_loss_db(nu), np.where(nu > 0.0, 0.25 * lam_m * nu * nu, 0.0))


def profile_nu(a_enu_m: np.ndarray, b_enu_m: np.ndarray, terrain, lam_m: float,
               step_m: float, cleared: np.ndarray | None = None,
               radii_m: np.ndarray | None = None) -> np.ndarray:
    """nu of the dominant obstacle of each link A[i] -> B[i] ((L, 3) each) over
    ``terrain`` (its ``height_m`` on arrays), from the profile described in the module
    docstring; -inf for a link without samples. ``cleared`` (L, R) marks the annuli
    ``radii_m[r] <= x < radii_m[r + 1]`` (horizontal distance x from A) where every
    sample is known to have nu <= -0.78: they are not sampled (the result differs only
    where the largest nu is at most -0.78, which has no loss and no excess)."""
    a = np.ascontiguousarray(a_enu_m, dtype=float).reshape(-1, 3)
    b = np.ascontiguousarray(b_enu_m, dtype=float).reshape(-1, 3)
    if cleared is None or radii_m is None:
        cleared, radii_m = np.zeros((len(a), 0), dtype=np.bool_), np.zeros(1)
    link, t, e, n = compiled(_profile_samples)(a, b, float(step_m), MAX_SAMPLES,
                                                np.ascontiguousarray(cleared),
                                                np.ascontiguousarray(radii_m, dtype=float))
    if len(link) == 0:
        return np.full(len(a), -np.inf)
    ground = np.ascontiguousarray(terrain.height_m(e, n), dtype=float).reshape(-1)
    return compiled(_profile_max_nu)(a, b, link, t, ground, float(lam_m))


def link_obstruction(a_enu_m: np.ndarray, b_enu_m: np.ndarray, terrain, frequency_hz: float,
                     step_m: float) -> Obstruction:
    """The obstruction of links A[i] -> B[i] over ``terrain`` (the whole profile)."""
    lam = wavelength_m(frequency_hz)
    return Obstruction.of_nu(profile_nu(a_enu_m, b_enu_m, terrain, lam, step_m), lam)


# ----------------------------------------------------------------------------- CasADi


SMOOTH_NU_TAU = 0.2  # soft-max scale over the samples' nu (above the max by <= tau log n)
SMOOTH_LOSS_TAU_DB = 0.3  # soft-plus scale of the loss (0.21 dB at nu = -0.78)
SMOOTH_SIGN_M = 0.05  # the sign of the terrain's height above the line, tanh(h / this)


def smooth_loss_db(a, b, terrain, lam_m: float, n_samples: int = 6):
    """A smooth (CasADi) approximation of J(nu) of the links A -> B (3 x 1 or 3 x M
    columns): ``n_samples`` profile points at the fixed fractions t_j = j / (n + 1) of
    the link, each with the profile's own nu_j = 2 sqrt(Delta_j / lambda) signed by
    tanh(h_j / 5 cm) (h_j the terrain's height above the line there), a soft-max of the
    nu_j (scale :data:`SMOOTH_NU_TAU`), J written for every nu (it turns negative below
    -0.78) and a soft-plus (scale :data:`SMOOTH_LOSS_TAU_DB`) in place of the cut at 0.
    Differentiable wherever Ipopt goes; coarse: an obstacle narrower than the sample
    spacing can fall between the samples."""
    import casadi as ca

    m = max(a.shape[1], b.shape[1])
    a = ca.repmat(a, 1, m) if a.shape[1] == 1 else a
    b = ca.repmat(b, 1, m) if b.shape[1] == 1 else b
    d = b - a
    s = ca.sqrt(ca.sum1(d * d))
    rows = []
    for j in range(1, n_samples + 1):
        t = j / (n_samples + 1.0)
        line = a + t * d
        ground = terrain.height_m(line[0, :], line[1, :])
        p = ca.vertcat(line[0, :], line[1, :], ground)
        pa, pb = p - a, b - p
        delta = ca.sqrt(ca.sum1(pa * pa)) + ca.sqrt(ca.sum1(pb * pb)) - s
        delta = 0.5 * (delta + ca.sqrt(delta * delta + 1e-12))  # >= 0, smoothly
        sign = ca.tanh((ground - line[2, :]) / SMOOTH_SIGN_M)
        rows.append(2.0 * ca.sqrt(delta / lam_m) * sign)
    nu = ca.vertcat(*rows)
    top = nu[0, :]
    for j in range(1, n_samples):
        top = ca.fmax(top, nu[j, :])
    total = 0
    for j in range(n_samples):
        total = total + ca.exp((nu[j, :] - top) / SMOOTH_NU_TAU)
    nu_max = top + SMOOTH_NU_TAU * ca.log(total)
    x = nu_max - 0.1
    j_db = 6.9 + 20.0 * ca.log(ca.sqrt(x * x + 1.0) + x) / math.log(10.0)
    tau = SMOOTH_LOSS_TAU_DB
    return tau * ca.log1p(ca.exp(j_db / tau))


# ----------------------------------------------------------------------------- the tables


def _sector_boxes(x: float, y: float, radii: np.ndarray, th0: float, th1: float) -> np.ndarray:
    """(R, 4) bounding boxes (e_min, e_max, n_min, n_max) of the annular sectors
    radii[i]..radii[i + 1], th0..th1 (radians) about (x, y): the extremes over the
    sector's corners and the axis directions inside it, padded for rounding."""
    angles = [th0, th1] + [k * 0.5 * math.pi for k in range(-4, 9)
                           if th0 < k * 0.5 * math.pi < th1]
    c = np.array([math.cos(t) for t in angles])
    sn = np.array([math.sin(t) for t in angles])
    r = np.stack([radii[:-1], radii[1:]], axis=1)[:, :, None]  # (R, 2, 1)
    es, ns = (x + r * c).reshape(len(r), -1), (y + r * sn).reshape(len(r), -1)
    pad = 1e-9 * np.maximum(max(1.0, abs(x), abs(y)), radii[1:])
    return np.column_stack([es.min(axis=1) - pad, es.max(axis=1) + pad,
                            ns.min(axis=1) - pad, ns.max(axis=1) + pad])


class Occluder:
    """Obstruction of the links from fixed responders to moving drones over one terrain,
    with the clearance tables of the module docstring (when the terrain bounds its
    height over boxes) to skip the profiles of links that provably clear."""

    def __init__(self, terrain, responders_enu_m: np.ndarray, frequency_hz: float,
                 step_m: float) -> None:
        self.terrain = terrain
        self.resp = np.asarray(responders_enu_m, dtype=float).reshape(-1, 3)
        self.lam = wavelength_m(frequency_hz)
        self.step_m = float(step_m)
        # nu <= -0.78 outside the ellipsoid Delta = lambda 0.78^2 / 4
        self.delta_m = self.lam * NU_CLEAR * NU_CLEAR / 4.0
        n_ann = max(1, math.ceil(math.log2(TABLE_RANGE_M / (0.5 * self.step_m))))
        self.radii = 0.5 * self.step_m * 2.0 ** np.arange(n_ann + 1)
        self.bound = None
        self.n_profiled = 0  # links whose profile was sampled (for benchmarks)
        self.n_links = 0
        self._box = getattr(terrain, "max_height_m", None)
        if self._box is not None and len(self.resp):
            # filled a sector at a time, when a link first lies in it
            self.bound = np.full((len(self.resp), n_ann, SECTORS), np.nan)
            self._filled = np.zeros((len(self.resp), SECTORS), dtype=bool)

    def _fill(self, k: int, j: int) -> None:
        """The bounds of responder k's sector j, annulus by annulus."""
        x, y = float(self.resp[k, 0]), float(self.resp[k, 1])
        th0 = -math.pi + 2.0 * math.pi * j / SECTORS
        th1 = -math.pi + 2.0 * math.pi * (j + 1) / SECTORS
        for i, box in enumerate(_sector_boxes(x, y, self.radii, th0, th1).tolist()):
            self.bound[k, i, j] = self._box(*box)
        self._filled[k, j] = True

    def cleared_annuli(self, k: np.ndarray, p_enu_m: np.ndarray) -> np.ndarray | None:
        """(L, R) the annuli where the tables show every profile sample of the link
        (responder k[i], drone p[i]) to have nu <= -0.78 (annuli beyond the link
        count as cleared); None without tables."""
        if self.bound is None:
            return None
        d = p_enu_m - self.resp[k]
        sector = (np.arctan2(d[:, 1], d[:, 0]) + math.pi) * (SECTORS / (2 * math.pi))
        sector = np.clip(sector.astype(np.int64), 0, SECTORS - 1)
        todo = ~self._filled[k, sector]
        if todo.any():
            for kk, jj in set(zip(k[todo].tolist(), sector[todo].tolist(), strict=True)):
                self._fill(kk, jj)
        return compiled(_cleared_annuli)(np.ascontiguousarray(d), self.resp[k, 2], k, sector,
                                         self.bound, self.radii, self.delta_m, _MARGIN_M)

    def obstruction(self, k: np.ndarray, p_enu_m: np.ndarray) -> Obstruction:
        """The obstruction of the links from responders ``k`` (indices) to drone
        antennas ``p_enu_m`` (L, 3)."""
        k = np.asarray(k, dtype=np.int64).reshape(-1)
        p = np.asarray(p_enu_m, dtype=float).reshape(-1, 3)
        nu = np.full(len(k), -np.inf)
        d = p - self.resp[k]
        horiz = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
        todo = np.flatnonzero(np.ceil(horiz / self.step_m) > 1.0)  # links with samples
        ok = self.cleared_annuli(k[todo], p[todo])
        if ok is not None:
            keep = ~ok.all(axis=1) | (horiz[todo] >= self.radii[-1])
            todo, ok = todo[keep], ok[keep]
        self.n_links += len(k)
        self.n_profiled += len(todo)
        if len(todo):
            nu[todo] = profile_nu(self.resp[k[todo]], p[todo], self.terrain, self.lam,
                                  self.step_m, ok, self.radii)
        return Obstruction.of_nu(nu, self.lam)


# ----------------------------------------------------------------------------- compiled loops
# (estimator._jit.compiled: numba on first use; + - * / and sqrt only, so the same values
# interpreted)


def _profile_samples(a: np.ndarray, b: np.ndarray, step: float, max_samples: int,
                     cleared: np.ndarray, radii: np.ndarray):
    """The profile samples of links A[i] -> B[i] outside their ``cleared`` annuli: the
    link of each, its fraction t along the link and its horizontal position (e, n)."""
    n_ann = cleared.shape[1]
    total = 0
    for i in range(len(a)):
        dx, dy = b[i, 0] - a[i, 0], b[i, 1] - a[i, 1]
        x_len = math.sqrt(dx * dx + dy * dy)
        n = min(max(math.ceil(x_len / step) - 1, 0), max_samples)
        total += n
    link = np.empty(total, dtype=np.int64)
    t = np.empty(total)
    e = np.empty(total)
    nn = np.empty(total)
    m = 0
    for i in range(len(a)):
        dx, dy = b[i, 0] - a[i, 0], b[i, 1] - a[i, 1]
        x_len = math.sqrt(dx * dx + dy * dy)
        n = min(max(math.ceil(x_len / step) - 1, 0), max_samples)
        r = 0  # the annulus of the sample's horizontal distance
        for j in range(n):
            tj = (j + 1.0) / (n + 1.0)
            x = tj * x_len
            while r < n_ann and x >= radii[r + 1]:
                r += 1
            if r < n_ann and x >= radii[r] and cleared[i, r]:
                continue
            link[m] = i
            t[m] = tj
            e[m] = a[i, 0] + tj * dx
            nn[m] = a[i, 1] + tj * dy
            m += 1
    return link[:m], t[:m], e[:m], nn[:m]


def _profile_max_nu(a: np.ndarray, b: np.ndarray, link: np.ndarray, t: np.ndarray,
                    ground: np.ndarray, lam: float) -> np.ndarray:
    """The largest nu per link over its samples: the terrain point P = (e, n, ground)
    under the line point A + t (B - A) has Delta = |AP| + |PB| - |AB| and
    nu = +-2 sqrt(Delta / lambda), + when P is above the line."""
    nu = np.full(len(a), -np.inf)
    for q in range(len(link)):
        i = link[q]
        dx, dy, dz = b[i, 0] - a[i, 0], b[i, 1] - a[i, 1], b[i, 2] - a[i, 2]
        px, py = a[i, 0] + t[q] * dx, a[i, 1] + t[q] * dy
        z_line = a[i, 2] + t[q] * dz
        g = ground[q]
        ex, ey, ez = px - a[i, 0], py - a[i, 1], g - a[i, 2]
        fx, fy, fz = b[i, 0] - px, b[i, 1] - py, b[i, 2] - g
        delta = (math.sqrt(ex * ex + ey * ey + ez * ez) + math.sqrt(fx * fx + fy * fy + fz * fz)
                 - math.sqrt(dx * dx + dy * dy + dz * dz))
        r = 2.0 * math.sqrt(max(delta, 0.0) / lam)
        v = r if g > z_line else -r
        if v > nu[i]:
            nu[i] = v
    return nu


def _cleared_annuli(d: np.ndarray, z_a: np.ndarray, k: np.ndarray, sector: np.ndarray,
                    bound: np.ndarray, radii: np.ndarray, delta: float,
                    margin: float) -> np.ndarray:
    """(L, R): annulus r of link i (from responder k[i], at height z_a[i], along d[i]) is
    cleared when the line's lowest point in it, less the vertical clearance that keeps
    a point below the line outside the ellipsoid Delta = ``delta`` (its distance across
    the line, v cos(eps), above min(b, sqrt(delta (2 u + delta))): u the axial distance
    from the link's lower end, b the ellipsoid's semi-minor axis), is above
    ``bound[k, r, sector]`` (+ ``margin``); annuli beyond the link are cleared. A
    near-vertical link clears nothing (the profile decides)."""
    n_ann = len(radii) - 1
    ok = np.zeros((len(k), n_ann), dtype=np.bool_)
    for i in range(len(k)):
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        x = math.sqrt(dx * dx + dy * dy)
        s = math.sqrt(x * x + dz * dz)
        if not (s > 0.0 and x / s > 1e-6):
            continue
        cos_e = x / s
        slope = dz / x
        semi = 0.5 * math.sqrt(delta * (2.0 * s + delta))
        for r in range(n_ann):
            r0 = radii[r]
            if r0 >= x:
                ok[i, r] = True
                continue
            x1 = min(radii[r + 1], x)
            if slope >= 0.0:
                z_lo = z_a[i] + slope * r0
                u = x1 / cos_e
            else:
                z_lo = z_a[i] + slope * x1
                u = (x - r0) / cos_e
            need = min(semi, math.sqrt(delta * (2.0 * u + delta))) / cos_e
            ok[i, r] = z_lo - need > bound[k[i], r, sector[i]] + margin
    return ok
