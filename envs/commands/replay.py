"""``osa replay LOG [LOG ...]``: the estimator over flight logs (shared/spec/cli.md)."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

from envs.commands._args import finite_float, non_negative_float


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run the estimator over flight logs",
        description="Run the estimator over one or more flight logs (several logs are fused), "
        "one track per responder (BSSID).",
    )
    p.add_argument("logs", nargs="+", metavar="LOG", help="flight log (.jsonl or .jsonl.gz)")
    p.add_argument(
        "--mode",
        default="baseline",
        help="baseline, nlos, empirical-r, ukf, ema, adaptive-r, all (the paper's six), "
        "robust (ours), or a comma-separated list (default: baseline)",
    )
    p.add_argument("--agl", type=non_negative_float, default=None, metavar="M",
                   help="configured flight height above ground (m); default: header, else 45")
    p.add_argument("--range-offset", type=finite_float, default=None, metavar="M",
                   help="pre-flight range calibration offset b0 (m); default: header, else 0")
    p.add_argument("--projection", choices=("tangent", "wgs84"), default="tangent",
                   help="ENU frame: the paper's tangent plane (eq. 1, default) or exact WGS84")
    p.add_argument("--json", action="store_true", help="print the JSON report only")
    p.add_argument("--quiet", action="store_true", help="do not print log warnings")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from estimator.logio import LogError
    from estimator.replay import ReplayOptions, format_table, parse_modes, replay_logs

    try:
        modes = parse_modes(args.mode)
    except ValueError as exc:
        print(f"osa replay: {exc}", file=sys.stderr)
        return 2
    opts = ReplayOptions(
        modes=modes,
        agl_m=args.agl,
        range_offset_m=args.range_offset,
        projection=args.projection,
        keep_history=False,  # TWM is accumulated online: memory stays bounded on long logs
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            report = replay_logs(args.logs, opts)
        except LogError as exc:
            print(f"osa replay: {exc}", file=sys.stderr)
            return 2
    if not args.quiet:
        for w in caught:
            print(f"osa replay: warning: {w.message}", file=sys.stderr)
    if args.json:
        print(json.dumps(report.to_json(), allow_nan=False))
    else:
        print(format_table(report))
    return 0
