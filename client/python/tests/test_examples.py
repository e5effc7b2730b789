"""The two examples run end to end against a real server (the README's commands)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List

import cv2
from conftest import ServerProcess, textured_image

import placedb

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        timeout=300,
    )


def test_replay_then_query_and_draw(server, rtabmap_frames: List[Path]) -> None:
    folder = str(rtabmap_frames[0].parent)
    replay = _run("replay_folder.py", folder, "--map", "examples", "--create", "--agent",
                  "robot-1", "--limit", "30", "--target", server.address)
    assert replay.returncode == 0, replay.stderr
    assert "30/30 frames" in replay.stdout
    with placedb.Client(server.address) as client:
        places = client.get_map("examples").places
    assert f"map examples: {places} places" in replay.stdout
    assert places >= 25

    with tempfile.TemporaryDirectory() as out:
        png = os.path.join(out, "matches.png")
        query = _run("query_and_draw.py", str(rtabmap_frames[12]), "--map", "examples",
                     "--folder", folder, "--top-k", "3", "--out", png,
                     "--target", server.address)
        assert query.returncode == 0, query.stderr
        lines = query.stdout.splitlines()
        assert lines[0].endswith("the query and 3 matches")
        assert "sequence 12" in lines[1]  # the same frame first
        drawn = cv2.imread(png)
        assert drawn is not None and drawn.shape[0] == 360
        assert drawn.shape[1] > 4 * 360  # four panels of 4:3 images


def test_replay_reports_an_unknown_map(server, rtabmap_frames: List[Path]) -> None:
    replay = _run("replay_folder.py", str(rtabmap_frames[0].parent), "--map", "absent",
                  "--limit", "2", "--target", server.address)
    assert replay.returncode == 1
    assert "NOT_FOUND" in replay.stderr and "absent" in replay.stderr


def test_backup_map_downloads_and_restores_on_another_server(server, tmp_path: Path) -> None:
    other = ServerProcess()
    try:
        with placedb.Client(server.address) as client:
            client.create_map("backed-up")
            frames = [textured_image(seed=200 + i) for i in range(6)]
            stored = sum(r.stored for r in client.ingest("backed-up", frames))
        archive = tmp_path / "backed-up.pdbsnap"
        backup = _run("backup_map.py", "backed-up", str(archive), "--target", server.address,
                      "--restore-to", other.address, "--restore-as", "restored")
        assert backup.returncode == 0, backup.stderr
        lines = backup.stdout.splitlines()
        assert lines[0].startswith("snapshot backed-up-") and lines[0].endswith(
            f": {stored} places")
        size = archive.stat().st_size
        assert lines[1].startswith(f"{archive}: {size} bytes, sha256 ")
        assert lines[2] == f"restored on {other.address} as restored: {stored} places"
        assert "download [" in backup.stderr and "upload [" in backup.stderr
        assert backup.stderr.count("100%") == 2
        with placedb.Client(other.address) as restored:
            assert restored.get_map("restored").places == stored

        # An existing file is kept: ALREADY_EXISTS, exit 1, the archive unchanged.
        before = archive.read_bytes()
        again = _run("backup_map.py", "backed-up", str(archive), "--target", server.address,
                     "--no-progress")
        assert again.returncode == 1
        assert "ALREADY_EXISTS" in again.stderr and "--overwrite" in again.stderr
        assert archive.read_bytes() == before
        absent = _run("backup_map.py", "absent", str(tmp_path / "absent.pdbsnap"), "--target",
                      server.address)
        assert absent.returncode == 1 and "NOT_FOUND" in absent.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == ["backed-up.pdbsnap"]
    finally:
        other.stop()
