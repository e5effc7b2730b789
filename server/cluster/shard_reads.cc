// The Shard RPCs a worker reads through (server/cluster/shard.h): Search, FetchPlaces,
// ListAgentPlaces, LearnVocabulary, GetVocabulary, and Checkpoint for a new replica's catch-up.
#include <grpcpp/grpcpp.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>

#include "core/base/timing.h"
#include "core/storage/codec.h"
#include "proto/convert_config.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/backend/place_reads.h"
#include "server/cluster/map_record.h"
#include "server/cluster/shard_impl.h"

namespace placedb::cluster {

using Clock = std::chrono::steady_clock;
using wire::ToGrpc;

Result<std::shared_ptr<PlaceMap>> Shard::Impl::MapOf(const std::string& map) const {
  MutexLock lock(mutex_);
  auto it = replicas_.find(map);
  if (it == replicas_.end()) {
    return Status::NotFound("map '" + map + "' is not held by shard " + options_.shard_id);
  }
  if (!it->second->map) {
    return Status::IoError("map '" + map + "' on shard " + options_.shard_id +
                           " is not open: " + it->second->problem);
  }
  return it->second->map;
}

grpc::Status Shard::Impl::AwaitApplied(grpc::ServerContext* context, const std::string& map,
                                       const PlaceMap& m, uint64_t min_sequence) {
  // Bounded by the call's deadline (30 s without one).
  const auto remaining = context->deadline() - std::chrono::system_clock::now();
  const auto until =
      Clock::now() + std::min<std::chrono::system_clock::duration>(
                         remaining, std::chrono::duration_cast<std::chrono::system_clock::duration>(
                                        std::chrono::seconds(30)));
  MutexLock lock(mutex_);
  while (m.applied_sequence() < min_sequence) {
    if (stopping_) return GrpcError(grpc::StatusCode::UNAVAILABLE, "shard is stopping");
    if (Clock::now() >= until || context->IsCancelled()) {
      return GrpcError(grpc::StatusCode::DEADLINE_EXCEEDED,
                       "map '" + map + "' on shard " + options_.shard_id + " applied " +
                           std::to_string(m.applied_sequence()) + " < min_sequence " +
                           std::to_string(min_sequence));
    }
    applied_cv_.WaitUntil(mutex_, std::min(until, Clock::now() + std::chrono::milliseconds(200)));
  }
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::AppliedMap(grpc::ServerContext* context, const std::string& map,
                                     uint64_t min_sequence, std::shared_ptr<PlaceMap>* out) {
  auto held = MapOf(map);
  if (!held.ok()) return ToGrpc(held.status());
  if (grpc::Status applied = AwaitApplied(context, map, **held, min_sequence); !applied.ok()) {
    return applied;
  }
  *out = std::move(held).value();
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::Search(grpc::ServerContext* context, const cv1::SearchRequest& request,
                                 cv1::SearchResponse* response) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  PlaceMap& m = *map;
  ProcessedFrame frame;
  if (Status decoded = FrameFromSearchRequest(request, m.options().database.feature_type, &frame);
      !decoded.ok()) {
    return GrpcError(grpc::StatusCode::INVALID_ARGUMENT, decoded.message());
  }
  QueryOptions options = wire::QueryOptionsFromProto(request.options(), request.agent_id());
  options.search_threads = options_.search.threads;
  options.max_word_share = options_.search.max_word_share;
  options.skip_words_min_places = options_.search.skip_words_min_places;
  options.timestamp_ns = request.timestamp_ns();
  const uint64_t applied = m.applied_sequence();  // every place up to it is searched
  const uint64_t vocabulary = m.vocabulary().checksum();
  if (frame.vocabulary_checksum == 0) frame.vocabulary_checksum = vocabulary;  // an older worker
  QueryResult result = m.Search(frame, options);
  response->set_vocabulary_checksum(vocabulary);
  response->set_valid(result.valid);
  response->set_rejection(result.rejection);
  wire::MatchesToProto(result.matches, response->mutable_matches());
  response->set_applied_sequence(applied);
  response->set_search_ms(result.timings.search_ms);
  response->set_verify_ms(result.timings.verify_ms);
  response->set_pose_ms(result.timings.pose_ms);
  return grpc::Status::OK;
}

namespace {

// A vocabulary's bytes in chunks after `first` (which carries the description).
grpc::Status StreamVocabulary(cv1::VocabularyChunk first, const std::string& bytes,
                              grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  constexpr size_t kChunk = 1 << 20;
  size_t at = 0;
  do {
    const size_t n = std::min(kChunk, bytes.size() - at);
    first.set_data(bytes.substr(at, n));
    if (!writer->Write(first)) return GrpcError(grpc::StatusCode::CANCELLED, "caller went away");
    first.Clear();
    at += n;
  } while (at < bytes.size());
  return grpc::Status::OK;
}

}  // namespace

grpc::Status Shard::Impl::LearnVocabulary(grpc::ServerContext* context,
                                          const cv1::LearnVocabularyRequest& request,
                                          grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  AdaptOptions options;  // one thread at nice 10: this replica keeps serving meanwhile
  options.learning = wire::LearningOptionsFromProto(request);
  const uint64_t applied = map->applied_sequence();
  auto learned = map->LearnVocabulary(options);
  if (!learned.ok()) return ToGrpc(learned.status());
  spdlog::info(
      "shard {}: map '{}': learned vocabulary {} from {} places ({} descriptors) at "
      "sequence {} in {:.1f} s",
      options_.shard_id, request.map(), learned->vocabulary.checksum_hex(),
      learned->source.places_offered, learned->source.descriptors_sampled, applied,
      learned->source.learn_ms / 1000);
  cv1::VocabularyChunk first;
  wire::VocabularySourceToProto(learned->source, first.mutable_vocabulary()->mutable_current());
  first.mutable_vocabulary()->set_map(request.map());
  first.set_applied_sequence(applied);
  return StreamVocabulary(std::move(first), learned->vocabulary.Serialize(), writer);
}

grpc::Status Shard::Impl::GetVocabulary(grpc::ServerContext* context,
                                        const cv1::GetVocabularyRequest& request,
                                        grpc::ServerWriter<cv1::VocabularyChunk>* writer) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  // The vocabulary first: a switch between the two reads shows the older record with it, never
  // bytes newer than the record.
  const AnyVocabulary vocabulary = map->vocabulary();
  const uint64_t applied = map->applied_sequence();
  VocabularyRecord record = map->info().vocabulary;
  if (record.current.checksum != vocabulary.checksum()) {
    return GrpcError(grpc::StatusCode::UNAVAILABLE,
                     "map '" + request.map() + "' is switching its vocabulary; ask again");
  }
  cv1::VocabularyChunk first;
  wire::VocabularyRecordToProto(record, map->switching_vocabulary(), first.mutable_vocabulary());
  first.mutable_vocabulary()->set_map(request.map());
  first.set_applied_sequence(applied);
  return StreamVocabulary(std::move(first), request.bytes() ? vocabulary.Serialize() : "", writer);
}

grpc::Status Shard::Impl::FetchPlaces(grpc::ServerContext* context,
                                      const cv1::FetchPlacesRequest& request,
                                      cv1::FetchPlacesResponse* response) {
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  const PlaceMap& m = *map;
  response->set_applied_sequence(m.applied_sequence());
  for (const uint32_t id : request.place_ids()) {
    cv1::FetchedPlace* out = nullptr;
    if (request.features()) {
      auto place = m.GetPlace(id);
      if (place.status().code() == StatusCode::kNotFound) continue;
      if (!place.ok()) return ToGrpc(place.status());
      out = response->add_places();
      out->set_bow(EncodeBow(place->payload.bow));
      out->set_features(EncodeLocalFeatures(place->payload.features, place->payload.direct,
                                            place->payload.geometry));
    } else {
      auto bow = m.GetBow(id);
      if (bow.status().code() == StatusCode::kNotFound) continue;
      if (!bow.ok()) return ToGrpc(bow.status());
      out = response->add_places();
      out->set_bow(EncodeBow(*bow));
    }
    out->set_place_id(id);
  }
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::ListAgentPlaces(grpc::ServerContext* context,
                                          const cv1::ListAgentPlacesRequest& request,
                                          cv1::ListAgentPlacesResponse* response) {
  if (request.agent_id().empty()) {
    return GrpcError(grpc::StatusCode::INVALID_ARGUMENT, "agent_id: is required");
  }
  std::shared_ptr<PlaceMap> map;
  const grpc::Status ready = AppliedMap(context, request.map(), request.min_sequence(), &map);
  if (!ready.ok()) return ready;
  const PlaceMap& m = *map;
  response->set_applied_sequence(m.applied_sequence());
  const size_t limit = request.limit() == 0 ? 256 : std::min<size_t>(request.limit(), 1024);
  PlaceFilter filter;
  filter.agent_id = request.agent_id();
  // A bounded walk per page (ids of other agents count too): the caller pages on.
  const PlacePage page =
      m.database()->ListPlacesBefore(request.before_place_id(), limit, filter, size_t(1) << 16);
  for (const auto& record : page.places) {
    auto bow = m.GetBow(record->id);
    if (bow.status().code() == StatusCode::kNotFound) continue;  // removed meanwhile
    if (!bow.ok()) return ToGrpc(bow.status());
    cv1::AgentPlace* out = response->add_places();
    out->set_place_id(record->id);
    out->set_sequence(record->metadata.sequence);
    out->set_bow(EncodeBow(*bow));
  }
  response->set_next_before_place_id(page.next_before);
  return grpc::Status::OK;
}

grpc::Status Shard::Impl::Checkpoint(const cv1::CheckpointRequest& request,
                                     grpc::ServerWriter<cv1::CheckpointChunk>* writer) {
  auto map = MapOf(request.map());
  if (!map.ok()) return ToGrpc(map.status());
  int64_t held_revision = 0;
  std::shared_ptr<Replica> replica;
  {
    MutexLock lock(mutex_);
    auto it = replicas_.find(request.map());
    if (it != replicas_.end()) {
      replica = it->second;
      held_revision = replica->create_revision;
    }
  }
  if (!replica) return ToGrpc(Status::NotFound("map '" + request.map() + "' is not held here"));
  if (request.create_revision() != 0 && held_revision != request.create_revision()) {
    return GrpcError(grpc::StatusCode::FAILED_PRECONDITION,
                     "map '" + request.map() + "' on shard " + options_.shard_id +
                         " is of create revision " + std::to_string(held_revision) + ", not " +
                         std::to_string(request.create_revision()));
  }
  // Unverified here: the new replica's Import verifies (opens and scrubs) what it received.
  Stopwatch phase;
  uint64_t applied = 0;
  Result<SnapshotInfo> created = Status::Internal("no checkpoint");
  {
    MutexLock lock(replica->apply_mutex);
    applied = (*map)->applied_sequence();
    created = snapshots_->CreateForTransfer(**map);
  }
  if (!created.ok()) return ToGrpc(created.status());
  const double create_ms = phase.Lap();
  struct Cleanup {
    SnapshotStore* store;
    std::string id;
    ~Cleanup() { (void)store->Delete(id); }
  } cleanup{snapshots_.get(), created->id};
  auto bytes = snapshots_->ArchiveBytes(created->id);
  if (!bytes.ok()) return ToGrpc(bytes.status());
  bool first = true;
  Status written = snapshots_->WriteArchive(created->id, 1 << 20, [&](std::string_view data) {
    cv1::CheckpointChunk chunk;
    if (first) {
      chunk.set_applied_sequence(applied);
      chunk.set_archive_bytes(*bytes);
      first = false;
    }
    chunk.set_data(std::string(data));
    if (!writer->Write(chunk)) return Status::IoError("the receiver went away");
    return Status::Ok();
  });
  spdlog::info(
      "shard {}: checkpoint of map '{}' at {} for a new replica: {} bytes (made in {:.2f} s, "
      "sent in {:.2f} s): {}",
      options_.shard_id, request.map(), applied, *bytes, create_ms / 1e3, phase.Lap() / 1e3,
      written.ok() ? "sent" : written.ToString());
  return ToGrpc(written);
}

}  // namespace placedb::cluster
