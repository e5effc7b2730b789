"""The token path: a server with a tokens file made by `placedb-server tokens add`."""

from __future__ import annotations

import os
import subprocess
import tempfile
from typing import Dict, Iterator, Tuple

import pytest
from conftest import ServerProcess, textured_image

import placedb


def _add_token(binary: str, tokens_file: str, *args: str) -> str:
    out = subprocess.run(
        [binary, "tokens", "add", *args, "--tokens-file", tokens_file],
        check=True,
        capture_output=True,
        text=True,
    )
    token = out.stdout.strip()
    assert token and "\n" not in token
    return token


@pytest.fixture(scope="module")
def secured() -> Iterator[Tuple[ServerProcess, Dict[str, str]]]:
    folder = tempfile.TemporaryDirectory(prefix="placedb-sdk-tokens-")
    tokens_file = os.path.join(folder.name, "tokens.yaml")
    binary = os.environ["PLACEDB_SERVER_BINARY"]
    tokens = {
        "admin": _add_token(binary, tokens_file, "ops", "--role", "admin"),
        "reader": _add_token(binary, tokens_file, "viewer", "--read", "lab*"),
        "writer": _add_token(binary, tokens_file, "robot-7", "--write", "lab*", "--read", "lab*"),
    }
    process = ServerProcess(["--tokens-file", tokens_file])
    yield process, tokens
    process.stop()
    folder.cleanup()


def test_tokens_grant_exactly_their_rights(secured) -> None:
    server, tokens = secured
    with placedb.Client(server.address, token=tokens["admin"]) as admin:
        admin.create_map("lab-1")
        admin.create_map("office")
        assert {m.name for m in admin.list_maps()} == {"lab-1", "office"}
    with placedb.Client(server.address, token=tokens["writer"]) as writer:
        results = list(writer.ingest("lab-1", [textured_image(seed=5)], agent_id="robot-7"))
        assert results[0].stored
        with pytest.raises(placedb.PermissionDenied, match="office"):
            list(writer.ingest("office", [textured_image(seed=5)]))
    with placedb.Client(server.address, token=tokens["reader"]) as reader:
        assert [m.name for m in reader.list_maps()] == ["lab-1"]
        answer = reader.query("lab-1", textured_image(seed=5))
        assert answer.matches[0].place_id == results[0].place_id
        assert reader.get_place("lab-1", results[0].place_id).agent_id == "robot-7"
        with pytest.raises(placedb.PermissionDenied, match="not an admin") as e:
            reader.create_map("lab-2")
        assert e.value.code.name == "PERMISSION_DENIED"
        with pytest.raises(placedb.PermissionDenied):
            reader.delete_place("lab-1", results[0].place_id)
        with pytest.raises(placedb.PermissionDenied):
            reader.query("office", textured_image(seed=5))
        info = reader.server_info()  # any principal; the server's details are left out
        assert info.version and info.detector == ""


def test_missing_or_unknown_token_is_unauthenticated(secured) -> None:
    server, _ = secured
    with placedb.Client(server.address) as anonymous:
        with pytest.raises(placedb.Unauthenticated, match="no credentials"):
            anonymous.list_maps()
        assert anonymous.health() == "serving"  # probes need no token
    with placedb.Client(server.address, token="not-a-token") as stranger:
        with pytest.raises(placedb.Unauthenticated, match="unknown token") as e:
            stranger.get_map("lab-1")
        assert e.value.code.name == "UNAUTHENTICATED"
        assert "not-a-token" not in e.value.message
