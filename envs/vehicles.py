"""The vehicle interface of the closed loop, and the stepped simulator behind it.

The loop (:class:`envs.loop.ClosedLoop`) flies a :class:`Vehicle`: something that
reports the autopilot's state, flies a plan (a :class:`Trajectory`) or holds, and,
advanced to a flight time, returns what the phone on board delivered meanwhile (its
log records, :class:`envs.phone.PhoneBatch`). Two implementations:

- :class:`SimVehicle`: the stepped simulator (:class:`sim.stepper.Stepper`), every
  agent of a realised world, in process;
- :class:`envs.mavlink_vehicle.MavlinkVehicle`: a MAVLink autopilot (``osa vehicle``
  or a drone): telemetry in, missions out, the phone's records from a record stream
  (:mod:`envs.phone`).

A vehicle reports only what its autopilot and phone would: where the loop learns a
range was heard is the estimator's association of that range with the phone's GNSS,
never the simulator's state. The simulator's truth (the true path, its length) is
offered for evaluation only (:meth:`SimVehicle.true_tracks`, ``path_length_m``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from envs.phone import PhoneBatch
from estimator.records import LogHeader, Trajectory
from sim.realisation import Realisation
from sim.stepper import REPLAY_ORDER, Emitted, LogSink, Stepper
from sim.vehicle import PathGuidance


@dataclass(frozen=True)
class VehicleState:
    """One agent as its autopilot reports it (navigation estimate, mission ENU)."""

    position_enu_m: tuple[float, float, float]
    velocity_enu_mps: tuple[float, float, float]


class Vehicle(Protocol):
    """What the closed loop flies (see the module docstring).

    ``t_s`` is the flight time (from the start of the search); every method takes the
    agent's index. A plan given to :meth:`fly` replaces the one being flown, from where
    the vehicle is; :meth:`segment_done` says it has been flown to its end (or that the
    vehicle holds). :meth:`advance_to` returns one :class:`PhoneBatch` per agent.
    """

    n_agents: int
    t_s: float

    def start(self) -> None:
        """Connect, check, arm: flight time starts at 0 here (idempotent)."""
        ...

    def header(self, agent: int) -> LogHeader:
        """The header of the agent's phone log (after :meth:`start`)."""
        ...

    def state(self, agent: int) -> VehicleState: ...

    def fly(self, agent: int, traj: Trajectory) -> None: ...

    def hold(self, agent: int) -> None: ...

    def segment_done(self, agent: int) -> bool: ...

    def advance_to(self, t_s: float) -> list[PhoneBatch]: ...

    def finish(self) -> list[PhoneBatch]:
        """End of the flight: what the phones still deliver; logs closed."""
        ...

    def close(self) -> None:
        """Release what the vehicle holds (idempotent; also after a failure)."""
        ...

    @property
    def path_length_m(self) -> float: ...

    def true_tracks(self) -> list[np.ndarray]: ...


class SimVehicle:
    """Every agent of a realised world, stepped in process (:class:`sim.Stepper`).

    ``log_paths`` (one per agent) receive each phone's log as the phone writes it
    (header, truth records, then each line when it reaches the file)."""

    def __init__(self, realisation: Realisation, *, header_agl_m: float | None = None,
                 log_paths: Sequence[str | os.PathLike] | None = None,
                 flush_lines: bool = False) -> None:
        self.stepper = Stepper(realisation, header_agl_m=header_agl_m)
        self.n_agents = len(self.stepper.agents)
        truth = realisation.truth_records()
        self.sinks: list[LogSink] = []
        if log_paths is not None:
            if len(log_paths) != self.n_agents:
                raise ValueError("one log path per agent")
            for a, p in zip(self.stepper.agents, log_paths, strict=True):
                self.sinks.append(LogSink(p, a.header, truth, flush_lines=flush_lines))
        self.log_paths = [Path(p) for p in log_paths] if log_paths is not None else []
        self._segment: dict[int, object] = {}
        self._path_m = [0.0] * self.n_agents
        self._last_pos = [self.stepper.state(i).position_m for i in range(self.n_agents)]
        # phone clock minus flight time (the simulator's clock model: exact)
        self._offset_s = [a.clock.boot_offset_ns * 1e-9 for a in self.stepper.agents]
        self.finished = False

    # ------------------------------------------------------------------ interface
    @property
    def t_s(self) -> float:
        return self.stepper.t_s

    def start(self) -> None:
        pass

    def header(self, agent: int) -> LogHeader:
        return self.stepper.agents[agent].header

    def state(self, agent: int) -> VehicleState:
        v = self.stepper.agents[agent].vehicle.state.velocity_mps
        return VehicleState(self.stepper.navigation_position_m(agent), tuple(v))

    def fly(self, agent: int, traj: Trajectory) -> None:
        self._segment[agent] = self.stepper.follow(agent, traj)

    def hold(self, agent: int) -> None:
        self._segment[agent] = self.stepper.hold(agent)

    def segment_done(self, agent: int) -> bool:
        g = self._segment.get(agent)
        return not isinstance(g, PathGuidance) or g.done

    def advance_to(self, t_s: float) -> list[PhoneBatch]:
        out = self.stepper.step_to(t_s)
        for i, a in enumerate(self.stepper.agents):
            p = tuple(a.vehicle.state.position_m)  # the true position (evaluation)
            self._path_m[i] += math.dist(p, self._last_pos[i])
            self._last_pos[i] = p
        return self._batches(out)

    def finish(self) -> list[PhoneBatch]:
        if self.finished:
            return [PhoneBatch(()) for _ in range(self.n_agents)]
        self.finished = True
        batches = self._batches(self.stepper.finish())
        for s in self.sinks:
            s.close()
        return batches

    def close(self) -> None:
        for s in self.sinks:
            s.close()

    def _batches(self, out: list[list[Emitted]]) -> list[PhoneBatch]:
        """Per agent: the records in the order a replay of its log reads them (the
        stepper delivers in delivery order: nothing later can be earlier)."""
        batches = []
        for i, (a, emitted) in enumerate(zip(self.stepper.agents, out, strict=True)):
            if self.sinks:
                self.sinks[i].add(emitted, a.t_s)
            recs = [e.record for e in sorted(emitted, key=REPLAY_ORDER)]
            through = emitted[-1].t_ns if emitted else None
            batches.append(PhoneBatch(recs, through, self._offset_s[i]))
        return batches

    # ------------------------------------------------------------------ evaluation
    @property
    def path_length_m(self) -> float:
        """The true distance flown (evaluation)."""
        return float(sum(self._path_m))

    def true_tracks(self) -> list[np.ndarray]:
        """The vehicles' true paths (evaluation: figures), every half second."""
        return [self.stepper.vehicle_track(i).enu_m[::10] for i in range(self.n_agents)]
