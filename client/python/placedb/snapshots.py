"""Moving snapshot archives: the download and upload halves of :class:`placedb.Client`'s calls.

An archive (format v1, core/storage/snapshots.h) ends with the SHA-256 of every byte before that
digest, so a download is checked end to end without a second request: the size the server
announces in the first message, then the trailing digest over what arrived. A download to a path
is written to ``<dest>.partial`` and moved to ``dest`` only once both checks pass; on any
failure (a broken stream, a mismatch, an exception from the progress callback) the partial file
is removed, so a file at ``dest`` is always a whole, checked archive.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import queue
import threading
from typing import IO, Any, Callable, Iterator, Optional, Union

import grpc

from placedb._pb import placedb_pb2 as pb
from placedb.errors import AlreadyExists, DataLoss, InvalidArgument, from_rpc_error
from placedb.results import Snapshot

#: ``progress(done_bytes, total_bytes)``; total is 0 when unknown (an upload from a pipe).
Progress = Callable[[int, int], None]
#: A file path, or a binary file object.
PathOrFile = Union[str, "os.PathLike[str]", IO[bytes]]

#: Bytes per upload message (the server sends downloads in pieces of the same size).
CHUNK_BYTES = 256 * 1024
_DIGEST_BYTES = 32


class _TrailingDigest:
    """SHA-256 of every byte but the last 32, and those 32 bytes: the archive's own digest."""

    def __init__(self) -> None:
        self._hash = hashlib.sha256()
        self._tail = b""

    def update(self, data: bytes) -> None:
        if len(data) >= _DIGEST_BYTES:  # the usual chunk: no copy of it
            self._hash.update(self._tail)
            self._hash.update(memoryview(data)[:-_DIGEST_BYTES])
            self._tail = bytes(data[-_DIGEST_BYTES:])
            return
        tail = self._tail + data
        cut = len(tail) - _DIGEST_BYTES
        if cut > 0:
            self._hash.update(tail[:cut])
            tail = tail[cut:]
        self._tail = tail

    def verify(self, what: str) -> str:
        """The digest in hex; :class:`DataLoss` unless it is the SHA-256 of what preceded it."""
        if len(self._tail) < _DIGEST_BYTES:
            raise DataLoss(f"{what}: {len(self._tail)} bytes are too short for an archive")
        if self._hash.digest() != self._tail:
            raise DataLoss(
                f"{what}: the archive's SHA-256 does not match its contents "
                f"(computed {self._hash.hexdigest()}, recorded {self._tail.hex()})"
            )
        return self._tail.hex()


def _receive(call: Any, out: IO[bytes], progress: Optional[Progress]) -> Snapshot:
    snapshot: Optional[Snapshot] = None
    total = done = 0
    digest = _TrailingDigest()
    try:
        for chunk in call:
            if snapshot is None:
                if not chunk.HasField("snapshot"):
                    raise DataLoss("download: the first message carries no snapshot")
                snapshot = Snapshot.from_proto(chunk.snapshot)
                total = chunk.archive_bytes
            done += len(chunk.data)
            if done > total:
                raise DataLoss(f"download: more than the {total} bytes announced arrived")
            out.write(chunk.data)
            digest.update(chunk.data)
            if progress is not None:
                progress(done, total)
    except grpc.RpcError as e:
        raise from_rpc_error(e) from None
    finally:
        call.cancel()  # a no-op once complete; stops the server's stream when we leave early
    if snapshot is None:
        raise DataLoss("download: the stream ended without a message")
    if done != total:
        raise DataLoss(f"download: {done} of the {total} bytes announced arrived")
    sha256 = digest.verify("download")
    return dataclasses.replace(snapshot, archive_bytes=total, archive_sha256=sha256)


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


def download(
    start: Callable[[], Any], dest: PathOrFile, progress: Optional[Progress], overwrite: bool
) -> Snapshot:
    """Runs ``start()`` (a DownloadSnapshot call) into ``dest``; see the module's docstring."""
    if not isinstance(dest, (str, os.PathLike)):
        return _receive(start(), dest, progress)
    path = os.fspath(dest)
    if os.path.lexists(path) and not overwrite:
        raise AlreadyExists(f"dest: {path} exists (overwrite=True replaces it)")
    partial = path + ".partial"
    try:
        out = open(partial, "wb")
    except OSError as e:
        raise InvalidArgument(f"dest: cannot write {partial}: {e.strerror}") from None
    try:
        with out:
            snapshot = _receive(start(), out, progress)
            out.flush()
            os.fsync(out.fileno())  # a backup is whole on disk before it has its name
        if overwrite:
            os.replace(partial, path)
        else:
            try:
                os.link(partial, path)  # unlike rename, fails if dest appeared meanwhile
            except FileExistsError:
                raise AlreadyExists(f"dest: {path} exists (overwrite=True replaces it)") from None
            except OSError:  # a file system without hard links
                if os.path.lexists(path):
                    raise AlreadyExists(
                        f"dest: {path} exists (overwrite=True replaces it)"
                    ) from None
                os.rename(partial, path)
            _remove(partial)
    except BaseException:
        _remove(partial)
        raise
    return snapshot


def upload(
    start: Callable[[Iterator[pb.SnapshotChunk]], Any],
    src: PathOrFile,
    progress: Optional[Progress],
    chunk_bytes: int = CHUNK_BYTES,
) -> Snapshot:
    """Streams ``src`` through ``start(requests)`` (an UploadSnapshot call's ``future``).

    The size is announced when known (a path, or a seekable file: the bytes from its position
    to its end), so the server refuses a stream of another length. ``progress`` runs in the
    caller's thread; an exception from it, or from reading ``src``, cancels the upload (the
    server keeps nothing) and is raised.
    """
    if chunk_bytes < 1:
        raise InvalidArgument(f"chunk_bytes: {chunk_bytes}, expected >= 1")
    if isinstance(src, (str, os.PathLike)):
        try:
            source: IO[bytes] = open(src, "rb")
        except OSError as e:
            raise InvalidArgument(f"src: cannot read {os.fspath(src)}: {e.strerror}") from None
        owned = True
    else:
        source, owned = src, False
    try:
        total = 0
        try:
            if source.seekable():
                position = source.tell()
                total = source.seek(0, os.SEEK_END) - position
                source.seek(position)
        except OSError:
            total = 0
        events: "queue.Queue[tuple]" = queue.Queue()
        stop = threading.Event()
        trailer = bytearray()  # the last 32 bytes sent: the digest the server checked

        def requests() -> Iterator[pb.SnapshotChunk]:
            # Runs in gRPC's request thread; reports to the caller's thread through `events`.
            sent = 0
            try:
                first = True
                while not stop.is_set():
                    data = source.read(chunk_bytes)
                    if not data and not first:
                        return
                    chunk = pb.SnapshotChunk(data=data)
                    if first:
                        chunk.archive_bytes = total
                        first = False
                    yield chunk
                    sent += len(data)
                    trailer[:] = (trailer + data[-_DIGEST_BYTES:])[-_DIGEST_BYTES:]
                    events.put(("sent", sent))
                    if not data:
                        return
            except Exception as e:
                events.put(("error", e))
                stop.wait()  # keep the stream open until the caller has cancelled it

        call = start(requests())
        # Every chunk's event is queued before the stream half-closes, so "done" comes last.
        call.add_done_callback(lambda _: events.put(("done", None)))
        sent = 0
        try:
            while True:
                try:
                    kind, value = events.get(timeout=1)
                except queue.Empty:  # only so that a signal is handled while waiting
                    continue
                if kind == "done":
                    break
                if kind == "error":
                    if isinstance(value, OSError):
                        raise InvalidArgument(
                            f"src: reading failed after {sent} bytes: {value}"
                        ) from None
                    raise value
                sent = value
                if progress is not None:
                    progress(sent, total)
            response = call.result()
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None
        finally:
            call.cancel()
            stop.set()
        return dataclasses.replace(
            Snapshot.from_proto(response), archive_bytes=sent, archive_sha256=trailer.hex()
        )
    finally:
        if owned:
            source.close()
