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

from estimator.association import (
    CLOCK_JUMP_FORWARD_S,
    AssociationConfig,
    AssociationStats,
)
from estimator.evaluation import TruthScorer, errors_m, twm_of_history
from estimator.geodesy import EnuFrame
from estimator.logio import (
    CLOCK_JUMP_GAP_S,
    LogStream,
    LogWarning,
    RejectCounts,
    display_name,
    iter_log_sorted,
    not_a_log,
)
from estimator.modes import (  # parse_modes: the command line imports it from here
    parse_modes,  # noqa: F401
    resolve_modes,
)
from estimator.online import EstimatorOptions, OnlineEstimator, track_estimate
from estimator.pipeline import ModeSpec, PipelineConfig, Published
from estimator.records import Estimate, TruthRecord
from estimator.tables import Column, fit_columns, text_table


@dataclass(frozen=True, kw_only=True)
class ReplayOptions:
    """What to replay and how; ``None`` overrides fall back to the log header, then defaults.

    ``modes``: specs or names, resolved once here (as :class:`EstimatorOptions`).
    """

    modes: tuple[ModeSpec | str, ...] = ("baseline",)
    agl_m: float | None = None  # --agl
    range_offset_m: float | None = None  # --range-offset
    projection: str = "tangent"  # "tangent" (eq. 1) or "wgs84" (exact, pymap3d)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    keep_history: bool = True  # published estimates per track (figures); off: O(1) memory

    def __post_init__(self) -> None:
        object.__setattr__(self, "modes", resolve_modes(self.modes))  # best -> refined
        for name in ("agl_m", "range_offset_m"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be finite")


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
    estimated: Estimate | None = field(default=None, repr=False)
    has_bias: bool = True  # the mode's filter estimates a range bias (the UKF's has none)
    flags: tuple[str, ...] = ()  # suspicious data in the logs it was computed from

    @property
    def converged(self) -> bool:
        return self.status == "converged"

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
        d.update(estimate_extras(self.estimated))
        if self.flags:
            d["flags"] = list(self.flags)
        return d


def estimate_extras(e: Estimate | None) -> dict:
    """The added JSON fields of modes beyond the paper's: ``r95_h_m``, ``candidates``."""
    out: dict = {}
    if e is None:
        return out
    if e.r95_h_m is not None and math.isfinite(e.r95_h_m):
        out["r95_h_m"] = round(e.r95_h_m, 4)
    if e.candidates:
        out["candidates"] = [
            {"lat": round(c.lat_deg, 8), "lon": round(c.lon_deg, 8), "alt_m": round(c.alt_m, 3),
             "sigma_h_m": round(c.sigma_h_m, 4), "weight": round(c.weight, 6)}
            for c in e.candidates
        ]
    return out


@dataclass
class ReplayReport:
    tracks: list[TrackResult]
    rejected: RejectCounts
    association: AssociationStats
    n_logs: int
    frame: EnuFrame | None
    truth: dict[str, TruthRecord]

    @property
    def flags(self) -> tuple[str, ...]:
        """Suspicious data the reader and the association found (docs/log-format.md,
        "Suspicious data"): ``duplicate_records``, ``clock_jump``."""
        flags = []
        if sum(self.association.duplicates.values()):
            flags.append("duplicate_records")
        if self.clock_jumps:
            flags.append("clock_jump")
        return tuple(flags)

    @property
    def clock_jumps(self) -> int:
        """Backward (seen by the reader) and forward (by the association) clock jumps."""
        return self.rejected.clock_jumps_back + sum(self.association.clock_jumps.values())

    def to_json(self) -> dict:
        a = self.association
        return {
            "estimates": [t.to_json() for t in self.tracks],
            "rejected_lines": dict(sorted(self.rejected.rejected.items())),
            "logs": self.n_logs,
            "skipped": self.rejected.skipped(),
            "association": {
                "rtt": sum(a.rtt.values()),
                "ok": sum(a.ok.values()),
                "associated": sum(a.associated.values()),
                "unassociated": sum(a.unassociated.values()),
                "gnss_quality": sum(a.gnss_quality.values()),
                "duplicates": sum(a.duplicates.values()),
                "clock_jumps": self.clock_jumps,
            },
            "flags": list(self.flags),
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


class _End:
    """Marks the end of one log's records in the merged stream."""


_END = _End()


def _log_records(stream: LogStream, it: Iterator, first, index: int, offset_s: float):
    """(common time, log index, seq, record) of one log, then an end marker."""
    seq = 0
    key = -math.inf
    if first is not None:
        key = first.t_ns * 1e-9 + offset_s
        yield (key, index, seq, first)
        seq += 1
    for rec in it:
        key = rec.t_ns * 1e-9 + offset_s
        yield (key, index, seq, rec)
        seq += 1
    yield (key, index, seq, _END)


def replay_logs(paths: Sequence[str], opts: ReplayOptions = ReplayOptions()) -> ReplayReport:
    """Run every mode of ``opts`` over the logs; raises LogError for an unreadable log.

    A file adapter over :class:`estimator.online.OnlineEstimator`: the logs' records
    are merged on the common timeline and pushed one at a time; truth records (if any)
    score the estimates through a :class:`estimator.evaluation.TruthScorer`.
    """
    streams, iters, firsts = [], [], []
    try:
        for p in paths:  # each log is opened once: a pipe or '-' loses nothing
            st = LogStream(path=str(p))
            it = iter_log_sorted(p, st)
            iters.append(it)
            firsts.append(next(it, None))  # primes the reader: header and truth are known now
            streams.append(st)
            if (err := not_a_log(st)) is not None:
                raise err
    except BaseException:
        for it in iters:
            it.close()
        raise
    _warn_same_agent(streams)
    truth: dict[str, TruthRecord] = {}
    for st in streams:
        for t in st.truth:
            truth.setdefault(t.bssid, t)
    scorer = TruthScorer(truth, frame=lambda: est.frame)
    est = OnlineEstimator(
        EstimatorOptions(
            modes=opts.modes,
            pipeline=opts.pipeline,
            association=opts.association,
            projection=opts.projection,
            keep_history=opts.keep_history,
        ),
        observers=(scorer,),
    )
    for i, st in enumerate(streams):
        hdr = st.header
        assert hdr is not None
        f = firsts[i]
        est.add_agent(
            f"{hdr.agent}#{i}",
            header=hdr,
            agl_m=opts.agl_m,
            range_offset_m=opts.range_offset_m,
            first_t_ns=f.t_ns if f is not None else None,
        )
    est.start()  # fixes the common timeline: the merge needs the agents' offsets
    merged = heapq.merge(
        *[
            _log_records(st, it, firsts[i], i, est.agents[i].offset_s or 0.0)
            for i, (st, it) in enumerate(zip(streams, iters, strict=True))
        ],
        key=lambda e: (e[0], e[1], e[2]),
    )
    for _t, i, _seq, rec in merged:
        if rec is _END:
            est.finish(i)
        else:
            est.push(rec, i)
    est.finish()

    rejected = RejectCounts()
    for st in streams:
        rejected.merge(st.counts)
    _warn_suspicious(streams, est)
    report = ReplayReport([], rejected, est.association, len(streams), est.frame, truth)
    report.tracks = [
        _result(b, mode, est, scorer, truth.get(b), report.flags)
        for b in est.seen_bssids()
        for mode in est.options.modes
    ]
    return report


def _warn_same_agent(streams: Sequence[LogStream]) -> None:
    """Two logs whose headers name the same agent are fused, with a warning: they may
    be two flights of one drone, or a copy of one flight (every range counted twice)."""
    agents: dict[str, str] = {}
    for st in streams:
        if st.n_header and st.header is not None:
            agent = st.header.agent
            if agent in agents:
                warnings.warn(f"{display_name(st.path)} and {agents[agent]} name the same "
                              f"agent '{agent}': fused as two logs (if one is a copy of the "
                              "other, every range counts twice)", LogWarning, stacklevel=3)
            agents.setdefault(agent, display_name(st.path))


def _warn_suspicious(streams: Sequence[LogStream], est: OnlineEstimator) -> None:
    """One warning per log with duplicates or clock jumps: what was done about them."""
    for st, agent in zip(streams, est.agents, strict=True):
        a = agent.associator.stats
        name = display_name(st.path)
        n_dup = sum(a.duplicates.values())
        if n_dup:
            warnings.warn(f"{name}: {n_dup} duplicate record{'s' if n_dup > 1 else ''} (same "
                          "t_ns and content) ignored", LogWarning, stacklevel=3)
        back, fwd = st.counts.clock_jumps_back, sum(a.clock_jumps.values())
        what = []
        if back:
            what.append(f"back {_times(back)} (the records after it were placed "
                        f"{CLOCK_JUMP_GAP_S:g} s after the ones before it)")
        if fwd:
            what.append(f"forward {_times(fwd)} (or the log paused for over "
                        f"{CLOCK_JUMP_FORWARD_S:g} s)")
        if what:
            warnings.warn(f"{name}: the phone clock jumped {' and '.join(what)}; no range was "
                          "associated across a jump", LogWarning, stacklevel=3)


def _times(n: int) -> str:
    return "once" if n == 1 else f"{n} times"


def _result(
    bssid: str,
    spec: ModeSpec,
    est: OnlineEstimator,
    scorer: TruthScorer,
    truth: TruthRecord | None,
    flags: tuple[str, ...] = (),
) -> TrackResult:
    empty = {k: 0 for k in ("n_meas", "n_bootstrap", "n_acc", "n_gate", "n_mad", "n_nis")}
    mode, has_bias = spec.name, spec.filter.has_bias
    tr = est.track(bssid, spec)
    conc = truth.concealment if truth is not None else None
    if tr is None:
        return TrackResult(bssid, mode, "no_data", empty, None, concealment=conc,
                           has_bias=has_bias, flags=flags)
    c = tr.counts
    counts = {
        "n_meas": c.n_meas,
        "n_bootstrap": c.n_bootstrap,
        "n_acc": c.n_acc,
        "n_gate": c.n_gate,
        "n_mad": c.n_mad,
        "n_nis": c.n_nis,
    }
    e = track_estimate(tr, est.frame, est.now_s())
    res = TrackResult(
        bssid, mode, tr.status, counts, tr.reported(), kappa=e.kappa, history=tr.history,
        bootstrap_t_s=tr.bootstrap_t_s, concealment=conc, estimated=e, has_bias=has_bias,
        flags=flags,
    )
    frame = est.frame
    if frame is not None and truth is not None:
        res.truth_enu_m = tuple(frame.to_enu(truth.lat_deg, truth.lon_deg, truth.alt_m))
    if e.has_position:
        res.lat_deg, res.lon_deg, res.alt_m = e.lat_deg, e.lon_deg, e.alt_m
        if res.truth_enu_m is not None:
            res.err_h_m, res.err_3d_m = errors_m(e.mean_enu_m, res.truth_enu_m)
            twm = scorer.twm_h_m(tr)
            res.twm_h_m = twm if twm is not None else twm_of_history(tr.history, res.truth_enu_m)
    return res


# the replay table's columns (least widths: the paper-style layout of short names)
REPLAY_COLUMNS = (
    Column("Mode", "<", 12), Column("status", "<", 14), Column("n_gate", ">", 7),
    Column("n_acc", ">", 7), Column("sigma_H", ">", 9), Column("sigma_Z", ">", 9),
    Column("err_2D", ">", 8), Column("TWM", ">", 7), Column("err_3D", ">", 8),
    Column("bias", ">", 7),
)


def format_table(report: ReplayReport) -> str:
    """A readable table, one block per responder, shaped like the paper's Table."""
    lines = []
    by_bssid: dict[str, list[TrackResult]] = {}
    for t in report.tracks:
        by_bssid.setdefault(t.bssid, []).append(t)

    def f(v: float | None, nd: int = 1) -> str:
        return "-" if v is None else f"{v:.{nd}f}"

    cells = {
        b: [(t.mode, t.status, str(t.counts["n_gate"]), str(t.counts["n_acc"]),
             f(t.estimate.sigma_h_m if t.estimate else None),
             f(t.estimate.sigma_z_m if t.estimate else None), f(t.err_h_m), f(t.twm_h_m),
             f(t.err_3d_m), f(t.estimate.bias_m if t.estimate and t.has_bias else None, 2))
            for t in rows]
        for b, rows in by_bssid.items()
    }
    # one set of widths for every block: the blocks line up under each other
    columns = fit_columns(REPLAY_COLUMNS, [r for rows in cells.values() for r in rows])
    for b, rows in by_bssid.items():
        conc = rows[0].concealment
        c0 = rows[0].counts
        head = f"{b}" + (f"  ({conc})" if conc else "")
        lines.append(f"{head}  n_meas={c0['n_meas']}  n_bootstrap={c0['n_bootstrap']}")
        lines.extend(text_table(columns, cells[b], indent="  "))
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
    if report.flags:
        n_dup, n_jump = sum(a.duplicates.values()), report.clock_jumps
        lines.append(
            f"flagged: {n_dup} duplicate record{'s' * (n_dup != 1)} ignored, {n_jump} clock "
            f"jump{'s' * (n_jump != 1)}; every status above was computed on this flagged data"
        )
    return "\n".join(lines)


def count_summary(report: ReplayReport) -> Counter:
    return Counter(t.status for t in report.tracks)
