#!/usr/bin/env python3
"""Backs a map up off the server: snapshot, download with a progress bar, optional restore.

    PYTHONPATH=build/client/python python3 client/python/examples/backup_map.py loop loop.pdbsnap
    PYTHONPATH=build/client/python python3 client/python/examples/backup_map.py loop loop.pdbsnap \
        --restore-to 127.0.0.1:50052 --restore-as loop-copy

Takes an online snapshot of MAP (ingest may go on), downloads its archive to FILE (checked
against the announced size and its SHA-256; never replaces an existing FILE unless
--overwrite), and with --restore-to uploads it to another server and restores it there as a new
map (same TLS flags). Snapshot calls need an admin token on both servers.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Callable

from replay_folder import add_connection_flags, client_from

import placedb


def progress_bar(label: str, width: int = 30) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback drawing ``label [#####.....] 42% 1.1/2.6 MB``."""
    started = time.monotonic()

    def draw(done: int, total: int) -> None:
        fraction = done / total if total else 0.0
        filled = int(width * fraction)
        rate = done / 1e6 / max(time.monotonic() - started, 1e-9)
        print(
            f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {fraction:4.0%} "
            f"{done / 1e6:.1f}/{total / 1e6:.1f} MB {rate:.1f} MB/s",
            end="\n" if total and done >= total else "",
            file=sys.stderr,
            flush=True,
        )

    return draw


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", help="the map to back up")
    parser.add_argument("file", help="where the archive goes")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing FILE")
    parser.add_argument("--restore-to", metavar="TARGET", help="upload and restore on this server")
    parser.add_argument("--restore-as", metavar="NAME", help="the restored map's name")
    parser.add_argument("--restore-token", help="bearer token for --restore-to (default: --token)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_connection_flags(parser)
    args = parser.parse_args()
    if bool(args.restore_to) != bool(args.restore_as):
        parser.error("--restore-to and --restore-as go together")

    def bar(label: str):
        return None if args.no_progress else progress_bar(label)

    try:
        with client_from(args) as source:
            snapshot = source.create_snapshot(args.map)
            print(f"snapshot {snapshot.id}: {snapshot.places} places")
            saved = source.download_snapshot(
                snapshot.id, args.file, progress=bar("download"), overwrite=args.overwrite
            )
            print(f"{args.file}: {saved.archive_bytes} bytes, sha256 {saved.archive_sha256}")
        if args.restore_to:
            # The same TLS flags; the target's own token when given.
            token = args.restore_token or args.token
            target_args = argparse.Namespace(**{**vars(args), "target": args.restore_to,
                                                "token": token})
            with client_from(target_args) as target:
                uploaded = target.upload_snapshot(args.file, progress=bar("upload"))
                restored = target.restore_snapshot(uploaded.id, args.restore_as)
                print(f"restored on {args.restore_to} as {restored.name}: {restored.places} places")
    except placedb.AlreadyExists as e:
        print(f"\nbackup_map: {e} (--overwrite replaces a file)", file=sys.stderr)
        return 1
    except placedb.Error as e:
        print(f"\nbackup_map: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
