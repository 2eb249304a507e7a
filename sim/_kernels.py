"""The multirotor's inner loops (:mod:`sim.vehicle`), compiled with numba.

One tick of the point-mass dynamics (:func:`tick`), the path and hold guidance laws
(:func:`path_command`, :func:`hold_command`) and a run of ticks under one of them
(:func:`fly`) are plain Python on floats and float arrays; numba compiles them on first
use and caches the machine code (``cache=True``: next to this file, or in numba's
user cache directory when that is read-only). ``NUMBA_DISABLE_JIT=1`` runs the same
source interpreted, with the same values bit for bit: the one operation whose
compiled and interpreted forms differ, ``math.hypot`` (CPython rounds it its own way,
numba calls libm), is never called: :func:`hypot` is CPython's algorithm written out
(where the Python code this replaced called ``math.hypot``) and ``np.hypot`` is libm's
in both forms (where it called NumPy).

This module is imported on a vehicle's first tick, not with :mod:`sim`, so commands
that never fly pay nothing for numba.

Layouts (float64 arrays):

- vehicle parameters ``p``: :data:`DT`, :data:`A_LONG`, ... (per tick limits);
- vehicle state ``st``: x, y, z, vx, vy, vz, yaw (controller state, true frame);
- path ``path``: rows s (arc length), x, y, z, tangent x, y, z, profile speed v, one
  column per node; ``dwell`` (hover seconds per node), ``stop_after`` (the next stop
  after each node);
- path guidance state ``gs``: node index, reference arc length, dwell left, next stop,
  done (0/1); guidance constants ``gc``: position gain, lag limit, crawl speed,
  acceptance radius.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

DT, A_LONG, A_LAT, A_Z, VMAX, VZ_MAX, YAW_STEP, WIND_E, WIND_N = range(9)
G_I, G_S, G_DWELL, G_STOP, G_DONE = range(5)
C_GAIN, C_LAG, C_CRAWL, C_ARRIVE = range(4)
HOLD, PATH = 0, 1

_SPLIT = 134217729.0  # 2^27 + 1: Veltkamp's splitter for doubles
_DBL_MIN = 2.2250738585072014e-308


@njit(cache=True)
def _two_product(x: float, y: float) -> tuple[float, float]:
    """x * y as an unevaluated sum hi + lo, exactly (Dekker)."""
    t = x * _SPLIT
    xh = t - (t - x)
    xl = x - xh
    t = y * _SPLIT
    yh = t - (t - y)
    yl = y - yh
    hi = x * y
    return hi, xh * yh - hi + xh * yl + xl * yh + xl * yl


@njit(cache=True)
def hypot(a: float, b: float) -> float:
    """sqrt(a^2 + b^2) rounded as CPython's ``math.hypot`` rounds it (its
    ``vector_norm``: lossless scaling, squaring and summation, then one correction
    step), so compiled and interpreted flights agree bit for bit."""
    a = abs(a)
    b = abs(b)
    mx = a if a > b or b != b else b  # the larger, NaN ignored (inf wins over NaN)
    if math.isinf(mx):
        return mx
    if a != a or b != b:
        return math.nan
    if mx == 0.0:
        return mx
    _, e = math.frexp(mx)
    if e < -1023:  # subnormal: scale into the normal range first
        return _DBL_MIN * hypot(a / _DBL_MIN, b / _DBL_MIN)
    scale = math.ldexp(1.0, -e)
    csum, frac1, frac2 = 1.0, 0.0, 0.0
    for x in (a * scale, b * scale):
        hi, lo = _two_product(x, x)
        s = csum + hi
        frac2 += (csum - s) + hi
        csum = s
        frac1 += lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2))
    hi, lo = _two_product(-h, h)
    s = csum + hi
    frac2 += (csum - s) + hi
    csum = s
    frac1 += lo
    h += (csum - 1.0 + (frac1 + frac2)) / (2.0 * h)
    return h / scale


@njit(cache=True)
def tick(st: np.ndarray, cx: float, cy: float, cz: float, p: np.ndarray) -> None:
    """Advance the state ``st`` one tick towards the velocity command (cx, cy, cz):
    air speed, along-track, lateral and vertical acceleration and vertical speed
    limits, trapezoidal position update, the nose after the course within the yaw
    rate. In place."""
    dt = p[DT]
    vmax = p[VMAX]
    we, wn = p[WIND_E], p[WIND_N]
    x, y, z, vx, vy, vz, yaw = st[0], st[1], st[2], st[3], st[4], st[5], st[6]
    if we != 0.0 or wn != 0.0:  # air speed: shorten the ground velocity along itself
        ax_, ay_ = cx - we, cy - wn
        if ax_ * ax_ + ay_ * ay_ > vmax * vmax:
            cw = cx * we + cy * wn
            c2 = cx * cx + cy * cy
            lam = (cw + math.sqrt(cw * cw - c2 * (we * we + wn * wn - vmax * vmax))) / c2
            cx *= lam
            cy *= lam
    elif cx * cx + cy * cy > vmax * vmax:
        sc = vmax / hypot(cx, cy)
        cx *= sc
        cy *= sc
    # horizontal: along-track and lateral acceleration limits
    dvx, dvy = cx - vx, cy - vy
    sp = hypot(vx, vy)
    if sp > 0.1:
        ux, uy = vx / sp, vy / sp
    else:
        dn = hypot(dvx, dvy)
        if dn > 0:
            ux, uy = dvx / dn, dvy / dn
        else:
            ux, uy = 1.0, 0.0
    along = dvx * ux + dvy * uy
    latx, laty = dvx - along * ux, dvy - along * uy
    a_long = p[A_LONG]
    if along > a_long:
        along = a_long
    elif along < -a_long:
        along = -a_long
    a_lat = p[A_LAT]
    lat = hypot(latx, laty)
    if lat > a_lat:
        latx *= a_lat / lat
        laty *= a_lat / lat
    nvx = vx + along * ux + latx
    nvy = vy + along * uy + laty
    ax_, ay_ = nvx - we, nvy - wn
    air = hypot(ax_, ay_)
    if air > vmax:
        nvx = we + ax_ * vmax / air
        nvy = wn + ay_ * vmax / air
    a_z = p[A_Z]
    dvz = cz - vz
    if dvz > a_z:
        dvz = a_z
    elif dvz < -a_z:
        dvz = -a_z
    nvz = vz + dvz
    vz_max = p[VZ_MAX]
    if nvz > vz_max:
        nvz = vz_max
    elif nvz < -vz_max:
        nvz = -vz_max
    x += 0.5 * (vx + nvx) * dt
    y += 0.5 * (vy + nvy) * dt
    z += 0.5 * (vz + nvz) * dt
    # the nose follows the course, within the yaw-rate limit
    sp = hypot(nvx, nvy)
    if sp > 0.5:
        step = p[YAW_STEP]
        d = math.atan2(nvy, nvx) - yaw
        d = (d + math.pi) % (2.0 * math.pi) - math.pi
        if d > step:
            yaw += step
        elif d < -step:
            yaw += -step
        else:
            yaw += d
    st[0], st[1], st[2], st[3], st[4], st[5], st[6] = x, y, z, nvx, nvy, nvz, yaw


@njit(cache=True)
def hold_command(point: np.ndarray, gain: float, px: float, py: float,
                 pz: float) -> tuple[float, float, float]:
    """Velocity command of the hold: a proportional pull to ``point``."""
    return gain * (point[0] - px), gain * (point[1] - py), gain * (point[2] - pz)


@njit(cache=True)
def path_command(path: np.ndarray, dwell: np.ndarray, stop_after: np.ndarray,
                 gs: np.ndarray, gc: np.ndarray, px: float, py: float, pz: float,
                 dt: float) -> tuple[float, float, float]:
    """Velocity command of the path guidance at the navigation position for one tick:
    feed-forward along the path at the profile speed plus a proportional pull to the
    reference point, which advances while the vehicle is within the lag limit or ahead
    of it, stops at every hover for its dwell and never passes the next stop. Updates
    ``gs``."""
    s, xs, ys, zs, v = path[0], path[1], path[2], path[3], path[7]
    last = path.shape[1] - 1
    i = int(gs[G_I])
    s_ref = gs[G_S]
    if i < last:  # the reference point and its profile speed
        f = (s_ref - s[i]) / (s[i + 1] - s[i])
        rx = xs[i] + f * (xs[i + 1] - xs[i])
        ry = ys[i] + f * (ys[i + 1] - ys[i])
        rz = zs[i] + f * (zs[i + 1] - zs[i])
        vr = v[i] + f * (v[i + 1] - v[i])
    else:
        rx, ry, rz, vr = xs[last], ys[last], zs[last], 0.0
    ex, ey, ez = rx - px, ry - py, rz - pz
    lag = math.sqrt(ex * ex + ey * ey + ez * ez)
    if gs[G_DWELL] > 0.0:  # hovering at a stop
        vr = 0.0
        if lag < 0.5:
            gs[G_DWELL] -= dt
    elif i < last and (lag < gc[C_LAG] or ex * path[4, i] + ey * path[5, i]
                       + ez * path[6, i] < 0.0):
        # advance along the profile (at least at crawl speed: the profile is 0 at a
        # stop), never past the next stop; also beyond the lag limit when the vehicle
        # is ahead of the reference (a new path started at speed: it overshot the
        # start): waiting there would balance the feed-forward against the pull back
        # and hold the vehicle still forever
        stop = int(gs[G_STOP])
        s_new = s_ref + max(vr, gc[C_CRAWL]) * dt
        if s_new >= s[stop]:
            s_new = s[stop]
            if stop < last:
                gs[G_DWELL] = dwell[stop]
                gs[G_STOP] = stop_after[stop]
        gs[G_S] = s_new
        while i < last and s[i + 1] <= s_new:
            i += 1
        gs[G_I] = i
    if i >= last:
        vr = 0.0
        if lag < gc[C_ARRIVE]:
            gs[G_DONE] = 1.0
    k = gc[C_GAIN]
    return vr * path[4, i] + k * ex, vr * path[5, i] + k * ey, vr * path[6, i] + k * ez


@njit(cache=True)
def fly(st: np.ndarray, nav: np.ndarray, p: np.ndarray, mode: int, point: np.ndarray,
        path: np.ndarray, dwell: np.ndarray, stop_after: np.ndarray, gs: np.ndarray,
        gc: np.ndarray, until_done: bool, rows: np.ndarray) -> int:
    """Fly ``len(rows)`` ticks under the hold (``mode`` HOLD, ``point``) or the path
    guidance (PATH), navigating on the state plus ``nav`` (per tick; an empty array:
    on the state itself). Columns 1-7 of each row get the state after the tick; with
    ``until_done``, stops after the tick where the path is done. The ticks flown."""
    n = rows.shape[0]
    with_nav = nav.shape[0] > 0
    dt = p[DT]
    for j in range(n):
        px, py, pz = st[0], st[1], st[2]
        if with_nav:
            px, py, pz = px + nav[j, 0], py + nav[j, 1], pz + nav[j, 2]
        if mode == HOLD:
            cx, cy, cz = hold_command(point, gc[C_GAIN], px, py, pz)
        else:
            cx, cy, cz = path_command(path, dwell, stop_after, gs, gc, px, py, pz, dt)
        tick(st, cx, cy, cz, p)
        for c in range(7):
            rows[j, c + 1] = st[c]
        if until_done and mode == PATH and gs[G_DONE] != 0.0:
            return j + 1
    return n


@njit(cache=True)
def grid_lerp(values: np.ndarray, t0: float, dt: float, t: np.ndarray) -> np.ndarray:
    """(len(t), C) rows of ``values`` (N, C), sampled every ``dt`` from ``t0``, linearly
    interpolated at times ``t``, clamped to the sampled span."""
    n, cols = values.shape
    out = np.empty((len(t), cols))
    for k in range(len(t)):
        f = min(max((t[k] - t0) / dt, 0.0), n - 1.0)
        i = min(int(f), max(n - 2, 0))
        w = f - i
        j = min(i + 1, n - 1)
        for c in range(cols):
            out[k, c] = values[i, c] * (1.0 - w) + values[j, c] * w
    return out


@njit(cache=True)
def lerp_after(v: np.ndarray, f: np.ndarray, k0: int) -> np.ndarray:
    """(len(f), C) rows of ``v`` (row r at grid index k0 + r) linearly interpolated at
    the fractional grid indices ``f`` (each with a row after it)."""
    out = np.empty((len(f), v.shape[1]))
    for m in range(len(f)):
        k = math.floor(f[m])
        w = f[m] - k
        i = k - k0
        for c in range(v.shape[1]):
            out[m, c] = v[i, c] * (1.0 - w) + v[i + 1, c] * w
    return out


@njit(cache=True)
def extent(p: np.ndarray) -> tuple[float, float, float, float, float]:
    """(e_min, e_max, n_min, n_max, z_min) of the (N >= 1, 3) positions ``p``."""
    e0 = e1 = p[0, 0]
    n0 = n1 = p[0, 1]
    z0 = p[0, 2]
    for i in range(1, p.shape[0]):
        e0, e1 = min(e0, p[i, 0]), max(e1, p[i, 0])
        n0, n1 = min(n0, p[i, 1]), max(n1, p[i, 1])
        z0 = min(z0, p[i, 2])
    return e0, e1, n0, n1, z0


@njit(cache=True)
def hill_exponents(e: np.ndarray, n: np.ndarray, hc: np.ndarray) -> np.ndarray:
    """(K, N) exponents -r^2 / (2 sigma^2) of the K Gaussian hills ``hc`` (rows: centre
    e, centre n, height, sigma^2) at the N points (e, n)."""
    out = np.empty((hc.shape[1], len(e)))
    for k in range(hc.shape[1]):
        for j in range(len(e)):
            de, dn = e[j] - hc[0, k], n[j] - hc[1, k]
            out[k, j] = -0.5 * (de * de + dn * dn) / hc[3, k]
    return out


@njit(cache=True)
def hills_terrain(e: np.ndarray, n: np.ndarray, base: float, slope_e: float, slope_n: float,
                  hc: np.ndarray, bumps: np.ndarray, cos_a: float, sin_a: float,
                  k: float) -> tuple[np.ndarray, np.ndarray]:
    """The hilly terrain's plane plus its hills (``bumps``: exp of :func:`hill_exponents`,
    added hill by hill) at the points (e, n), and the ripple's phase there,
    k (cos a e + sin a n)."""
    h = np.empty(len(e))
    phase = np.empty(len(e))
    for j in range(len(e)):
        v = base + slope_e * e[j] + slope_n * n[j]
        for i in range(hc.shape[1]):
            v = v + hc[2, i] * bumps[i, j]
        h[j] = v
        phase[j] = k * (cos_a * e[j] + sin_a * n[j])
    return h, phase


@njit(cache=True)
def densify(t: np.ndarray, en: np.ndarray, z: np.ndarray,
            step_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split each segment of the reference (t, en, z) into equal pieces of at most
    ``step_m`` (horizontally and vertically), linearly interpolated."""
    n = len(t) - 1
    pieces = np.empty(n, np.int64)
    total = 0
    for i in range(n):
        seg = max(np.hypot(en[i + 1, 0] - en[i, 0], en[i + 1, 1] - en[i, 1]),
                  abs(z[i + 1] - z[i]))
        pieces[i] = int(max(1.0, np.ceil(seg / step_m)))
        total += pieces[i]
    t_d = np.empty(total + 1)
    en_d = np.empty((total + 1, 2))
    z_d = np.empty(total + 1)
    j = 0
    for i in range(n):
        p = pieces[i]
        dt, de, dn, dz = t[i + 1] - t[i], en[i + 1, 0] - en[i, 0], en[i + 1, 1] - en[i, 1], \
            z[i + 1] - z[i]
        for k in range(p):
            f = k / p
            t_d[j] = t[i] + f * dt
            en_d[j, 0] = en[i, 0] + f * de
            en_d[j, 1] = en[i, 1] + f * dn
            z_d[j] = z[i] + f * dz
            j += 1
    t_d[total], en_d[total, 0], en_d[total, 1], z_d[total] = t[n], en[n, 0], en[n, 1], z[n]
    return t_d, en_d, z_d


@njit(cache=True)
def path_nodes(t_d: np.ndarray, pd: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The path's nodes: the dense points without zero-length steps, with their arc
    length, the hover time each holds (a zero-length step with time) and the
    reference time spent moving up to each. (nodes (m, 3), s, dwell_s, t_move_s)."""
    n = len(t_d)
    keep = np.empty(n, np.bool_)
    keep[0] = True
    seg = np.empty(n)  # seg[i]: length of the step ending at dense point i
    seg[0] = 0.0
    m = 1
    for i in range(1, n):
        dx, dy, dz = pd[i, 0] - pd[i - 1, 0], pd[i, 1] - pd[i - 1, 1], pd[i, 2] - pd[i - 1, 2]
        seg[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
        keep[i] = seg[i] > 1e-9
        if keep[i]:
            m += 1
    pts = np.empty((m, 3))
    s = np.empty(m)
    dwell = np.zeros(m)
    t_move = np.empty(m)
    s_all, t_acc, node = 0.0, 0.0, 0
    pts[0, :] = pd[0, :]
    s[0], t_move[0] = 0.0, 0.0
    for i in range(1, n):
        s_all += seg[i]
        dt = t_d[i] - t_d[i - 1]
        if keep[i]:
            t_acc += dt
            node += 1
            pts[node, :] = pd[i, :]
            s[node], t_move[node] = s_all, t_acc
        elif dt > 0:
            dwell[node] += dt
    return pts, s, dwell, t_move


@njit(cache=True)
def limit_passes(v2: np.ndarray, step: np.ndarray, start_v2: float) -> np.ndarray:
    """The speed profile's two passes on v^2: backward, v2[i] <= v2[i+1] + step[i]
    (braking before each stop), then forward from v2[0] <= start_v2,
    v2[i] <= v2[i-1] + step[i-1] (acceleration). A new array."""
    out = v2.copy()
    for i in range(len(out) - 2, -1, -1):
        lim = out[i + 1] + step[i]
        if out[i] > lim:
            out[i] = lim
    if out[0] > start_v2:
        out[0] = start_v2
    for i in range(1, len(out)):
        lim = out[i - 1] + step[i - 1]
        if out[i] > lim:
            out[i] = lim
    return out


@njit(cache=True)
def path_profile(pts: np.ndarray, s: np.ndarray, dwell: np.ndarray, t_move: np.ndarray,
                 course: np.ndarray, lim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The path's (8, m) array (see the module docstring) and the next stop after each
    node, from its m >= 2 nodes and ``course``, the direction of each step
    (``numpy.arctan2``: NumPy's own rounding). ``lim``: path step, maximum speed,
    vertical speed, yaw rate (rad/s), lateral and along-track acceleration, sharp turn
    (rad), crawl speed, start speed squared.

    The speed at each node is the least of the reference speed, the maximum speed, the
    climb limit |dz/ds| v <= v_z and the turn limits v^2 kappa <= a_lat, v kappa <= r
    (sharp corners at crawl speed, stops at 0), then braking and acceleration passes;
    between stops the reference never stands still."""
    ds, vmax, vz, yaw_r, a_lat, a_long, sharp, crawl, start_v2 = (
        lim[0], lim[1], lim[2], lim[3], lim[4], lim[5], lim[6], lim[7], lim[8])
    m = len(s)
    out = np.empty((8, m))
    cell = np.empty(m - 1)
    v_cell = np.empty(m - 1)
    h_len = np.empty(m - 1)
    for i in range(m - 1):
        dx, dy, dz = pts[i + 1, 0] - pts[i, 0], pts[i + 1, 1] - pts[i, 1], pts[i + 1, 2] - pts[i, 2]
        c = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        cell[i] = c
        out[4, i], out[5, i], out[6, i] = dx / c, dy / c, dz / c
        t_cell = t_move[i + 1] - t_move[i]
        v_ref = c / t_cell if t_cell > 0 else np.inf
        v_climb = vz * c / max(abs(dz), 1e-12)
        v_cell[i] = min(min(v_ref, v_climb), vmax)
        h_len[i] = np.hypot(dx, dy)
    out[4, m - 1], out[5, m - 1], out[6, m - 1] = out[4, m - 2], out[5, m - 2], out[6, m - 2]
    # the course, held over vertical steps, unwrapped (numpy.unwrap's rule)
    psi = np.empty(m - 1)
    first = -1
    for i in range(m - 1):
        if h_len[i] > 1e-6 * ds:
            first = i
            break
    if first < 0:
        psi[:] = 0.0
    else:
        last_valid = first
        for i in range(m - 1):
            if h_len[i] > 1e-6 * ds:
                last_valid = i
            psi[i] = course[last_valid] if i >= first else course[first]
        corr = 0.0
        prev = psi[0]
        for i in range(1, m - 1):
            dd = psi[i] - prev
            prev = psi[i]
            ddmod = (dd + math.pi) % (2.0 * math.pi) - math.pi
            if ddmod == -math.pi and dd > 0:
                ddmod = math.pi
            c = ddmod - dd
            if abs(dd) < math.pi:
                c = 0.0
            corr += c
            psi[i] = psi[i] + corr
    v_node = np.empty(m)
    v_node[0] = v_cell[0]
    v_node[m - 1] = v_cell[m - 2]
    for i in range(m - 2):  # interior node i + 1
        turn = abs(psi[i + 1] - psi[i])
        arc = 0.5 * (h_len[i] + h_len[i + 1])
        curv = turn / max(arc, 1e-9) if turn > 0 else 0.0
        v_turn = min(yaw_r / curv if curv > 0 else np.inf,
                     math.sqrt(a_lat / curv) if curv > 0 else np.inf)
        v = min(min(v_cell[i], v_cell[i + 1]), v_turn)
        if turn > sharp:
            v = 0.0
        v_node[i + 1] = v
    stop_after = np.empty(m)
    nxt = m - 1
    for i in range(m - 1, -1, -1):
        v_node[i] = max(v_node[i], crawl)
        stop = i == m - 1 or dwell[i] > 0
        if stop:
            v_node[i] = 0.0
        v_node[i] = v_node[i] * v_node[i]
        stop_after[i] = nxt
        if dwell[i] > 0:
            nxt = i
    step = np.empty(m - 1)
    for i in range(m - 1):
        step[i] = 2.0 * a_long * cell[i]
    v2 = limit_passes(v_node, step, start_v2)
    for i in range(m):
        v = math.sqrt(v2[i])
        floor = 0.0 if (i == m - 1 or dwell[i] > 0) else crawl
        out[7, i] = max(v, floor)
        out[0, i] = s[i]
        out[1, i], out[2, i], out[3, i] = pts[i, 0], pts[i, 1], pts[i, 2]
    return out, stop_after
