# ruff: noqa: N999 - the module is named after its command, `osa import` (a keyword)
"""``osa import --gnss FILE --ranges FILE -o LOG``: real flights in (docs/import.md).

A GNSS recorder file (GnssLogger, PX4 ULog, ArduPilot DataFlash, a ROS 2 bag, NMEA)
and a ranging file (Android RangingResult CSV, SensorReadout) become one flight log
that ``osa replay`` reads like any other. The work is
:func:`estimator.importers.import_flight`; this module checks the options and the
output first, prints what was read and written, and turns refusals into one line
and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import UTC, datetime

from envs.commands._args import finite_float, non_negative_float, positive_float
from envs.commands._outputs import OutputRefusedError, add_force_option, claim_output_file
from estimator.importers.joiner import GNSS_FORMATS, RANGES_FORMATS


def _utc_ns(text: str) -> int:
    """An ISO 8601 time (``2025-06-12T10:12:00Z``; no zone means UTC) in Unix ns."""
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an ISO 8601 time: {text!r}") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return round(dt.timestamp() * 1e6) * 1000


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="turn a real flight's GNSS and ranging files into a flight log",
        description="Write one flight log from a GNSS recorder file and a WiFi RTT ranging "
        "file, joined on one time axis (docs/import.md). The formats are recognised from "
        "the content unless named.",
    )
    p.add_argument("--gnss", required=True, metavar="FILE",
                   help="GNSS file: GnssLogger .txt, PX4 .ulg, ArduPilot .bin, ROS 2 bag "
                   "(directory, .db3 or .mcap) or NMEA text")
    p.add_argument("--ranges", required=True, metavar="FILE",
                   help="ranging file: Android RangingResult CSV or SensorReadout log")
    p.add_argument("-o", "--output", "--out", required=True, metavar="LOG",
                   help="flight log to write (.jsonl or .jsonl.gz)")
    p.add_argument("--agent", default="unknown", metavar="NAME",
                   help="the agent named in the log header (default: unknown)")
    p.add_argument("--agl", type=non_negative_float, default=None, metavar="M",
                   help="configured flight height above ground, header config.agl_m")
    p.add_argument("--range-offset", type=finite_float, default=None, metavar="M",
                   help="pre-flight range calibration offset b0, header config.range_offset_m")
    p.add_argument("--gnss-format", choices=GNSS_FORMATS, default=None, metavar="F",
                   help=f"the GNSS file's format: {', '.join(GNSS_FORMATS)} "
                   "(default: recognised)")
    p.add_argument("--ranges-format", choices=RANGES_FORMATS, default=None, metavar="F",
                   help=f"the ranging file's format: {', '.join(RANGES_FORMATS)} "
                   "(default: recognised)")
    p.add_argument("--topic", default=None, metavar="T",
                   help="the GNSS stream: a bag's NavSatFix topic, a ULog topic NAME or "
                   "NAME[ID], GPS[N] of a DataFlash log, a GnssLogger provider")
    p.add_argument("--geoid-offset", type=finite_float, default=None, metavar="M",
                   help="geoid undulation N (m) for heights above mean sea level when the "
                   "file gives none (ellipsoidal = MSL + N)")
    p.add_argument("--gnss-acc", type=positive_float, default=None, metavar="M",
                   help="horizontal accuracy (m) of fixes that carry none (default: such "
                   "fixes are skipped and counted)")
    p.add_argument("--ranges-start-utc", type=_utc_ns, default=None, metavar="TIME",
                   help="UTC time (ISO 8601) of a SensorReadout file's time zero, when its "
                   "metadata line lacks it or is wrong")
    p.add_argument("--json", action="store_true", help="print the counts as one JSON object")
    p.add_argument("--no-progress", action="store_true", help="no progress on stderr")
    add_force_option(p)
    p.set_defaults(func=run)


def _fail(message: object) -> int:
    print(f"osa import: {message}", file=sys.stderr)
    return 2


def _reasons(d: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in d.items())


def format_report(j: dict) -> str:
    """The readable report of :meth:`estimator.importers.ImportReport.to_json`."""
    lines = []
    for key, noun in (("gnss", "fixes"), ("ranges", "results")):
        s = j[key]
        written = f"{s['written']} written"
        if key == "ranges":
            written += f" ({s['ok']} ok, {s['failed']} failed)"
        lines.append(f"{key}: {s['file']} ({s['format']}, {s['stream']}): "
                     f"{s['records_read']} {noun} read, {written}, "
                     f"{s['outside_overlap']} outside the overlap")
        if s["skipped"]:
            lines.append(f"  skipped: {_reasons(s['skipped'])}")
        if s["other_records"]:
            other = list(s["other_records"].items())
            more = f", ... ({len(other) - 8} more)" if len(other) > 8 else ""
            lines.append(f"  other records (not used): {_reasons(dict(other[:8]))}{more}")
        if key == "gnss" and s["heights"]:
            lines.append(f"  heights: {_reasons(s['heights'])}")
    t = j["time"]
    lines.append(f"time: {t['clock']} clock: {t['reason']}")
    off = "unknown" if t["offset_s"] is None else (
        f"{t['offset_s']:.6f} s +- {t['offset_uncertainty_s'] * 1e3:.3f} ms")
    lines.append(f"  clock offset (UTC - t_ns): {off}; GNSS and ranges aligned within "
                 f"{t['alignment_uncertainty_s'] * 1e3:.3f} ms")
    span = (f"{t['overlap_start_utc']} to {t['overlap_end_utc']} "
            if t["overlap_start_utc"] else "no UTC: phone clock only, ")
    lines.append(f"  overlap: {span}({t['overlap_s'] / 60:.1f} min)")
    r = j["records"]
    lines.append(f"wrote {j['output']}: {r['gnss']} gnss, {r['rtt']} rtt ({r['rtt_ok']} ok), "
                 f"start_utc {j['start_utc'] or '-'}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from estimator.importers import ImportOptions, ImportRefused, import_flight

    out = args.output
    named = out.endswith(".jsonl") or out.endswith(".jsonl.gz")
    bad_name = f"{out}: the log must be named .jsonl or .jsonl.gz"
    if not named and not os.path.lexists(out):  # refused before a folder is created
        return _fail(bad_name)
    try:  # an existing file: an input, or one to keep, is said first
        claim_output_file(out, force=args.force, inputs=[args.gnss, args.ranges])
    except OutputRefusedError as exc:
        return _fail(exc)
    if not named:
        return _fail(bad_name)
    opts = ImportOptions(
        gnss_format=args.gnss_format, ranges_format=args.ranges_format, topic=args.topic,
        geoid_offset_m=args.geoid_offset, gnss_acc_m=args.gnss_acc,
        ranges_start_utc_ns=args.ranges_start_utc, agent=args.agent, agl_m=args.agl,
        range_offset_m=args.range_offset,
    )
    from envs.commands.run import StepProgress

    progress = StepProgress("osa import", 4, enabled=not args.no_progress)
    try:
        report = import_flight(args.gnss, args.ranges, out, opts, step=progress.step)
    except (ImportRefused, OSError) as exc:
        if progress.bar is not None:
            progress.bar.close()
        if isinstance(exc, ImportRefused):
            return _fail(exc)
        return _fail(f"cannot write {out}: {exc.strerror or exc}")
    progress.close()
    j = report.to_json()
    for w in j["warnings"]:
        print(f"osa import: warning: {w}", file=sys.stderr)
    if args.json:
        print(json.dumps(j, allow_nan=False))
    else:
        print(format_report(j))
    return 0
