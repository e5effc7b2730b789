"""Snapshots through the SDK: create, list, download, upload to a second server, restore.

Two real servers (each its own data directory), and one stopped and restarted in the middle of
a download. The download's own checks (announced size, trailing SHA-256, nothing left behind)
are also driven by a small in-process gRPC server that serves a real archive cut short, altered
or broken off, which a correct server never does.
"""

from __future__ import annotations

import hashlib
import io
import os
import random
import signal
import subprocess
import threading
import time
from concurrent import futures
from pathlib import Path
from typing import Dict, Iterator, List, Tuple

import grpc
import numpy as np
import pytest
from conftest import ServerProcess, unused_loopback_port

import placedb
from placedb._pb import placedb_pb2 as pb
from placedb._pb import placedb_pb2_grpc as pb_grpc


#: Maps verify matches geometrically, so the compared answers include inliers.
VERIFIED = placedb.MapSettings(verification="direct")


@pytest.fixture(scope="module")
def second() -> Iterator[ServerProcess]:
    """Another server with its own data directory: where archives are uploaded."""
    process = ServerProcess()
    yield process
    process.stop()


@pytest.fixture(scope="module")
def source(server) -> Tuple[str, Dict[int, int]]:
    """Map "snap-src": RTAB-Map frames 0-39 by agent robot-1; frame index -> place id."""
    frames = _frames()[:40]
    places = {}
    with placedb.Client(server.address) as c:
        c.create_map("snap-src", VERIFIED)
        for result in c.ingest("snap-src", frames, agent_id="robot-1"):
            assert result.error is None, result.error
            if result.stored:
                places[result.index] = result.place_id
    assert len(places) >= 30
    return "snap-src", places


def _frames() -> List[Path]:
    folder = Path(os.environ["PLACEDB_SHARED_DIR"]) / "data" / "rtabmap-loop"
    return sorted(folder.glob("*.jpg"), key=lambda p: int(p.stem))


def _answers(client: placedb.Client, map: str, frames: List[Path]) -> List[list]:
    """Each frame's ranked (place id, agent, sequence, score, inliers), verified."""
    return [
        [
            (m.place_id, m.agent_id, m.sequence, m.score, m.inliers)
            for m in client.query(map, f, top_k=8, verify=True).matches
        ]
        for f in frames
    ]


def _leftovers(folder: str) -> List[str]:
    return sorted(os.listdir(folder))


class _Progress:
    """Records progress(done, total) calls."""

    def __init__(self) -> None:
        self.calls: List[Tuple[int, int]] = []

    def __call__(self, done: int, total: int) -> None:
        self.calls.append((done, total))

    def check_ends_at(self, total: int) -> None:
        assert self.calls, "progress was never called"
        done = [d for d, _ in self.calls]
        assert done == sorted(done) and len(set(done)) == len(done), "not strictly increasing"
        assert {t for _, t in self.calls} == {total}
        assert self.calls[-1] == (total, total)


# ---- Round trip ---------------------------------------------------------------------------------


def test_create_download_upload_restore_answers_identically(
    server, second, source, tmp_path: Path
) -> None:
    map_name, places = source
    with placedb.Client(server.address) as a, placedb.Client(second.address) as b:
        info = a.get_map(map_name)
        snapshot = a.create_snapshot(map_name)
        assert snapshot.id.startswith(map_name + "-")
        assert snapshot.map == map_name
        assert snapshot.places == info.places == len(places)
        assert snapshot.feature_type == "orb"
        assert snapshot.vocabulary_checksum == info.vocabulary_checksum
        assert snapshot.bytes > 0 and snapshot.created_unix_ms > 0
        assert (snapshot.archive_bytes, snapshot.archive_sha256) == (0, "")
        assert snapshot in a.list_snapshots()
        assert a.list_snapshots(map=map_name) == [snapshot]
        assert a.list_snapshots(map="other") == []

        archive = tmp_path / "snap-src.pdbsnap"
        progress = _Progress()
        downloaded = a.download_snapshot(snapshot.id, archive, progress=progress)
        assert downloaded.id == snapshot.id and downloaded.places == snapshot.places
        data = archive.read_bytes()
        assert downloaded.archive_bytes == len(data) > 0
        assert data.startswith(b"PDBSNAP\n")
        assert downloaded.archive_sha256 == data[-32:].hex()
        assert hashlib.sha256(data[:-32]).hexdigest() == downloaded.archive_sha256
        progress.check_ends_at(len(data))
        assert _leftovers(str(tmp_path)) == ["snap-src.pdbsnap"]

        # An existing file is never replaced unless asked; overwrite gives the same archive.
        with pytest.raises(placedb.AlreadyExists, match="overwrite=True"):
            a.download_snapshot(snapshot.id, archive)
        assert archive.read_bytes() == data
        again = a.download_snapshot(snapshot.id, archive, overwrite=True)
        assert again.archive_sha256 == downloaded.archive_sha256
        buffer = io.BytesIO()
        a.download_snapshot(snapshot.id, buffer)
        assert buffer.getvalue() == data

        progress = _Progress()
        uploaded = b.upload_snapshot(archive, progress=progress)
        progress.check_ends_at(len(data))
        assert uploaded.map == map_name and uploaded.places == snapshot.places
        assert uploaded.vocabulary_checksum == snapshot.vocabulary_checksum
        assert (uploaded.archive_bytes, uploaded.archive_sha256) == (
            len(data),
            downloaded.archive_sha256,
        )
        assert [s.id for s in b.list_snapshots()] == [uploaded.id]

        restored_b = b.restore_snapshot(uploaded.id, "snap-copy")
        restored_a = a.restore_snapshot(snapshot.id, "snap-copy-a")
        for restored in (restored_a, restored_b):
            assert restored.state == "available"
            assert restored.places == info.places
            assert restored.config == info.config
        # Every query gets the same places, in the same order, with the same scores and inliers.
        queries = _frames()[0:60:6]
        expected = _answers(a, map_name, queries)
        assert sum(len(m) for m in expected) > len(queries)
        assert _answers(b, "snap-copy", queries) == expected
        assert _answers(a, "snap-copy-a", queries) == expected

        with pytest.raises(placedb.AlreadyExists, match="snap-copy"):
            b.restore_snapshot(uploaded.id, "snap-copy")
        a.delete_snapshot(snapshot.id)
        assert snapshot.id not in [s.id for s in a.list_snapshots()]
        assert a.get_map(map_name).places == info.places  # the map is not touched


def test_unknown_snapshot_is_not_found_and_leaves_no_file(server, tmp_path: Path) -> None:
    with placedb.Client(server.address) as client:
        dest = tmp_path / "absent.pdbsnap"
        with pytest.raises(placedb.NotFound, match="no-such-snapshot"):
            client.download_snapshot("no-such-snapshot", dest)
        assert _leftovers(str(tmp_path)) == []
        with pytest.raises(placedb.NotFound):
            client.delete_snapshot("no-such-snapshot")
        with pytest.raises(placedb.NotFound):
            client.restore_snapshot("no-such-snapshot", "never")
        with pytest.raises(placedb.NotFound):
            client.create_snapshot("no-such-map")
        with pytest.raises(placedb.InvalidArgument):
            client.download_snapshot("../maps", dest)
        assert "never" not in [m.name for m in client.list_maps()]


# ---- A snapshot while two agents ingest ---------------------------------------------------------


def test_snapshot_during_a_two_agent_ingest_restores_and_answers(server) -> None:
    """The restored map holds a prefix of each agent's stream and answers like a map built from
    just those frames."""
    frames = _frames()
    streams = {"agent-a": frames[0:40], "agent-b": frames[40:80]}
    results: Dict[str, List[placedb.IngestResult]] = {a: [] for a in streams}
    started = threading.Barrier(3)
    halfway = threading.Event()
    errors: List[BaseException] = []

    with placedb.Client(server.address) as admin:
        admin.create_map("snap-live", VERIFIED)

        def run(agent: str) -> None:
            try:
                with placedb.Client(server.address) as own:
                    started.wait()
                    for r in own.ingest("snap-live", streams[agent], agent_id=agent,
                                        max_in_flight=2):
                        results[agent].append(r)
                        if len(results[agent]) == 10:
                            halfway.set()
            except BaseException as e:  # reported below
                errors.append(e)
                halfway.set()

        threads = [threading.Thread(target=run, args=(a,)) for a in streams]
        for t in threads:
            t.start()
        started.wait()
        assert halfway.wait(timeout=300)
        snapshot = admin.create_snapshot("snap-live")
        for t in threads:
            t.join()
        assert not errors, errors
        final = admin.get_map("snap-live").places
        assert 0 < snapshot.places < final, "the snapshot was taken while both agents ingested"

        restored = admin.restore_snapshot(snapshot.id, "snap-live-restored")
        assert restored.places == snapshot.places
        # Per agent, the restored places are the first ones the stream stored.
        prefix: Dict[str, int] = {}
        for agent, answered in results.items():
            stored = [r for r in answered if r.stored]
            kept = 0
            for r in stored:
                try:
                    place = admin.get_place("snap-live-restored", r.place_id)
                except placedb.NotFound:
                    break
                assert (place.agent_id, place.sequence) == (agent, r.sequence)
                kept += 1
            for r in stored[kept:]:
                with pytest.raises(placedb.NotFound):
                    admin.get_place("snap-live-restored", r.place_id)
            prefix[agent] = stored[kept - 1].index + 1 if kept else 0
        assert sum(
            sum(1 for r in results[a][: prefix[a]] if r.stored) for a in streams
        ) == snapshot.places

        # A map built from just those prefixes answers the same (by agent and sequence: its
        # place ids differ).
        admin.create_map("snap-live-reference", VERIFIED)
        for agent in streams:
            list(admin.ingest("snap-live-reference", streams[agent][: prefix[agent]],
                              agent_id=agent))
        assert admin.get_map("snap-live-reference").places == snapshot.places
        queries = frames[5:80:9]

        def ranked(map: str) -> List[list]:
            return [[row[1:] for row in answer] for answer in _answers(admin, map, queries)]

        expected = ranked("snap-live-reference")
        assert any(expected)
        assert ranked("snap-live-restored") == expected


# ---- A server restart in the middle of a download ------------------------------------------------


def _sift_frames(count: int, keypoints: int) -> Iterator[placedb.Frame]:
    """Precomputed SIFT features (512 bytes a descriptor): a large archive from few frames."""
    rng = np.random.default_rng(7)
    for _ in range(count):
        rows = np.zeros((keypoints, 6), np.float32)
        rows[:, 0] = rng.uniform(0, 639, keypoints)
        rows[:, 1] = rng.uniform(0, 479, keypoints)
        rows[:, 2] = 8.0
        rows[:, 4] = 0.05
        rows[:, 5] = 1
        descriptors = rng.uniform(0, 0.2, (keypoints, 128)).astype(np.float32)
        yield placedb.Frame(keypoints=rows, descriptors=descriptors, image_size=(640, 480))


def test_a_server_restart_during_a_download_leaves_nothing_and_it_downloads_after(
    tmp_path: Path,
) -> None:
    """The server stops after the first chunk (its drain ends the stream): Unavailable, no
    file; restarted on the same data directory, the snapshot downloads whole and restores."""
    first = ServerProcess()
    data_dir = first.data_dir
    restarted = None
    try:
        with placedb.Client(first.address) as client:
            client.create_map("restart", placedb.MapSettings(vocabulary="sift"))
            results = list(client.ingest("restart", _sift_frames(16, 2000)))
            assert all(r.stored for r in results), results[0]
            snapshot = client.create_snapshot("restart")
            dest = tmp_path / "restart.pdbsnap"
            seen: List[Tuple[int, int]] = []

            def stop_the_server(done: int, total: int) -> None:
                seen.append((done, total))
                if len(seen) == 1:
                    # SIGTERM, and back to reading once the server drains (health goes
                    # not_serving just before the download's next chunk sees the drain). Not
                    # waiting for the exit: the handler is blocked writing to this reader.
                    first.process.send_signal(signal.SIGTERM)
                    with placedb.Client(first.address, timeout=5) as probe:
                        try:
                            while probe.health() == "serving":
                                time.sleep(0.01)
                        except placedb.Unavailable:  # no longer listening: draining too
                            pass

            # The drain's UNAVAILABLE, or CANCELLED when the server's final cancel overtakes
            # the status queued behind chunks this reader has not read yet.
            with pytest.raises((placedb.Unavailable, placedb.Cancelled)):
                client.download_snapshot(snapshot.id, dest, progress=stop_the_server)
            # gRPC buffers a few MB ahead of the reader: far less than this archive.
            assert seen[-1][0] < seen[-1][1]
            assert _leftovers(str(tmp_path)) == []
        assert first.process.wait(timeout=60) == 0

        restarted = ServerProcess(data_dir=data_dir)
        with placedb.Client(restarted.address) as client:
            assert [s.id for s in client.list_snapshots()] == [snapshot.id]
            whole = client.download_snapshot(snapshot.id, dest)
            assert whole.archive_bytes == dest.stat().st_size == seen[-1][1]
            client.delete_snapshot(snapshot.id)
            kept = client.upload_snapshot(dest)
            restored = client.restore_snapshot(kept.id, "restart-copy")
            assert restored.places == snapshot.places == len(results)
            probe = next(_sift_frames(1, 2000))
            assert client.query("restart-copy", probe).matches == client.query(
                "restart", probe
            ).matches
    finally:
        if restarted is not None:
            restarted.stop()  # before `first` removes the data directory
        first.stop()


# ---- Bad archives -------------------------------------------------------------------------------


class _Unseekable(io.RawIOBase):
    """A pipe-like reader: the upload cannot know its size."""

    def __init__(self, data: bytes) -> None:
        self._data = io.BytesIO(data)

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        chunk = self._data.read(len(buffer))
        buffer[: len(chunk)] = chunk
        return len(chunk)


def test_bad_archives_are_refused_and_leave_nothing(server, second, source, tmp_path) -> None:
    map_name, _ = source
    with placedb.Client(server.address) as a, placedb.Client(second.address) as b:
        snapshot = a.create_snapshot(map_name)
        good = io.BytesIO()
        a.download_snapshot(snapshot.id, good)
        data = good.getvalue()
        a.delete_snapshot(snapshot.id)

        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 0x40
        digest_flipped = bytearray(data)
        digest_flipped[-1] ^= 0x01
        cases = [
            ("half", data[: len(data) // 2], placedb.DataLoss),
            ("one byte short", data[:-1], placedb.DataLoss),
            ("one byte flipped", bytes(flipped), placedb.DataLoss),
            ("digest flipped", bytes(digest_flipped), placedb.DataLoss),
            ("text", b"this is not a snapshot archive\n" * 100, placedb.InvalidArgument),
            ("a PNG", Path(_frames()[0]).read_bytes()[:4096], placedb.InvalidArgument),
            ("empty", b"", placedb.InvalidArgument),
            ("trailing bytes", data + b"\0", placedb.InvalidArgument),
        ]
        before_snapshots = b.list_snapshots()
        before_maps = b.list_maps()
        for name, archive, error in cases:
            path = tmp_path / "bad.pdbsnap"
            path.write_bytes(archive)
            with pytest.raises(error) as raised:
                b.upload_snapshot(path)
            assert str(tmp_path) not in raised.value.message, name
            assert b.list_snapshots() == before_snapshots, name
            assert b.list_maps() == before_maps, name
        # Without an announced size (a pipe) a short archive is still refused.
        with pytest.raises(placedb.DataLoss):
            b.upload_snapshot(io.BufferedReader(_Unseekable(data[:-100])))
        assert b.list_snapshots() == before_snapshots

        # The same archive, whole and from a pipe, is kept.
        kept = b.upload_snapshot(io.BufferedReader(_Unseekable(data)))
        assert kept.places == snapshot.places and kept.archive_bytes == len(data)
        assert [s.id for s in b.list_snapshots()] == [kept.id] + [
            s.id for s in before_snapshots
        ]
        b.delete_snapshot(kept.id)


def test_a_failing_source_or_progress_cancels_the_upload(server, second, source) -> None:
    map_name, _ = source
    with placedb.Client(server.address) as a, placedb.Client(second.address) as b:
        snapshot = a.create_snapshot(map_name)
        good = io.BytesIO()
        a.download_snapshot(snapshot.id, good)
        data = good.getvalue()
        assert len(data) > 3 * 256 * 1024, "the archive spans several chunks"
        before = b.list_snapshots()

        class Failing(io.RawIOBase):
            def __init__(self) -> None:
                self.offset = 0

            def readable(self) -> bool:
                return True

            def readinto(self, buffer) -> int:
                if self.offset >= 2 * 256 * 1024:
                    raise OSError(5, "Input/output error")
                chunk = data[self.offset : self.offset + len(buffer)]
                buffer[: len(chunk)] = chunk
                self.offset += len(chunk)
                return len(chunk)

        with pytest.raises(placedb.InvalidArgument, match="src: reading failed"):
            b.upload_snapshot(Failing())

        def stop_at_the_second_chunk(done: int, total: int) -> None:
            if done > 256 * 1024:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            b.upload_snapshot(io.BytesIO(data), progress=stop_at_the_second_chunk)
        assert b.list_snapshots() == before
        a.delete_snapshot(snapshot.id)


# ---- The download's own checks, against a server that misbehaves --------------------------------


class _Misbehaving(pb_grpc.PlaceDbServicer):
    """Serves `archive` as the snapshot "s", altered per the requested id."""

    def __init__(self, archive: bytes) -> None:
        self.archive = archive

    def DownloadSnapshot(self, request, context):
        data, total = self.archive, len(self.archive)
        if request.id == "truncated":
            data = data[: len(data) // 2]
        elif request.id == "flipped":
            flipped = bytearray(data)
            flipped[len(data) // 3] ^= 0x01
            data = bytes(flipped)
        elif request.id == "longer":
            data = data + b"x"
        elif request.id == "unannounced":
            total = 0
        chunk_bytes = 64 * 1024
        for offset in range(0, max(len(data), 1), chunk_bytes):
            chunk = pb.SnapshotChunk(data=data[offset : offset + chunk_bytes])
            if offset == 0:
                chunk.snapshot.id = request.id
                chunk.snapshot.map = "m"
                chunk.archive_bytes = total
            yield chunk
            if request.id == "broken" and offset == 0:
                context.abort(grpc.StatusCode.UNAVAILABLE, "the server is shutting down")


@pytest.fixture(scope="module")
def misbehaving(server, source) -> Iterator[str]:
    with placedb.Client(server.address) as a:
        snapshot = a.create_snapshot(source[0])
        good = io.BytesIO()
        a.download_snapshot(snapshot.id, good)
        a.delete_snapshot(snapshot.id)
    fake = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    pb_grpc.add_PlaceDbServicer_to_server(_Misbehaving(good.getvalue()), fake)
    address = f"127.0.0.1:{unused_loopback_port()}"
    fake.add_insecure_port(address)
    fake.start()
    yield address
    fake.stop(None)


@pytest.mark.parametrize(
    "case,error,message",
    [
        ("truncated", placedb.DataLoss, "bytes announced arrived"),
        ("flipped", placedb.DataLoss, "SHA-256 does not match"),
        ("longer", placedb.DataLoss, "more than the"),
        ("unannounced", placedb.DataLoss, "more than the 0 bytes"),
        ("broken", placedb.Unavailable, "shutting down"),
    ],
)
def test_a_bad_download_raises_and_leaves_nothing(
    misbehaving, tmp_path: Path, case: str, error, message: str
) -> None:
    with placedb.Client(misbehaving) as client:
        dest = tmp_path / "backup.pdbsnap"
        with pytest.raises(error, match=message):
            client.download_snapshot(case, dest)
        assert _leftovers(str(tmp_path)) == []
        # The whole archive from the same server passes the same checks.
        whole = client.download_snapshot("whole", dest)
        assert whole.archive_bytes == dest.stat().st_size
        assert _leftovers(str(tmp_path)) == ["backup.pdbsnap"]


def test_the_trailing_digest_check_does_not_depend_on_chunking() -> None:
    """Any split of an archive-like stream verifies; one flipped bit anywhere does not."""
    from placedb.snapshots import _TrailingDigest

    rng = random.Random(15)
    for _ in range(300):
        body = rng.randbytes(rng.randint(0, 300))
        data = body + hashlib.sha256(body).digest()
        cuts = sorted(rng.sample(range(len(data) + 1), rng.randint(0, 6)))
        bounds = list(zip([0] + cuts, cuts + [len(data)]))
        flipped = bytearray(data)
        flipped[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        good, bad = _TrailingDigest(), _TrailingDigest()
        for a, b in bounds:
            good.update(data[a:b])
            bad.update(bytes(flipped[a:b]))
        assert good.verify("t") == data[-32:].hex()
        with pytest.raises(placedb.DataLoss, match="SHA-256 does not match"):
            bad.verify("t")
    short = _TrailingDigest()
    short.update(b"PDBSNAP\n")
    with pytest.raises(placedb.DataLoss, match="too short"):
        short.verify("t")


def test_a_progress_callback_that_raises_stops_the_download(misbehaving, tmp_path: Path) -> None:
    def stop(done: int, total: int) -> None:
        raise KeyboardInterrupt

    with placedb.Client(misbehaving) as client:
        with pytest.raises(KeyboardInterrupt):
            client.download_snapshot("whole", tmp_path / "backup.pdbsnap", progress=stop)
    assert _leftovers(str(tmp_path)) == []


# ---- Rights -------------------------------------------------------------------------------------


def _add_token(binary: str, tokens_file: str, *args: str) -> str:
    out = subprocess.run(
        [binary, "tokens", "add", *args, "--tokens-file", tokens_file],
        check=True,
        capture_output=True,
        text=True,
    )
    return out.stdout.strip()


def test_snapshots_need_the_admin_right(tmp_path: Path) -> None:
    tokens_file = str(tmp_path / "tokens.yaml")
    binary = os.environ["PLACEDB_SERVER_BINARY"]
    admin_token = _add_token(binary, tokens_file, "ops", "--role", "admin")
    reader_token = _add_token(binary, tokens_file, "viewer", "--read", "*")
    writer_token = _add_token(binary, tokens_file, "robot", "--write", "*", "--read", "*")
    process = ServerProcess(["--tokens-file", tokens_file])
    try:
        with placedb.Client(process.address, token=admin_token) as admin:
            admin.create_map("guarded")
            snapshot = admin.create_snapshot("guarded")
            archive = tmp_path / "guarded.pdbsnap"
            admin.download_snapshot(snapshot.id, archive)
        for token in (reader_token, writer_token):
            with placedb.Client(process.address, token=token) as other:
                calls = [
                    lambda: other.create_snapshot("guarded"),
                    lambda: other.list_snapshots(),
                    lambda: other.delete_snapshot(snapshot.id),
                    lambda: other.download_snapshot(snapshot.id, tmp_path / "stolen"),
                    lambda: other.upload_snapshot(archive),
                    lambda: other.restore_snapshot(snapshot.id, "guarded-copy"),
                ]
                for call in calls:
                    with pytest.raises(placedb.PermissionDenied, match="admin"):
                        call()
                assert not (tmp_path / "stolen").exists()
                assert not (tmp_path / "stolen.partial").exists()
        with placedb.Client(process.address, token=admin_token) as admin:
            assert [s.id for s in admin.list_snapshots()] == [snapshot.id]
            assert [m.name for m in admin.list_maps()] == ["guarded"]
    finally:
        process.stop()
