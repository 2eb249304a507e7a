"""``osa replay LOG [LOG ...]``: the estimator over flight logs (docs/cli.md).

A log named twice is refused before anything is read (fusing a log with itself would
count every range twice and shrink the covariance by sqrt 2). Every log is opened
once and read in one pass (a pipe, a fifo or ``-``, standard input, loses nothing);
before anything is estimated each one is checked as it is read
(:func:`estimator.replay.replay_logs`): a file without a single valid record is not a
flight log (exit 2, one line naming it). Two different files whose headers name the
same agent are fused as given, with a warning: they may be two flights of one drone,
or a copy of one flight.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from envs.commands._args import float_in
from envs.commands._outputs import OutputRefusedError, add_force_option, claim_output_dir
from estimator.logio import AGL_MAX_M, AGL_MIN_M, RANGE_OFFSET_MAX_M


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run the estimator over flight logs",
        description="Run the estimator over one or more flight logs (several logs are fused), "
        "one track per responder (BSSID).",
    )
    p.add_argument("logs", nargs="+", metavar="LOG",
                   help="flight log (.jsonl or .jsonl.gz; - reads standard input)")
    p.add_argument(
        "--mode",
        default="baseline",
        help="baseline, nlos, empirical-r, ukf, ema, adaptive-r, all (the paper's six), "
        "robust or refined (ours), best (the recommended mode: refined), or a list joined "
        "by ',' or '+', e.g. all+refined (default: baseline)",
    )
    p.add_argument("--agl", type=float_in(AGL_MIN_M, AGL_MAX_M), default=None,
                   metavar="M", help=f"configured flight height above ground (m, in "
                   f"[{AGL_MIN_M:g}, {AGL_MAX_M:g}]); default: header, else 45")
    p.add_argument("--range-offset", type=float_in(-RANGE_OFFSET_MAX_M, RANGE_OFFSET_MAX_M),
                   default=None, metavar="M", help="pre-flight range calibration offset b0 "
                   f"(m, |b0| <= {RANGE_OFFSET_MAX_M:g}); default: header, else 0")
    p.add_argument("--projection", choices=("tangent", "wgs84"), default="tangent",
                   help="ENU frame: the paper's tangent plane (eq. 1, default) or exact WGS84")
    p.add_argument("--json", action="store_true", help="print the JSON report only")
    p.add_argument("--quiet", action="store_true", help="do not print log warnings")
    p.add_argument("--figures", default=None, metavar="DIR",
                   help="also draw trajectory.png and convergence.png (as osa run does) "
                   "into the folder DIR")
    add_force_option(p)
    p.set_defaults(func=run)


def _same_file(a: str, b: str) -> bool:
    if a == "-" or b == "-":
        return a == b
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def check_logs(paths: list[str]) -> None:
    """Refuse (``LogError``, one line naming the file) a log given twice, before any
    is opened (a second open of a pipe would find it empty)."""
    from estimator.logio import LogError, display_name

    for i, path in enumerate(paths):
        for earlier in paths[:i]:
            if _same_file(path, earlier):
                raise LogError(f"{display_name(path)}: given twice (a log fused with itself "
                               "counts every range twice)")


def run(args: argparse.Namespace) -> int:
    from envs.commands._outputs import json_text
    from estimator.logio import LogError
    from estimator.replay import ReplayOptions, format_table, parse_modes, replay_logs

    try:
        modes = parse_modes(args.mode)
    except ValueError as exc:
        print(f"osa replay: {exc}", file=sys.stderr)
        return 2
    figures = None
    if args.figures is not None:
        # a missing file or a folder is said by the reader, as without --figures
        streams = [p for p in args.logs if p == "-" or (os.path.exists(p)
                                                          and not os.path.isdir(p)
                                                          and not os.path.isfile(p))]
        if streams:  # the figures read the logs again: a pipe would be empty then
            print(f"osa replay: --figures reads the logs a second time: {streams[0]} is "
                  "not a regular file (save it to a file first)", file=sys.stderr)
            return 2
        try:
            figures = claim_output_dir(args.figures, command="replay", force=args.force,
                                       inputs=args.logs, quiet=args.json)
        except OutputRefusedError as exc:
            print(f"osa replay: {exc}", file=sys.stderr)
            return 2
    opts = ReplayOptions(
        modes=modes,
        agl_m=args.agl,
        range_offset_m=args.range_offset,
        projection=args.projection,
        # TWM is accumulated online: memory stays bounded on long logs; the convergence
        # figure needs each track's published estimates
        keep_history=figures is not None,
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            check_logs(args.logs)
            report = replay_logs(args.logs, opts)
        except LogError as exc:
            print(f"osa replay: {exc}", file=sys.stderr)
            return 2
    if not args.quiet:
        seen: set[str] = set()
        for w in caught:
            if issubclass(w.category, ResourceWarning):
                continue  # the interpreter's housekeeping, not the user's
            text = str(w.message)
            if text not in seen:
                seen.add(text)
                print(f"osa replay: warning: {text}", file=sys.stderr)
    if figures is not None:
        from envs.plots import plot_convergence, plot_trajectory

        title = ", ".join(os.path.basename(p) for p in args.logs)
        drawn = [plot_trajectory(report, args.logs, figures / "trajectory.png", title=title),
                 plot_convergence(report, figures / "convergence.png")]
    if args.json:
        print(json_text(report.to_json()))
    else:
        print(format_table(report))
        if figures is not None:
            print(f"\nwrote {', '.join(str(p) for p in drawn)}")
    return 0
