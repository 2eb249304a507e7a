"""Write one simulated flight in every recorder format ``osa import`` reads, and import
each pair (docs/import.md shows the files and the reports this makes).

The flight is ``three-aps`` cut to 6 minutes (seed 0). Its GNSS fixes are written as a
GnssLogger file, a PX4 ULog (v1.13 and v1.14 layouts), an ArduPilot DataFlash log, ROS 2
bags (sqlite3 and MCAP) and NMEA; its ranging results as an Android RangingResult CSV and
a SensorReadout log (the writers are the tests', tests/estimator/importers/writers.py).
Then ``osa import`` joins each GNSS file with the CSV (GnssLogger also with the
SensorReadout file) and prints one summary line per import. Run from the repository:

    python examples/import_formats.py --out import-examples
    python examples/import_formats.py --out import-examples --files-only   # no imports
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from envs.cli import main as osa  # noqa: E402
from tests.estimator.importers import writers as W  # noqa: E402, N812
from tests.estimator.importers.flights import simulate_short  # noqa: E402


def write_all(out: Path) -> dict[str, tuple[Path, Path]]:
    fl = simulate_short(out / "simulated.jsonl")
    csv = W.write_android_csv(out / "rtt.csv", fl)
    gl = W.write_gnsslogger(out / "gnss_log.txt", fl)
    start = (fl.utc0_ns // W.NS - 2) * W.NS  # the recording started 2 s before take-off
    return {
        "gnsslogger": (gl, csv),
        "ulog": (W.write_ulog(out / "flight.ulg", fl), csv),
        "ulog-v1.14": (W.write_ulog(out / "flight_v114.ulg", fl, variant="v1.14"), csv),
        "dataflash": (W.write_dataflash(out / "00000001.BIN", fl), csv),
        "rosbag2-sqlite3": (W.write_rosbag(out / "bag_sqlite3", fl), csv),
        "rosbag2-mcap": (W.write_rosbag(out / "bag_mcap", fl, storage="mcap"), csv),
        "nmea": (W.write_nmea(out / "gps.nmea", fl), csv),
        "sensorreadout": (gl, W.write_sensorreadout(out / "readout.csv", fl, start)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="import-examples", help="folder to write (new)")
    ap.add_argument("--files-only", action="store_true",
                    help="write the recorder files, import nothing")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=False)
    pairs = write_all(out)
    if a.files_only:
        return
    for name, (gnss, ranges) in pairs.items():
        log = out / f"imported_{name}.jsonl"
        report = out / f"imported_{name}.json"
        import contextlib
        import io

        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            code = osa(["import", "--gnss", str(gnss), "--ranges", str(ranges), "-o", str(log),
                        "--agl", "45", "--agent", "uav-1", "--json", "--no-progress"])
        if code != 0:
            raise SystemExit(code)
        report.write_text(buf.getvalue())
        j = json.loads(buf.getvalue())
        t = j["time"]
        print(f"{name:16s} {j['records']['gnss']:5d} gnss {j['records']['rtt']:5d} rtt  "
              f"clock {t['clock']:5s} aligned within {t['alignment_uncertainty_s'] * 1e3:.3f} ms"
              f"  -> {log}")


if __name__ == "__main__":
    main()
