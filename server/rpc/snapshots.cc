// Snapshots: CreateSnapshot, ListSnapshots, DeleteSnapshot, RestoreSnapshot, and the two
// streams (DownloadSnapshot, UploadSnapshot), watched like Ingest streams (Watch).
#include "core/storage/snapshots.h"

#include <unistd.h>

#include <cstdio>
#include <fstream>

#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

using wire::HidePaths;
using wire::ToGrpc;

namespace {

void SnapshotToProto(const SnapshotInfo& info, v1::Snapshot* out) {
  out->set_id(info.id);
  out->set_map(info.map);
  out->set_created_unix_ms(info.created_unix_ms);
  out->set_feature_type(info.feature_type);
  out->set_vocabulary_checksum(info.vocabulary_checksum);
  out->set_places(info.places);
  out->set_bytes(info.bytes);
}

constexpr size_t kSnapshotChunkBytes = size_t(256) << 10;  // well under any max_message_bytes

}  // namespace

grpc::Status PlaceDbService::CreateSnapshot(grpc::ServerContext* context,
                                            const v1::CreateSnapshotRequest* request,
                                            v1::Snapshot* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("CreateSnapshot", context, Unavailable());
  const Clock::time_point start = Clock::now();
  SnapshotInfo info;
  if (grpc::Status created = backend_->CreateSnapshot(request->map(), &info); !created.ok()) {
    return Finish("CreateSnapshot", context, created);
  }
  metrics_->ObserveSnapshot("create", MsSince(start) / 1000.0);
  SnapshotToProto(info, response);
  spdlog::info("snapshot '{}' of map '{}' created: {} places, {} bytes, peer={}", ForLog(info.id),
               ForLog(info.map), info.places, info.bytes, Peer(context));
  return Finish("CreateSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::ListSnapshots(grpc::ServerContext* context,
                                           const v1::ListSnapshotsRequest*,
                                           v1::ListSnapshotsResponse* response) {
  CallScope scope(this);
  std::vector<SnapshotInfo> snapshots;
  if (grpc::Status listed = backend_->ListSnapshots(&snapshots); !listed.ok()) {
    return Finish("ListSnapshots", context, listed);
  }
  for (const SnapshotInfo& info : snapshots) SnapshotToProto(info, response->add_snapshots());
  return Finish("ListSnapshots", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::DeleteSnapshot(grpc::ServerContext* context,
                                            const v1::DeleteSnapshotRequest* request,
                                            v1::DeleteSnapshotResponse*) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DeleteSnapshot", context, Unavailable());
  if (grpc::Status deleted = backend_->DeleteSnapshot(request->id()); !deleted.ok()) {
    return Finish("DeleteSnapshot", context, deleted);
  }
  spdlog::info("snapshot '{}' deleted, peer={}", ForLog(request->id()), Peer(context));
  return Finish("DeleteSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::RestoreSnapshot(grpc::ServerContext* context,
                                             const v1::RestoreSnapshotRequest* request,
                                             v1::MapDescription* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("RestoreSnapshot", context, Unavailable());
  if (Status valid = ValidateSnapshotId(request->id()); !valid.ok()) {
    return Finish("RestoreSnapshot", context, ToGrpc(valid.WithContext("id")));
  }
  const Clock::time_point start = Clock::now();
  if (grpc::Status restored = backend_->RestoreSnapshot(*request, response); !restored.ok()) {
    return Finish("RestoreSnapshot", context, restored);
  }
  metrics_->ObserveSnapshot("restore", MsSince(start) / 1000.0);
  spdlog::info("snapshot '{}' restored as map '{}', peer={}", ForLog(request->id()),
               ForLog(request->new_map()), Peer(context));
  return Finish("RestoreSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::DownloadSnapshotStream(
    grpc::ServerContext* context, const v1::DownloadSnapshotRequest* request,
    const std::function<bool(const v1::SnapshotChunk&)>& write) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DownloadSnapshot", context, Unavailable());
  // A stream like Ingest's: counted against max_concurrent_streams, and cancelled by the watchdog
  // when the client takes no chunk for stream_idle_timeout_ms. Never idle otherwise: every pause
  // between writes is the server reading its files.
  Watch watch(context, "DownloadSnapshot");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("DownloadSnapshot", context, listed.status());
  watch.HeaderArrived();  // the request is the whole header
  watch.HeldBack();
  SnapshotInfo info;
  uint64_t size = 0;
  bool first = true;
  bool drained = false;
  const grpc::Status written = backend_->WriteSnapshotArchive(
      request->id(), kSnapshotChunkBytes,
      [&](const SnapshotInfo& described, uint64_t bytes) {
        info = described;
        size = bytes;
        return Status::Ok();
      },
      [&](std::string_view bytes) -> Status {
        if (context->IsCancelled()) return Status::Cancelled("the client cancelled the download");
        if (draining_flag_) {  // shutting down: the client downloads again from the start
          drained = true;
          return Status::Cancelled("the server is shutting down");
        }
        v1::SnapshotChunk chunk;
        if (first) {
          SnapshotToProto(info, chunk.mutable_snapshot());
          chunk.set_archive_bytes(size);
          first = false;
        }
        chunk.set_data(std::string(bytes));
        watch.Writing();
        const bool sent = write(chunk);
        watch.Written();
        if (!sent) return Status::Cancelled("the client went away during the download");
        metrics_->SnapshotBytesSent(bytes.size());
        return Status::Ok();
      });
  if (auto closed = watch.Closed()) return Finish("DownloadSnapshot", context, *closed);
  if (drained) return Finish("DownloadSnapshot", context, Unavailable());
  if (!written.ok()) return Finish("DownloadSnapshot", context, written);
  spdlog::info("snapshot '{}' downloaded: {} bytes, peer={}", ForLog(request->id()), size,
               Peer(context));
  return Finish("DownloadSnapshot", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::UploadSnapshotStream(
    grpc::ServerContext* context,
    const std::function<grpc::Status(v1::SnapshotChunk*, bool* done)>& read,
    v1::Snapshot* response) {
  CallScope scope(this);
  std::shared_ptr<SnapshotStore> store;
  if (grpc::Status kept = backend_->Snapshots(&store); !kept.ok()) {
    return Finish("UploadSnapshot", context, kept);
  }
  if (draining_flag_) return Finish("UploadSnapshot", context, Unavailable());
  // A stream like Ingest's: counted against max_concurrent_streams, and cancelled by the watchdog
  // when no chunk arrives for stream_idle_timeout_ms (the import after the last one is the
  // server's work: not idle).
  Watch watch(context, "UploadSnapshot");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("UploadSnapshot", context, listed.status());
  watch.HeaderArrived();
  // The archive is spooled into a dot-file of the snapshots folder (removed on every path, and by
  // SnapshotStore::Open after a crash), then imported.
  static std::atomic<uint64_t> uploads{0};
  const std::string spool =
      store->path() + "/.upload-" + std::to_string(::getpid()) + "-" + std::to_string(++uploads);
  struct Spool {
    std::string path;
    ~Spool() { std::remove(path.c_str()); }
  } cleanup{spool};
  std::ofstream out(spool, std::ios::binary | std::ios::trunc);
  if (!out) return Finish("UploadSnapshot", context, ToGrpc(Status::IoError("cannot spool")));
  uint64_t expected = 0;
  uint64_t received = 0;
  // The archive's first bytes, checked once they hold kUploadHeadBytes: an upload that is no
  // archive, or whose framing is over a limit (a 1 GiB SNAPSHOT.json), is refused there instead
  // of after spooling up to limits.max_snapshot_bytes. Import checks everything again.
  constexpr size_t kUploadHeadBytes = 4096;
  std::string head;
  bool head_checked = false;
  for (size_t n = 0;; ++n) {
    v1::SnapshotChunk chunk;
    bool done = false;
    if (grpc::Status status = read(&chunk, &done); !status.ok()) {
      return Finish("UploadSnapshot", context, status);
    }
    if (auto closed = watch.Closed()) return Finish("UploadSnapshot", context, *closed);
    if (context->IsCancelled()) {
      return Finish("UploadSnapshot", context,
                    draining_flag_ ? Unavailable() : Cancelled(context, "during the upload"));
    }
    if (done) break;
    watch.Received();
    const uint64_t limit = config_.limits.max_snapshot_bytes;
    if (n == 0 && chunk.archive_bytes() > 0) {
      expected = chunk.archive_bytes();
      // Refused before any byte is spooled: over the limit, or more than the disk can take.
      if (expected > limit) {
        return Finish("UploadSnapshot", context,
                      grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                                   "archive_bytes: " + std::to_string(expected) +
                                       " bytes announced, over limits.max_snapshot_bytes = " +
                                       std::to_string(limit)));
      }
      if (Status room = store->CheckRoomForImport(expected); !room.ok()) {
        return Finish("UploadSnapshot", context, ToGrpc(room.WithContext("archive_bytes")));
      }
    }
    received += chunk.data().size();
    metrics_->SnapshotBytesReceived(chunk.data().size());
    if (received > limit) {
      return Finish("UploadSnapshot", context,
                    grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                                 "the upload is longer than limits.max_snapshot_bytes = " +
                                     std::to_string(limit)));
    }
    if (expected && received > expected) {
      return Finish("UploadSnapshot", context,
                    ToGrpc(Status::InvalidArgument("archive_bytes: the upload is longer than the " +
                                                   std::to_string(expected) + " bytes announced")));
    }
    if (!head_checked) {
      head.append(chunk.data(), 0, kUploadHeadBytes - head.size());
      if (head.size() == kUploadHeadBytes) {
        head_checked = true;
        if (Status sound = CheckSnapshotArchiveHead(head); !sound.ok()) {
          return Finish("UploadSnapshot", context, ToGrpc(sound));
        }
      }
    }
    out.write(chunk.data().data(), std::streamsize(chunk.data().size()));
    if (!out) {
      return Finish("UploadSnapshot", context, ToGrpc(Status::IoError("spooling the upload")));
    }
  }
  out.close();
  if (expected && received != expected) {
    return Finish(
        "UploadSnapshot", context,
        ToGrpc(Status::Corruption("the upload is truncated: " + std::to_string(received) + " of " +
                                  std::to_string(expected) + " bytes announced")));
  }
  watch.HeldBack();  // verifying: the server's work, not the client's silence
  const Clock::time_point start = Clock::now();
  SnapshotInfo info;
  if (grpc::Status imported = backend_->ImportSnapshot(spool, &info); !imported.ok()) {
    return Finish("UploadSnapshot", context, imported);
  }
  metrics_->ObserveSnapshot("import", MsSince(start) / 1000.0);
  SnapshotToProto(info, response);
  spdlog::info("snapshot '{}' of map '{}' uploaded: {} places, {} bytes, peer={}", ForLog(info.id),
               ForLog(info.map), info.places, received, Peer(context));
  return Finish("UploadSnapshot", context, grpc::Status::OK);
}

}  // namespace placedb::server
