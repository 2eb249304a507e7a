"""Replay flight logs through the pipeline: one track per responder (BSSID) and mode.

Several logs (several agents) are fused: each log is associated against its own GNSS
(its own monotonic clock), then the associated ranges of all logs are merged in time
and fed to shared per-BSSID tracks. Logs are put on one timeline through their
headers' ``start_utc`` (taken as the wall time of the log's first record); a log
without it is assumed to start with the earliest one (a warning says so).

The ENU frame is fixed at the first synchronised anchor of the replay (eq. 1 by
default, exact WGS84 as an option); outputs are converted back to WGS84.
"""

from __future__ import annotations

import heapq
import math
import warnings
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime

from estimator.association import AssociationConfig, AssociationStats, Associator, GeoRange
from estimator.geodesy import EnuFrame, make_frame
from estimator.logio import LogStream, LogWarning, RejectCounts, iter_log_sorted
from estimator.pipeline import (
    DEFAULT_AGL_M,
    MODES,
    PAPER_MODES,
    PipelineConfig,
    Published,
    SharedFront,
    Track,
)
from estimator.records import AssociatedRange, TruthRecord


@dataclass(frozen=True, kw_only=True)
class ReplayOptions:
    """What to replay and how; ``None`` overrides fall back to the log header, then defaults."""

    modes: tuple[str, ...] = ("baseline",)
    agl_m: float | None = None  # --agl
    range_offset_m: float | None = None  # --range-offset
    projection: str = "tangent"  # "tangent" (eq. 1) or "wgs84" (exact, pymap3d)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    keep_history: bool = True  # published estimates per track (figures); off: O(1) memory

    def __post_init__(self) -> None:
        unknown = [m for m in self.modes if m not in MODES]
        if unknown:
            raise ValueError(f"unknown mode(s) {unknown}; choose from {sorted(MODES)} or 'all'")
        for name in ("agl_m", "range_offset_m"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be finite")


def parse_modes(text: str) -> tuple[str, ...]:
    """``all`` (the paper's six), one name, or a list joined by ``,`` or ``+``
    (``all+robust``: the six and ours); ``all`` expands in place, repeats are dropped."""
    names = [m.strip() for m in text.replace("+", ",").split(",") if m.strip()]
    modes: list[str] = []
    for m in names:
        for name in PAPER_MODES if m == "all" else (m,):
            if name not in modes:
                modes.append(name)
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise ValueError(f"unknown mode {text!r}; choose from {', '.join(MODES)} or all")
    return tuple(modes)


@dataclass
class TrackResult:
    """The outcome of one (bssid, mode) track, with errors when truth is known."""

    bssid: str
    mode: str
    status: str
    counts: dict[str, int]
    estimate: Published | None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    err_h_m: float | None = None
    err_3d_m: float | None = None
    twm_h_m: float | None = None
    kappa: float | None = None
    truth_enu_m: tuple[float, float, float] | None = None
    concealment: str | None = None
    history: list[Published] = field(default_factory=list, repr=False)
    bootstrap_t_s: float | None = None

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def has_bias(self) -> bool:
        """Whether the mode's filter estimates a range bias (the UKF's state has none)."""
        return MODES[self.mode].filter != "ukf"

    def to_json(self) -> dict:
        d: dict = {"bssid": self.bssid, "mode": self.mode, "status": self.status,
                   "converged": self.converged}
        e = self.estimate
        if e is not None:
            d.update(
                lat=round(self.lat_deg, 8),
                lon=round(self.lon_deg, 8),
                alt_m=round(self.alt_m, 3),
                sigma_h_m=round(e.sigma_h_m, 4),
                sigma_z_m=round(e.sigma_z_m, 4),
            )
            if self.has_bias:  # the UKF has no bias state: no bias_m at all
                d["bias_m"] = round(e.bias_m, 4)
        d.update({k: self.counts[k] for k in ("n_meas", "n_bootstrap", "n_acc", "n_gate")})
        d.update(n_mad=self.counts["n_mad"], n_nis=self.counts["n_nis"])
        if e is not None and self.err_h_m is not None:
            d["err_h_m"] = round(self.err_h_m, 3)
            d["err_3d_m"] = round(self.err_3d_m, 3)
            if self.twm_h_m is not None:
                d["twm_h_m"] = round(self.twm_h_m, 3)
        if self.kappa is not None and math.isfinite(self.kappa):
            d["kappa"] = round(self.kappa, 3)
        if self.concealment is not None:
            d["concealment"] = self.concealment
        return d


@dataclass
class ReplayReport:
    tracks: list[TrackResult]
    rejected: RejectCounts
    association: AssociationStats
    n_logs: int
    frame: EnuFrame | None
    truth: dict[str, TruthRecord]

    def to_json(self) -> dict:
        a = self.association
        return {
            "estimates": [t.to_json() for t in self.tracks],
            "rejected_lines": dict(sorted(self.rejected.rejected.items())),
            "logs": self.n_logs,
            "skipped": {
                "unknown_types": sum(self.rejected.unknown_types.values()),
                "lines_with_unknown_fields": self.rejected.unknown_fields,
            },
            "association": {
                "rtt": sum(a.rtt.values()),
                "ok": sum(a.ok.values()),
                "associated": sum(a.associated.values()),
                "unassociated": sum(a.unassociated.values()),
                "gnss_quality": sum(a.gnss_quality.values()),
            },
            **(
                {"frame": {"projection": getattr(self.frame, "name", ""),
                           "lat0": self.frame.lat0_deg, "lon0": self.frame.lon0_deg,
                           "h0_m": self.frame.h0_m}}
                if self.frame is not None
                else {}
            ),
        }

    def get(self, bssid: str, mode: str) -> TrackResult:
        for t in self.tracks:
            if t.bssid == bssid and t.mode == mode:
                return t
        raise KeyError((bssid, mode))


def _utc_epoch_s(text: str | None) -> float | None:
    if not text:
        return None
    try:
        return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


@dataclass
class _LogSource:
    stream: LogStream
    records: Iterator
    first: object | None
    agl_m: float
    associator: Associator
    offset_s: float = 0.0


def _open_sources(paths: Sequence[str], opts: ReplayOptions) -> list[_LogSource]:
    sources = []
    for p in paths:
        st = LogStream(path=str(p))
        it = iter_log_sorted(p, st)
        first = next(it, None)  # primes the reader: header and truth are known now
        hdr = st.header
        assert hdr is not None
        agl = opts.agl_m if opts.agl_m is not None else hdr.agl_m
        agl = agl if agl is not None else DEFAULT_AGL_M
        off = opts.range_offset_m if opts.range_offset_m is not None else hdr.range_offset_m
        acfg = AssociationConfig(
            t_sync_s=opts.association.t_sync_s,
            max_acc_m=opts.association.max_acc_m,
            range_offset_m=off if off is not None else 0.0,
        )
        sources.append(_LogSource(st, it, first, agl, Associator(acfg)))
    if len(sources) > 1:
        epochs = [_utc_epoch_s(s.stream.header.start_utc) for s in sources]
        known = [e for e in epochs if e is not None]
        ref = min(known) if known else 0.0
        for s, e in zip(sources, epochs, strict=True):
            t0 = s.first.t_ns * 1e-9 if s.first is not None else 0.0
            if e is None:
                warnings.warn(
                    f"{s.stream.path}: no start_utc in header; assumed to start with the "
                    "earliest log",
                    LogWarning,
                    stacklevel=3,
                )
                e = ref
            s.offset_s = (e - ref) - t0
    return sources


def _associated(src: _LogSource, index: int) -> Iterator[tuple[float, int, int, GeoRange, float]]:
    def recs() -> Iterator:
        if src.first is not None:
            yield src.first
        yield from src.records

    for seq, g in enumerate(src.associator.run(recs())):
        yield (g.t_ns * 1e-9 + src.offset_s, index, seq, g, src.agl_m)


def replay_logs(paths: Sequence[str], opts: ReplayOptions = ReplayOptions()) -> ReplayReport:
    """Run every mode of ``opts`` over the logs; raises LogError for an unreadable log."""
    sources = _open_sources([str(p) for p in paths], opts)
    truth: dict[str, TruthRecord] = {}
    for s in sources:  # primed: every log's truth records are known before processing
        for t in s.stream.truth:
            truth.setdefault(t.bssid, t)
    streams = [_associated(s, i) for i, s in enumerate(sources)]
    merged = heapq.merge(*streams, key=lambda e: (e[0], e[1], e[2]))
    frame: EnuFrame | None = None
    tracks: dict[tuple[str, str], Track] = {}
    order: list[str] = []
    for t_s, _i, _seq, g, agl in merged:
        if frame is None:
            frame = make_frame(opts.projection, g.lat_deg, g.lon_deg, g.alt_m)
        e, n, u = frame.to_enu(g.lat_deg, g.lon_deg, g.alt_m)
        m = AssociatedRange(
            t_s=t_s,
            bssid=g.bssid,
            range_m=g.range_m,
            rssi_dbm=g.rssi_dbm,
            anchor_enu_m=(e, n, u),
            anchor_acc_m=g.acc_m,
            anchor_vacc_m=g.vacc_m,
            agl_m=agl,
            agent=sources[_i].stream.header.agent,
        )
        if g.bssid not in order:
            order.append(g.bssid)
            front = SharedFront(opts.pipeline)
            tru = truth.get(g.bssid)
            truth_enu = tuple(frame.to_enu(tru.lat_deg, tru.lon_deg, tru.alt_m)) if tru else None
            for mode in opts.modes:
                tracks[(g.bssid, mode)] = Track(
                    g.bssid, mode, opts.pipeline, keep_history=opts.keep_history, front=front,
                    truth_enu_m=truth_enu,
                )
        for mode in opts.modes:
            tracks[(g.bssid, mode)].process(m)

    rejected = RejectCounts()
    assoc = AssociationStats()
    for s in sources:
        rejected.merge(s.stream.counts)
        for name in ("rtt", "ok", "unassociated", "gnss_quality", "associated", "interpolated"):
            getattr(assoc, name).update(getattr(s.associator.stats, name))
    for b in sorted(assoc.rtt):  # seen, never associated: no_data
        if b not in order:
            order.append(b)
    results = []
    for b in order:
        for mode in opts.modes:
            tr = tracks.get((b, mode))
            results.append(_result(b, mode, tr, frame, truth.get(b)))
    return ReplayReport(results, rejected, assoc, len(sources), frame, truth)


def _twm(history: list[Published], truth: tuple[float, float, float]) -> float | None:
    """Time-weighted mean 2-D error over the stable estimates (all, if none is stable)."""
    pts = [p for p in history if p.stable] or history
    if not pts:
        return None
    errs = [math.hypot(p.enu_m[0] - truth[0], p.enu_m[1] - truth[1]) for p in pts]
    span = pts[-1].t_s - pts[0].t_s
    if len(pts) == 1 or span <= 0:
        return sum(errs) / len(errs)
    acc = 0.0
    for k in range(len(pts) - 1):
        acc += errs[k] * (pts[k + 1].t_s - pts[k].t_s)
    return acc / span


def _result(
    bssid: str,
    mode: str,
    tr: Track | None,
    frame: EnuFrame | None,
    truth: TruthRecord | None,
) -> TrackResult:
    empty = {k: 0 for k in ("n_meas", "n_bootstrap", "n_acc", "n_gate", "n_mad", "n_nis")}
    if tr is None:
        return TrackResult(bssid, mode, "no_data", empty, None,
                           concealment=truth.concealment if truth else None)
    c = tr.counts
    counts = {
        "n_meas": c.n_meas,
        "n_bootstrap": c.n_bootstrap,
        "n_acc": c.n_acc,
        "n_gate": c.n_gate,
        "n_mad": c.n_mad,
        "n_nis": c.n_nis,
    }
    est = tr.reported()
    kappa = None
    if tr.bootstrap_result is not None:
        kappa = tr.bootstrap_result.kappa
    elif tr.last_bootstrap is not None:
        kappa = tr.last_bootstrap.kappa
    res = TrackResult(
        bssid, mode, tr.status, counts, est, kappa=kappa, history=tr.history,
        bootstrap_t_s=tr.bootstrap_t_s,
    )
    if truth is not None:
        res.concealment = truth.concealment
    if frame is not None and truth is not None:
        res.truth_enu_m = tuple(frame.to_enu(truth.lat_deg, truth.lon_deg, truth.alt_m))
    if est is not None and frame is not None:
        res.lat_deg, res.lon_deg, res.alt_m = frame.to_geodetic(*est.enu_m)
        if res.truth_enu_m is not None:
            t = res.truth_enu_m
            p = est.enu_m
            res.err_h_m = math.hypot(p[0] - t[0], p[1] - t[1])
            res.err_3d_m = math.sqrt(
                (p[0] - t[0]) ** 2 + (p[1] - t[1]) ** 2 + (p[2] - t[2]) ** 2
            )
            res.twm_h_m = tr.twm.twm_h_m if tr.twm is not None else _twm(tr.history, t)
    return res


def format_table(report: ReplayReport) -> str:
    """A readable table, one block per responder, shaped like the paper's Table."""
    lines = []
    by_bssid: dict[str, list[TrackResult]] = {}
    for t in report.tracks:
        by_bssid.setdefault(t.bssid, []).append(t)

    def f(v: float | None, nd: int = 1) -> str:
        return "-" if v is None else f"{v:.{nd}f}"

    for b, rows in by_bssid.items():
        conc = rows[0].concealment
        c0 = rows[0].counts
        head = f"{b}" + (f"  ({conc})" if conc else "")
        lines.append(f"{head}  n_meas={c0['n_meas']}  n_bootstrap={c0['n_bootstrap']}")
        lines.append(
            f"  {'Mode':<12}{'status':<14}{'n_gate':>7}{'n_acc':>7}{'sigma_H':>9}{'sigma_Z':>9}"
            f"{'err_2D':>8}{'TWM':>7}{'err_3D':>8}{'bias':>7}"
        )
        for t in rows:
            e = t.estimate
            lines.append(
                f"  {t.mode:<12}{t.status:<14}{t.counts['n_gate']:>7}{t.counts['n_acc']:>7}"
                f"{f(e.sigma_h_m if e else None):>9}{f(e.sigma_z_m if e else None):>9}"
                f"{f(t.err_h_m):>8}{f(t.twm_h_m):>7}{f(t.err_3d_m):>8}"
                f"{f(e.bias_m if e and t.has_bias else None, 2):>7}"
            )
        lines.append("")
    rj = report.rejected.rejected
    if rj:
        lines.append("rejected lines: " + ", ".join(f"{k}={v}" for k, v in sorted(rj.items())))
    a = report.association
    lines.append(
        f"logs: {report.n_logs}  rtt: {sum(a.rtt.values())}  ok: {sum(a.ok.values())}  "
        f"associated: {sum(a.associated.values())}  unassociated: "
        f"{sum(a.unassociated.values())}  gnss_quality: {sum(a.gnss_quality.values())}"
    )
    return "\n".join(lines)


def count_summary(report: ReplayReport) -> Counter:
    return Counter(t.status for t in report.tracks)
