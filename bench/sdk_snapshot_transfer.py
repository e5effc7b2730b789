#!/usr/bin/python3
"""What the Python SDK's snapshot transfers cost over the bare gRPC stream (issue 15).

One run starts a placedb-server on loopback with a temp data directory, ingests --frames frames
(the RTAB-Map loop, cycled: every frame is a new place), takes a snapshot, then alternates for
--rounds rounds:
  download_raw     the generated stub's DownloadSnapshot, chunks counted and dropped (baseline)
  download_memory  Client.download_snapshot into a BytesIO (size and SHA-256 checks)
  download_file    Client.download_snapshot to a file (.partial, checks, fsync, link)
  upload_raw       the stub's UploadSnapshot from memory in 256 KiB chunks (baseline)
  upload_file      Client.upload_snapshot from that file (size announced, progress queue)
Every upload is verified and kept by the server, then deleted. Prints `name value unit` lines:
the machine's load first, the archive's size, each mode's median time and MB/s, and the SDK's
overhead against its same-run baseline (an upload's time is mostly the server's verification).

    PYTHONPATH=build/client/python /usr/bin/python3 bench/sdk_snapshot_transfer.py \
        [--frames 300] [--rounds 5] [--build build] [--vocabulary FILE] [--shared DIR]
"""

from __future__ import annotations

import argparse
import io
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List

import grpc

import placedb
from placedb._pb import placedb_pb2 as pb
from placedb._pb import placedb_pb2_grpc as pb_grpc


def line(name: str, value: float, unit: str) -> None:
    print(f"{name} {value:.4g} {unit}", flush=True)


def start_server(binary: str, vocabulary: str, data_dir: str) -> "tuple[subprocess.Popen, str]":
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{s.getsockname()[1]}"
    process = subprocess.Popen(
        [binary, "--listen", address, "--data-dir", data_dir, "--metrics-listen", "off",
         "--console-listen", "off", "--vocabulary", "default=" + vocabulary, "--log-level", "warn"]
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            with placedb.Client(address, timeout=1) as probe:
                if probe.health() == "serving":
                    return process, address
        except placedb.Error:
            time.sleep(0.1)
    process.kill()
    raise SystemExit(f"placedb-server did not serve on {address}")


def main() -> int:
    repo = Path(__file__).resolve().parent.parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--build", default=os.environ.get("PLACEDB_BUILD_DIR", str(repo / "build")))
    parser.add_argument("--vocabulary", default=str(repo / "var/vocabulary/default.pdbv"))
    parser.add_argument(
        "--shared", default=os.environ.get("PLACEDB_SHARED_DIR", str(repo.parent / "shared"))
    )
    args = parser.parse_args()
    folder = Path(args.shared) / "data" / "rtabmap-loop"
    images = sorted(folder.glob("*.jpg"), key=lambda p: int(p.stem))
    if not images:
        raise SystemExit(f"no frames in {folder}")

    load1, load5, _ = os.getloadavg()
    line("machine_cores", os.cpu_count() or 0, "cores")
    line("machine_load_1min", load1, "runnable")
    line("machine_load_5min", load5, "runnable")
    root = tempfile.TemporaryDirectory(prefix="placedb-bench-sdk-")
    process, address = start_server(
        os.path.join(args.build, "server", "placedb-server"), args.vocabulary,
        os.path.join(root.name, "data"),
    )
    try:
        with placedb.Client(address, timeout=None) as client:
            client.create_map("bench")
            frames = (images[i % len(images)] for i in range(args.frames))
            stored = sum(r.stored for r in client.ingest("bench", frames, agent_id="b"))
            started = time.monotonic()
            snapshot = client.create_snapshot("bench")
            line("snapshot_create", (time.monotonic() - started) * 1e3, "ms")
            line("snapshot_places", stored, "places")
            # The baseline: the generated stub on its own channel, no SDK in between.
            channel = grpc.insecure_channel(address, options=[
                ("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)])
            stub = pb_grpc.PlaceDbStub(channel)
            archive = Path(root.name) / "bench.pdbsnap"
            client.download_snapshot(snapshot.id, archive)
            data = archive.read_bytes()
            line("archive_bytes", len(data), "bytes")

            def download_raw() -> None:
                got = sum(len(c.data) for c in stub.DownloadSnapshot(
                    pb.DownloadSnapshotRequest(id=snapshot.id)))
                assert got == len(data)

            def download_memory() -> None:
                client.download_snapshot(snapshot.id, io.BytesIO())

            def download_file() -> None:
                client.download_snapshot(snapshot.id, archive, overwrite=True)

            def chunks():
                for offset in range(0, len(data), 256 * 1024):
                    chunk = pb.SnapshotChunk(data=data[offset : offset + 256 * 1024])
                    if offset == 0:
                        chunk.archive_bytes = len(data)
                    yield chunk

            def upload_raw() -> None:
                client.delete_snapshot(stub.UploadSnapshot(chunks()).id)

            def upload_file() -> None:
                client.delete_snapshot(client.upload_snapshot(archive).id)

            modes: Dict[str, Callable[[], None]] = {
                "download_raw": download_raw,
                "download_memory": download_memory,
                "download_file": download_file,
                "upload_raw": upload_raw,
                "upload_file": upload_file,
            }
            times: Dict[str, List[float]] = {name: [] for name in modes}
            for _ in range(args.rounds):
                for name, run in modes.items():
                    started = time.monotonic()
                    run()
                    times[name].append((time.monotonic() - started) * 1e3)
            medians = {name: statistics.median(t) for name, t in times.items()}
            for name, ms in medians.items():
                line(f"{name}_median", ms, "ms")
                line(f"{name}_throughput", len(data) / 1e6 / (ms / 1e3), "MB/s")
            for sdk, raw in (("download_memory", "download_raw"),
                             ("download_file", "download_raw"), ("upload_file", "upload_raw")):
                line(f"{sdk}_overhead_vs_{raw}", (medians[sdk] / medians[raw] - 1) * 100, "%")
            started = time.monotonic()
            client.restore_snapshot(snapshot.id, "bench-restored")
            line("snapshot_restore", (time.monotonic() - started) * 1e3, "ms")
    finally:
        process.terminate()
        process.wait()
        root.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
