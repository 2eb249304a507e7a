"""The online estimator: log records in, estimates out, one object for every agent.

:class:`OnlineEstimator` is the real-time form of the pipeline (sec. System
Architecture): each agent (a phone on a UAV, a walking first responder...) pushes the
records of its own log as they arrive (``gnss`` fixes and ``rtt`` results, each on the
agent's own monotonic clock). Per agent, ranges are associated with that agent's GNSS
(:class:`estimator.association.Associator`); the associated ranges of all agents are
then put on one timeline and fed, in time order, to one set of per-BSSID tracks (one
per mode), as ``osa replay`` fuses several logs.

Timeline: with one agent, the phone clock itself (seconds). With several, each agent's
clock is shifted so that its first record falls at its header's ``start_utc`` relative
to the earliest agent (an agent without ``start_utc`` is taken to start with the
earliest). A range is released to the tracks only once no agent can still produce an
earlier one (each agent's *watermark*: its oldest range still waiting for a GNSS fix,
or the time of its latest record, or what :meth:`OnlineEstimator.mark_time` said), so
the tracks see exactly the order a batch replay of the same logs gives, in memory
bounded by the association window (2 T_sync).

The ENU frame is fixed at the first released anchor (eq. 1 by default, exact WGS84 as
an option); estimates are returned in it and in WGS84.
"""

from __future__ import annotations

import heapq
import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Protocol

from estimator.association import AssociationConfig, AssociationStats, Associator, GeoRange
from estimator.geodesy import EnuFrame, make_frame
from estimator.logio import LogWarning
from estimator.modes import resolve_mode, resolve_modes
from estimator.pipeline import (
    DEFAULT_AGL_M,
    ModeSpec,
    PipelineConfig,
    Published,
    SharedFront,
    Track,
    TrackObserver,
    make_track,
)
from estimator.records import (
    AssociatedRange,
    Candidate,
    Estimate,
    GnssFix,
    LogHeader,
    RangeSample,
)


class RangeObserver(Protocol):
    """Told of every associated range as it is released to the tracks (in the order the
    tracks see them): the range, corrected, with its GNSS anchor (WGS84), the time it was
    taken on its agent's phone clock (``g.t_ns``) and the agent's index. A closed loop
    learns from it where each range was heard, from the phone's own GNSS."""

    def associated(self, agent: int, g: GeoRange) -> None: ...


def utc_epoch_s(text: str | None) -> float | None:
    """Seconds since the epoch of an ISO 8601 time (``Z`` allowed; without a zone it is
    UTC, as ``start_utc`` says, never the machine's zone); None if unreadable."""
    if not text:
        return None
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        return None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


@dataclass
class Agent:
    """One agent's association state and its place on the common timeline."""

    index: int
    name: str
    agl_m: float
    associator: Associator
    start_epoch_s: float | None
    first_t_ns: int | None = None
    start_utc: str | None = None  # as given (to name it when it is unreadable)
    offset_s: float | None = None
    last_t_s: float = -math.inf  # common time of the latest record or mark
    finished: bool = False
    seq: int = 0

    def watermark_s(self) -> float:
        """No range released later by this agent can be earlier than this (common time)."""
        if self.finished:
            return math.inf
        if self.offset_s is None:
            return -math.inf
        pending = self.associator.earliest_pending_ns()
        if pending is None:
            return self.last_t_s
        return min(self.last_t_s, pending * 1e-9 + self.offset_s)


@dataclass(frozen=True, kw_only=True)
class EstimatorOptions:
    """What the online estimator runs: modes, pipeline, association and frame.

    ``modes`` are :class:`estimator.pipeline.ModeSpec` objects, or names (and aliases)
    resolved once, here, through the registry :data:`estimator.modes.MODES`; after
    construction they are specs.
    """

    modes: tuple[ModeSpec | str, ...] = ("baseline",)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    projection: str = "tangent"  # "tangent" (eq. 1) or "wgs84" (exact, pymap3d)
    keep_history: bool = False  # published estimates per track (figures); off: O(1) memory

    def __post_init__(self) -> None:
        object.__setattr__(self, "modes", resolve_modes(self.modes))  # best -> refined
        if not self.modes:
            raise ValueError("at least one mode is needed")


class OnlineEstimator:
    """``push(record, agent) -> published estimates``, for every agent and responder.

    Register agents with :meth:`add_agent` before pushing (their start times define
    the common timeline); push each agent's records in its own time order (``t_ns``
    non-decreasing, as the log readers deliver them); call :meth:`finish` at the end
    of an agent's stream (it resolves ranges still waiting for a GNSS fix).
    """

    def __init__(
        self,
        options: EstimatorOptions = EstimatorOptions(),
        *,
        observers: Sequence[TrackObserver] = (),
        range_observers: Sequence[RangeObserver] = (),
    ) -> None:
        self.options = options
        self.observers = tuple(observers)
        self.range_observers = tuple(range_observers)
        self.agents: list[Agent] = []
        self._by_name: dict[str, Agent] = {}
        self.frame: EnuFrame | None = None
        self.tracks: dict[tuple[str, str], Track] = {}
        self.bssids: list[str] = []  # in order of first associated range
        self._heap: list[tuple[float, int, int, GeoRange, Agent]] = []
        self._ref_epoch_s: float | None = None
        self._started = False

    # ------------------------------------------------------------------ agents
    def add_agent(
        self,
        name: str,
        *,
        header: LogHeader | None = None,
        agl_m: float | None = None,
        range_offset_m: float | None = None,
        start_utc: str | None = None,
        first_t_ns: int | None = None,
    ) -> int:
        """Register an agent; returns its index. Overrides beat the header's config.

        ``first_t_ns`` (the agent's first record, when known in advance, as a log
        reader knows it) places the agent on the timeline before its first push.
        """
        if self._started:
            raise RuntimeError("agents must be registered before the first push")
        if name in self._by_name:
            raise ValueError(f"agent {name!r} is registered twice")
        h = header
        agl = agl_m if agl_m is not None else (h.agl_m if h is not None else None)
        off = range_offset_m if range_offset_m is not None else (
            h.range_offset_m if h is not None else None
        )
        start = start_utc if start_utc is not None else (h.start_utc if h is not None else None)
        a = self.options.association
        acfg = AssociationConfig(
            t_sync_s=a.t_sync_s,
            max_acc_m=a.max_acc_m,
            range_offset_m=off if off is not None else 0.0,
        )
        agent = Agent(
            index=len(self.agents),
            name=name,
            agl_m=agl if agl is not None else DEFAULT_AGL_M,
            associator=Associator(acfg),
            start_epoch_s=utc_epoch_s(start),
            first_t_ns=first_t_ns,
            start_utc=start,
        )
        self.agents.append(agent)
        self._by_name[name] = agent
        return agent.index

    def agent(self, key: int | str) -> Agent:
        if isinstance(key, str):
            try:
                return self._by_name[key]
            except KeyError:
                raise KeyError(f"no agent named {key!r}") from None
        return self.agents[key]

    def start(self) -> None:
        """Fix the common timeline now (else the first push does); agents are then closed."""
        if not self._started:
            self._start()

    def _start(self) -> None:
        """Fix the common timeline (called at the first push)."""
        if not self.agents:  # a lone stream without registration: one default agent
            self.add_agent("uav-1")
        self._started = True
        known = [a.start_epoch_s for a in self.agents if a.start_epoch_s is not None]
        self._ref_epoch_s = min(known) if known else 0.0
        if len(self.agents) > 1:
            for a in self.agents:
                if a.start_epoch_s is None:
                    why = (f"start_utc {a.start_utc!r} is not an ISO 8601 time" if a.start_utc
                           else "no start_utc")
                    warnings.warn(
                        f"agent {a.name}: {why}; assumed to start with the earliest agent",
                        LogWarning,
                        stacklevel=3,
                    )
        for a in self.agents:
            if a.first_t_ns is not None:
                self._place(a, a.first_t_ns)

    def _place(self, a: Agent, first_t_ns: int) -> None:
        a.first_t_ns = first_t_ns
        if len(self.agents) == 1:
            a.offset_s = 0.0
        else:
            epoch = a.start_epoch_s if a.start_epoch_s is not None else self._ref_epoch_s
            a.offset_s = (epoch - self._ref_epoch_s) - first_t_ns * 1e-9
        a.last_t_s = max(a.last_t_s, first_t_ns * 1e-9 + a.offset_s)

    def common_time_s(self, agent: int | str, t_ns: int) -> float | None:
        """An agent's phone time on the common timeline (None before it is placed)."""
        a = self.agent(agent)
        return None if a.offset_s is None else t_ns * 1e-9 + a.offset_s

    # ------------------------------------------------------------------ input
    def push(self, rec: GnssFix | RangeSample, agent: int | str = 0) -> list[Published]:
        """Feed one record of ``agent``; return what the tracks published because of it."""
        if not self._started:
            self._start()
        a = self.agent(agent)
        if a.finished:
            raise RuntimeError(f"agent {a.name} has finished")
        if a.offset_s is None:
            self._place(a, rec.t_ns)
        a.last_t_s = max(a.last_t_s, rec.t_ns * 1e-9 + a.offset_s)
        for g in a.associator.push(rec):
            self._queue(a, g)
        return self._release()

    def push_many(self, recs: Iterable[GnssFix | RangeSample],
                  agent: int | str = 0) -> list[Published]:
        """:meth:`push` of each of ``agent``'s records in turn: the same effects and
        publications, with one agent lookup, and a run of fixes taken at once (only its
        first valid fix can resolve waiting ranges; the heap's releases keep their
        order): what a stream of 10 Hz fixes costs less."""
        if not self._started:
            self._start()
        a = self.agent(agent)
        if a.finished:
            raise RuntimeError(f"agent {a.name} has finished")
        out: list[Published] = []
        fixes: list[GnssFix] = []  # a run of fixes: one associator call, one release

        def take(batch: list, resolved: list[GeoRange]) -> None:
            if a.offset_s is None:
                self._place(a, batch[0].t_ns)
            # max of t * 1e-9 + offset over the batch: the (monotone) map of the max
            a.last_t_s = max(a.last_t_s, max(r.t_ns for r in batch) * 1e-9 + a.offset_s)
            for g in resolved:
                self._queue(a, g)
            if self._heap:
                out.extend(self._release())

        for rec in recs:
            if isinstance(rec, GnssFix):
                fixes.append(rec)
                continue
            if fixes:
                take(fixes, a.associator.push_fixes(fixes))
                fixes = []
            take([rec], a.associator.push(rec))
        if fixes:
            take(fixes, a.associator.push_fixes(fixes))
        return out

    def mark_time(self, agent: int | str, t_ns: int) -> list[Published]:
        """Say that ``agent`` has delivered every record up to its phone time ``t_ns``."""
        if not self._started:
            self._start()
        a = self.agent(agent)
        if a.offset_s is None:
            return []
        a.last_t_s = max(a.last_t_s, t_ns * 1e-9 + a.offset_s)
        return self._release()

    def finish(self, agent: int | str | None = None) -> list[Published]:
        """End of ``agent``'s stream (every agent when None): resolve its waiting ranges."""
        if not self._started:
            self._start()
        agents = self.agents if agent is None else [self.agent(agent)]
        for a in agents:
            if a.finished:
                continue
            if a.offset_s is not None:
                for g in a.associator.flush():
                    self._queue(a, g)
            a.finished = True
        out = self._release()
        if all(a.finished for a in self.agents):
            out.extend(self._finalize())
        return out

    def _finalize(self) -> list[Published]:
        """End of every stream: final refinement of the tracks that refine (``refined``)."""
        out = []
        for tr in self.tracks.values():
            fin = getattr(tr, "finalize", None)
            pub = fin() if fin is not None else None
            if pub is not None:
                out.append(pub)
        return out

    def _queue(self, a: Agent, g: GeoRange) -> None:
        heapq.heappush(self._heap, (g.t_ns * 1e-9 + a.offset_s, a.index, a.seq, g, a))
        a.seq += 1

    def _release(self) -> list[Published]:
        heap = self._heap
        if not heap:
            return []
        limit = min(a.watermark_s() for a in self.agents)
        out: list[Published] = []
        while heap and heap[0][0] <= limit:
            t_s, _i, _seq, g, a = heapq.heappop(heap)
            out.extend(self._process(t_s, g, a))
        return out

    def _process(self, t_s: float, g: GeoRange, a: Agent) -> list[Published]:
        opts = self.options
        for ob in self.range_observers:
            ob.associated(a.index, g)
        if self.frame is None:
            self.frame = make_frame(opts.projection, g.lat_deg, g.lon_deg, g.alt_m)
        e, n, u = self.frame.to_enu(g.lat_deg, g.lon_deg, g.alt_m)
        m = AssociatedRange(
            t_s=t_s,
            bssid=g.bssid,
            range_m=g.range_m,
            rssi_dbm=g.rssi_dbm,
            anchor_enu_m=(e, n, u),
            anchor_acc_m=g.acc_m,
            anchor_vacc_m=g.vacc_m,
            agl_m=a.agl_m,
            agent=a.name,
            anchor_fix=g.fix,
        )
        if g.bssid not in self.bssids:
            self.bssids.append(g.bssid)
            front = SharedFront(opts.pipeline)
            for mode in opts.modes:
                self.tracks[(g.bssid, mode.name)] = make_track(
                    g.bssid,
                    mode,
                    opts.pipeline,
                    keep_history=opts.keep_history,
                    front=front,
                    observers=self.observers,
                )
        out = []
        for mode in opts.modes:
            pub = self.tracks[(g.bssid, mode.name)].process(m)
            if pub is not None:
                out.append(pub)
        return out

    # ------------------------------------------------------------------ output
    @property
    def association(self) -> AssociationStats:
        """Association counts summed over the agents."""
        total = AssociationStats()
        for a in self.agents:
            total.merge(a.associator.stats)
        return total

    def seen_bssids(self) -> list[str]:
        """Every responder seen: associated ones first (in order), then the others sorted."""
        seen = list(self.bssids)
        rtt = set()
        for a in self.agents:
            rtt |= set(a.associator.stats.rtt)
        seen += sorted(b for b in rtt if b not in self.bssids)
        return seen

    def _mode_name(self, mode: ModeSpec | str | None) -> str:
        return resolve_mode(mode).name if mode else self.options.modes[0].name

    def track(self, bssid: str, mode: ModeSpec | str | None = None) -> Track | None:
        """The track of ``bssid`` in ``mode`` (a spec or a name; default: the first mode)."""
        return self.tracks.get((bssid, self._mode_name(mode)))

    def estimate(self, bssid: str, mode: ModeSpec | str | None = None) -> Estimate:
        """The reported estimate of ``bssid`` in ``mode`` (default: the first mode)."""
        name = self._mode_name(mode)
        tr = self.tracks.get((bssid, name))
        if tr is None:
            return Estimate(t_s=self.now_s(), bssid=bssid, mode=name, status="no_data")
        return track_estimate(tr, self.frame, self.now_s())

    def estimates(self, mode: ModeSpec | str | None = None) -> list[Estimate]:
        """The reported estimate of every responder seen, in one mode (default the first)."""
        return [self.estimate(b, mode) for b in self.seen_bssids()]

    def now_s(self) -> float:
        """The latest time the estimator has been told about (common timeline)."""
        ts = [a.last_t_s for a in self.agents if a.offset_s is not None]
        return max(ts) if ts else 0.0


def track_estimate(tr: Track, frame: EnuFrame | None, t_now_s: float) -> Estimate:
    """The :class:`Estimate` a track reports (its last stable one, else its latest).

    Modes beyond the paper's add ``r95_h_m`` (their published 95 % horizontal radius)
    and, when ambiguous, the ``candidates`` (WGS84 and ENU, sigma_h, weight).
    """
    c = tr.counts
    counts = dict(n_meas=c.n_meas, n_bootstrap=c.n_bootstrap, n_acc=c.n_acc, n_gate=c.n_gate)
    boot = tr.bootstrap_result or tr.last_bootstrap
    kappa = boot.kappa if boot is not None and math.isfinite(boot.kappa) else None
    pub = tr.reported()
    if pub is None or frame is None:
        return Estimate(
            t_s=t_now_s, bssid=tr.bssid, mode=tr.spec.name, status=tr.status, kappa=kappa,
            **counts,
        )
    lat, lon, alt = frame.to_geodetic(*pub.enu_m)
    cands = []
    for mean, sigma_h, weight in tr.candidates:
        clat, clon, calt = frame.to_geodetic(*mean)
        cands.append(Candidate(mean_enu_m=mean, lat_deg=clat, lon_deg=clon, alt_m=calt,
                               sigma_h_m=sigma_h, weight=weight))
    return Estimate(
        t_s=pub.t_s,
        bssid=tr.bssid,
        mode=tr.spec.name,
        status=tr.status,
        mean_enu_m=pub.enu_m,
        cov_m2=pub.cov_m2,
        lat_deg=lat,
        lon_deg=lon,
        alt_m=alt,
        bias_m=pub.bias_m if tr.reports_bias else None,
        sigma_h_m=pub.sigma_h_m,
        sigma_z_m=pub.sigma_z_m,
        r95_h_m=pub.r95_h_m,
        stable=pub.stable,
        kappa=kappa,
        candidates=tuple(cands),
        **counts,
    )
