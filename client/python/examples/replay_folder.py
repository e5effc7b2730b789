#!/usr/bin/env python3
"""Replays a folder of images into a placedb map as one agent, with progress.

    PYTHONPATH=build/client/python python3 client/python/examples/replay_folder.py \
        /work/shared/data/rtabmap-loop --map loop --create --agent robot-1

Frames are sent as their files' bytes in natural order (2.jpg before 10.jpg); each frame's
sequence is its position in that order, which query_and_draw.py uses to find a match's file.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path
from typing import List

import placedb

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def natural_key(path: Path) -> List[object]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def image_files(folder: Path) -> List[Path]:
    """The folder's JPEG and PNG files in natural order."""
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=natural_key)


def client_from(args: argparse.Namespace) -> placedb.Client:
    tls = None
    if args.tls or args.ca_cert or args.cert:
        tls = placedb.TLS(ca_cert=args.ca_cert, cert=args.cert, key=args.key)
    return placedb.Client(args.target, token=args.token, tls=tls)


def add_connection_flags(parser: argparse.ArgumentParser) -> None:
    """The CLI's connection flags: --target --token --tls --ca-cert --cert --key."""
    parser.add_argument("--target", default="127.0.0.1:50051", help="server host:port")
    parser.add_argument("--token", help="bearer token (placedb-server tokens add)")
    parser.add_argument("--tls", action="store_true", help="TLS with the system roots")
    parser.add_argument("--ca-cert", help="CA bundle of the server's certificate (PEM)")
    parser.add_argument("--cert", help="client certificate for mutual TLS (PEM)")
    parser.add_argument("--key", help="client key for mutual TLS (PEM)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a folder of JPEG / PNG frames")
    parser.add_argument("--map", required=True, help="the map to ingest into")
    parser.add_argument("--create", action="store_true", help="create the map first")
    parser.add_argument("--agent", default="replay", help="agent id of the frames")
    parser.add_argument("--fps", type=float, default=10.0, help="timestamps: frames per second")
    parser.add_argument("--in-flight", type=int, default=8, help="frames sent and unanswered")
    parser.add_argument("--limit", type=int, help="the first LIMIT frames only")
    add_connection_flags(parser)
    args = parser.parse_args()

    files = image_files(args.folder)[: args.limit]
    if not files:
        print(f"no JPEG or PNG files in {args.folder}", file=sys.stderr)
        return 1
    start_ns = time.time_ns()
    frames = (
        placedb.Frame(image=path, timestamp_ns=start_ns + int(i * 1e9 / args.fps))
        for i, path in enumerate(files)
    )
    stored = invalid = refused = 0
    started = time.monotonic()
    try:
        with client_from(args) as client:
            if args.create:
                client.create_map(args.map)
            for result in client.ingest(
                args.map, frames, agent_id=args.agent, max_in_flight=args.in_flight
            ):
                if result.error is not None:
                    refused += 1
                    print(f"\n{files[result.index].name}: {result.error}", file=sys.stderr)
                elif result.stored:
                    stored += 1
                else:
                    invalid += 1
                done = result.index + 1
                rate = done / max(time.monotonic() - started, 1e-9)
                print(
                    f"\r{done}/{len(files)} frames  {stored} stored  {invalid} invalid  "
                    f"{refused} refused  {rate:.1f} frames/s",
                    end="",
                    flush=True,
                )
            print()
            print(f"map {args.map}: {client.get_map(args.map).places} places")
    except placedb.Error as e:
        print(f"\nreplay_folder: {e}", file=sys.stderr)
        return 1
    return 0 if refused == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
