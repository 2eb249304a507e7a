"""``osa upload FILE --connection URL``: upload a mission, read it back, compare.

Exit status 0 only when the vehicle holds exactly the mission in FILE (items, and
fence and rally points unless ``--no-fence``); 2 for an unreadable file or a bad
URL; 1 for any vehicle error (no heartbeat, timeout, NACK, read-back mismatch).
Errors are one line on stderr (docs/cli.md, docs/mavlink.md).
"""

from __future__ import annotations

import argparse
import sys

from envs.commands._args import non_negative_int, positive_float

EXIT_OK = 0
EXIT_VEHICLE = 1
EXIT_USAGE = 2


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "upload",
        help="upload a .plan/.waypoints mission to a MAVLink vehicle and verify it",
        description="Upload a mission (.plan or .waypoints) to a MAVLink vehicle, download it "
        "back and compare item by item. pymavlink URLs (udpout:127.0.0.1:14550, udpin:..., "
        "tcp:...) use pymavlink; MAVSDK URLs (udpin://..., udpout://..., tcp://..., "
        "serial://...) use MAVSDK.",
    )
    p.add_argument("file", metavar="FILE", help="mission file (.plan, .waypoints or .txt)")
    p.add_argument("--connection", "-c", metavar="URL", required=True,
                   help="vehicle connection, e.g. udpout:127.0.0.1:14550 or udpin://0.0.0.0:14540")
    p.add_argument("--timeout", metavar="S", type=positive_float, default=5.0,
                   help="seconds to wait for the vehicle's heartbeat (default 5)")
    p.add_argument("--message-timeout", metavar="S", type=positive_float, default=0.5,
                   help="seconds to wait for each answer during a transfer (default 0.5)")
    p.add_argument("--retries", metavar="N", type=non_negative_int, default=5,
                   help="resends of an unanswered message before giving up (default 5; "
                   "MAVSDK URLs use MAVSDK's own resend count)")
    p.add_argument("--no-fence", action="store_true",
                   help="upload the mission items only, not the geofence or rally points")
    p.add_argument("--autopilot", choices=("auto", "px4", "ardupilot"), default="auto",
                   help="mission numbering: 'auto' (default) from the vehicle's heartbeat "
                   "(ArduPilot: a home item in seq 0, the mission from seq 1; anything else: "
                   "the mission from seq 0); 'px4' or 'ardupilot' force it")
    p.set_defaults(func=run)
    return p


def _fail(status: int, message: str) -> int:
    print(f"osa upload: {' '.join(str(message).split())}", file=sys.stderr)
    return status


def run(args: argparse.Namespace) -> int:
    from planner.files import PLAN_SUFFIXES, MissionFileError, _suffix, read_mission
    from planner.mavlink import TransferConfig, upload_mission
    from planner.mavlink_wire import InvalidConnectionError, UploadError

    try:
        mission = read_mission(args.file)
    except MissionFileError as exc:
        return _fail(EXIT_USAGE, str(exc))
    config = TransferConfig(connect_timeout_s=args.timeout,
                            message_timeout_s=args.message_timeout, retries=args.retries,
                            autopilot=args.autopilot)
    try:
        # a .plan says what the fence and rally points are (empty: none), a WPL cannot
        report = upload_mission(mission, args.connection, config=config,
                                fence=not args.no_fence,
                                replace_fence=_suffix(args.file) in PLAN_SUFFIXES)
    except InvalidConnectionError as exc:
        return _fail(EXIT_USAGE, str(exc))
    except UploadError as exc:
        return _fail(EXIT_VEHICLE, f"{type(exc).__name__}: {exc}")
    numbering = ("ArduPilot numbering, home item in seq 0" if report.autopilot == "ardupilot"
                 else "mission from seq 0")
    print(f"uploaded and verified {args.file} on vehicle {report.vehicle[0]}/{report.vehicle[1]} "
          f"via {report.backend} ({numbering}): mission items {report.items}, fence items "
          f"{report.fence_items}, rally points {report.rally_items}, {report.elapsed_s:.2f} s")
    return EXIT_OK
