"""pip install ./client/python into a venv over Debian's grpcio, protobuf and numpy, offline
(--no-index: nothing may be downloaded): the wheel carries the stubs generated from
proto/placedb.proto and the placedb-py command; the installed package, imported outside the
checkout, talks to a real placedb-server (blocking and asyncio)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

import pytest

import placedb

ROOT = Path(__file__).resolve().parents[3]


def _run(command: List[str], env: Dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True, timeout=300)


def _checkout_copy(target: Path, with_proto: bool = True) -> Path:
    """The parts of the checkout the package build reads (client/python, proto/placedb.proto
    and proto/health.proto), copied so that the build writes nothing into the checkout."""
    shutil.copytree(
        ROOT / "client" / "python",
        target / "client" / "python",
        ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__", "tests"),
    )
    if with_proto:
        (target / "proto").mkdir()
        for name in ("placedb.proto", "health.proto"):
            shutil.copyfile(ROOT / "proto" / name, target / "proto" / name)
    return target / "client" / "python"


@pytest.fixture(scope="module")
def clean_env() -> Dict[str, str]:
    """The environment without the build tree's package on PYTHONPATH, and without pip's
    configuration (no index, no extra wheel folders: only what Debian installed counts)."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "PYTHONHOME") and not k.startswith("PIP_")
    }
    env["PIP_CONFIG_FILE"] = os.devnull
    return env


def _make_venv(venv: Path, env: Dict[str, str]) -> None:
    command = [sys.executable, "-m", "venv", "--system-site-packages", str(venv)]
    made = _run(command, env, venv.parent)
    assert made.returncode == 0, made.stderr


def _pip_install(venv: Path, package: Path, env: Dict[str, str]) -> subprocess.CompletedProcess:
    return _run(
        [
            str(venv / "bin" / "pip"),
            "install",
            "--no-build-isolation",
            "--no-index",
            "--no-cache-dir",
            "--disable-pip-version-check",
            str(package),
        ],
        env,
        package,
    )


def test_pip_install_in_a_venv_offline(
    server, rtabmap_frames: List[Path], tmp_path: Path, clean_env: Dict[str, str]
) -> None:
    package = _checkout_copy(tmp_path / "checkout")
    venv = tmp_path / "venv"
    _make_venv(venv, clean_env)
    installed = _pip_install(venv, package, clean_env)
    assert installed.returncode == 0, installed.stdout + installed.stderr
    assert "Successfully installed placedb-" in installed.stdout

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    script = """
import asyncio, importlib.metadata, json, sys
import placedb, placedb.aio
from placedb._pb import placedb_pb2

address, image = sys.argv[1], sys.argv[2]
with placedb.Client(address) as client:
    client.create_map("pip")
    stored = [r.stored for r in client.ingest("pip", [image, image], agent_id="pip")]

async def places():
    async with placedb.aio.AsyncClient(address) as client:
        return (await client.health(), (await client.get_map("pip")).places)

print(json.dumps({
    "file": placedb.__file__,
    "prefix": sys.prefix,
    "version": placedb.__version__,
    "metadata_version": importlib.metadata.version("placedb"),
    "stubs": placedb_pb2.__file__,
    "has_observation": hasattr(placedb_pb2, "Observation"),
    "stored": stored,
    "async": asyncio.run(places()),
}))
"""
    ran = _run(
        [str(venv / "bin" / "python"), "-c", script, server.address, str(rtabmap_frames[0])],
        clean_env,
        elsewhere,
    )
    assert ran.returncode == 0, ran.stderr
    out = json.loads(ran.stdout)
    site = Path(out["prefix"]) / "lib"
    assert Path(out["file"]).is_relative_to(site), out  # the venv's copy, not the checkout's
    assert Path(out["stubs"]).is_relative_to(site) and out["has_observation"], out
    cmake_version = re.search(
        r"project\(placedb VERSION ([0-9.]+)", (ROOT / "CMakeLists.txt").read_text()
    ).group(1)
    assert out["version"] == out["metadata_version"] == cmake_version == placedb.__version__
    assert out["stored"] == [True, True]
    assert out["async"] == ["serving", 2]
    # The stubs were generated from this checkout's proto, which the package carries beside them.
    installed_proto = Path(out["stubs"]).parent / "placedb.proto"
    assert installed_proto.read_text() == (ROOT / "proto" / "placedb.proto").read_text()

    # The console entry point.
    cli = _run([str(venv / "bin" / "placedb-py"), "--version"], clean_env, elsewhere)
    assert cli.returncode == 0 and cli.stdout.strip() == f"placedb {cmake_version}", cli
    cli = _run([str(venv / "bin" / "placedb-py"), "ingest-tum", "--help"], clean_env, elsewhere)
    assert cli.returncode == 0 and "groundtruth.txt" in cli.stdout, cli


def test_pip_install_without_the_proto_says_why(tmp_path: Path, clean_env: Dict[str, str]) -> None:
    package = _checkout_copy(tmp_path / "checkout", with_proto=False)
    venv = tmp_path / "venv"
    _make_venv(venv, clean_env)
    installed = _pip_install(venv, package, clean_env)
    assert installed.returncode != 0
    assert "proto/placedb.proto is missing: build the package from a placedb checkout" in (
        installed.stdout + installed.stderr
    ), installed.stdout + installed.stderr
