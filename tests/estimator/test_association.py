"""GNSS-RTT time association (sec. Range Measurement Model): T_sync = 1.2 s."""

from __future__ import annotations

import random

import pytest

from estimator.association import AssociationConfig, Associator, GeoRange
from estimator.records import GnssFix, RangeSample

B = "a4:77:33:0f:1e:02"
B2 = "a4:77:33:0f:1e:03"


def _ns(t_s: float) -> int:
    return round(t_s * 1e9)


def fix(t_s: float, lat: float = 36.715, lon: float = -4.478, alt: float = 100.0, *,
        acc: float = 1.0, vacc: float | None = None, kind: str | None = "3d",
        ) -> GnssFix:  # fmt: skip
    return GnssFix(
        t_ns=_ns(t_s), lat_deg=lat, lon_deg=lon, alt_m=alt, acc_m=acc, vacc_m=vacc, fix=kind
    )


def rtt(t_s: float, rng: float | None = 50.0, *, status: str = "ok", bssid: str = B,
        rssi: float | None = -70.0) -> RangeSample:  # fmt: skip
    return RangeSample(t_ns=_ns(t_s), bssid=bssid, status=status, range_m=rng, rssi_dbm=rssi)


def run(records, cfg: AssociationConfig = AssociationConfig()) -> tuple[list[GeoRange], Associator]:
    a = Associator(cfg)
    return list(a.run(records)), a


def test_interpolates_between_fixes_100ms_apart() -> None:
    a = Associator()
    assert a.push(fix(10.0, 36.715, -4.478, 100.0, acc=1.0, vacc=2.0)) == []
    assert a.push(rtt(10.025, 74.312)) == []  # waits for the next fix
    out = a.push(fix(10.1, 36.716, -4.476, 104.0, acc=3.0, vacc=1.5))
    assert len(out) == 1
    g = out[0]
    # w = 25 ms / 100 ms = 0.25
    assert g.lat_deg == pytest.approx(36.71525, abs=1e-12)
    assert g.lon_deg == pytest.approx(-4.4775, abs=1e-12)
    assert g.alt_m == pytest.approx(101.0, abs=1e-12)
    assert g.acc_m == 3.0  # the larger of the two
    assert g.vacc_m == 2.0
    assert g.interpolated
    assert (g.t_ns, g.bssid, g.range_m, g.rssi_dbm) == (10_025_000_000, B, 74.312, -70.0)
    assert a.flush() == []
    assert a.stats.associated[B] == 1 and a.stats.interpolated[B] == 1


def test_interpolates_between_fixes_3s_apart() -> None:
    # each fix 1.5 s away: within 2 T_sync = 2.4 s, so still interpolated (w = 0.5)
    out, a = run([fix(0.0, 36.0, -4.0, 100.0), rtt(1.5), fix(3.0, 36.002, -4.004, 130.0)])
    assert len(out) == 1
    assert out[0].interpolated
    assert out[0].lat_deg == pytest.approx(36.001, abs=1e-12)
    assert out[0].lon_deg == pytest.approx(-4.002, abs=1e-12)
    assert out[0].alt_m == pytest.approx(115.0, abs=1e-12)
    assert a.stats.interpolated[B] == 1


def test_interpolation_limit_is_inclusive() -> None:
    # 2.4 s on both sides is "within 2 T_sync"
    out, _ = run([fix(0.0, 36.0), rtt(2.4), fix(4.8, 36.048)])
    assert len(out) == 1 and out[0].interpolated
    assert out[0].lat_deg == pytest.approx(36.024, abs=1e-12)


def test_next_fix_too_far_uses_previous_within_t_sync() -> None:
    # previous 1.0 s before, next 3.0 s after (> 2.4 s): the nearest within 1.2 s
    out, a = run([fix(0.0, 36.0, -4.0, 100.0, acc=2.5, vacc=3.0), rtt(1.0),
                  fix(4.0, 37.0, -5.0, 200.0)])  # fmt: skip
    assert len(out) == 1
    g = out[0]
    assert (g.lat_deg, g.lon_deg, g.alt_m, g.acc_m, g.vacc_m) == (36.0, -4.0, 100.0, 2.5, 3.0)
    assert not g.interpolated
    assert a.stats.interpolated[B] == 0 and a.stats.associated[B] == 1


def test_previous_fix_too_far_uses_next_within_t_sync() -> None:
    out, _ = run([fix(0.0, 36.0), rtt(3.0), fix(4.0, 37.0, -5.0, 200.0)])
    assert len(out) == 1
    assert (out[0].lat_deg, out[0].lon_deg, out[0].alt_m) == (37.0, -5.0, 200.0)
    assert not out[0].interpolated


def test_nearest_fix_boundary_is_inclusive() -> None:
    out, _ = run([fix(0.0, 36.0), rtt(1.2)])  # exactly T_sync, no next fix
    assert len(out) == 1 and out[0].lat_deg == 36.0


def test_unassociated_when_no_fix_close_enough() -> None:
    # previous 1.3 s (> T_sync) and next 2.5 s (> 2 T_sync) away
    out, a = run([fix(0.0, 36.0), rtt(1.3), fix(3.8, 37.0)])
    assert out == []
    assert a.stats.unassociated[B] == 1
    assert a.stats.associated[B] == 0
    assert (a.stats.rtt[B], a.stats.ok[B]) == (1, 1)
    # no fix at all
    out, a = run([rtt(1.0), rtt(2.0, bssid=B2)])
    assert out == []
    assert a.stats.unassociated == {B: 1, B2: 1}


def test_fix_none_is_ignored() -> None:
    records = [
        fix(0.0, 36.0, -4.0, 100.0),
        fix(0.9, 10.0, 10.0, 0.0, kind="none"),  # would be the bracketing fix if used
        rtt(1.0),
        fix(1.05, 10.0, 10.0, 0.0, kind="none"),
        fix(2.0, 36.002, -4.002, 102.0),
        rtt(5.0),
        fix(5.1, 10.0, 10.0, 0.0, kind="none"),  # the only fix near 5.0 s
    ]
    out, a = run(records)
    assert len(out) == 1
    assert out[0].interpolated
    assert out[0].lat_deg == pytest.approx(36.001, abs=1e-12)  # halfway between 0 s and 2 s
    assert out[0].lon_deg == pytest.approx(-4.001, abs=1e-12)
    assert out[0].alt_m == pytest.approx(101.0, abs=1e-12)
    assert a.stats.unassociated[B] == 1  # the 5.0 s sample: 3 s after the last usable fix


def test_fix_without_fix_field_is_used() -> None:
    out, _ = run([fix(0.0, 36.0, kind=None), rtt(0.5)])
    assert len(out) == 1 and out[0].lat_deg == 36.0


def test_quality_gate() -> None:
    records = [
        fix(0.0, 36.0, acc=2.0),
        rtt(0.05, 11.0),  # interpolated with acc max(2, 14.99) = 14.99 < 15: kept
        fix(0.1, 36.1, acc=14.99),
        rtt(0.15, 12.0),  # interpolated with acc max(14.99, 15.0) = 15: dropped
        fix(0.2, 36.2, acc=15.0),
        rtt(0.25, 13.0),  # interpolated, acc max(15, 1) = 15: dropped
        fix(0.3, 36.3, acc=1.0),
        rtt(0.35, 14.0),  # interpolated, acc 1: kept
        fix(0.4, 36.4, acc=1.0),
        fix(5.0, 36.5, acc=40.0),
        rtt(5.5, 15.0),  # nearest fix only (acc 40): dropped
    ]
    out, a = run(records)
    assert [g.range_m for g in out] == [11.0, 14.0]
    assert [g.acc_m for g in out] == [14.99, 1.0]
    assert a.stats.gnss_quality[B] == 3
    assert a.stats.associated[B] == 2
    assert a.stats.unassociated[B] == 0
    out, a = run(records, AssociationConfig(max_acc_m=50.0))
    assert [g.range_m for g in out] == [11.0, 12.0, 13.0, 14.0, 15.0]


@pytest.mark.parametrize(
    ("b0", "raw", "expected"),
    [
        (0.0, 74.312, 74.312),
        (0.5, 10.0, 9.5),
        (0.5, 0.3, 0.0),  # d_raw - b0 < 0
        (0.0, -0.4, 0.0),  # a negative raw range at very short distance
        (0.0, 0.0, 0.0),
        (-0.3, 10.0, 10.3),
    ],
)
def test_range_offset(b0: float, raw: float, expected: float) -> None:
    out, _ = run([fix(0.0), rtt(0.5, raw)], AssociationConfig(range_offset_m=b0))
    assert len(out) == 1
    assert out[0].range_m == pytest.approx(expected, abs=1e-12)
    assert out[0].range_m >= 0.0


def test_non_ok_samples_are_counted_but_not_used() -> None:
    records = [
        fix(0.0),
        rtt(0.1, None, status="fail", rssi=None),
        rtt(0.2, None, status="no_response", rssi=None),
        rtt(0.3, 20.0, status="fail"),  # a range with a failure status is still a failure
        rtt(0.4, None, status="ok"),  # ok without a range is not usable
        rtt(0.5, 30.0, bssid=B2),
        fix(1.0),
    ]
    out, a = run(records)
    assert [(g.bssid, g.range_m) for g in out] == [(B2, 30.0)]
    assert a.stats.rtt == {B: 4, B2: 1}
    assert a.stats.ok == {B2: 1}
    assert a.stats.unassociated == {}
    assert a.stats.associated == {B2: 1}


def test_output_follows_input_time_order() -> None:
    rng = random.Random(7)
    records: list[GnssFix | RangeSample] = []
    for i in range(400):  # 40 s: fixes at 1 Hz with a 6 s outage, ranging at 10 Hz
        t = i * 0.1
        if i % 10 == 0 and not 150 <= i < 210:
            records.append(fix(t, 36.0 + i * 1e-5, -4.0, 100.0 + i * 0.1))
        records.append(rtt(t + 0.03, 20.0 + rng.random(), bssid=rng.choice([B, B2])))
    a = Associator()
    out: list[GeoRange] = []
    sizes = []
    for rec in records:
        got = a.push(rec)
        sizes.append(len(got))
        out += got
    out += a.flush()
    t_in = [r.t_ns for r in records if isinstance(r, RangeSample)]
    t_out = [g.t_ns for g in out]
    assert t_out == sorted(t_out)
    assert set(t_out) <= set(t_in)
    # the outage: fixes at 14 s and 21 s; samples later than 15.2 s and earlier than 19.8 s
    # have no fix within T_sync and are not bracketed within 2.4 s
    lost = [t for t in t_in if t not in set(t_out)]
    assert lost == [t for t in t_in if _ns(15.2) < t < _ns(19.8)]
    assert len(lost) == 46
    assert sum(a.stats.unassociated.values()) == 46
    assert sum(a.stats.associated.values()) == 400 - 46
    # the outage's samples are resolved by later samples' arrival, not only by fixes
    assert max(sizes) > 1


def test_expiry_resolves_waiting_samples_without_a_fix() -> None:
    a = Associator()
    a.push(fix(0.0, 36.0))
    assert a.push(rtt(0.5, 1.0)) == []
    assert a.push(rtt(2.9, 2.0)) == []  # 2.4 s later: the first is still waiting
    got = a.push(rtt(2.95, 3.0))  # 2.45 s later: the first can no longer be bracketed
    assert [(g.range_m, g.lat_deg, g.interpolated) for g in got] == [(1.0, 36.0, False)]
    assert a.flush() == []  # 2.9 s and 2.95 s: no fix within 1.2 s
    assert a.stats.unassociated[B] == 2


def test_flush_associates_trailing_sample_with_previous_fix() -> None:
    a = Associator()
    a.push(fix(100.0, 36.0, -4.0, 50.0, acc=0.8))
    a.push(rtt(100.5, 42.0))
    a.push(rtt(101.5, 43.0))  # 1.5 s after the last fix: too far
    out = a.flush()
    assert len(out) == 1
    g = out[0]
    assert (g.range_m, g.lat_deg, g.lon_deg, g.alt_m, g.acc_m) == (42.0, 36.0, -4.0, 50.0, 0.8)
    assert not g.interpolated
    assert a.stats.unassociated[B] == 1
    assert a.flush() == []  # nothing left


def test_fix_at_the_same_time_as_sample() -> None:
    out, _ = run([fix(1.0, 36.0), rtt(1.0), fix(1.1, 36.1)])
    assert len(out) == 1
    assert out[0].interpolated and out[0].lat_deg == 36.0


def test_push_fixes_equals_pushing_each_fix() -> None:
    """Runs of fixes (some with fix "none") between ranges: push_fixes gives the ranges
    and the latest fix that pushing the fixes one by one gives."""
    rnd = random.Random(4)
    for _ in range(200):
        recs, t = [], 0.0
        for _ in range(60):
            t += rnd.uniform(0.02, 0.6)
            if rnd.random() < 0.3:
                recs.append(rtt(t, rnd.uniform(10.0, 90.0)))
            else:
                recs.append(fix(t, 36.715 + 1e-5 * t, kind="none" if rnd.random() < 0.2 else "3d"))
        one, a1 = run(recs)
        a2, two, run_fixes = Associator(), [], []
        for r in recs:
            if isinstance(r, GnssFix):
                run_fixes.append(r)
                continue
            two += a2.push_fixes(run_fixes) + a2.push(r)
            run_fixes = []
        two += a2.push_fixes(run_fixes) + a2.flush()
        assert one == two and a1._last_fix == a2._last_fix and len(one) > 5
