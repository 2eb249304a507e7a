"""Run a scenario: fly it, sense it, and write the flight log (log-format.md).

``simulate(scenario, seed, path)`` draws every random number from generators spawned
from ``numpy.random.SeedSequence(seed)`` (one per component, so the vehicle, clock,
GNSS and FTM streams are independent), hence the same scenario and seed give the same
arrays and a byte-identical log, ``.jsonl`` or ``.jsonl.gz``.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimator.logio import LogWriter
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord
from sim.clock import PhoneClock, exponential_delays
from sim.ftm import STATUS_NAMES, FtmTrack, simulate_ftm
from sim.gnss import GnssTrack, simulate_gnss
from sim.scenario import Scenario, load_scenario
from sim.vehicle import VehicleTrack, fly


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
        g = self.gnss
        lat = np.round(self.gnss_lla[:, 0], 9).tolist()
        lon = np.round(self.gnss_lla[:, 1], 9).tolist()
        alt = np.round(self.gnss_lla[:, 2], 3).tolist()
        acc = g.acc_m.tolist()
        vacc = g.vacc_m.tolist() if g.vacc_m is not None else [None] * len(acc)
        sats = g.sats.tolist()
        fix = g.fix
        recs: list[GnssFix | RangeSample] = [
            GnssFix(t_ns=t, lat_deg=a, lon_deg=b, alt_m=c, acc_m=d, vacc_m=e, fix=fix, sats=s)
            for t, a, b, c, d, e, s in zip(
                self.gnss_t_ns().tolist(), lat, lon, alt, acc, vacc, sats, strict=True
            )
        ]
        f = self.ftm
        bssid = np.array(self.bssids, dtype=object)[f.responder].tolist() if len(f.t_s) else []
        status = np.array(STATUS_NAMES, dtype=object)[f.status].tolist()
        ok = f.ok.tolist()
        rng_m = np.round(f.range_m, 3).tolist()
        std = np.round(f.range_std_m, 3).tolist()
        rssi = f.rssi_dbm.tolist()
        succ = f.successful.tolist()
        att = f.attempted
        for t, b, st, o, r, sd, rs, sc in zip(
            self.rtt_t_ns().tolist(), bssid, status, ok, rng_m, std, rssi, succ, strict=True
        ):
            if o:
                recs.append(
                    RangeSample(
                        t_ns=t,
                        bssid=b,
                        status=st,
                        range_m=r,
                        range_std_m=sd,
                        rssi_dbm=rs,
                        attempted=att,
                        successful=sc,
                    )
                )
            else:
                recs.append(RangeSample(t_ns=t, bssid=b, status=st, attempted=att, successful=sc))
        return [recs[i] for i in self.write_order.tolist()]


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise TypeError(f"seed must be an integer, got {type(seed).__name__}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return int(seed)


def run_scenario(scenario: Scenario, seed: int) -> SimResult:
    """Simulate ``scenario`` with ``seed`` without writing anything."""
    seed = _check_seed(seed)
    streams = np.random.SeedSequence(seed).spawn(5)
    rng_vehicle, rng_clock, rng_gnss, rng_ftm, rng_write = (
        np.random.default_rng(s) for s in streams
    )
    world = scenario.world
    vehicle = fly(scenario.trajectory(), world, scenario.vehicle, rng_vehicle)
    clock = PhoneClock.draw(scenario.clock, rng_clock)
    gnss = simulate_gnss(vehicle, scenario.gnss, scenario.clock, rng_gnss)
    ftm = simulate_ftm(vehicle, world, scenario.ftm, scenario.clock, rng_ftm)
    lat, lon, alt = world.frame.to_geodetic(gnss.enu_m[:, 0], gnss.enu_m[:, 1], gnss.enu_m[:, 2])
    lla = np.column_stack([np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(alt)])
    # lines reach the file after a small writer delay: delivery order, not t_ns order
    delivered = np.concatenate([gnss.t_delivery_s, ftm.t_delivery_s])
    written = delivered + exponential_delays(
        rng_write, scenario.clock.write_delay_s, len(delivered)
    )
    order = np.argsort(written, kind="stable")
    header = LogHeader(
        agent=scenario.log.agent,
        start_utc=scenario.log.start_utc,
        # configured H_AGL if the scenario sets one, else the median height flown above
        # the ground (what a pilot would have configured for this flight)
        agl_m=round(
            scenario.log.agl_m
            if scenario.log.agl_m is not None
            else float(np.median(vehicle.agl_m)),
            3,
        ),
        range_offset_m=scenario.log.range_offset_m,
    )
    return SimResult(
        scenario=scenario,
        seed=seed,
        vehicle=vehicle,
        gnss=gnss,
        gnss_lla=lla,
        ftm=ftm,
        clock=clock,
        header=header,
        truth=world.truth_records(),
        responder_enu_m=world.responder_enu_m(),
        write_order=order,
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
