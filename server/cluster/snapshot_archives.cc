#include "server/cluster/snapshot_archives.h"

#include <algorithm>
#include <atomic>
#include <deque>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "core/base/thread_annotations.h"
#include "core/storage/sha256.h"
#include "server/cluster/placement.h"

namespace placedb::cluster {

namespace {

using SystemClock = std::chrono::system_clock;

// Chunks a reader holds while its consumer of the stream runs ahead (4 MiB).
constexpr size_t kReadAhead = 8;
// A reader waits at most this long for the next chunk.
constexpr auto kIdle = std::chrono::seconds(30);

std::string Context(const std::string& id) {
  return "snapshot '" + id + "'";
}

}  // namespace

std::string EncodeSnapshotManifest(const SnapshotManifest& m) {
  nlohmann::json json;
  json["id"] = m.info.id;
  json["map"] = m.info.map;
  json["created_unix_ms"] = m.info.created_unix_ms;
  json["feature_type"] = m.info.feature_type;
  json["vocabulary_checksum"] = m.info.vocabulary_checksum;
  json["places"] = m.info.places;
  json["bytes"] = m.info.bytes;
  json["base"] = m.base;
  json["config"] = nlohmann::json::parse(m.config_json.empty() ? "{}" : m.config_json);
  json["archive_bytes"] = m.archive_bytes;
  json["sha256"] = m.sha256;
  json["subject"] = m.subject;
  json["first_sequence"] = m.first_sequence;
  json["chunks"] = m.chunks;
  return json.dump();
}

Result<SnapshotManifest> DecodeSnapshotManifest(const std::string& text) {
  try {
    const nlohmann::json json = nlohmann::json::parse(text);
    SnapshotManifest m;
    m.info.id = json.at("id").get<std::string>();
    m.info.map = json.at("map").get<std::string>();
    m.info.created_unix_ms = json.at("created_unix_ms").get<int64_t>();
    m.info.feature_type = json.value("feature_type", std::string());
    m.info.vocabulary_checksum = json.value("vocabulary_checksum", uint64_t(0));
    m.info.places = json.value("places", uint64_t(0));
    m.info.bytes = json.value("bytes", uint64_t(0));
    m.base = json.at("base").get<uint64_t>();
    m.config_json = json.at("config").dump();
    m.archive_bytes = json.at("archive_bytes").get<uint64_t>();
    m.sha256 = json.at("sha256").get<std::string>();
    m.subject = json.at("subject").get<std::string>();
    m.first_sequence = json.at("first_sequence").get<uint64_t>();
    m.chunks = json.at("chunks").get<uint64_t>();
    return m;
  } catch (const std::exception& e) {
    return Status::Corruption(std::string("snapshot manifest is not valid: ") + e.what());
  }
}

Result<FetchedCheckpoint> FetchCheckpoint(v1::Shard::Stub* stub, grpc::ClientContext* context,
                                          const v1::CheckpointRequest& request,
                                          const std::string& spool, const std::string& from) {
  FetchedCheckpoint out;
  uint64_t expected = 0;
  std::ofstream file(spool, std::ios::binary | std::ios::trunc);
  auto reader = stub->Checkpoint(context, request);
  v1::CheckpointChunk chunk;
  for (bool first = true; reader->Read(&chunk); first = false) {
    if (first) {
      expected = chunk.archive_bytes();
      out.applied = chunk.applied_sequence();
    }
    file.write(chunk.data().data(), std::streamsize(chunk.data().size()));
    out.bytes += chunk.data().size();
  }
  const grpc::Status finished = reader->Finish();
  if (!finished.ok()) {
    return Status::IoError("checkpoint of '" + request.map() + "' from " + from + ": " +
                           finished.error_message());
  }
  file.flush();
  if (!file) return Status::IoError("spooling the checkpoint of '" + request.map() + "' failed");
  if (out.bytes != expected) {
    return Status::Corruption("checkpoint of '" + request.map() + "' from " + from + ": " +
                              std::to_string(out.bytes) + " of " + std::to_string(expected) +
                              " bytes");
  }
  return out;
}

SnapshotArchives::SnapshotArchives(JetStream* jetstream, EtcdClient* etcd, std::string cluster_name,
                                   int stream_replicas)
    : jetstream_(jetstream),
      etcd_(etcd),
      cluster_name_(std::move(cluster_name)),
      stream_replicas_(stream_replicas),
      stream_(SnapshotStreamName(cluster_name_)) {}

std::string SnapshotArchives::Key(const std::string& id) const {
  return ClusterKeys(cluster_name_).Snapshot(id);
}

Status SnapshotArchives::EnsureStream() {
  StreamConfig config;
  config.name = stream_;
  config.subjects = {"placedb." + cluster_name_ + ".snapshots.>"};
  config.replicas = stream_replicas_;
  config.max_message_bytes = int32_t(kSnapshotChunkBytes + (64 << 10));
  return jetstream_->EnsureStream(config).WithContext("the snapshots stream");
}

Status SnapshotArchives::StoreChunks(const std::string& path, const std::string& id,
                                     SnapshotManifest* manifest, SystemClock::time_point deadline) {
  PLACEDB_RETURN_IF_ERROR(EnsureStream());
  std::ifstream in(path, std::ios::binary);
  if (!in) return Status::IoError("cannot read the archive to store");
  // Subject and message ids unique to this store: a purged earlier attempt's ids are still in the
  // duplicate window (a duplicate would name a purged sequence), and a store racing for the same
  // id (refused at the manifest) purges its own chunks only.
  static std::atomic<uint64_t> puts{0};
  const std::string nonce =
      std::to_string(SystemClock::now().time_since_epoch().count()) + "-" + std::to_string(++puts);
  const std::string subject = SnapshotSubject(cluster_name_, id) + "." + nonce;
  const auto fail = [&](const Status& status) {
    (void)jetstream_->PurgeStream(stream_, subject, 0);
    return status.WithContext("storing " + Context(id));
  };
  Sha256 sha;
  std::string buffer(kSnapshotChunkBytes, '\0');
  uint64_t index = 0, bytes = 0, first = 0;
  for (;;) {
    in.read(buffer.data(), std::streamsize(buffer.size()));
    const size_t got = size_t(in.gcount());
    if (got == 0) break;
    const std::string_view piece(buffer.data(), got);
    sha.Update(piece);
    Result<PubAck> ack = Status::IoError("the deadline had passed");
    // Retried with the same message id while JetStream has no quorum or leader (IO_ERROR).
    while (SystemClock::now() < deadline) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - SystemClock::now());
      ack = jetstream_->Publish(subject, piece, id + "/" + nonce + "/" + std::to_string(index),
                                std::min<std::chrono::milliseconds>(left, std::chrono::seconds(5)));
      if (ack.ok() || ack.status().code() != StatusCode::kIoError) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    if (!ack.ok()) return fail(ack.status());
    if (index == 0) first = ack->sequence;
    ++index;
    bytes += got;
  }
  if (in.bad()) return fail(Status::IoError("reading the archive"));
  manifest->info.id = id;
  manifest->archive_bytes = bytes;
  manifest->sha256 = Sha256::Hex(sha.Final());
  manifest->subject = subject;
  manifest->first_sequence = first;
  manifest->chunks = index;
  return Status::Ok();
}

Status SnapshotArchives::Put(const std::string& path, SnapshotManifest* manifest,
                             SystemClock::time_point deadline) {
  // A free id: as a single server's store, "-<n>" when the archive's own is taken.
  const std::string wanted = manifest->info.id;
  std::string id = wanted;
  for (int n = 1;; ++n) {
    auto held = etcd_->Get(Key(id));
    if (!held.ok()) return held.status().WithContext(Context(id));
    if (held->kvs.empty()) break;
    id = wanted + "-" + std::to_string(n);
  }
  PLACEDB_RETURN_IF_ERROR(StoreChunks(path, id, manifest, deadline));
  const auto fail = [&](const Status& status) {
    (void)jetstream_->PurgeStream(stream_, manifest->subject, 0);
    return status.WithContext("storing " + Context(id));
  };
  // The commit point: listed from here on, whole.
  auto created = etcd_->Txn({Compare::Absent(Key(id))},
                            {TxnOp::Put(Key(id), EncodeSnapshotManifest(*manifest))});
  if (!created.ok()) return fail(created.status());
  if (!created->succeeded) {
    return fail(Status::AlreadyExists("id: " + Context(id) + " was stored meanwhile"));
  }
  return Status::Ok();
}

std::string EncodeMapBase(const MapBase& base) {
  nlohmann::json json;
  json["create_revision"] = base.create_revision;
  json["manifest"] = nlohmann::json::parse(EncodeSnapshotManifest(base.manifest));
  return json.dump();
}

Result<MapBase> DecodeMapBase(const std::string& text) {
  auto json = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (json.is_discarded() || !json.is_object() || !json.contains("create_revision") ||
      !json["create_revision"].is_number_integer() || !json.contains("manifest")) {
    return Status::Corruption("base is not {\"create_revision\": N, \"manifest\": {...}}");
  }
  MapBase out;
  out.create_revision = json["create_revision"].get<int64_t>();
  auto manifest = DecodeSnapshotManifest(json["manifest"].dump());
  if (!manifest.ok()) return manifest.status();
  out.manifest = std::move(manifest).value();
  return out;
}

Status SnapshotArchives::PutBase(const std::string& map, const std::string& path, MapBase* base,
                                 int64_t expected_mod_revision, std::vector<Compare> guards,
                                 SystemClock::time_point deadline) {
  const std::string key = ClusterKeys(cluster_name_).Base(map);
  PLACEDB_RETURN_IF_ERROR(StoreChunks(path, "base:" + map, &base->manifest, deadline));
  guards.push_back(expected_mod_revision == 0 ? Compare::Absent(key)
                                              : Compare::ModRevisionIs(key, expected_mod_revision));
  auto written = etcd_->Txn(guards, {TxnOp::Put(key, EncodeMapBase(*base))});
  Status failure;
  if (!written.ok()) {
    failure = written.status();
  } else if (!written->succeeded) {
    failure = Status::FailedPrecondition(
        "the base of map '" + map +
        "' (or the coordinator) changed meanwhile: another compaction won");
  }
  if (!failure.ok()) {
    // Not the map's base: its chunks go (a timed-out write that did commit is caught by the
    // reader's SHA-256 and size check, and the next compaction replaces it).
    if (!written.ok()) {
      if (auto now = GetBase(map);
          now.ok() && now->has_value() && (**now).manifest.subject == base->manifest.subject) {
        return Status::Ok();  // it did commit
      }
    }
    (void)jetstream_->PurgeStream(stream_, base->manifest.subject, 0);
    return failure.WithContext("storing the base of map '" + map + "'");
  }
  return Status::Ok();
}

Result<std::optional<MapBase>> SnapshotArchives::GetBase(const std::string& map) {
  auto read = etcd_->Get(ClusterKeys(cluster_name_).Base(map));
  if (!read.ok()) return read.status().WithContext("reading the base of map '" + map + "'");
  if (read->kvs.empty()) return std::optional<MapBase>();
  auto base = DecodeMapBase(read->kvs[0].value);
  if (!base.ok()) return base.status().WithContext("the base of map '" + map + "'");
  base->mod_revision = read->kvs[0].mod_revision;
  return std::optional<MapBase>(std::move(base).value());
}

Status SnapshotArchives::DeleteChunks(const SnapshotManifest& manifest) {
  if (manifest.subject.empty()) return Status::Ok();
  return jetstream_->PurgeStream(stream_, manifest.subject, 0)
      .WithContext("purging the chunks of " + Context(manifest.info.id));
}

Status SnapshotArchives::DeleteBase(const std::string& map) {
  auto base = GetBase(map);
  if (!base.ok()) return base.status();
  if (!base->has_value()) return Status::Ok();
  auto deleted = etcd_->Delete(ClusterKeys(cluster_name_).Base(map));
  if (!deleted.ok()) return deleted.status();
  return DeleteChunks((**base).manifest);
}

Result<std::vector<SnapshotManifest>> SnapshotArchives::List() {
  const std::string prefix = ClusterKeys(cluster_name_).Snapshot("");
  auto read = etcd_->Get(prefix, /*prefix=*/true);
  if (!read.ok()) return read.status();
  std::vector<SnapshotManifest> out;
  for (const KeyValue& kv : read->kvs) {
    auto manifest = DecodeSnapshotManifest(kv.value);
    if (!manifest.ok()) return manifest.status().WithContext(kv.key);
    out.push_back(std::move(manifest).value());
  }
  std::stable_sort(out.begin(), out.end(),
                   [](const SnapshotManifest& a, const SnapshotManifest& b) {
                     return a.info.created_unix_ms > b.info.created_unix_ms;
                   });
  return out;
}

Result<SnapshotManifest> SnapshotArchives::Get(const std::string& id) {
  PLACEDB_RETURN_IF_ERROR(ValidateSnapshotId(id).WithContext("id"));
  auto read = etcd_->Get(Key(id));
  if (!read.ok()) return read.status();
  if (read->kvs.empty()) return Status::NotFound("id: " + Context(id) + " does not exist");
  return DecodeSnapshotManifest(read->kvs[0].value);
}

Status SnapshotArchives::Read(const SnapshotManifest& manifest, SystemClock::time_point deadline,
                              const std::function<Status(std::string_view)>& sink) {
  // An ordered consumer of the snapshot's subject from its first chunk; the consumer's thread
  // queues (at most kReadAhead chunks), this one hands them on.
  struct Queue {
    Mutex mutex;
    CondVar cv;
    std::deque<std::string> chunks GUARDED_BY(mutex);
    bool stop GUARDED_BY(mutex) = false;
  } queue;
  auto consumer =
      jetstream_->Consume(stream_, manifest.subject, std::max<uint64_t>(manifest.first_sequence, 1),
                          [&queue](uint64_t, std::string_view data) {
                            MutexLock lock(queue.mutex);
                            while (!queue.stop && queue.chunks.size() >= kReadAhead)
                              queue.cv.Wait(queue.mutex);
                            if (queue.stop) return;
                            queue.chunks.emplace_back(data);
                            queue.cv.NotifyAll();
                          });
  if (!consumer.ok()) return consumer.status().WithContext("reading " + Context(manifest.info.id));
  const auto until = std::chrono::steady_clock::now() + (deadline - SystemClock::now());
  Sha256 sha;
  uint64_t chunks = 0, bytes = 0;
  Status result;
  while (chunks < manifest.chunks) {
    std::string piece;
    {
      MutexLock lock(queue.mutex);
      // Bounded by the deadline, and by kIdle without a chunk (its chunks purged meanwhile).
      const auto wait_until = std::min(until, std::chrono::steady_clock::now() + kIdle);
      while (queue.chunks.empty() && std::chrono::steady_clock::now() < wait_until) {
        queue.cv.WaitUntil(queue.mutex, wait_until);
      }
      if (queue.chunks.empty()) {
        result = Status::IoError("reading " + Context(manifest.info.id) + ": " +
                                 std::to_string(chunks) + " of " + std::to_string(manifest.chunks) +
                                 " chunks came from the snapshots stream (deleted meanwhile?)");
        break;
      }
      piece = std::move(queue.chunks.front());
      queue.chunks.pop_front();
      queue.cv.NotifyAll();
    }
    sha.Update(piece);
    bytes += piece.size();
    ++chunks;
    if (Status sunk = sink(piece); !sunk.ok()) {
      result = sunk;
      break;
    }
  }
  {
    MutexLock lock(queue.mutex);
    queue.stop = true;
    queue.cv.NotifyAll();
  }
  (*consumer)->Stop();  // waits for its last callback: `queue` outlives it
  if (!result.ok()) return result;
  const std::string digest = Sha256::Hex(sha.Final());
  if (bytes != manifest.archive_bytes || digest != manifest.sha256) {
    return Status::Corruption(Context(manifest.info.id) + ": the stored archive reads back as " +
                              std::to_string(bytes) + " bytes with SHA-256 " + digest +
                              ", the manifest says " + std::to_string(manifest.archive_bytes) +
                              " bytes, " + manifest.sha256);
  }
  return Status::Ok();
}

Status SnapshotArchives::ReadToFile(const SnapshotManifest& manifest, const std::string& path,
                                    SystemClock::time_point deadline) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) return Status::IoError("cannot write " + path);
  PLACEDB_RETURN_IF_ERROR(Read(manifest, deadline, [&out](std::string_view piece) {
    out.write(piece.data(), std::streamsize(piece.size()));
    return out ? Status::Ok() : Status::IoError("writing the archive's copy");
  }));
  out.flush();
  return out ? Status::Ok() : Status::IoError("writing the archive's copy");
}

Status SnapshotArchives::Delete(const std::string& id) {
  auto manifest = Get(id);
  if (!manifest.ok()) return manifest.status();
  auto deleted = etcd_->Delete(Key(id));
  if (!deleted.ok()) return deleted.status();
  if (*deleted == 0) return Status::NotFound("id: " + Context(id) + " does not exist");
  // Listed no more; then its chunks (a failed purge leaves unlisted bytes in the stream).
  (void)jetstream_->PurgeStream(stream_, manifest->subject, 0);
  return Status::Ok();
}

}  // namespace placedb::cluster
