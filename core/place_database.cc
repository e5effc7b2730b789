#include "core/place_database.h"

#include <algorithm>
#include <mutex>

namespace placedb {

Status ValidateDatabaseConfig(const DatabaseConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateOrbConfig(config.orb));
  PLACEDB_RETURN_IF_ERROR(ValidateFilterConfig(config.filter));
  PLACEDB_RETURN_IF_ERROR(ValidateVerificationConfig(config.verification));
  if (!(config.min_box_confidence >= 0.0f && config.min_box_confidence <= 1.0f)) {
    return Status::InvalidArgument("min_box_confidence must be in [0, 1]");
  }
  for (int id : config.dynamic_classes) {
    if (id < 0 || id > 1000) {
      return Status::InvalidArgument("dynamic_classes: class id " + std::to_string(id) +
                                     " is not a valid class id");
    }
  }
  return Status::Ok();
}

namespace {

size_t RecordBytes(const PlaceRecord& record) {
  return sizeof(PlaceRecord) + record.metadata.agent_id.capacity() +
         record.boxes_used.capacity() * sizeof(DynamicBox);
}

std::string InvalidReason(const FrameCounts& counts, int place_threshold) {
  return "invalid place representation: " + std::to_string(counts.static_) +
         " static descriptors (" + std::to_string(counts.dynamic) + " of " +
         std::to_string(counts.total) + " dropped as dynamic) is not more than placeThreshold " +
         std::to_string(place_threshold);
}

}  // namespace

size_t PayloadBytes(const PlacePayload& payload) {
  return sizeof(PlacePayload) + payload.features.keypoints.capacity() * sizeof(Keypoint) +
         payload.features.descriptors.capacity() * sizeof(Descriptor256) +
         payload.bow.capacity() * sizeof(BowEntry) +
         (payload.direct.node_ids.capacity() + payload.direct.offsets.capacity() +
          payload.direct.feature_ids.capacity()) *
             sizeof(uint32_t);
}

Status InMemoryPayloadStore::Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) {
  std::unique_lock lock(mutex_);
  const size_t bytes = PayloadBytes(*payload);
  if (!payloads_.emplace(id, std::move(payload)).second) {
    return Status::AlreadyExists("payload of place " + std::to_string(id) + " already stored");
  }
  bytes_ += bytes;
  return Status::Ok();
}

Result<std::shared_ptr<const PlacePayload>> InMemoryPayloadStore::Get(PlaceId id) const {
  std::shared_lock lock(mutex_);
  auto it = payloads_.find(id);
  if (it == payloads_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  return it->second;
}

Status InMemoryPayloadStore::Erase(PlaceId id) {
  std::unique_lock lock(mutex_);
  auto it = payloads_.find(id);
  if (it == payloads_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  bytes_ -= PayloadBytes(*it->second);
  payloads_.erase(it);
  return Status::Ok();
}

size_t InMemoryPayloadStore::MemoryBytes() const {
  std::shared_lock lock(mutex_);
  // Plus a rough per-entry cost of the hash map node.
  return bytes_ + payloads_.size() * (sizeof(PlaceId) + sizeof(void*) * 4);
}

PlaceDatabase::PlaceDatabase(std::shared_ptr<const Vocabulary> vocabulary, DatabaseConfig config,
                             std::shared_ptr<PayloadStore> payloads)
    : vocabulary_(std::move(vocabulary)),
      config_(std::move(config)),
      payloads_(payloads ? std::move(payloads) : std::make_shared<InMemoryPayloadStore>()),
      index_(vocabulary_->word_count(), config_.scoring) {}

Result<std::unique_ptr<PlaceDatabase>> PlaceDatabase::Create(
    std::shared_ptr<const Vocabulary> vocabulary, DatabaseConfig config,
    std::shared_ptr<PayloadStore> payloads) {
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(config));
  return std::unique_ptr<PlaceDatabase>(
      new PlaceDatabase(std::move(vocabulary), std::move(config), std::move(payloads)));
}

std::vector<DynamicBox> PlaceDatabase::SelectBoxes(const std::vector<DynamicBox>& boxes) const {
  std::vector<DynamicBox> selected;
  for (const DynamicBox& box : boxes) {
    const bool dynamic_class =
        std::find(config_.dynamic_classes.begin(), config_.dynamic_classes.end(), box.class_id) !=
        config_.dynamic_classes.end();
    if (dynamic_class && box.confidence >= config_.min_box_confidence) selected.push_back(box);
  }
  return selected;
}

Result<ProcessedFrame> PlaceDatabase::Process(const Observation& observation) const {
  ProcessedFrame frame;
  Stopwatch total;
  Stopwatch stage;

  FeatureSet extracted;
  const FeatureSet* features = nullptr;
  if (observation.features.has_value()) {
    PLACEDB_RETURN_IF_ERROR(ValidateFeatures(*observation.features));
    features = &*observation.features;
  } else {
    auto result = ExtractOrb(observation.image, config_.orb);
    if (!result.ok()) return result.status();
    extracted = std::move(result).value();
    features = &extracted;
  }
  frame.timings.extract_ms = stage.Lap();

  DynamicObjects dynamic;
  dynamic.boxes = SelectBoxes(observation.dynamic.boxes);
  dynamic.mask = observation.dynamic.mask;
  auto filtered = ClassifyDescriptors(*features, dynamic, config_.filter);
  if (!filtered.ok()) return filtered.status();
  frame.counts.total = uint32_t(filtered->total());
  frame.counts.dynamic = uint32_t(filtered->dynamic_indices.size());
  frame.counts.static_ = uint32_t(filtered->static_indices.size());
  frame.counts.dynamic_coverage = filtered->frame_dynamic_coverage;
  frame.valid = filtered->valid;
  frame.boxes_used = std::move(dynamic.boxes);
  frame.timings.filter_ms = stage.Lap();

  if (!frame.valid) {
    // The paper's efficiency gain: an invalid representation is neither transformed, stored
    // nor matched.
    frame.rejection = InvalidReason(frame.counts, config_.filter.place_threshold);
    frame.timings.total_ms = total.ElapsedMs();
    return frame;
  }
  frame.static_features = filtered->dynamic_indices.empty()
                              ? *features
                              : SelectFeatures(*features, filtered->static_indices);
  vocabulary_->Transform(frame.static_features.descriptors, &frame.bow, &frame.direct,
                         config_.verification.levels_up);
  NormalizeForScoring(&frame.bow, config_.scoring);
  frame.timings.transform_ms = stage.Lap();
  frame.timings.total_ms = total.ElapsedMs();
  return frame;
}

Result<AddResult> PlaceDatabase::Add(const Observation& observation) {
  auto processed = Process(observation);
  if (!processed.ok()) return processed.status();
  ProcessedFrame& frame = *processed;
  AddResult result;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  if (!frame.valid) {
    result.rejection = frame.rejection;
    CountInvalid();
    return result;
  }
  Stopwatch store;
  auto id = Insert(frame, observation.metadata);
  if (!id.ok()) return id.status();
  result.stored = true;
  result.id = *id;
  result.timings.store_ms = store.ElapsedMs();
  result.timings.total_ms += result.timings.store_ms;
  return result;
}

Result<PlaceId> PlaceDatabase::Insert(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                      std::optional<PlaceId> id) {
  if (!frame.valid) return Status::InvalidArgument("cannot insert an invalid frame");
  if (frame.direct.levels_up != config_.verification.levels_up) {
    return Status::InvalidArgument("frame's direct index is at level " +
                                   std::to_string(frame.direct.levels_up) + ", the database uses " +
                                   std::to_string(config_.verification.levels_up));
  }
  // Build the immutable record and payload before taking the lock.
  auto record = std::make_shared<PlaceRecord>();
  record->metadata = metadata;
  record->counts = frame.counts;
  record->boxes_used = frame.boxes_used;
  auto payload = std::make_shared<PlacePayload>();
  payload->features = frame.static_features;
  payload->direct = frame.direct;
  payload->bow = frame.bow;

  std::unique_lock lock(mutex_);
  record->id = id.value_or(next_id_);
  const PlaceId place = record->id;
  PLACEDB_RETURN_IF_ERROR(InsertLocked(std::move(record), payload->bow));
  if (Status stored = payloads_->Put(place, payload); !stored.ok()) {
    UndoInsertLocked(place, payload->bow);
    return stored;
  }
  return place;
}

Status PlaceDatabase::Restore(PlaceRecord record, const BowVector& bow) {
  std::unique_lock lock(mutex_);
  return InsertLocked(std::make_shared<const PlaceRecord>(std::move(record)), bow);
}

Status PlaceDatabase::InsertLocked(std::shared_ptr<const PlaceRecord> record,
                                   const BowVector& bow) {
  const PlaceId place = record->id;
  if (place == 0) return Status::InvalidArgument("place id 0 is reserved");
  if (records_.count(place)) {
    return Status::AlreadyExists("place " + std::to_string(place) + " already exists");
  }
  PLACEDB_RETURN_IF_ERROR(index_.Add(place, bow));
  descriptors_kept_ += record->counts.static_;
  descriptors_dropped_ += record->counts.dynamic;
  record_bytes_ += RecordBytes(*record);
  records_.emplace(place, std::move(record));
  next_id_ = std::max(next_id_, place + 1);
  return Status::Ok();
}

// Reverts InsertLocked() when the payload store refused the payload.
void PlaceDatabase::UndoInsertLocked(PlaceId id, const BowVector& bow) {
  auto it = records_.find(id);
  if (it == records_.end()) return;
  (void)index_.Remove(id, bow);
  descriptors_kept_ -= it->second->counts.static_;
  descriptors_dropped_ -= it->second->counts.dynamic;
  record_bytes_ -= RecordBytes(*it->second);
  records_.erase(it);
}

PlaceId PlaceDatabase::ReserveId() {
  std::unique_lock lock(mutex_);
  return next_id_++;
}

void PlaceDatabase::ReserveIdsBelow(PlaceId next) {
  std::unique_lock lock(mutex_);
  next_id_ = std::max(next_id_, next);
}

void PlaceDatabase::CountInvalid(uint64_t frames) {
  std::unique_lock lock(mutex_);
  invalid_rejected_ += frames;
}

Status PlaceDatabase::Remove(PlaceId id) {
  std::unique_lock lock(mutex_);
  auto it = records_.find(id);
  if (it == records_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  auto payload = payloads_->Get(id);
  if (!payload.ok()) return payload.status().WithContext("removing place " + std::to_string(id));
  // A persistent store makes the removal durable here; if it cannot, the place stays.
  if (Status erased = payloads_->Erase(id); !erased.ok()) return erased;
  PLACEDB_RETURN_IF_ERROR(index_.Remove(id, (*payload)->bow));
  const PlaceRecord& record = *it->second;
  descriptors_kept_ -= record.counts.static_;
  descriptors_dropped_ -= record.counts.dynamic;
  record_bytes_ -= RecordBytes(record);
  records_.erase(it);  // in-flight queries keep their shared_ptr until they finish
  return Status::Ok();
}

Result<QueryResult> PlaceDatabase::Query(const Observation& observation,
                                         const QueryOptions& options) const {
  auto processed = Process(observation);
  if (!processed.ok()) return processed.status();
  return Search(*processed, options);
}

QueryResult PlaceDatabase::Search(const ProcessedFrame& frame, const QueryOptions& options) const {
  QueryResult result;
  result.valid = frame.valid;
  result.rejection = frame.rejection;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  if (!frame.valid || options.top_k == 0) return result;

  Stopwatch stage;
  std::vector<std::pair<ScoredPlace, std::shared_ptr<const PlaceRecord>>> candidates;
  {
    std::shared_lock lock(mutex_);
    std::function<bool(PlaceId)> accept;
    if (options.accept) {
      accept = [&](PlaceId id) {
        auto it = records_.find(id);
        return it != records_.end() && options.accept(*it->second);
      };
    }
    const std::vector<ScoredPlace> ranked = index_.Query(frame.bow, options.top_k, accept);
    candidates.reserve(ranked.size());
    for (const ScoredPlace& scored : ranked) {
      candidates.emplace_back(scored, records_.at(scored.place));
    }
  }
  result.timings.search_ms = stage.Lap();

  const VerificationConfig& verification = config_.verification;
  const size_t to_verify = verification.mode == VerificationMode::kDisabled
                               ? 0
                               : (verification.candidates > 0
                                      ? std::min(candidates.size(), size_t(verification.candidates))
                                      : candidates.size());
  for (size_t i = 0; i < candidates.size(); ++i) {
    const auto& [scored, record] = candidates[i];
    Match match;
    match.place = scored.place;
    match.score = scored.score;
    match.metadata = record->metadata;
    if (i < to_verify) {
      auto payload = payloads_->Get(scored.place);
      if (!payload.ok()) continue;  // removed while we searched
      auto verified = VerifyGeometry(frame.static_features, frame.direct, (*payload)->features,
                                     (*payload)->direct, verification);
      if (verified.ok()) {
        match.inliers = verified->inliers;
        match.verified = verified->verified;
      }
    }
    if (options.verified_only && !match.verified) continue;
    result.matches.push_back(std::move(match));
  }
  result.timings.verify_ms = stage.Lap();
  result.timings.total_ms += result.timings.search_ms + result.timings.verify_ms;
  return result;
}

std::shared_ptr<const PlaceRecord> PlaceDatabase::Get(PlaceId id) const {
  std::shared_lock lock(mutex_);
  auto it = records_.find(id);
  return it == records_.end() ? nullptr : it->second;
}

std::vector<PlaceId> PlaceDatabase::ListPlaces() const {
  std::vector<PlaceId> ids;
  {
    std::shared_lock lock(mutex_);
    ids.reserve(records_.size());
    for (const auto& [id, record] : records_) ids.push_back(id);
  }
  std::sort(ids.begin(), ids.end());
  return ids;
}

DatabaseStats PlaceDatabase::Stats() const {
  std::shared_lock lock(mutex_);
  DatabaseStats stats;
  stats.places = records_.size();
  stats.descriptors_kept = descriptors_kept_;
  stats.descriptors_dropped = descriptors_dropped_;
  stats.invalid_rejected = invalid_rejected_;
  stats.index_bytes = index_.MemoryBytes();
  stats.record_bytes = record_bytes_;
  stats.payload_bytes = payloads_->MemoryBytes();
  return stats;
}

PlaceId PlaceDatabase::next_id() const {
  std::shared_lock lock(mutex_);
  return next_id_;
}

}  // namespace placedb
