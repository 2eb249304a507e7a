"""An imported flight replays to the estimate of the simulated log it was made from.

For each recorder format, the short simulated flight's records are written in that
format (tests/estimator/importers/writers.py), imported, and replayed in the modes
baseline, empirical-r and refined; every track must end with the same status, and
the estimates may differ only by what the format rounds away. The tolerance of each
case, on the horizontal position, the height and refined's 95 % radius:

- GnssLogger + CSV with elapsedRealtimeNanos: 0 (nothing is rounded: the same t_ns,
  doubles written in full, ranges in mm as simulated).
- ULog v1.13 and DataFlash: positions in 1e-7 degree steps (up to 5.6 mm of latitude),
  heights in mm (ULog) or cm (DataFlash), GNSS times moved onto the phone clock
  through a UTC offset known to about 1 ms (about 6 mm of flight at 6.5 m/s): 2 cm;
  DataFlash's HAcc in cm steps changes the anchors' weights: r95 within 5 cm.
- ULog v1.14, ROS 2 bags, SensorReadout: doubles, only the times move (ms and us
  steps): 1 cm.
- NMEA: 1e-7 minute positions, mm heights, ms times, acc from HDOP with four
  decimals, and no vertical accuracy (refined's vertical noise falls back to 1.7 x
  the horizontal): 5 cm.
"""

from __future__ import annotations

import shutil

import pytest

from estimator.importers import ImportOptions, import_flight
from estimator.logio import read_log
from tests.estimator.importers.flights import estimates, largest_differences
from tests.estimator.importers.writers import (
    NS,
    storage_file,
    utc_ms,
    write_android_csv,
    write_dataflash,
    write_gnsslogger,
    write_nmea,
    write_rosbag,
    write_sensorreadout,
    write_ulog,
)

OPTS = ImportOptions(agl_m=45.0, range_offset_m=0.0, agent="uav-1")


def _import(gnss, ranges, tmp_path, opts=OPTS):
    out = tmp_path / "imported.jsonl"
    report = import_flight(gnss, ranges, out, opts)
    return out, report


def _check(reference, out, tol_h, tol_z, tol_r95):
    dh, dz, dr = largest_differences(reference, estimates(out))
    assert dh <= tol_h, f"horizontal {dh:.3g} m"
    assert dz <= tol_z, f"vertical {dz:.3g} m"
    assert dr <= tol_r95, f"r95 {dr:.3g} m"
    return dh, dz, dr


def test_gnsslogger_and_csv_on_the_phone_clock_replay_exactly(flight, reference, tmp_path):
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, report = _import(gnss, rtt, tmp_path)
    j = report.to_json()
    assert j["time"]["clock"] == "phone" and j["time"]["alignment_uncertainty_s"] == 0.0
    log = read_log(out)
    # t_ns is the phone's clock itself: the very times of the simulated log
    assert {r.t_ns for r in log.rtt} == {r.t_ns for r in flight.rtt}
    assert log.header.agl_m == 45.0 and log.header.range_offset_m == 0.0
    assert log.header.agent == "uav-1" and log.header.start_utc.startswith("2025-06-12T10:12")
    assert j["ranges"]["written"] == len(flight.rtt) and j["ranges"]["outside_overlap"] == 0
    # every fix inside the ranges' span plus the one before and the one after it
    inside = [g for g in flight.gnss if flight.rtt[0].t_ns <= g.t_ns <= flight.rtt[-1].t_ns]
    assert j["gnss"]["written"] == len(inside) + 2
    assert j["gnss"]["written"] + j["gnss"]["outside_overlap"] == len(flight.gnss)
    _check(reference, out, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("variant", ["v1.13", "v1.14"])
def test_ulog(flight, reference, tmp_path, variant):
    gnss = write_ulog(tmp_path / "flight.ulg", flight, variant=variant)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=variant == "v1.13")
    out, report = _import(gnss, rtt, tmp_path)
    j = report.to_json()
    assert j["gnss"]["stream"] == ("vehicle_gps_position[0]" if variant == "v1.13"
                                   else "sensor_gps[0]")
    assert j["gnss"]["heights"] == {"ellipsoid": len(flight.gnss)}
    assert j["time"]["clock"] == "utc"
    if variant == "v1.14":  # no phone clock at all: t_ns is UTC
        assert j["time"]["offset_s"] == 0.0
        first = read_log(out).rtt[0]
        assert first.t_ns == utc_ms(flight.utc_ns(flight.rtt[0].t_ns)) * 1_000_000
        _check(reference, out, 0.01, 0.01, 0.01)
    else:
        _check(reference, out, 0.02, 0.02, 0.02)


def test_dataflash(flight, reference, tmp_path):
    gnss = write_dataflash(tmp_path / "00000042.BIN", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, report = _import(gnss, rtt, tmp_path)
    j = report.to_json()
    assert j["gnss"]["format"] == "dataflash"
    assert j["gnss"]["heights"] == {"undulation": len(flight.gnss)}  # Alt + GPA.Und
    assert j["gnss"]["other_records"] == {"GPS[1]": (len(flight.gnss) + 2) // 3}
    _check(reference, out, 0.02, 0.02, 0.05)


@pytest.mark.parametrize("layout", ["sqlite3-directory", "mcap-file-alone",
                                    "db3-file-alone"])
def test_rosbag2(flight, reference, tmp_path, layout):
    storage = "mcap" if layout.startswith("mcap") else "sqlite3"
    bag = write_rosbag(tmp_path / "bag", flight, storage=storage)
    if layout.endswith("alone"):  # the storage file without its metadata.yaml
        alone = tmp_path / "alone" / storage_file(bag).name
        alone.parent.mkdir()
        shutil.copy(storage_file(bag), alone)
        bag = alone
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, report = _import(bag, rtt, tmp_path)
    j = report.to_json()
    assert j["gnss"]["stream"] == "NavSatFix on /fix"
    assert j["gnss"]["other_records"] == {"/battery": (len(flight.gnss) + 9) // 10}
    _check(reference, out, 0.01, 0.01, 0.01)


def test_nmea(flight, reference, tmp_path):
    gnss = write_nmea(tmp_path / "gps.nmea", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, report = _import(gnss, rtt, tmp_path)
    j = report.to_json()
    assert j["gnss"]["heights"] == {"undulation": len(flight.gnss)}  # MSL + GGA's N
    assert j["gnss"]["other_records"] == {"GNGSA": len(flight.gnss)}
    assert all(g.vacc_m is None for g in read_log(out).gnss)
    _check(reference, out, 0.05, 0.05, 0.05)


def test_sensorreadout(flight, reference, tmp_path):
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    start = (flight.utc0_ns // NS - 3) * NS  # the recording started 3 s before take-off
    rtt = write_sensorreadout(tmp_path / "readout.csv", flight, start)
    out, report = _import(gnss, rtt, tmp_path)
    j = report.to_json()
    assert j["ranges"]["format"] == "sensorreadout"
    assert j["ranges"]["other_records"] == {"event 0": (len(flight.gnss) + 4) // 5}
    # the file's clock is its own (since the recording started): joined on UTC, which
    # the metadata line gives to the second
    assert j["time"]["clock"] == "utc"
    assert j["time"]["alignment_uncertainty_s"] >= 1.0
    _check(reference, out, 0.01, 0.01, 0.01)


def test_a_phone_that_restarted_between_the_files_is_joined_on_utc(flight, reference,
                                                                    tmp_path):
    """The GNSS file's elapsedRealtimeNanos is of the boot the simulation drew; the
    ranging file's of a later boot (the phone restarted: its clock began again, 2 h
    33 min later). Joining on the phone clock would shift every range by hours; the
    import must see the two boots and use UTC."""
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    shift = -(2 * 3600 + 33 * 60) * NS - 123_456_789
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed_shift_ns=shift)
    out, report = _import(gnss, rtt, tmp_path)
    t = report.to_json()["time"]
    assert t["clock"] == "utc"
    assert "different boots" in t["reason"] and "restarted" in t["reason"]
    assert abs(t["utc_offsets_s"]["ranges"] - t["utc_offsets_s"]["gnss"] - 9180.123) < 0.01
    # t_ns is the ranging phone's (new) clock; the fixes were moved onto it through UTC
    log = read_log(out)
    assert log.rtt[0].t_ns == flight.rtt[0].t_ns + shift
    _check(reference, out, 0.01, 0.01, 0.01)


def test_heights_above_sea_level_need_an_undulation(flight, tmp_path):
    """A ULog without ellipsoidal heights: MSL with a warning, or MSL + --geoid-offset."""
    gnss = write_ulog(tmp_path / "flight.ulg", flight, msl_only=True, undulation_m=50.125)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, report = _import(gnss, rtt, tmp_path)
    assert report.to_json()["gnss"]["heights"] == {"msl_as_ellipsoid": len(flight.gnss)}
    assert any("--geoid-offset" in w for w in report.warnings)
    by_t = {g.t_ns: g.alt_m for g in flight.gnss}
    first = read_log(out).gnss[0]
    sim_alt = min(by_t.items(), key=lambda kv: abs(kv[0] - first.t_ns))[1]
    assert first.alt_m == pytest.approx(sim_alt - 50.125, abs=1e-3)
    out2 = tmp_path / "with_n.jsonl"
    report2 = import_flight(gnss, rtt, out2, ImportOptions(geoid_offset_m=50.125))
    assert report2.warnings == []
    # a file with ellipsoidal heights does not use it, and says so
    full = write_ulog(tmp_path / "full.ulg", flight)
    report3 = import_flight(full, rtt, tmp_path / "o3.jsonl", ImportOptions(geoid_offset_m=50))
    assert report3.to_json()["gnss"]["heights"] == {"ellipsoid": len(flight.gnss)}
    assert any("--geoid-offset not used" in w for w in report3.warnings)
    assert report2.to_json()["gnss"]["heights"] == {"geoid_offset": len(flight.gnss)}
    assert read_log(out2).gnss[0].alt_m == pytest.approx(sim_alt, abs=1e-3)


def test_dataflash_without_undulation_takes_the_geoid_offset(flight, tmp_path):
    gnss = write_dataflash(tmp_path / "old.bin", flight, with_und=False)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out = tmp_path / "o.jsonl"
    report = import_flight(gnss, rtt, out, ImportOptions(geoid_offset_m=50.125))
    assert report.to_json()["gnss"]["heights"] == {"geoid_offset": len(flight.gnss)}
    g = read_log(out).gnss[5]
    src = min(flight.gnss, key=lambda f: abs(f.t_ns - g.t_ns))
    assert g.alt_m == pytest.approx(src.alt_m, abs=0.006)  # Alt in cm steps
