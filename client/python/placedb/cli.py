"""placedb-py: recordings into a placedb map from the command line (installed by pip).

    placedb-py ingest-bag MAP run.bag --topic /camera/image_raw \\
        [--depth-topic /camera/depth/image_raw] [--camera-info-topic /camera/camera_info]
    placedb-py ingest-tum MAP rgbd_dataset_freiburg1_xyz [--intrinsics 517.3,516.5,318.6,255.3]

Capture times come from the recording (header stamps, TUM timestamps), poses from a TUM
folder's groundtruth.txt. Connection flags as the C++ CLI's (docs/cli.md): ``--address``
(env PLACEDB_ADDRESS), ``--token`` (env PLACEDB_TOKEN), ``--tls --ca-cert --cert --key``.
Exit codes as the C++ CLI's: 0 success, 1 an RPC failed or a frame was refused with an error,
2 usage or unreadable input (a missing topic, a ROS 2 bag, no python3-rosbag).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from typing import Iterator, List, Optional

import placedb
from placedb.recordings import Recording


def _address(value: str) -> str:
    # The C++ CLI's convention: a bare port means localhost.
    return f"localhost:{value}" if value.isdigit() else value


def _intrinsics(value: str) -> tuple:
    parts = value.split(",")
    try:
        if len(parts) != 4:
            raise ValueError
        return tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r}: expected fx,fy,cx,cy") from None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="placedb-py", description="Ingest recordings (ROS 1 bags, TUM RGB-D folders)."
    )
    parser.add_argument("--version", action="version", version=f"placedb {placedb.__version__}")
    connection = argparse.ArgumentParser(add_help=False)
    group = connection.add_argument_group("connection (as the placedb CLI's)")
    group.add_argument(
        "--address",
        default=os.environ.get("PLACEDB_ADDRESS", "localhost:50051"),
        type=_address,
        help="server host:port, or a port (default: env PLACEDB_ADDRESS, else localhost:50051)",
    )
    group.add_argument("--token", default=os.environ.get("PLACEDB_TOKEN"), help="bearer token")
    group.add_argument("--tls", action="store_true", help="TLS (system roots unless --ca-cert)")
    group.add_argument("--ca-cert", help="CA bundle of the server's certificate (PEM)")
    group.add_argument("--cert", help="client certificate for mutual TLS (PEM)")
    group.add_argument("--key", help="client key for mutual TLS (PEM)")
    ingest = argparse.ArgumentParser(add_help=False)
    group = ingest.add_argument_group("ingest")
    group.add_argument("--agent", default="recording", help="agent id of the frames")
    group.add_argument("--create", action="store_true", help="create the map when it is absent")
    group.add_argument("--in-flight", type=int, default=8, help="frames sent and unanswered")
    group.add_argument("--limit", type=int, help="the first LIMIT frames only")
    group.add_argument(
        "--max-offset",
        type=float,
        default=0.02,
        help="seconds between a frame and the depth (TUM: also pose) paired with it (0.02)",
    )
    group.add_argument("--quiet", action="store_true", help="no progress line")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    bag = commands.add_parser(
        "ingest-bag",
        parents=[ingest, connection],
        help="a ROS 1 bag's image topic (header stamps as capture times)",
        description="Ingest a ROS 1 bag's image topic (Debian's python3-rosbag reads it); "
        "each frame's capture time is its header stamp.",
    )
    bag.add_argument("map")
    bag.add_argument("bag", help="a ROS 1 .bag file")
    bag.add_argument("--topic", required=True, help="sensor_msgs/Image or CompressedImage")
    bag.add_argument("--depth-topic", help="registered depth: 16UC1 (mm) or 32FC1 (m) images")
    bag.add_argument("--camera-info-topic", help="sensor_msgs/CameraInfo: the depth's intrinsics")

    tum = commands.add_parser(
        "ingest-tum",
        parents=[ingest, connection],
        help="a TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt)",
        description="Ingest a TUM RGB-D folder: rgb.txt's timestamps as capture times, depth "
        "from depth.txt, poses from groundtruth.txt (when present).",
    )
    tum.add_argument("map")
    tum.add_argument("folder")
    tum.add_argument("--no-depth", action="store_true", help="ignore depth.txt")
    tum.add_argument("--no-poses", action="store_true", help="ignore groundtruth.txt")
    tum.add_argument(
        "--depth-scale",
        type=float,
        default=placedb.recordings.TUM_DEPTH_SCALE,
        help="metres per depth unit (TUM: 1/5000)",
    )
    tum.add_argument(
        "--intrinsics", type=_intrinsics, help="fx,fy,cx,cy of the colour camera, sent with depth"
    )
    return parser


def _client(args: argparse.Namespace) -> placedb.Client:
    tls = None
    if args.tls or args.ca_cert or args.cert or args.key:
        tls = placedb.TLS(ca_cert=args.ca_cert, cert=args.cert, key=args.key)
    return placedb.Client(args.address, token=args.token, tls=tls)


class _UnreadableFrame(Exception):
    """A frame of the recording could not be read (local input, exit code 2)."""


def _limited(recording: Recording, limit: Optional[int]) -> Iterator[placedb.Frame]:
    """The recording's first ``limit`` frames (no more are read: the stats count what is sent)."""
    try:
        yield from itertools.islice(recording, limit)
    except placedb.Error as e:
        raise _UnreadableFrame(str(e)) from None


def _time(ns: Optional[int]) -> str:
    if ns is None:
        return "-"
    seconds, rest = divmod(ns, 1_000_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{rest // 1_000_000:03d}Z"


def _ingest(args: argparse.Namespace, recording: Recording) -> int:
    total = len(recording) if args.limit is None else min(args.limit, len(recording))
    stored = invalid = refused = 0
    started = time.monotonic()
    with _client(args) as client:
        if args.create:
            try:
                client.get_map(args.map)
            except placedb.NotFound:
                client.create_map(args.map)
                print(f"created map {args.map}", file=sys.stderr)
        results = client.ingest(
            args.map,
            _limited(recording, args.limit),
            agent_id=args.agent,
            max_in_flight=args.in_flight,
        )
        for result in results:
            if result.error is not None:
                refused += 1
                print(f"\nframe {result.index}: {result.error}", file=sys.stderr)
            elif result.stored:
                stored += 1
            else:
                invalid += 1
            if not args.quiet:
                done = result.index + 1
                rate = done / max(time.monotonic() - started, 1e-9)
                print(
                    f"\r{done}/{total} frames  {stored} stored  {invalid} invalid  "
                    f"{refused} refused  {rate:.1f} frames/s",
                    end="",
                    flush=True,
                    file=sys.stderr,
                )
        if not args.quiet:
            print(file=sys.stderr)
        stats = recording.stats
        print(
            f"{recording.source}: {stats.frames} frames into map {args.map} (agent {args.agent}): "
            f"{stored} stored, {invalid} not valid places, {refused} refused; captured "
            f"{_time(stats.first_ns)} .. {_time(stats.last_ns)}"
        )
        details = []
        if stats.depth_paired or stats.depth_missing:
            details.append(
                f"depth: {stats.depth_paired} paired, {stats.depth_missing} without "
                f"(none within {args.max_offset} s)"
            )
        if stats.poses or stats.poses_missing:
            details.append(f"poses: {stats.poses}, {stats.poses_missing} outside the ground truth")
        if stats.receive_time_stamps:
            details.append(f"{stats.receive_time_stamps} header stamps of 0: bag receive times")
        for line in details:
            print(f"  {line}")
    return 0 if refused == 0 else 1


def main(argv: Optional[List[str]] = None) -> int:
    args = _parser().parse_args(argv)
    if args.limit is not None and args.limit < 1:
        print("placedb-py: --limit must be >= 1", file=sys.stderr)
        return 2
    if (args.cert is None) != (args.key is None):
        print("placedb-py: --cert and --key go together", file=sys.stderr)
        return 2
    try:
        if args.command == "ingest-bag":
            recording = placedb.read_bag(
                args.bag,
                args.topic,
                depth_topic=args.depth_topic,
                camera_info_topic=args.camera_info_topic,
                max_offset=args.max_offset,
            )
        else:
            recording = placedb.read_tum(
                args.folder,
                depth=False if args.no_depth else None,
                poses=False if args.no_poses else None,
                max_offset=args.max_offset,
                depth_scale=args.depth_scale,
                intrinsics=args.intrinsics,
            )
    except (placedb.InvalidArgument, placedb.FailedPrecondition) as e:
        print(f"placedb-py: {e}", file=sys.stderr)
        return 2
    end_line = "" if args.quiet else "\n"  # ends an interrupted progress line
    try:
        return _ingest(args, recording)
    except _UnreadableFrame as e:
        print(f"{end_line}placedb-py: {e}", file=sys.stderr)
        return 2
    except placedb.Error as e:
        hint = ""
        if isinstance(e, placedb.Unavailable):
            hint = f" (is placedb-server running at {args.address}?)"
        elif isinstance(e, placedb.NotFound) and not args.create:
            hint = " (--create creates the map)"
        print(f"{end_line}placedb-py: {e}{hint}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{end_line}placedb-py: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
