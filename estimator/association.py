"""GNSS-RTT time association (sec. Range Measurement Model), streaming.

For an RTT sample at time t, with the last fix at or before t (t0) and the first fix at
or after t (t1):

* if both exist with t - t0 <= 2 T_sync and t1 - t <= 2 T_sync, the anchor is linearly
  interpolated between them (position, accuracy as the larger of the two: a suspect fix
  makes the interpolated anchor suspect);
* otherwise the nearer of the two is used only if it lies within T_sync = 1.2 s;
* otherwise the sample is unassociated (counted, not used).

Fixes with ``fix == "none"`` are ignored. The GNSS quality gate then passes only anchors
with acc_m < 15 m (sec. Hardware and Software). The corrected range is
d = max(0, d_raw - b0). Records must arrive ordered by time (the log readers do that);
memory is bounded by the samples waiting for their next fix (at most 2 T_sync).

Suspicious data (docs/log-format.md, "Suspicious data") is handled and counted here,
for files and live streams alike: a record equal to one already pushed at the same
``t_ns`` (a duplicated line, a log concatenated with itself) is dropped; a gap of more
than :data:`CLOCK_JUMP_FORWARD_S` between consecutive records is a forward clock jump
(or a logging outage): nothing is interpolated or matched across it.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, fields

from estimator.records import GNSS_FIX_TYPES, GnssFix, RangeSample

CLOCK_JUMP_FORWARD_S = 60.0  # no record for this long: a forward clock jump or an outage


@dataclass(frozen=True, kw_only=True)
class AssociationConfig:
    t_sync_s: float = 1.2  # T_sync, sec. Range Measurement Model
    max_acc_m: float = 15.0  # GNSS quality proxy gate, sec. Hardware and Software
    range_offset_m: float = 0.0  # b0, d = max(0, d_raw - b0)


@dataclass(frozen=True, slots=True)
class GeoRange:
    """A corrected range with its WGS84 anchor (before projection to the ENU frame)."""

    t_ns: int
    bssid: str
    range_m: float
    rssi_dbm: float | None
    lat_deg: float
    lon_deg: float
    alt_m: float
    acc_m: float
    vacc_m: float | None
    interpolated: bool
    fix: str | None = None  # the fix type (of the worse fix when interpolated)


@dataclass
class AssociationStats:
    """Per-BSSID counts of what happened to RTT records."""

    rtt: Counter = field(default_factory=Counter)  # every rtt record
    ok: Counter = field(default_factory=Counter)  # status ok
    unassociated: Counter = field(default_factory=Counter)
    gnss_quality: Counter = field(default_factory=Counter)  # acc_m >= 15 m
    associated: Counter = field(default_factory=Counter)  # passed to the estimator
    interpolated: Counter = field(default_factory=Counter)
    # suspicious data, by record kind ("gnss" or the BSSID) / by kind of jump
    duplicates: Counter = field(default_factory=Counter)  # dropped: seen at this t_ns
    clock_jumps: Counter = field(default_factory=Counter)  # "forward" gaps

    def merge(self, other: AssociationStats) -> None:
        """Add ``other``'s counts (several agents' association into one report)."""
        for f in fields(self):
            getattr(self, f.name).update(getattr(other, f.name))


class Associator:
    """Streaming association of one log's time-ordered records."""

    def __init__(self, cfg: AssociationConfig = AssociationConfig()) -> None:
        self.cfg = cfg
        self.stats = AssociationStats()
        self._last_fix: GnssFix | None = None
        self._pending: list[tuple[RangeSample, GnssFix | None]] = []
        self._t_ns = -1  # time of the latest record pushed
        self._at_t: list[GnssFix | RangeSample] = []  # the records pushed at that time

    def _screen(self, rec: GnssFix | RangeSample) -> bool:
        """Count suspicious data; False for a duplicate (to drop)."""
        t = rec.t_ns
        if t == self._t_ns:
            if rec in self._at_t:
                self.stats.duplicates[getattr(rec, "bssid", "gnss")] += 1
                return False
            self._at_t.append(rec)
            return True
        if t > self._t_ns:
            if self._t_ns >= 0 and t - self._t_ns > CLOCK_JUMP_FORWARD_S * 1e9:
                self.stats.clock_jumps["forward"] += 1
                self._last_fix = None  # nothing before the jump is used after it
            self._t_ns = t
            self._at_t = [rec]
        return True

    def push(self, rec: GnssFix | RangeSample) -> list[GeoRange]:
        """Feed one record; return the ranges resolved by it (in time order)."""
        out: list[GeoRange] = []
        if not self._screen(rec):
            return out
        if isinstance(rec, GnssFix):
            if rec.fix == "none":
                return out
            for sample, prev in self._pending:
                self._resolve(sample, prev, rec, out)
            self._pending.clear()
            self._last_fix = rec
            return out
        self.stats.rtt[rec.bssid] += 1
        if not rec.ok:
            return out
        self.stats.ok[rec.bssid] += 1
        self._expire(rec.t_ns, out)
        prev = self._last_fix
        self._pending.append((rec, prev))
        return out

    def push_fixes(self, fixes: Sequence[GnssFix]) -> list[GeoRange]:
        """:meth:`push` of consecutive fixes: the first valid one resolves the waiting
        ranges, the last valid one is the latest fix."""
        valid = [f for f in fixes if self._screen(f) and f.fix != "none"]
        out: list[GeoRange] = []
        if valid:
            for sample, prev in self._pending:
                self._resolve(sample, prev, valid[0], out)
            self._pending.clear()
            self._last_fix = valid[-1]
        return out

    def earliest_pending_ns(self) -> int | None:
        """Time of the oldest ok sample still waiting for its next fix (None if none)."""
        return self._pending[0][0].t_ns if self._pending else None

    def flush(self) -> list[GeoRange]:
        """End of stream: resolve every waiting sample without a following fix."""
        out: list[GeoRange] = []
        for sample, prev in self._pending:
            self._resolve(sample, prev, None, out)
        self._pending.clear()
        return out

    def run(self, records: Iterable[GnssFix | RangeSample]) -> Iterator[GeoRange]:
        for rec in records:
            yield from self.push(rec)
        yield from self.flush()

    def _expire(self, now_ns: int, out: list[GeoRange]) -> None:
        limit = int(2.0 * self.cfg.t_sync_s * 1e9)
        keep = []
        for sample, prev in self._pending:
            if now_ns - sample.t_ns > limit:
                self._resolve(sample, prev, None, out)
            else:
                keep.append((sample, prev))
        self._pending = keep

    def _resolve(
        self,
        s: RangeSample,
        prev: GnssFix | None,
        nxt: GnssFix | None,
        out: list[GeoRange],
    ) -> None:
        cfg = self.cfg
        t = s.t_ns
        two_t = 2.0 * cfg.t_sync_s * 1e9
        one_t = cfg.t_sync_s * 1e9
        interp = False
        bracketed = prev is not None and nxt is not None
        if bracketed and t - prev.t_ns <= two_t and nxt.t_ns - t <= two_t:
            span = nxt.t_ns - prev.t_ns
            w = 0.0 if span <= 0 else (t - prev.t_ns) / span
            lat = prev.lat_deg + w * (nxt.lat_deg - prev.lat_deg)
            lon = prev.lon_deg + w * (nxt.lon_deg - prev.lon_deg)
            alt = prev.alt_m + w * (nxt.alt_m - prev.alt_m)
            acc = max(prev.acc_m, nxt.acc_m)
            vacc = (
                max(prev.vacc_m, nxt.vacc_m)
                if prev.vacc_m is not None and nxt.vacc_m is not None
                else None
            )
            fix = _worse_fix(prev.fix, nxt.fix)
            interp = True
        else:
            best: GnssFix | None = None
            best_dt = one_t
            for f in (prev, nxt):
                if f is not None and abs(t - f.t_ns) <= best_dt:
                    best, best_dt = f, abs(t - f.t_ns)
            if best is None:
                self.stats.unassociated[s.bssid] += 1
                return
            lat, lon, alt = best.lat_deg, best.lon_deg, best.alt_m
            acc, vacc = best.acc_m, best.vacc_m
            fix = best.fix
        if not acc < cfg.max_acc_m:
            self.stats.gnss_quality[s.bssid] += 1
            return
        self.stats.associated[s.bssid] += 1
        self.stats.interpolated[s.bssid] += interp
        assert s.range_m is not None
        d = max(0.0, s.range_m - cfg.range_offset_m)
        out.append(
            GeoRange(
                t_ns=t,
                bssid=s.bssid,
                range_m=d,
                rssi_dbm=s.rssi_dbm,
                lat_deg=lat,
                lon_deg=lon,
                alt_m=alt,
                acc_m=acc,
                vacc_m=vacc,
                interpolated=interp,
                fix=fix,
            )
        )


def _worse_fix(a: str | None, b: str | None) -> str | None:
    """The lower-quality of two fix types (GNSS_FIX_TYPES order); None if either is unknown."""
    if a is None or b is None:
        return None
    ra = GNSS_FIX_TYPES.index(a) if a in GNSS_FIX_TYPES else 0
    rb = GNSS_FIX_TYPES.index(b) if b in GNSS_FIX_TYPES else 0
    return a if ra <= rb else b
