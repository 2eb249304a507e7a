"""Heights that follow the ground: the vertices an autopilot needs to hold a height above
a terrain model while it flies straight lines between mission items.

An autopilot flies straight between items (frames 6 and 0: straight in latitude,
longitude and altitude). Over hills a leg at one altitude is soon too high or too low,
so :func:`follow_terrain` adds vertices where the ground changes: along a horizontal
polyline (the pattern's corners are kept), every point of every straight leg between
the vertices it returns stays within [target - ``below_m``, target + ``above_m``]
above the terrain, the target being the height above ground wanted there.

Method: the path is sampled every ``step_m``; each sample gives a band of allowed
heights, the ground plus the target, less ``below_m`` and plus ``above_m``, each
tightened by ``safety_m`` (what the ground can do between two samples). From a vertex
the funnel of slopes that keeps the leg inside every band ahead is narrowed sample by
sample (the greedy "string pulling" of a 1-D corridor); where it closes, or at a corner
of the polyline, a vertex is placed at the last sample, at the height nearest the
target the funnel allows, and the next leg starts there. The number of vertices is
small where the ground is smooth (a straight leg over a slope needs none) and grows
with its roughness, never with the path's length alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from planner.models import TerrainModel


def follow_terrain(
    points_en: np.ndarray,
    target_agl_m: float | Sequence[float],
    terrain: TerrainModel,
    *,
    below_m: float = 2.0,
    above_m: float = 25.0,
    safety_m: float = 0.5,
    step_m: float = 1.0,
) -> np.ndarray:
    """(M, 3) vertices (e, n, z above the frame origin) over the horizontal polyline
    ``points_en`` (K, 2): its corners and the vertices the ground needs (see the module
    docstring). ``target_agl_m`` is one height above ground or one per point of the
    polyline (linear in between along it)."""
    p = np.asarray(points_en, dtype=float).reshape(-1, 2)
    if len(p) == 0:
        raise ValueError("an empty path")
    if not (below_m >= 0 and above_m >= 0 and 0 <= safety_m and step_m > 0):
        raise ValueError("below_m, above_m, safety_m >= 0 and step_m > 0")
    if 2.0 * safety_m >= below_m + above_m:
        raise ValueError("the band is too narrow for the safety margin")
    tgt = np.broadcast_to(np.asarray(target_agl_m, dtype=float), (len(p),)).astype(float)
    # dense samples along the polyline, the corners among them
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    p, tgt = p[keep], tgt[keep]
    seg = seg[seg > 1e-9]
    xs, ts, corner = [p[:1]], [tgt[:1]], [True]
    for k, L in enumerate(seg):
        n = max(1, math.ceil(L / step_m))
        f = (np.arange(1, n + 1) / n)[:, None]
        xs.append(p[k] + f * (p[k + 1] - p[k]))
        ts.append(tgt[k] + f[:, 0] * (tgt[k + 1] - tgt[k]))
        corner += [False] * (n - 1) + [True]
    xy = np.vstack(xs)
    target = np.concatenate(ts)
    is_corner = np.array(corner)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    ground = np.asarray(terrain.height_m(xy[:, 0], xy[:, 1]), dtype=float)
    want = ground + target
    lo = want - below_m + safety_m
    hi = want + above_m - safety_m
    out_idx = [0]
    out_z = [float(want[0])]
    k0, z0 = 0, float(want[0])
    n_s = len(s)
    k = 1
    slope_lo, slope_hi = -math.inf, math.inf
    while k < n_s:
        ds = s[k] - s[k0]
        new_lo = max(slope_lo, (lo[k] - z0) / ds)
        new_hi = min(slope_hi, (hi[k] - z0) / ds)
        if new_lo > new_hi:  # the funnel closes at k: a vertex at the last sample
            if k - 1 == k0:  # a cliff within one sample: follow it (the check reports it)
                z = float(np.clip(want[k], lo[k], hi[k]))
                out_idx.append(k)
                out_z.append(z)
                k0, z0, k = k, z, k + 1
            else:
                j = k - 1
                z = _nearest(want[j], z0, s[j] - s[k0], slope_lo, slope_hi)
                out_idx.append(j)
                out_z.append(z)
                k0, z0, k = j, z, j + 1
            slope_lo, slope_hi = -math.inf, math.inf
            continue
        slope_lo, slope_hi = new_lo, new_hi
        if is_corner[k] or k == n_s - 1:
            z = _nearest(want[k], z0, ds, slope_lo, slope_hi)
            out_idx.append(k)
            out_z.append(z)
            k0, z0 = k, z
            slope_lo, slope_hi = -math.inf, math.inf
        k += 1
    return np.column_stack([xy[out_idx], np.array(out_z)])


def _nearest(want: float, z0: float, ds: float, slope_lo: float, slope_hi: float) -> float:
    """The height at distance ``ds`` nearest ``want`` within the funnel's slopes."""
    return float(np.clip(want, z0 + slope_lo * ds, z0 + slope_hi * ds))


def agl_along(vertices_enu_m: np.ndarray, terrain: TerrainModel,
              step_m: float = 0.5) -> np.ndarray:
    """Heights above ``terrain`` every ``step_m`` along straight legs between vertices
    (e, n, z above the frame origin)."""
    from planner.patterns import densify

    d = densify(np.asarray(vertices_enu_m, dtype=float), step_m)
    return d[:, 2] - np.asarray(terrain.height_m(d[:, 0], d[:, 1]), dtype=float)
