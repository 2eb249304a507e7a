"""Seeded flight-log worlds for the estimator's tests and benchmarks (numpy only).

Independent of ``sim/`` on purpose: these worlds fix the error model the estimator is
judged against, so they must not change when the simulator does. Every draw comes
from the explicit ``np.random.Generator`` of the world's seed; the same seed writes
byte-identical logs (``estimator.logio.LogWriter``, with ``truth`` records).

Error model (issue 8):

* hilly ground: a smooth analytic terrain of three sinusoids (relief about +-15 m);
* UAV flights: circular sweeps or lawnmower sweeps, terrain-following at 35-55 m AGL
  (the header says 45 m), 4 Hz ranging, response probability falling with slant range;
* range noise sigma = 0.3 sqrt(0.09 + 4e-4 d^2 + 3e-3 q^2), q = max(0, -RSSI - 40),
  RSSI = -38 - 25 log10 d (+ 2 dB noise), a constant per-responder hardware offset
  0.3-1.0 m (+ a per-agent offset), 3 % positive gross outliers (log-normal, median 4 m);
* GNSS = truth + per-axis first-order Gauss-Markov bias (sigma 1.5 m horizontal, 2.5 m
  vertical, tau 1200 s) + white noise 0.12 m; ``acc_m`` an optimistic HDOP proxy
  ~0.9 m. RTK: bias 2 cm, ``fix`` rtk_fixed, ``acc_m`` ~0.014 m;
* a vegetation pass like the paper's AP_AB (a nearly straight 28 m pass in 21 s,
  ~31 ranges, positive NLoS excess);
* three agents: two UAVs and a walking ground agent (1.5 m above ground, 1.4 m/s,
  GNSS bias 3 m, its own range offset), each on its own phone clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimator.geodesy import ExactENU
from estimator.logio import LogWriter
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord

ORIGIN = (36.7151, -4.4783, 100.0)
BSSID = "a4:77:33:0f:1e:02"
START_UTC_S = 1_778_235_120.0  # 2026-05-08T10:12:00Z

PathFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class GnssModel:
    """A receiver: Gauss-Markov bias per axis, white noise, what it logs as accuracy."""

    bias_h_m: float = 1.5
    bias_v_m: float = 2.5
    tau_s: float = 1200.0
    white_h_m: float = 0.12
    white_v_m: float = 0.2
    acc_m: float = 0.9  # logged accM: an optimistic HDOP proxy
    vacc_m: float = 1.5
    fix: str = "3d"
    rate_hz: float = 5.0


STANDALONE = GnssModel()
RTK = GnssModel(bias_h_m=0.02, bias_v_m=0.03, white_h_m=0.01, white_v_m=0.015, acc_m=0.014,
                vacc_m=0.02, fix="rtk_fixed")
WALKER_GNSS = GnssModel(bias_h_m=3.0, bias_v_m=5.0, white_h_m=0.3, white_v_m=0.5, acc_m=2.5,
                        vacc_m=4.0)


@dataclass(frozen=True)
class Terrain:
    """h(e, n) = sum of three sinusoids (m above the origin's ellipsoidal height - 100)."""

    phases: tuple[float, float, float]

    def height(self, e, n):
        p0, p1, p2 = self.phases
        return (7.0 * np.sin(np.asarray(e) / 60.0 + p0) + 6.0 * np.cos(np.asarray(n) / 50.0 + p1)
                + 3.0 * np.sin((np.asarray(e) - np.asarray(n)) / 35.0 + p2))


@dataclass
class AgentTruth:
    """What an agent really did (evaluation only): its ranges' true anchors and sigmas."""

    name: str
    path: Path
    gnss: GnssModel
    t_s: np.ndarray  # agent's phone time of each delivered range (s)
    anchors_enu_m: np.ndarray  # true antenna positions (N, 3), world frame
    sigma_m: np.ndarray  # true range noise sigma (N,)
    offset_m: float  # total constant range offset (responder + agent)


@dataclass
class World:
    name: str
    seed: int
    ap_enu_m: np.ndarray  # world frame (ExactENU at ORIGIN)
    agents: list[AgentTruth] = field(default_factory=list)
    concealment: str = "open"

    @property
    def paths(self) -> list[Path]:
        return [a.path for a in self.agents]

    @property
    def n_ranges(self) -> int:
        return sum(len(a.t_s) for a in self.agents)


def range_sigma_m(d_m: np.ndarray, rssi_dbm: np.ndarray) -> np.ndarray:
    """0.3 sqrt(0.09 + 4e-4 d^2 + 3e-3 q^2), q = max(0, -RSSI - 40)."""
    q = np.maximum(0.0, -rssi_dbm - 40.0)
    return 0.3 * np.sqrt(0.09 + 4e-4 * d_m**2 + 3e-3 * q**2)


def gauss_markov(rng: np.random.Generator, t_s: np.ndarray, sigma: float, tau_s: float
                 ) -> np.ndarray:
    """A stationary first-order Gauss-Markov sequence at times ``t_s`` (sorted)."""
    out = np.empty(t_s.size)
    x = rng.normal(0.0, sigma)
    prev = t_s[0]
    for i, t in enumerate(t_s):
        phi = math.exp(-(t - prev) / tau_s)
        x = phi * x + math.sqrt(max(0.0, 1.0 - phi * phi)) * sigma * rng.normal()
        out[i] = x
        prev = t
    return out


def _terrain(rng: np.random.Generator) -> Terrain:
    return Terrain(tuple(float(v) for v in rng.uniform(0, 2 * np.pi, 3)))


def orbit_path(rng: np.random.Generator, terrain: Terrain, centre: np.ndarray) -> PathFn:
    """Circular sweeps of varying radius about ``centre``, terrain-following 35-55 m AGL."""
    r0 = rng.uniform(40.0, 65.0)
    ra = rng.uniform(10.0, 25.0)
    pr = rng.uniform(60.0, 120.0)
    phr = rng.uniform(0, 2 * np.pi)
    omega = rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 8.0) / r0
    th0 = rng.uniform(0, 2 * np.pi)
    pa = rng.uniform(70.0, 150.0)
    pha = rng.uniform(0, 2 * np.pi)

    def fn(t):
        t = np.asarray(t, float)
        r = r0 + ra * np.sin(2 * np.pi * t / pr + phr)
        th = th0 + omega * t
        e = centre[0] + r * np.cos(th)
        n = centre[1] + r * np.sin(th)
        agl = 45.0 + 10.0 * np.sin(2 * np.pi * t / pa + pha)
        return np.column_stack((e, n, terrain.height(e, n) + agl))

    return fn


def sweep_path(rng: np.random.Generator, terrain: Terrain, centre: np.ndarray) -> PathFn:
    """Lawnmower sweeps (4-5 legs 30 m apart) about ``centre``, back and forth."""
    length = rng.uniform(110.0, 150.0)
    spacing = 30.0
    legs = int(rng.integers(4, 6))
    heading = rng.uniform(0, np.pi)
    c, s = math.cos(heading), math.sin(heading)
    pts = []
    for k in range(legs):
        y = (k - (legs - 1) / 2) * spacing
        xs = (-length / 2, length / 2) if k % 2 == 0 else (length / 2, -length / 2)
        pts += [(xs[0], y), (xs[1], y)]
    pts = np.array(pts + pts[::-1][1:])  # fly back over the same legs
    xy = np.column_stack((centre[0] + c * pts[:, 0] - s * pts[:, 1],
                          centre[1] + s * pts[:, 0] + c * pts[:, 1]))
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    arc = np.concatenate(([0.0], np.cumsum(seg)))
    v = rng.uniform(5.0, 8.0)
    pa = rng.uniform(70.0, 150.0)
    pha = rng.uniform(0, 2 * np.pi)

    def fn(t):
        t = np.asarray(t, float)
        sarc = np.mod(v * t, arc[-1])
        e = np.interp(sarc, arc, xy[:, 0])
        n = np.interp(sarc, arc, xy[:, 1])
        agl = 45.0 + 10.0 * np.sin(2 * np.pi * t / pa + pha)
        return np.column_stack((e, n, terrain.height(e, n) + agl))

    return fn


def _write_agent(
    path: Path,
    rng: np.random.Generator,
    *,
    name: str,
    path_fn: PathFn,
    duration_s: float,
    gnss: GnssModel,
    ap: np.ndarray,
    offset_m: float,
    t0_ns: int,
    start_s: float,
    agl_header_m: float,
    d50_m: float = 100.0,
    p_max: float = 0.95,
    rtt_hz: float = 4.0,
    nlos_mean_m: float = 0.0,
    rssi_loss_db: float = 0.0,
    outlier_rate: float = 0.03,
    concealment: str = "open",
) -> AgentTruth:
    frame = ExactENU(*ORIGIN)
    tg = np.arange(0.0, duration_s, 1.0 / gnss.rate_hz)
    truth = path_fn(tg)
    bias = np.column_stack([gauss_markov(rng, tg, s, gnss.tau_s)
                            for s in (gnss.bias_h_m, gnss.bias_h_m, gnss.bias_v_m)])
    white = rng.normal(0.0, 1.0, (tg.size, 3)) * np.array(
        [gnss.white_h_m, gnss.white_h_m, gnss.white_v_m])
    rep = truth + bias + white
    lat, lon, alt = frame.to_geodetic(rep[:, 0], rep[:, 1], rep[:, 2])
    wob = 0.06 * np.sin(2 * np.pi * tg / 97.0 + rng.uniform(0, 6.3))
    acc = np.clip(gnss.acc_m * (1.0 + wob + rng.normal(0, 0.02, tg.size)), 0.001, None)
    vacc = np.clip(gnss.vacc_m * (1.0 + wob + rng.normal(0, 0.02, tg.size)), 0.001, None)
    sats = rng.integers(17, 23, tg.size)
    recs: list[GnssFix | RangeSample] = [
        GnssFix(t_ns=t0_ns + round(t * 1e9), lat_deg=float(a), lon_deg=float(b),
                alt_m=round(float(c), 4), acc_m=round(float(h), 4), vacc_m=round(float(v), 4),
                fix=gnss.fix, sats=int(k))
        for t, a, b, c, h, v, k in zip(tg, lat, lon, alt, acc, vacc, sats, strict=True)
    ]
    ta = np.arange(0.05, duration_s - 0.3, 1.0 / rtt_hz) + rng.uniform(0, 0.05, 1)
    ta = ta + rng.uniform(0.0, 0.04, ta.size)
    anchors = path_fn(ta)
    d = np.linalg.norm(anchors - ap, axis=1)
    p_resp = p_max / (1.0 + np.exp((d - d50_m) / 15.0))
    ok = rng.uniform(size=ta.size) < p_resp
    ta, anchors, d = ta[ok], anchors[ok], d[ok]
    dd = np.maximum(d, 1.0)
    rssi_true = -38.0 - 25.0 * np.log10(dd) - rssi_loss_db
    rssi = np.round(rssi_true + rng.normal(0.0, 2.0, d.size))
    sigma = range_sigma_m(dd, rssi_true)
    noise = rng.normal(0.0, 1.0, d.size) * sigma
    gross = np.where(rng.uniform(size=d.size) < outlier_rate,
                     rng.lognormal(math.log(4.0), 0.5, d.size), 0.0)
    excess = rng.exponential(nlos_mean_m, d.size) if nlos_mean_m > 0 else 0.0
    meas = d + offset_m + noise + gross + excess
    recs += [RangeSample(t_ns=t0_ns + round(t * 1e9), bssid=BSSID, status="ok",
                         range_m=round(float(x), 4), rssi_dbm=float(r), attempted=8,
                         successful=int(rng.integers(5, 9)))
             for t, x, r in zip(ta, meas, rssi, strict=True)]
    recs.sort(key=lambda r: r.t_ns)
    alat, alon, aalt = frame.to_geodetic(*ap)
    hdr = LogHeader(agent=name, start_utc=_utc(start_s), agl_m=agl_header_m, range_offset_m=0.0)
    with LogWriter(path, hdr) as w:
        w.write(TruthRecord(bssid=BSSID, lat_deg=float(alat), lon_deg=float(alon),
                            alt_m=float(aalt), concealment=concealment))
        w.write_all(recs)
    return AgentTruth(name=name, path=path, gnss=gnss, t_s=ta, anchors_enu_m=anchors,
                      sigma_m=sigma, offset_m=offset_m)


def _utc(epoch_s: float) -> str:
    from datetime import UTC, datetime

    return datetime.fromtimestamp(epoch_s, UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _responder(rng: np.random.Generator, terrain: Terrain, spread_m: float = 20.0) -> np.ndarray:
    e, n = rng.uniform(-spread_m, spread_m, 2)
    return np.array([e, n, float(terrain.height(e, n)) + 0.5])


def los_world(seed: int, out_dir: Path, *, gnss: GnssModel = STANDALONE,
              duration_s: float = 150.0) -> World:
    """One UAV, one open responder: circular or lawnmower sweeps over hilly ground."""
    rng = np.random.default_rng([8, 1, seed])
    terrain = _terrain(rng)
    ap = _responder(rng, terrain)
    centre = ap[:2] + rng.normal(0.0, 15.0, 2)
    make = orbit_path if rng.uniform() < 0.7 else sweep_path
    fn = make(rng, terrain, centre)
    tag = "rtk" if gnss.fix == "rtk_fixed" else "std"
    w = World(f"los-{tag}", seed, ap)
    w.agents.append(_write_agent(
        Path(out_dir) / f"los-{tag}-{seed}.jsonl", rng, name="uav-1", path_fn=fn,
        duration_s=duration_s, gnss=gnss, ap=ap, offset_m=rng.uniform(0.3, 1.0),
        t0_ns=int(rng.integers(10**12, 10**13)), start_s=START_UTC_S, agl_header_m=45.0))
    return w


def vegetation_pass_world(seed: int, out_dir: Path) -> World:
    """The paper's AP_AB: a nearly straight 28 m pass in 21 s, ~31 NLoS ranges."""
    rng = np.random.default_rng([8, 2, seed])
    terrain = _terrain(rng)
    ap = _responder(rng, terrain, 10.0)
    heading = rng.uniform(0, 2 * np.pi)
    u = np.array([math.cos(heading), math.sin(heading)])
    nrm = np.array([-u[1], u[0]])
    lateral = rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 25.0)
    along0 = rng.uniform(-8.0, 8.0)
    start = ap[:2] + lateral * nrm - (14.0 + along0) * u
    z0 = float(terrain.height(*start)) + 45.0
    wander = rng.uniform(0.15, 0.3)

    def fn(t):
        t = np.asarray(t, float)
        s = np.clip(t - 2.0, 0.0, 21.0) * 28.0 / 21.0
        lat = wander * np.sin(2 * np.pi * t / 9.0)
        xy = start[None, :] + s[:, None] * u[None, :] + lat[:, None] * nrm[None, :]
        return np.column_stack((xy, z0 + 0.3 * np.sin(t / 3.0)))

    w = World("vegetation-pass", seed, ap, concealment="vegetation")
    w.agents.append(_write_agent(
        Path(out_dir) / f"veg-{seed}.jsonl", rng, name="uav-1", path_fn=fn, duration_s=25.0,
        gnss=STANDALONE, ap=ap, offset_m=rng.uniform(0.3, 1.0),
        t0_ns=int(rng.integers(10**12, 10**13)), start_s=START_UTC_S, agl_header_m=45.0,
        p_max=0.32, d50_m=200.0, nlos_mean_m=1.2, rssi_loss_db=12.0, concealment="vegetation"))
    # responses only during the pass itself (2-23 s)
    return w


def walker_path(rng: np.random.Generator, terrain: Terrain, centre: np.ndarray,
                speed_mps: float = 1.4) -> PathFn:
    """A walk at 1.4 m/s round an ellipse near ``centre``, 1.5 m above the ground."""
    a = rng.uniform(30.0, 45.0)
    b = rng.uniform(18.0, 28.0)
    rot = rng.uniform(0, np.pi)
    perim = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    omega = rng.choice([-1.0, 1.0]) * 2 * math.pi * speed_mps / perim
    th0 = rng.uniform(0, 2 * np.pi)
    c, s = math.cos(rot), math.sin(rot)

    def fn(t):
        th = th0 + omega * np.asarray(t, float)
        x, y = a * np.cos(th), b * np.sin(th)
        e = centre[0] + c * x - s * y
        n = centre[1] + s * x + c * y
        return np.column_stack((e, n, terrain.height(e, n) + 1.5))

    return fn


def three_agent_world(seed: int, out_dir: Path, *, duration_s: float = 150.0) -> World:
    """Two UAVs (standalone GNSS) and a walking ground agent with worse GNSS."""
    rng = np.random.default_rng([8, 3, seed])
    terrain = _terrain(rng)
    ap = _responder(rng, terrain)
    offset_ap = rng.uniform(0.3, 1.0)
    w = World("three-agents", seed, ap)
    out = Path(out_dir)
    for k in (1, 2):
        centre = ap[:2] + rng.normal(0.0, 15.0, 2)
        fn = orbit_path(rng, terrain, centre)
        w.agents.append(_write_agent(
            out / f"three-{seed}-uav{k}.jsonl", rng, name=f"uav-{k}", path_fn=fn,
            duration_s=duration_s, gnss=STANDALONE, ap=ap,
            offset_m=offset_ap + rng.uniform(-0.2, 0.2),
            t0_ns=int(rng.integers(10**12, 10**13)), start_s=START_UTC_S + 40.0 * (k - 1),
            agl_header_m=45.0))
    fn = walker_path(rng, terrain, ap[:2] + rng.normal(0.0, 10.0, 2))
    w.agents.append(_write_agent(
        out / f"three-{seed}-walker.jsonl", rng, name="walker-1", path_fn=fn,
        duration_s=duration_s + 60.0, gnss=WALKER_GNSS, ap=ap,
        offset_m=offset_ap + rng.uniform(0.5, 1.5), t0_ns=int(rng.integers(10**12, 10**13)),
        start_s=START_UTC_S + 10.0, agl_header_m=1.5, d50_m=60.0))
    return w


WORLDS = {
    "los-standalone": lambda seed, d: los_world(seed, d, gnss=STANDALONE),
    "los-rtk": lambda seed, d: los_world(seed, d, gnss=RTK),
    "vegetation-pass": vegetation_pass_world,
    "three-agents": three_agent_world,
}


# ----------------------------------------------------------------------------- references


def associated_enu(paths, frame=None):
    """All associated ranges of the logs in one ENU frame (world frame by default).

    Returns (anchors (N, 3), ranges (N,), agent index (N,)). The association is the
    estimator's own (:class:`estimator.association.Associator`); the range offset is
    each header's ``range_offset_m``.
    """
    from estimator.association import AssociationConfig, Associator
    from estimator.logio import read_log

    frame = frame or ExactENU(*ORIGIN)
    us, ds, ks = [], [], []
    for k, p in enumerate(paths):
        log = read_log(p)
        cfg = AssociationConfig(range_offset_m=log.header.range_offset_m or 0.0)
        for g in Associator(cfg).run(sorted(log.gnss + log.rtt, key=lambda r: r.t_ns)):
            us.append(frame.to_enu(g.lat_deg, g.lon_deg, g.alt_m))
            ds.append(g.range_m)
            ks.append(k)
    return np.array(us, float).reshape(-1, 3), np.array(ds, float), np.array(ks, int)


def batch_reference_fit(paths, *, frame=None, loss: str = "soft_l1", f_scale_m: float = 1.0
                        ) -> np.ndarray:
    """The plain batch robust fit of issue 8: scipy least_squares on [x, y, z, b] over
    every associated range, unweighted, multi-start (the anchors' centroid 45 m down and
    four points 30 m around it), the lowest cost kept; in ``frame`` (default the world's
    exact ENU; pass the replay's frame to compare in the same ENU frame)."""
    from scipy.optimize import least_squares

    u, d, _ = associated_enu(paths, frame)

    def resid(th):
        return np.linalg.norm(th[:3] - u, axis=1) + th[3] - d

    c = u.mean(axis=0)
    c[2] -= 45.0
    starts = [c] + [c + 30.0 * np.array([math.cos(a), math.sin(a), 0.0])
                    for a in (0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi)]
    best = None
    for s in starts:
        sol = least_squares(resid, np.array([*s, 0.0]), loss=loss, f_scale=f_scale_m,
                            method="trf", x_scale=1.0, max_nfev=200)
        if best is None or sol.cost < best.cost:
            best = sol
    return best.x


def crlb_cov_h(world: World) -> np.ndarray:
    """2 x 2 horizontal Cramer-Rao bound of the world (evaluation only, true geometry).

    Parameters [x, y, z, b_agent...]; the measurement covariance holds the true range
    noise and each agent's Gauss-Markov GNSS error projected on the line of sight
    (C = diag(sigma^2) + sum_axes G C_gm G^T): the bound an unbiased estimator that
    knew the noise model exactly could reach (outliers and NLoS excess excluded).
    """
    ap = world.ap_enu_m
    na = len(world.agents)
    blocks = []
    for k, a in enumerate(world.agents):
        if a.t_s.size == 0:
            continue
        diff = ap - a.anchors_enu_m
        r = np.linalg.norm(diff, axis=1)
        H = diff / r[:, None]
        J = np.zeros((r.size, 3 + na))
        J[:, :3] = H
        J[:, 3 + k] = 1.0
        dt = np.abs(a.t_s[:, None] - a.t_s[None, :])
        rho = np.exp(-dt / a.gnss.tau_s)
        g = a.gnss
        C = np.diag(a.sigma_m**2)
        for ax, s in enumerate((g.bias_h_m, g.bias_h_m, g.bias_v_m)):
            C += (s * s) * rho * np.outer(H[:, ax], H[:, ax])
            C += np.diag((g.white_h_m if ax < 2 else g.white_v_m) ** 2 * H[:, ax] ** 2)
        blocks.append((J, C))
    info = np.zeros((3 + na, 3 + na))
    for J, C in blocks:
        info += J.T @ np.linalg.solve(C, J)
    keep = [i for i in range(3 + na) if info[i, i] > 0]
    cov = np.linalg.inv(info[np.ix_(keep, keep)])
    return cov[:2, :2]


def reference_error_m(world: World, projection: str = "tangent") -> float:
    """Horizontal error of :func:`batch_reference_fit` in the frame a replay with this
    ``projection`` uses (the eq. 1 tangent plane, or exact WGS84, at the first anchor)."""
    from estimator.geodesy import make_frame

    _, tangent = associated_ranges(world.paths)
    if tangent is None:
        return math.inf
    frame = tangent if projection == "tangent" else make_frame(
        projection, tangent.lat0_deg, tangent.lon0_deg, tangent.h0_m)
    fit = batch_reference_fit(world.paths, frame=frame)
    lat, lon, alt = ExactENU(*ORIGIN).to_geodetic(*world.ap_enu_m)
    te, tn, _ = frame.to_enu(lat, lon, alt)
    return math.hypot(fit[0] - te, fit[1] - tn)


def associated_ranges(paths):
    """The associated ranges of the logs exactly as :class:`estimator.online.OnlineEstimator`
    sees them (common timeline from the headers' start_utc, tangent-plane ENU at the first
    released anchor), for timing the tracks alone. Returns (ranges, frame)."""
    import heapq

    from estimator.association import AssociationConfig, Associator
    from estimator.geodesy import TangentPlaneENU
    from estimator.logio import read_log
    from estimator.online import utc_epoch_s
    from estimator.records import AssociatedRange

    logs = [read_log(p) for p in paths]
    epochs = [utc_epoch_s(lg.header.start_utc) for lg in logs]
    known = [e for e in epochs if e is not None]
    ref = min(known) if known else 0.0
    streams = []
    for k, lg in enumerate(logs):
        recs = sorted(lg.gnss + lg.rtt, key=lambda r: r.t_ns)
        if not recs:
            continue
        off = 0.0 if len(logs) == 1 else (
            (epochs[k] if epochs[k] is not None else ref) - ref) - recs[0].t_ns * 1e-9
        cfg = AssociationConfig(range_offset_m=lg.header.range_offset_m or 0.0)
        geo = Associator(cfg).run(recs)
        name = f"{lg.header.agent}#{k}"
        agl = lg.header.agl_m if lg.header.agl_m is not None else 45.0
        streams.append([(g.t_ns * 1e-9 + off, k, i, g, name, agl) for i, g in enumerate(geo)])
    merged = list(heapq.merge(*streams, key=lambda e: (e[0], e[1], e[2])))
    if not merged:
        return [], None
    g0 = merged[0][3]
    frame = TangentPlaneENU(g0.lat_deg, g0.lon_deg, g0.alt_m)
    out = [AssociatedRange(t_s=t, bssid=g.bssid, range_m=g.range_m, rssi_dbm=g.rssi_dbm,
                           anchor_enu_m=frame.to_enu(g.lat_deg, g.lon_deg, g.alt_m),
                           anchor_acc_m=g.acc_m, anchor_vacc_m=g.vacc_m, agl_m=agl,
                           agent=name, anchor_fix=g.fix)
           for t, _k, _i, g, name, agl in merged]
    return out, frame
