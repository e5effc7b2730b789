"""Fixtures of the SDK's tests: a real placedb-server process on a loopback port.

ctest (tests/CMakeLists.txt, python_sdk_test) sets PLACEDB_SERVER_BINARY, PLACEDB_TEST_CERTS,
PLACEDB_DEFAULT_VOCABULARY, PLACEDB_SIFT_VOCABULARY, PLACEDB_SHARED_DIR and PYTHONPATH (the
build tree's package). Every server gets a fresh temp data directory (vocabularies "default" and
"sift") and is stopped with SIGTERM.
"""

from __future__ import annotations

import os
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import numpy as np
import pytest

import placedb


def _env(name: str) -> str:
    value = os.environ.get(name)
    if not value:
        pytest.fail(f"{name} is not set (run the tests through ctest)")
    return value


def unused_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """placedb-server with a temp data directory (or ``data_dir``, e.g. a stopped server's, which
    is then left in place); ``address`` once it answers health checks (over ``tls`` when the
    server's ``extra_args`` ask for TLS)."""

    def __init__(
        self,
        extra_args: Optional[List[str]] = None,
        tls: Optional[placedb.TLS] = None,
        data_dir: Optional[str] = None,
    ) -> None:
        self.binary = _env("PLACEDB_SERVER_BINARY")
        self.root = None if data_dir else tempfile.TemporaryDirectory(prefix="placedb-sdk-")
        self.data_dir = data_dir or os.path.join(self.root.name, "data")
        self.address = f"127.0.0.1:{unused_loopback_port()}"
        args = [
            self.binary,
            "--listen",
            self.address,
            "--data-dir",
            self.data_dir,
            "--metrics-listen",
            "off",
            "--console-listen",
            "off",
            "--vocabulary",
            "default=" + _env("PLACEDB_DEFAULT_VOCABULARY"),
            "--vocabulary",
            "sift=" + _env("PLACEDB_SIFT_VOCABULARY"),
            "--log-level",
            "warn",
        ] + (extra_args or [])
        self.process = subprocess.Popen(args)
        deadline = time.monotonic() + 30
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"placedb-server exited with {self.process.returncode}")
            try:
                # A new channel per probe: a failed one backs off for longer and longer.
                with placedb.Client(self.address, tls=tls, timeout=1) as probe:
                    if probe.health() == "serving":
                        break
            except placedb.Error:
                pass
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"placedb-server did not serve on {self.address}")
            time.sleep(0.1)

    def terminate(self) -> None:
        """SIGTERM (the server drains), and waits for the process; the data directory stays."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def stop(self) -> None:
        self.terminate()
        if self.root is not None:
            self.root.cleanup()


@pytest.fixture(scope="module")
def server() -> Iterator[ServerProcess]:
    process = ServerProcess()
    yield process
    process.stop()


@pytest.fixture
def client(server: ServerProcess) -> Iterator[placedb.Client]:
    with placedb.Client(server.address) as c:
        yield c


@pytest.fixture(scope="session")
def rtabmap_frames() -> List[Path]:
    """The RTAB-Map loop's JPEGs (512 x 384), in frame order 1, 2, 3, ..."""
    folder = Path(_env("PLACEDB_SHARED_DIR")) / "data" / "rtabmap-loop"
    frames = sorted(folder.glob("*.jpg"), key=lambda p: int(p.stem))
    if len(frames) < 30:
        pytest.fail(f"{folder} holds {len(frames)} frames: the shared data is required")
    return frames


@pytest.fixture(scope="session")
def slambook_rgbd() -> List[Tuple[Path, Path, Tuple[float, ...]]]:
    """slambook2's 5 RGB-D frames of a static room (640 x 480): (colour PNG, depth PGM in
    millimetres, pose x y z qx qy qz qw)."""
    folder = Path(_env("PLACEDB_SHARED_DIR")) / "data" / "slambook2-rgbd"
    try:
        poses = [
            tuple(float(v) for v in line.split())
            for line in (folder / "pose.txt").read_text().splitlines()
            if line.strip()
        ]
    except OSError as e:
        pytest.fail(f"{folder}: {e.strerror}: the shared data is required")
    frames = [
        (folder / "color" / f"{i}.png", folder / "depth" / f"{i}.pgm", poses[i - 1])
        for i in range(1, 6)
    ]
    if len(poses) != 5 or not all(c.is_file() and d.is_file() for c, d, _ in frames):
        pytest.fail(f"{folder}: expected color/1..5.png, depth/1..5.pgm and 5 poses")
    return frames


def textured_image(seed: int, width: int = 320, height: int = 240) -> np.ndarray:
    """A deterministic gray uint8 image with corners everywhere (8 x 8 pixel random blocks)."""
    rng = np.random.default_rng(seed)
    blocks = rng.integers(0, 256, size=(height // 8, width // 8), dtype=np.uint8)
    return np.kron(blocks, np.ones((8, 8), dtype=np.uint8))
