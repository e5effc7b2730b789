"""Transport security: Client(tls=placedb.TLS(...)) against a mutual-TLS placedb-server.

The certificates are tests/tls_certificates.h's, written by the placedb-test-certs helper.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from typing import Dict, Iterator, Tuple

import pytest
from conftest import ServerProcess, textured_image

import placedb


@pytest.fixture(scope="module")
def mutual_tls() -> Iterator[Tuple[ServerProcess, Dict[str, str]]]:
    folder = tempfile.TemporaryDirectory(prefix="placedb-sdk-certs-")
    subprocess.run([os.environ["PLACEDB_TEST_CERTS"], folder.name], check=True)
    certs = {
        name: os.path.join(folder.name, name)
        for name in ("ca.pem", "server.pem", "server.key", "client.pem", "client.key",
                     "other-client.pem", "other-client.key")
    }
    good = placedb.TLS(ca_cert=certs["ca.pem"], cert=certs["client.pem"], key=certs["client.key"])
    process = ServerProcess(
        ["--tls-cert", certs["server.pem"], "--tls-key", certs["server.key"],
         "--tls-client-ca", certs["ca.pem"]],
        tls=good,
    )
    yield process, certs
    process.stop()
    folder.cleanup()


def test_mutual_tls_round_trip(mutual_tls) -> None:
    server, certs = mutual_tls
    tls = placedb.TLS(ca_cert=certs["ca.pem"], cert=certs["client.pem"], key=certs["client.key"])
    with placedb.Client(server.address, tls=tls) as client:
        client.create_map("secure")
        (result,) = client.ingest("secure", [textured_image(seed=9)], agent_id="robot-8")
        assert result.stored
        answer = client.query("secure", textured_image(seed=9))
        assert answer.matches[0].place_id == result.place_id


def test_tls_refusals(mutual_tls) -> None:
    server, certs = mutual_tls
    # No client certificate, a certificate from another CA, plaintext: refused at the handshake.
    for tls in (
        placedb.TLS(ca_cert=certs["ca.pem"]),
        placedb.TLS(ca_cert=certs["ca.pem"], cert=certs["other-client.pem"],
                    key=certs["other-client.key"]),
        None,
    ):
        with placedb.Client(server.address, tls=tls, timeout=5) as client:
            with pytest.raises(placedb.Unavailable):
                client.list_maps()
    # The server's certificate is not signed by the system roots.
    with placedb.Client(server.address, tls=True, timeout=5) as client:
        with pytest.raises(placedb.Unavailable):
            client.list_maps()
    # Checked before connecting.
    with pytest.raises(placedb.InvalidArgument, match="cert and key go together"):
        placedb.Client(server.address, tls=placedb.TLS(cert=certs["client.pem"]))
    with pytest.raises(placedb.InvalidArgument, match="tls.ca_cert: cannot read"):
        placedb.Client(server.address, tls=placedb.TLS(ca_cert="/nonexistent/ca.pem"))
