"""Heights that follow the ground: the vertices an autopilot needs to hold a height above
a terrain model while it flies straight lines between mission items.

An autopilot flies straight between items (frames 6 and 0: straight in latitude,
longitude and altitude). Over hills a leg at one altitude is soon too high or too low,
so :func:`follow_terrain` adds vertices where the ground changes: along a horizontal
polyline (the pattern's corners are kept), every point of every straight leg between
the vertices it returns stays within [target - ``below_m``, target + ``above_m``]
above the terrain (or within ``band_m``), the target being the height above ground
wanted there.

Method: the path is sampled every ``step_m``; between two samples a leg is straight,
so it keeps its band there if at both samples it keeps it over the highest (and under
the lowest) ground of the interval between them. That ground is found on sub-samples
at most half a terrain cell apart (:func:`_ground_bounds`), widened by half the largest
rise between two of them (a bilinear cell's edge can peak between sub-samples), and
each sample's band is further tightened by ``safety_m``. Where the ground changes by
more than the band within two samples (a cliff in a 1 m LiDAR model), the intervals
there are halved until the bands open (down to ``min_step_m``). From a vertex the
funnel of slopes that keeps the leg inside every band ahead is narrowed sample by
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

_MAX_HALVINGS = 12  # a 1 m interval down to 0.25 mm: beyond any cliff a band can climb


def follow_terrain(
    points_en: np.ndarray,
    target_agl_m: float | Sequence[float],
    terrain: TerrainModel,
    *,
    below_m: float = 2.0,
    above_m: float = 25.0,
    safety_m: float = 0.5,
    step_m: float = 1.0,
    band_m: tuple[float, float] | None = None,
    min_step_m: float = 0.01,
) -> np.ndarray:
    """(M, 3) vertices (e, n, z above the frame origin) over the horizontal polyline
    ``points_en`` (K, 2): its corners and the vertices the ground needs (see the module
    docstring). ``target_agl_m`` is one height above ground or one per point of the
    polyline (linear in between along it). ``band_m`` = (low, high): the heights above
    ground allowed everywhere, whatever the target (which is held inside it), instead
    of target - ``below_m`` to target + ``above_m``."""
    p = np.asarray(points_en, dtype=float).reshape(-1, 2)
    if len(p) == 0:
        raise ValueError("an empty path")
    if not (below_m >= 0 and above_m >= 0 and 0 <= safety_m and step_m > 0
            and min_step_m > 0):
        raise ValueError("below_m, above_m, safety_m >= 0 and step_m, min_step_m > 0")
    width = below_m + above_m if band_m is None else band_m[1] - band_m[0]
    if 2.0 * safety_m >= width:
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
    if len(xy) == 1:
        g0 = float(np.asarray(terrain.height_m(xy[:, 0], xy[:, 1]), dtype=float)[0])
        t0 = float(target[0]) if band_m is None else float(np.clip(target[0], *band_m))
        return np.array([[xy[0, 0], xy[0, 1], g0 + t0]])
    cell = _cell_m(terrain)
    sub_m = 0.25 * step_m if cell is None else min(0.25 * step_m, 0.5 * cell)
    for _ in range(_MAX_HALVINGS + 1):
        g_hi, g_lo, ground = _ground_bounds(xy, terrain, sub_m)
        if band_m is None:
            lo_agl, hi_agl, want_agl = target - below_m, target + above_m, target
        else:
            lo_agl = np.full(len(xy), float(band_m[0]))
            hi_agl = np.full(len(xy), float(band_m[1]))
            want_agl = np.clip(target, band_m[0] + safety_m, band_m[1] - safety_m)
        # each sample keeps the band over the ground of the intervals on both sides
        top = np.concatenate([g_hi[:1], np.maximum(g_hi[:-1], g_hi[1:]), g_hi[-1:]])
        bottom = np.concatenate([g_lo[:1], np.minimum(g_lo[:-1], g_lo[1:]), g_lo[-1:]])
        lo = top + lo_agl + safety_m
        hi = bottom + hi_agl - safety_m
        shut = lo > hi
        if not shut.any():
            break
        length = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        split = (shut[:-1] | shut[1:]) & (length > 2.0 * min_step_m)
        if not split.any():
            break  # a wall the band cannot climb even so: followed, and reported by a check
        at = np.flatnonzero(split) + 1
        xy = np.insert(xy, at, 0.5 * (xy[at - 1] + xy[at]), axis=0)
        target = np.insert(target, at, 0.5 * (target[at - 1] + target[at]))
        is_corner = np.insert(is_corner, at, False)
    want = ground + want_agl
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    out_idx = [0]
    z0 = float(min(max(want[0], lo[0]), hi[0]))
    out_z = [z0]
    k0 = 0
    n_s = len(s)
    k = 1
    slope_lo, slope_hi = -math.inf, math.inf
    while k < n_s:
        ds = s[k] - s[k0]
        new_lo = max(slope_lo, (lo[k] - z0) / ds)
        new_hi = min(slope_hi, (hi[k] - z0) / ds)
        if new_lo > new_hi:  # the funnel closes at k: a vertex at the last sample
            if k - 1 == k0:  # a wall within one sample: follow it (the check reports it)
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


def _cell_m(terrain: TerrainModel) -> float | None:
    """The terrain's cell size (m), when it is a grid (a DEM's pixel, a grid's spacing)."""
    px = getattr(terrain, "pixel_m", None)
    if px is not None:
        return float(min(px))
    sp = getattr(terrain, "spacing_m", None)
    return float(sp) if sp is not None else None


def _ground_bounds(xy: np.ndarray, terrain: TerrainModel,
                   sub_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The highest and lowest ground of each straight interval between consecutive
    samples ``xy``, and the ground at the samples. Each interval is cut into sub-steps of
    at most ``sub_m``; the bounds are the sub-samples' extremes widened by half the
    largest rise of a sub-step in the interval or next to it (ground that rises at most
    that steeply cannot peak higher between two sub-samples)."""
    d = np.diff(xy, axis=0)
    q = max(2, math.ceil(float(np.max(np.linalg.norm(d, axis=1))) / sub_m))
    f = np.linspace(0.0, 1.0, q + 1)
    pts = xy[:-1, None, :] + f[None, :, None] * d[:, None, :]
    g = np.asarray(terrain.height_m(pts[..., 0].ravel(), pts[..., 1].ravel()),
                   dtype=float).reshape(pts.shape[:2])
    rise = np.abs(np.diff(g, axis=1))
    worst = rise.max(axis=1)
    worst[1:] = np.maximum(worst[1:], rise[:-1, -1])
    worst[:-1] = np.maximum(worst[:-1], rise[1:, 0])
    ground = np.concatenate([g[:, 0], g[-1:, -1]])
    return g.max(axis=1) + 0.5 * worst, g.min(axis=1) - 0.5 * worst, ground


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
