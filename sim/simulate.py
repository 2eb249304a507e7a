"""Run a scenario's fixed flight: fly it, sense it, and write the flight log.

``run_scenario(scenario, seed)`` realises the world (:func:`sim.realisation.realise`)
and flies the scenario's ``[flight]`` with the stepper (:class:`sim.stepper.Stepper`):
the first agent takes off from rest at the path's first point and flies it to its end.
Every random number comes from streams named under ``SeedSequence(seed)``, hence the
same scenario and seed give the same arrays and a byte-identical log, ``.jsonl`` or
``.jsonl.gz``.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimator.logio import LogWriter
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord
from sim.clock import PhoneClock
from sim.ftm import FtmTrack
from sim.gnss import GnssTrack
from sim.realisation import Realisation, realise
from sim.scenario import Scenario, load_scenario
from sim.stepper import Stepper
from sim.vehicle import (
    FlightError,
    VehicleState,
    VehicleTrack,
    path_guidance,
    trajectory_error,
)


@dataclass(frozen=True, eq=False)
class SimResult:
    """A simulated flight: its truth and sensor arrays, the log's header and write order.

    ``vehicle`` is the true path (GNSS antenna), ``gnss`` the delivered fixes with their
    true errors, ``ftm`` every ranging result with its hidden truth. ``gnss_lla`` holds
    the reported (lat_deg, lon_deg, alt_m) columns. ``write_order`` indexes the
    concatenation [gnss fixes, rtt results] in the order lines reach the file.
    """

    scenario: Scenario
    seed: int
    vehicle: VehicleTrack
    gnss: GnssTrack
    gnss_lla: np.ndarray
    ftm: FtmTrack
    clock: PhoneClock
    header: LogHeader
    truth: tuple[TruthRecord, ...]
    responder_enu_m: np.ndarray
    write_order: np.ndarray
    file_records: tuple = ()
    realisation: Realisation | None = None
    path: Path | None = None

    @property
    def duration_s(self) -> float:
        return self.vehicle.duration_s

    @property
    def bssids(self) -> tuple[str, ...]:
        return tuple(r.bssid for r in self.scenario.world.responders)

    @property
    def n_gnss(self) -> int:
        return len(self.gnss.t_s)

    @property
    def n_rtt(self) -> int:
        return len(self.ftm.t_s)

    def __repr__(self) -> str:
        return f"SimResult({self.summary()})"

    def ok_counts(self) -> dict[str, int]:
        """``ok`` results per responder name."""
        return {r.name: self.ftm.ok_count(k) for k, r in enumerate(self.scenario.world.responders)}

    def gnss_t_ns(self) -> np.ndarray:
        return self.clock.to_ns(self.gnss.t_delivery_s)

    def rtt_t_ns(self) -> np.ndarray:
        return self.clock.to_ns(self.ftm.t_delivery_s)

    def summary(self) -> str:
        """One line: duration, fixes, results and ``ok`` per responder."""
        per = ", ".join(f"{name} {n} ok" for name, n in self.ok_counts().items()) or "none"
        return (
            f"{self.scenario.name} seed {self.seed}: {self.duration_s / 60:.1f} min, "
            f"{self.n_gnss} gnss, {self.n_rtt} rtt ({per})"
        )

    def records(self) -> list[GnssFix | RangeSample]:
        """The gnss and rtt records in file order (values rounded as written)."""
        return list(self.file_records)


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise TypeError(f"seed must be an integer, got {type(seed).__name__}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return int(seed)


def run_scenario(scenario: Scenario, seed: int) -> SimResult:
    """Simulate ``scenario``'s fixed flight with ``seed`` without writing anything."""
    seed = _check_seed(seed)
    real = realise(scenario, seed)
    world = real.world
    traj = scenario.trajectory()
    vcfg = scenario.agents[0].vehicle
    g = path_guidance(traj, world, vcfg)
    start = VehicleState(0.0, g.start_m, (0.0, 0.0, 0.0))
    stepper = Stepper(real, agents=scenario.agents[:1], starts=[start],
                      navigate_on_gnss=False)
    stepper.command(0, g)
    agent = stepper.agents[0]
    t_max = 3.0 * traj.duration_s + 600.0
    try:
        while not g.done and agent.t_s < t_max:
            agent.vehicle.advance(min(agent.t_s + 60.0, t_max), until_done=True)
            stepper.step_to(agent.t_s)
    except FlightError as exc:
        raise trajectory_error(exc, traj, world) from None
    stepper.finish()
    vehicle = stepper.vehicle_track(0)
    gnss = stepper.gnss_track(0)
    ftm = stepper.ftm_track(0)
    lat, lon, alt = world.frame.to_geodetic(gnss.enu_m[:, 0], gnss.enu_m[:, 1], gnss.enu_m[:, 2])
    lla = np.column_stack([np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(alt)])
    emitted = sorted(agent.emitted, key=lambda e: (e.write_s, e.t_ns))
    n_fix = len(gnss.t_s)
    order = np.array([e.index if e.source == 0 else n_fix + e.index for e in emitted],
                     dtype=np.int64)
    header = dataclasses.replace(
        agent.header,
        # configured H_AGL if the scenario sets one, else the median height flown above
        # the ground (what a pilot would have configured for this flight)
        agl_m=round(
            scenario.log.agl_m
            if scenario.log.agl_m is not None
            else float(np.median(vehicle.agl_m)),
            3,
        ),
    )
    return SimResult(
        scenario=scenario,
        seed=seed,
        vehicle=vehicle,
        gnss=gnss,
        gnss_lla=lla,
        ftm=ftm,
        clock=agent.clock,
        header=header,
        truth=real.truth_records(),
        responder_enu_m=real.responder_enu_m(),
        write_order=order,
        file_records=tuple(e.record for e in emitted),
        realisation=real,
    )


def write_log(result: SimResult, path: str | os.PathLike) -> Path:
    """Write ``result`` as a flight log (gzip when the name ends in ``.gz``)."""
    out = Path(path)
    records = result.records()
    with LogWriter(out, result.header) as w:
        w.write_all(result.truth)
        w.write_all(records)
    return out


def simulate(
    scenario: Scenario | str | os.PathLike,
    seed: int = 0,
    path: str | os.PathLike | None = None,
) -> SimResult:
    """Simulate a scenario (object, preset name or TOML path); write the log if ``path``."""
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    result = run_scenario(sc, seed)
    if path is None:
        return result
    out = write_log(result, path)
    return dataclasses.replace(result, path=out)
