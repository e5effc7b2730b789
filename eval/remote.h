// The live-server backend of the harness: every grid point becomes a map on a running
// placedb-server (proto/placedb.proto), filled with one Ingest stream of the database entries
// (encoded image bytes as stored on disk, plus the run's boxes / mask PNG for BoBW+DO) and
// queried with one Query RPC per query entry; the map is deleted afterwards. The calls go through
// the CLI's client library (client/connection.h, client/ingest_stream.h).
//
// Figures: latency is the client's wall-clock round trip of each Query (decode, extraction,
// filter, transform, search, verification and transport); database size is the map's files on
// disk (MapStats.bytes_on_disk) as well as its in-memory bytes.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "client/connection.h"
#include "core/base/status.h"
#include "core/vocabulary/vocabulary.h"
#include "eval/runner.h"

namespace placedb::eval {

// Connects to `address` (host:port) and checks the server answers GetServerInfo. When
// `local_vocabulary` is given and the server's "default" vocabulary has another checksum, `log`
// is told (the results would not compare with in-process runs). A server that does not answer is
// FAILED_PRECONDITION naming the address; the backend's later calls keep the server's code
// (proto/status.h).
Result<std::unique_ptr<Backend>> MakeServerBackend(
    const std::string& address, std::shared_ptr<const Vocabulary> local_vocabulary,
    const std::function<void(const std::string&)>& log);
// The same with the connection's TLS files and token (client/connection.h; its timeout_s is
// ignored: the backend's calls have no deadline). Unreadable TLS files: FAILED_PRECONDITION naming
// the flag.
Result<std::unique_ptr<Backend>> MakeServerBackend(
    client::ConnectionOptions connection, std::shared_ptr<const Vocabulary> local_vocabulary,
    const std::function<void(const std::string&)>& log);

}  // namespace placedb::eval
