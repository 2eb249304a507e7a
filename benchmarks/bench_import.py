"""``osa import``: time per format on a 30-minute flight, memory on a day-long ULog, and
how far the imported flight's estimate is from the simulated log it came from.

1. A ~30-minute flight is simulated (``paper-ap1f`` with three of its circles flown a
   second time; 10 Hz GNSS) and written in every recorder format by the tests' writers
   (tests/estimator/importers/writers.py). Each is imported ``--repeats`` times in this
   process (the medians of wall and CPU seconds are reported; the interpreter's start
   and the first import of pyulog, pymavlink and rosbags are not counted; on a shared
   machine the CPU time is the steadier figure) and replayed in the paper's six
   modes and refined: the largest horizontal difference to the original's estimates
   (m), for baseline and EMA (whose gate decisions depend on the path: a millimetre
   can flip one, and the filter then takes another path) and for the other modes.
2. A day-long PX4 log (24 h; ``vehicle_gps_position`` at 5 Hz and ``sensor_accel`` at
   ``--accel-hz``, the bulk of the file) is imported in a fresh process with a small
   ranging file spanning the day; its peak resident memory (Linux VmHWM) is compared
   with a process that only loads the same modules, the file's size and the size of
   the GNSS topic pyulog keeps.

    python benchmarks/bench_import.py --repeats 5 --accel-hz 50
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimator.importers import ImportOptions, import_flight  # noqa: E402

MODES = ("baseline", "nlos", "empirical-r", "ukf", "ema", "adaptive-r", "refined")
PATH_DEPENDENT = ("baseline", "ema")


def thirty_minutes(path: Path):
    import sim
    from tests.estimator.importers import writers as W  # noqa: N812

    sc = sim.load_scenario("paper-ap1f")
    f = sc.flight
    sc = dataclasses.replace(sc, name="paper-ap1f-30min",
                             flight=dataclasses.replace(f, circles=f.circles + f.circles[:3]))
    result = sim.simulate(sc, 0, path)
    print(result.summary(), flush=True)
    return W.flight_from_log(path)


def write_all(d: Path, fl) -> dict[str, tuple[Path, Path]]:
    from tests.estimator.importers import writers as W  # noqa: N812

    csv = W.write_android_csv(d / "rtt.csv", fl)
    csv_utc = W.write_android_csv(d / "rtt_utc.csv", fl, elapsed=False)
    sr = W.write_sensorreadout(d / "readout.csv", fl, (fl.utc0_ns // W.NS - 2) * W.NS)
    gl = W.write_gnsslogger(d / "gnss_log.txt", fl)
    return {
        "gnsslogger + android-csv": (gl, csv),
        "ulog v1.13 + android-csv": (W.write_ulog(d / "a.ulg", fl), csv),
        "ulog v1.14 + android-csv (UTC)": (W.write_ulog(d / "b.ulg", fl, variant="v1.14"),
                                           csv_utc),
        "dataflash + android-csv": (W.write_dataflash(d / "a.bin", fl), csv),
        "rosbag2 sqlite3 + android-csv": (W.write_rosbag(d / "bag3", fl), csv),
        "rosbag2 mcap + android-csv": (W.write_rosbag(d / "bagm", fl, storage="mcap"), csv),
        "nmea + android-csv": (W.write_nmea(d / "a.nmea", fl), csv),
        "gnsslogger + sensorreadout": (gl, sr),
    }


def time_formats(d: Path, repeats: int) -> None:
    import os

    from tests.estimator.importers.flights import estimates, largest_differences

    src = d / "sim.jsonl"
    fl = thirty_minutes(src)
    files = write_all(d, fl)
    ref = estimates(src, MODES)
    opts = ImportOptions(agl_m=45.0, range_offset_m=0.0)
    print(f"\n{'format':34s} {'wall s':>7s} {'cpu s':>6s} {'fixes':>6s} {'ranges':>6s}"
          f" {'dH m':>9s} {'dH b/ema':>9s} {'dr95 m':>9s}")
    for name, (g, r) in files.items():
        out = d / "out.jsonl"
        times, cpu = [], []
        for _ in range(repeats + 1):  # the first run loads the format's library
            out.unlink(missing_ok=True)
            t0, c0 = time.perf_counter(), time.process_time()
            rep = import_flight(g, r, out, opts)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        j = rep.to_json()
        got = estimates(out, MODES)
        steady = {k: v for k, v in ref.items() if k[1] not in PATH_DEPENDENT}
        path = {k: v for k, v in ref.items() if k[1] in PATH_DEPENDENT}
        dh, _, dr = largest_differences(steady, {k: got[k] for k in steady})
        dhp, _, _ = largest_differences(path, {k: got[k] for k in path})
        print(f"{name:34s} {statistics.median(times[1:]):7.3f} "
              f"{statistics.median(cpu[1:]):6.3f} "
              f"{j['records']['gnss']:6d} {j['records']['rtt']:6d} {dh:9.2e} {dhp:9.2e} "
              f"{dr:9.2e}", flush=True)
    print(f"medians of {repeats} imports (after one to load the libraries); load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


def _measure(args: list[str]) -> dict:
    out = subprocess.run([sys.executable, __file__, *args], check=True, capture_output=True,
                         text=True, cwd=ROOT).stdout
    return json.loads(out.strip().splitlines()[-1])


def day_memory(d: Path, accel_hz: float, hours: float) -> None:
    from tests.estimator.importers import writers as W  # noqa: N812

    ulg = d / "day.ulg"
    t0 = time.perf_counter()
    sizes = W.write_day_ulog(ulg, hours=hours, accel_hz=accel_hz)
    print(f"\nday-long ULog: {hours:g} h, {sizes['gnss']} GNSS + {sizes['accel']} accel "
          f"messages, {sizes['bytes'] / 1e6:.0f} MB (written in "
          f"{time.perf_counter() - t0:.0f} s)", flush=True)
    # a ranging file spanning the day: one failed request every 10 s
    rtt = d / "day_rtt.csv"
    with open(rtt, "w") as fh:
        fh.write("utc_ms,bssid,status,distance_mm,distance_std_dev_mm,rssi,num_attempted,"
                 "num_successful\n")
        utc0_ms = 1_749_723_120_000
        for k in range(1, round(hours * 360)):
            fh.write(f"{utc0_ms + k * 10_000},a4:77:33:0f:1e:02,fail,,,,8,0\n")
    base = _measure(["--child-baseline"])
    run = _measure(["--child-import", str(ulg), str(rtt), str(d / "day.jsonl")])
    topic = sizes["gnss"] * W.logged_dtype(W.VEHICLE_GPS_POSITION_V113).itemsize
    print(f"peak RSS: {run['maxrss_mb']:.0f} MB importing (modules alone "
          f"{base['maxrss_mb']:.0f} MB: +{run['maxrss_mb'] - base['maxrss_mb']:.0f} MB); "
          f"file {sizes['bytes'] / 1e6:.0f} MB, GNSS topic {topic / 1e6:.0f} MB; "
          f"{run['seconds']:.0f} s, {run['gnss']} fixes written")


def reset_peak_rss() -> None:
    """Linux: start the peak-memory count afresh (a child's ``ru_maxrss`` begins at the
    forking parent's peak, across ``exec``; VmHWM is reset here to be sure)."""
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB): Linux's VmHWM, else ``ru_maxrss``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1e3
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def _child_baseline() -> None:
    reset_peak_rss()
    import pyulog  # noqa: F401

    from estimator.importers import ulog  # noqa: F401

    print(json.dumps({"maxrss_mb": peak_rss_mb()}))


def _child_import(ulg: str, rtt: str, out: str) -> None:
    reset_peak_rss()
    import pyulog  # noqa: F401

    from estimator.importers import ulog  # noqa: F401

    t0 = time.perf_counter()
    rep = import_flight(Path(ulg), Path(rtt), Path(out), ImportOptions())
    print(json.dumps({"maxrss_mb": peak_rss_mb(), "seconds": time.perf_counter() - t0,
                      "gnss": rep.to_json()["records"]["gnss"]}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--accel-hz", type=float, default=50.0)
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--skip-day", action="store_true", help="no day-long ULog")
    ap.add_argument("--skip-formats", action="store_true", help="only the day-long ULog")
    ap.add_argument("--child-baseline", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-import", nargs=3, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child_baseline:
        return _child_baseline()
    if a.child_import:
        return _child_import(*a.child_import)
    d = Path(tempfile.mkdtemp(prefix="osa-bench-import-"))
    try:
        if not a.skip_formats:
            time_formats(d, a.repeats)
        if not a.skip_day:
            day_memory(d, a.accel_hz, a.hours)
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return None


if __name__ == "__main__":
    main()
