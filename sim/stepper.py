"""The simulator stepper: advance every agent of a world until time t, get what its phone logs.

:class:`Stepper` holds a :class:`sim.realisation.Realisation` and one
:class:`AgentSim` per agent (vehicle, GNSS receiver, FTM radio, phone clock).
``command(agent, guidance)`` sets what an agent flies from where it is (position and
velocity: a new command never restarts from rest); ``step_to(t)`` advances every
agent to ``t`` and returns the records their phones delivered in the meantime, in
delivery order. Everything runs on absolute time grids and streams named by index, so
stepping to t in several pieces gives exactly the records of one step to t with the
same commands.

Records are :class:`estimator.records.GnssFix` and :class:`RangeSample` stamped with
the phone's monotonic clock (``t_ns`` = delivery time). Each carries the time its line
reaches the log file (delivery plus a small writer delay), so a log written from them
(:class:`LogSink`) is slightly out of ``t_ns`` order, as real logs are; a reader
sorting by ``t_ns`` (stable) sees them in (``t_ns``, write time) order, which is the
order :data:`REPLAY_ORDER` sorts them in.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import operator
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from estimator.logio import LogWriter
from estimator.records import (
    GnssFix,
    LogHeader,
    RangeSample,
    Trajectory,
    records_from_columns,
)
from sim._random import BlockedGaussMarkov
from sim.clock import PhoneClock
from sim.ftm import STATUS_NAMES, FtmRadio, FtmTrack, ftm_track, occluder_for
from sim.gnss import GnssReceiver, GnssTrack, gnss_track
from sim.realisation import (
    AGENT_CLOCK,
    AGENT_GNSS,
    AGENT_RADIO,
    AGENT_WANDER,
    AGENT_WRITER,
    Realisation,
)
from sim.scenario import AgentSpec
from sim.vehicle import (
    LANDED_AGL_M,
    Guidance,
    HoldGuidance,
    LandedGuidance,
    Multirotor,
    PathGuidance,
    VehicleState,
    VehicleTrack,
    path_guidance,
)

GNSS_SOURCE, RTT_SOURCE = 0, 1
_DELIVERY_ORDER = operator.itemgetter(0, 2, 3)  # (t_ns, source, index) of an Emitted


class Emitted(NamedTuple):
    """One log record as the phone delivered it."""

    t_ns: int
    write_s: float  # when the line reaches the file (simulated seconds)
    source: int  # GNSS_SOURCE | RTT_SOURCE
    index: int  # row in the agent's fix or result arrays
    record: GnssFix | RangeSample
    delivery_s: float = 0.0  # when the phone delivered it (simulated seconds)


# the sort key of the order a log reader gives: by t_ns, ties in file (write) order
REPLAY_ORDER = operator.itemgetter(0, 1)  # (Emitted.t_ns, Emitted.write_s)
_EMITTED = functools.partial(tuple.__new__, Emitted)  # Emitted of a full row, unchecked


@dataclass
class AgentSim:
    """One agent: its vehicle, GNSS receiver, FTM radio, phone clock and what it logged."""

    index: int
    spec: AgentSpec
    vehicle: Multirotor
    gnss: GnssReceiver
    radio: FtmRadio
    clock: PhoneClock
    header: LogHeader
    writer_seed: np.random.SeedSequence
    gnss_steps: list[GnssTrack] = field(default_factory=list)
    ftm_steps: list[FtmTrack] = field(default_factory=list)
    emitted: list[Emitted] = field(default_factory=list)
    _pending: list[Emitted] = field(
        default_factory=list
    )
    _n_fix: int = 0
    _n_rtt: int = 0
    _delays: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)

    WRITE_BLOCK = 1024

    def write_delays_s(self, source: int, first: int, n: int, mean_s: float) -> np.ndarray:
        """The writer's delays of records ``first .. first + n - 1`` of ``source``: drawn
        by the records' identity (blocks of :attr:`WRITE_BLOCK` per source, each from
        its own stream), so they do not depend on how the flight was stepped."""
        if mean_s <= 0.0:
            return np.zeros(n)
        out: list[np.ndarray] = []
        k, end = first, first + n
        while k < end:
            b = k // self.WRITE_BLOCK
            blk = self._delays.get((source, b))
            if blk is None:
                rng = np.random.default_rng(
                    np.random.SeedSequence(self.writer_seed.entropy,
                                           spawn_key=(*self.writer_seed.spawn_key, source, b))
                )
                blk = self._delays[(source, b)] = rng.exponential(mean_s, self.WRITE_BLOCK)
                for key in [q for q in self._delays if q[0] == source and q[1] < b - 1]:
                    del self._delays[key]
            stop = min(end, (b + 1) * self.WRITE_BLOCK)
            out.append(blk[k - b * self.WRITE_BLOCK : stop - b * self.WRITE_BLOCK])
            k = stop
        return out[0] if len(out) == 1 else np.concatenate(out) if out else np.zeros(0)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def t_s(self) -> float:
        return self.vehicle.t_s


class Stepper:
    """All agents of one realised world, advanced together (see the module docstring)."""

    TRACE_KEPT_S = 3600.0  # with keep_records=False: the recent past kept (simulated s)

    def __init__(
        self,
        realisation: Realisation,
        *,
        agents: Sequence[AgentSpec] | None = None,
        starts: Sequence[VehicleState] | None = None,
        header_agl_m: float | None = None,
        navigate_on_gnss: bool = True,
        keep_records: bool = True,
    ) -> None:
        # False: the phone's records and measurement steps are handed out as delivered
        # and not kept (file_records, gnss_track and ftm_track then see none), and of the
        # vehicle's trace and the GNSS draws only the last TRACE_KEPT_S to 2 x that are
        # (vehicle_track starts there): a vehicle that runs for hours does not grow
        self.keep_records = keep_records
        self.realisation = realisation
        sc = realisation.scenario
        self.world = realisation.world
        specs = tuple(agents) if agents is not None else sc.agents
        if not specs:
            raise ValueError("a stepper needs at least one agent")
        resp = realisation.responder_enu_m()
        models = tuple(sc.ftm.concealment(r.concealment) for r in self.world.responders)
        self.bssids = realisation.bssids
        occluder = occluder_for(sc.ftm, self.world.terrain, resp)  # one for every radio
        self.agents: list[AgentSim] = []
        self._nav_cache: dict[int, tuple[int, tuple[float, float, float]]] = {}
        for i, spec in enumerate(specs):
            if starts is not None:
                start = starts[i]
            else:
                e, n = sc.start_enu_m(i)
                start = VehicleState(0.0, (e, n, float(self.world.ground_m(e, n))), (0, 0, 0))
            cfg = spec.vehicle
            rx = GnssReceiver(spec.gnss, sc.clock, realisation.agent_seed(i, AGENT_GNSS))
            wander = BlockedGaussMarkov(
                realisation.agent_seed(i, AGENT_WANDER), cfg.sample_dt_s,
                np.full(3, cfg.tracking_sigma_m), cfg.tracking_tau_s, order=2,
            ) if cfg.tracking_sigma_m > 0 else None
            veh = Multirotor(
                cfg, self.world, start, wander=wander, name=spec.name,
                nav_error=rx.process.bias_at if navigate_on_gnss else None,
            )
            radio = FtmRadio(sc.ftm, sc.clock, resp, models, realisation.offsets_m,
                             realisation.shadowing, realisation.agent_seed(i, AGENT_RADIO),
                             occluder)
            clock = PhoneClock.draw(
                sc.clock, np.random.default_rng(realisation.agent_seed(i, AGENT_CLOCK))
            )
            agl = header_agl_m if header_agl_m is not None else sc.header_agl_m
            header = LogHeader(
                agent=spec.name,
                start_utc=sc.log.start_utc,
                agl_m=round(float(agl), 3),
                range_offset_m=sc.log.range_offset_m,
            )
            self.agents.append(AgentSim(
                i, spec, veh, rx, radio, clock, header,
                realisation.agent_seed(i, AGENT_WRITER),
            ))

    # ------------------------------------------------------------------ commands
    @property
    def t_s(self) -> float:
        return min(a.t_s for a in self.agents)

    def agent(self, key: int | str) -> AgentSim:
        if isinstance(key, str):
            for a in self.agents:
                if a.name == key:
                    return a
            raise KeyError(f"no agent named {key!r}")
        return self.agents[key]

    def state(self, agent: int | str = 0) -> VehicleState:
        """The agent's true controller state (evaluation and the vehicle model only)."""
        return self.agent(agent).vehicle.state

    def command(self, agent: int | str, guidance: Guidance) -> None:
        """Fly ``guidance`` from now on (from the current position and velocity)."""
        self.agent(agent).vehicle.set_guidance(guidance)

    ARRIVE_M = 0.5  # acceptance radius at a segment's end (the estimate drifts with GNSS)

    def follow(self, agent: int | str, traj: Trajectory) -> PathGuidance:
        """Fly ``traj`` from where the agent is (a leg to its start is added if needed);
        the segment is done within :attr:`ARRIVE_M` of its end."""
        a = self.agent(agent)
        nav = self.navigation_position_m(agent)
        h_walk = a.spec.vehicle.ground_height_m
        if h_walk is not None:  # a walker follows the path's ground track at its own height
            traj = dataclasses.replace(traj, enu_m=np.column_stack(
                [traj.enu_m[:, :2], np.full(len(traj.enu_m), h_walk)]), height_ref="terrain")
            # its height is the ground's, not GNSS's
            nav = (nav[0], nav[1], a.vehicle.position_m[2])
        # the path is flown on the autopilot's estimate: start the leg where it believes
        speed = math.hypot(*a.vehicle.velocity_mps[:2])
        g = path_guidance(traj, self.world, a.spec.vehicle, start_speed_mps=speed, from_m=nav,
                          arrive_m=self.ARRIVE_M)
        a.vehicle.set_guidance(g)
        return g

    def hold(self, agent: int | str) -> HoldGuidance | LandedGuidance:
        """Brake and hold where the autopilot believes the vehicle is; a vehicle still on
        the ground (within ``LANDED_AGL_M``) stays landed instead (holding its believed
        height there would fly it into the ground as its navigation error drifts)."""
        a = self.agent(agent)
        p = a.vehicle.position_m
        if (a.spec.vehicle.ground_height_m is None
                and p[2] - float(self.world.ground_m(p[0], p[1])) <= LANDED_AGL_M):
            g = LandedGuidance()
            a.vehicle.set_guidance(g)
            return g
        g = HoldGuidance(self.navigation_position_m(agent), a.spec.vehicle)
        a.vehicle.set_guidance(g)
        return g

    def navigation_position_m(self, agent: int | str = 0) -> tuple[float, float, float]:
        """Where the autopilot believes the vehicle is (truth + its navigation error)."""
        a = self.agent(agent)
        v = a.vehicle
        if v.nav_error is None:
            return v.position_m
        cached = self._nav_cache.get(a.index)
        if cached is not None and cached[0] == v.k:  # asked again before the next tick
            return cached[1]
        p = v.position_m
        b = v.nav_error(np.array([v.t_s]))[0].tolist()
        nav = (p[0] + b[0], p[1] + b[1], p[2] + b[2])
        self._nav_cache[a.index] = (v.k, nav)
        return nav

    # ------------------------------------------------------------------ stepping
    def step_to(self, t_s: float) -> list[list[Emitted]]:
        """Advance every agent to ``t_s``; per agent, the records delivered meanwhile."""
        return [self._advance(a, t_s) for a in self.agents]

    def _advance(self, a: AgentSim, t_s: float, *, flush: bool = False) -> list[Emitted]:
        a.vehicle.advance(t_s)
        t_end = a.vehicle.t_s
        v = a.vehicle
        g = a.gnss.measure_until(t_end, v.position_at)
        f = a.radio.range_until(t_end, v.position_at, v.antenna_at)
        if self.keep_records:
            a.gnss_steps.append(g)
            a.ftm_steps.append(f)
        self._queue(a, g, f)
        # emit what was delivered by now, but not past the earliest callback of a
        # request still to be processed: every agent's records leave in delivery order
        limit = math.inf if flush else min(t_end, a.radio.horizon_s)
        out = [e for e in a._pending if e.delivery_s <= limit]
        a._pending = [e for e in a._pending if e.delivery_s > limit]
        out.sort(key=_DELIVERY_ORDER)
        if self.keep_records:
            a.emitted.extend(out)
        else:
            self._forget(a, t_end)
        return out

    def _forget(self, a: AgentSim, t_s: float) -> None:
        """Forget what ``a`` flew and drew more than TRACE_KEPT_S before ``t_s``, once
        that is TRACE_KEPT_S worth (amortised: the trace is copied once per period)."""
        cut = t_s - self.TRACE_KEPT_S
        if cut - a.vehicle.trace_start_s >= self.TRACE_KEPT_S:
            a.vehicle.forget_before(cut)
            gnss = a.gnss.process
            gnss.forget_before(max(gnss.last_epoch_at_or_before(cut), 0))

    def finish(self) -> list[list[Emitted]]:
        """End of the flight: deliver what is still on its way (measured, not delivered)."""
        return [self._advance(a, a.vehicle.t_s, flush=True) for a in self.agents]

    def _queue(self, a: AgentSim, g: GnssTrack, f: FtmTrack) -> None:
        frame = self.world.frame
        n = len(g.t_s)
        if n:
            lat, lon, alt = frame.to_geodetic(g.enu_m[:, 0], g.enu_m[:, 1], g.enu_m[:, 2])
            t_ns = a.clock.to_ns(g.t_delivery_s).tolist()
            lat_lon = np.round(np.vstack([lat, lon]), 9)
            recs = records_from_columns(GnssFix, {
                "t_ns": t_ns,
                "lat_deg": lat_lon[0].tolist(),
                "lon_deg": lat_lon[1].tolist(),
                "alt_m": np.round(np.atleast_1d(alt), 3).tolist(),
                "acc_m": g.acc_m.tolist(),
                "vacc_m": g.vacc_m.tolist() if g.vacc_m is not None else [None] * n,
                "fix": [a.spec.gnss.fix] * n,
                "sats": g.sats.tolist(),
            })
            a._pending.extend(self._to_emit(a, g.t_delivery_s, t_ns, GNSS_SOURCE,
                                                 a._n_fix, recs))
            a._n_fix += n
        n = len(f.t_s)
        if n:
            t_ns = a.clock.to_ns(f.t_delivery_s).tolist()
            status = [STATUS_NAMES[s] for s in f.status.tolist()]
            ok = [s == "ok" for s in status]

            def if_ok(values: np.ndarray) -> list:
                return [v if k else None for v, k in zip(values.tolist(), ok, strict=True)]

            recs = records_from_columns(RangeSample, {
                "t_ns": t_ns,
                "bssid": [self.bssids[j] for j in f.responder.tolist()],
                "status": status,
                "range_m": if_ok(np.round(f.range_m, 3)),
                "range_std_m": if_ok(np.round(f.range_std_m, 3)),
                "rssi_dbm": if_ok(f.rssi_dbm),
                "attempted": [a.radio.cfg.attempted] * n,
                "successful": f.successful.tolist(),
            })
            a._pending.extend(self._to_emit(a, f.t_delivery_s, t_ns, RTT_SOURCE,
                                                 a._n_rtt, recs))
            a._n_rtt += n

    def _to_emit(self, a: AgentSim, t_delivery_s: np.ndarray, t_ns: list[int],
                      source: int, first: int, recs: list) -> list[Emitted]:
        """New records as they will be emitted (write time: delivery + writer delay)."""
        n = len(recs)
        delay = a.write_delays_s(source, first, n,
                                 self.realisation.scenario.clock.write_delay_s)
        write = (t_delivery_s + delay).tolist()
        return list(map(_EMITTED, zip(t_ns, write, itertools.repeat(source, n),
                                           range(first, first + n), recs,
                                           t_delivery_s.tolist(), strict=True)))

    # ------------------------------------------------------------------ traces
    def vehicle_track(self, agent: int | str = 0) -> VehicleTrack:
        return self.agent(agent).vehicle.track()

    def gnss_track(self, agent: int | str = 0) -> GnssTrack:
        a = self.agent(agent)
        return gnss_track(a.gnss_steps, a.spec.gnss.fix)

    def ftm_track(self, agent: int | str = 0) -> FtmTrack:
        a = self.agent(agent)
        return ftm_track(a.ftm_steps, self.realisation.offsets_m, a.radio.cfg.attempted)

    def file_records(self, agent: int | str = 0) -> list[GnssFix | RangeSample]:
        """Everything the agent logged, in file (write) order."""
        a = self.agent(agent)
        return [e.record for e in sorted(a.emitted, key=lambda e: (e.write_s, e.t_ns))]


class LogSink:
    """Writes one agent's log as it flies: header and truth first, then each line when
    it reaches the file (write time), flushed line by line."""

    def __init__(self, path: str | os.PathLike, header: LogHeader, truth: Iterable = (),
                 *, flush_lines: bool = False) -> None:
        self.path = Path(path)
        self._w = LogWriter(self.path, header)
        self._w.write_all(truth)
        self._buf: list[tuple[float, int, int, GnssFix | RangeSample]] = []
        self._n = 0
        self.flush_lines = flush_lines

    def add(self, emitted: Iterable[Emitted], now_s: float) -> None:
        """Take newly delivered records and write those whose write time has come."""
        for e in emitted:
            self._buf.append((e.write_s, e.t_ns, self._n, e.record))
            self._n += 1
        self._write(now_s)

    def _write(self, until_s: float) -> None:
        if not self._buf:
            return
        self._buf.sort(key=lambda x: (x[0], x[1], x[2]))
        k = 0
        while k < len(self._buf) and self._buf[k][0] <= until_s:
            self._w.write(self._buf[k][3])
            k += 1
        del self._buf[:k]
        if k and self.flush_lines:
            self._w.flush()

    def close(self) -> None:
        self._write(math.inf)
        self._w.close()

    def __enter__(self) -> LogSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
