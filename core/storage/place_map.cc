// PlaceMap (map_store.h): its lifetime, queries, durable writes (Add, Commit, CloseLoop, invalid
// frames, counted observations), the replica's ApplyAt/ApplyBatch, removals, reads from disk
// (places, BoW vectors, statistics, thumbnails), stats and checkpoints. Opening (Load),
// the commit queue and the integrity checks are in place_loader.cc, commit_queue.cc and
// map_integrity.cc.
#include <rocksdb/db.h>
#include <rocksdb/utilities/checkpoint.h>
#include <rocksdb/write_batch.h>

#include <algorithm>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <span>
#include <system_error>
#include <unordered_set>

#include "core/base/text.h"
#include "core/base/timing.h"
#include "core/storage/commit_queue.h"
#include "core/storage/map_storage.h"
#include "core/storage/map_store.h"

namespace fs = std::filesystem;

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

namespace {

uint64_t DirectoryBytes(const std::string& path) {
  uint64_t total = 0;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(path, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    std::error_code size_ec;
    if (it->is_regular_file(size_ec)) {
      const auto size = it->file_size(size_ec);
      if (!size_ec) total += size;
    }
  }
  return total;
}

}  // namespace

PlaceMap::PlaceMap(MapInfo info, std::string path, std::unique_ptr<MapStorage> storage,
                   AnyVocabulary vocabulary)
    : info_(std::move(info)),
      path_(std::move(path)),
      storage_(std::move(storage)),
      vocabulary_(std::move(vocabulary)),
      commits_(std::make_unique<CommitQueue>()) {
  if (!info_.vocabulary.stored()) {
    // Generation 0: the file's vocabulary the map was created with, described by itself.
    VocabularySource& source = info_.vocabulary.current;
    source.checksum = vocabulary_.checksum();
    source.branching = uint32_t(vocabulary_.branching());
    source.depth = uint32_t(vocabulary_.depth());
    source.words = vocabulary_.word_count();
    info_.vocabulary.since_unix_ms = info_.created_unix_ms;
  }
  commits_->thread = std::thread([this] { RunCommitter(); });
}

PlaceMap::~PlaceMap() {
  CancelPreparedSwitch();  // its family is dropped while the database is open
  StopCommitter();
  database_.reset();
  if (storage_ && storage_->db) {
    rocksdb::FlushOptions flush;
    (void)storage_->db->Flush(flush, storage_->handles);
  }
}

Status PlaceMap::Deleted() const {
  return Status::NotFound("map '" + info_.name + "' was deleted");
}

Result<QueryResult> PlaceMap::Query(const Observation& observation,
                                    const QueryOptions& options) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->Query(observation, options);
}

QueryResult PlaceMap::Search(const ProcessedFrame& frame, const QueryOptions& options) const {
  ReaderLock alive(lifecycle_);
  if (closed_) {
    QueryResult result;
    result.rejection = Deleted().message();
    return result;
  }
  std::optional<ProcessedFrame> copy;
  auto current = OfCurrentVocabulary(frame, &copy);
  if (!current.ok()) {
    QueryResult result;
    result.rejection = current.status().message();
    return result;
  }
  return database_->Search(**current, options);
}

MapInfo PlaceMap::info() const {
  MutexLock lock(state_mutex_);
  return info_;
}

std::shared_ptr<const PlaceDatabase> PlaceMap::database() const {
  MutexLock lock(state_mutex_);
  return database_;
}

AnyVocabulary PlaceMap::vocabulary() const {
  MutexLock lock(state_mutex_);
  return vocabulary_;
}

Result<const ProcessedFrame*> PlaceMap::OfCurrentVocabulary(
    const ProcessedFrame& frame, std::optional<ProcessedFrame>* copy) const {
  if (database_->OfThisVocabulary(frame) || frame.stream_pending) return &frame;
  copy->emplace(frame);
  PLACEDB_RETURN_IF_ERROR(database_->Retransform(&**copy));
  return &**copy;
}

Status PlaceMap::CheckVocabulary(const AnyVocabulary& vocabulary) const {
  MutexLock lock(state_mutex_);
  // A map that stores its vocabulary uses it whatever the caller has (a file's vocabulary).
  if (info_.vocabulary.stored()) return Status::Ok();
  if (!vocabulary) {
    return Status::InvalidArgument("vocabulary is missing (map '" + info_.name +
                                   "' does not store its own)");
  }
  const FeatureType type = info_.options.database.feature_type;
  if (vocabulary.feature_type() == type && vocabulary.checksum() == info_.vocabulary_checksum) {
    return Status::Ok();
  }
  return Status::FailedPrecondition("map '" + info_.name + "' was built with " +
                                    VocabularyKindName(type) + " vocabulary " +
                                    Hex64(info_.vocabulary_checksum) + ", not " +
                                    vocabulary.kind() + " vocabulary " + vocabulary.checksum_hex());
}

Result<AddResult> PlaceMap::Add(const Observation& observation) {
  // Extraction runs outside the lifecycle lock (it touches no storage), so deleting the map
  // does not wait for it.
  auto frame =
      database()->Process(observation, FrameRole::kStream, ThumbnailsFor(FrameRole::kStream));
  if (!frame.ok()) return frame.status();
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  PLACEDB_RETURN_IF_ERROR(database_->AdvanceStream(&*frame, observation.metadata.agent_id));
  return CommitLocked(*frame, observation.metadata);
}

Status PlaceMap::AdvanceStream(ProcessedFrame* frame, const std::string& agent_id) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->AdvanceStream(frame, agent_id);
}

Result<LoopClosureOutcome> PlaceMap::CloseLoop(const ProcessedFrame& given,
                                               const PlaceMetadata& metadata, AddResult* added,
                                               std::vector<LoopConstraint> found) {
  AddResult local;
  AddResult& result = added ? *added : local;
  result = AddResult();
  // One shared hold for the whole call: the store callback commits with CommitLocked() and the
  // long-term memory reads payloads from RocksDB, both under this hold. Taking the shared lock
  // again inside could deadlock behind a waiting DeleteMap (std::shared_mutex is not
  // reentrant and may block new readers while a writer waits).
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  std::optional<ProcessedFrame> copy;
  auto current = OfCurrentVocabulary(given, &copy);
  if (!current.ok()) return current.status();
  const ProcessedFrame& frame = **current;
  bool committed = false;
  auto store = [&]() REQUIRES_SHARED(lifecycle_) -> Result<PlaceId> {
    auto stored = CommitLocked(frame, metadata);
    if (!stored.ok()) return stored.status();
    committed = true;
    result = *stored;
    if (!stored->stored) {
      return Status::Internal("loop closure: the frame was not stored" +
                              (stored->rejection.empty() ? "" : ": " + stored->rejection));
    }
    return stored->id;
  };
  auto outcome = database_->CloseLoop(frame, metadata, store);
  if (!outcome.ok()) return outcome.status();
  if (!committed && outcome->merged) {
    // Merged into the previous place by rehearsal: only its statistics are written, durably
    // (acknowledged means counted).
    PLACEDB_RETURN_IF_ERROR(
        CountObservationAt(outcome->place, frame, metadata,
                           "counting a frame merged into place " + std::to_string(outcome->place)));
  }
  if (!committed) {
    // Merged into the previous place by rehearsal: no place written.
    result.stored = false;
    result.id = 0;
    result.counts = frame.counts;
    result.boxes_used = frame.boxes_used;
    result.timings = frame.timings;
    result.depth_state = frame.depth_state;
  }
  result.timings.loop_closure_ms = outcome->update_ms;
  result.timings.total_ms += outcome->update_ms;
  AddDetectorLoop(*outcome, metadata, &found);
  PLACEDB_RETURN_IF_ERROR(LogLoops(outcome->place, std::move(found)));
  return outcome;
}

Status PlaceMap::LogLoops(PlaceId place, std::vector<LoopConstraint> found) {
  if (found.empty()) return Status::Ok();
  for (LoopConstraint& constraint : found) {
    constraint.query_place = place;
    if (constraint.place_metadata.agent_id.empty()) {
      if (auto record = database_->Get(constraint.place)) {
        constraint.place_metadata = record->metadata;
      }
    }
  }
  const std::string what = "logging " + std::to_string(found.size()) +
                           " loop constraint(s) of place " + std::to_string(place);
  rocksdb::WriteBatch batch;
  return loops_->Write(&found, &batch,
                       [&] { return storage_->Write(&batch, what, MapStorage::Kind::kAddition); });
}

Result<std::vector<LoopConstraint>> PlaceMap::ReadLoops(uint64_t from, size_t max,
                                                        const LoopFilter& filter,
                                                        uint64_t* scanned) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return loops_->Read(from, max, filter, scanned);
}

uint64_t PlaceMap::WaitForLoops(uint64_t sequence, std::chrono::steady_clock::time_point deadline,
                                bool* deleted) const {
  const uint64_t last = loops_->WaitBeyond(sequence, deadline);
  *deleted = loops_->closed();
  return last;
}

Result<LoopClosureOutcome> PlaceMap::CloseLoop(const ProcessedFrame& frame,
                                               const PlaceMetadata& metadata,
                                               const std::function<Result<PlaceId>()>& store,
                                               PlaceSource* source) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  std::optional<ProcessedFrame> copy;
  auto current = OfCurrentVocabulary(frame, &copy);
  if (!current.ok()) return current.status();
  return database_->CloseLoop(**current, metadata, store, source);
}

void PlaceMap::ResetLoopClosure(const std::string& agent_id) {
  ReaderLock alive(lifecycle_);
  if (!closed_) database_->ResetLoopClosure(agent_id);
}

Status PlaceMap::CountObservationAt(PlaceId place, const ProcessedFrame& frame,
                                    const PlaceMetadata& metadata, const std::string& what) {
  if (!storage_->dynamics) return Status::Ok();
  // A place removed meanwhile keeps none (the map's aggregate still counts the frame); a removal
  // racing this write may leave an entry without a place, which readers skip.
  rocksdb::WriteBatch batch;
  storage_->AddDynamics(&batch, database_->Get(place) ? place : 0, FrameDynamics(frame, metadata));
  return storage_->Write(&batch, what, MapStorage::Kind::kAddition);
}

Result<bool> PlaceMap::CountQueryHit(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                     const QueryResult& result) {
  const double above = info_.options.count_query_hits_above;
  if (above <= 0 || !result.valid || result.matches.empty()) return false;
  const Match& best = result.matches.front();
  if (!(best.score > above)) return false;
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  PLACEDB_RETURN_IF_ERROR(CountObservationAt(
      best.place, frame, metadata, "counting a query hit at place " + std::to_string(best.place)));
  return true;
}

Result<AddResult> PlaceMap::StoreInvalid(const ProcessedFrame& frame,
                                         const PlaceMetadata& metadata) {
  AddResult result;
  result.depth_state = frame.depth_state;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  result.rejection = frame.rejection;
  Stopwatch store;
  rocksdb::WriteBatch batch;
  batch.Merge(storage_->cf(kMeta), kInvalidCountKey, CounterOperand(1));
  if (storage_->dynamics) storage_->AddInvalidDynamics(&batch, FrameDynamics(frame, metadata));
  if (info_.options.store_invalid) {
    InvalidObservation observation;
    observation.serial = storage_->next_invalid_serial.fetch_add(1);
    observation.metadata = metadata;
    observation.counts = frame.counts;
    observation.boxes_used = frame.boxes_used;
    observation.reason = frame.rejection;
    batch.Put(storage_->cf(kInvalid), U64Key(observation.serial),
              EncodeInvalidObservation(observation));
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, "storing an invalid observation", MapStorage::Kind::kAddition));
    ++storage_->invalid_stored;
  } else {
    // Only a counter: not worth an fsync of its own; it rides on the next synced write.
    PLACEDB_RETURN_IF_ERROR(
        storage_->Write(&batch, "counting an invalid frame", MapStorage::Kind::kCounter));
  }
  database_->CountInvalid();
  result.timings.store_ms = store.ElapsedMs();
  result.timings.total_ms += result.timings.store_ms;
  return result;
}

Result<AddResult> PlaceMap::Commit(const ProcessedFrame& frame, const PlaceMetadata& metadata) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return CommitLocked(frame, metadata);
}

Result<AddResult> PlaceMap::CommitLocked(const ProcessedFrame& given, const PlaceMetadata& metadata,
                                         std::vector<LoopConstraint> found) {
  std::optional<ProcessedFrame> copy;
  auto current = OfCurrentVocabulary(given, &copy);
  if (!current.ok()) return current.status();
  const ProcessedFrame& frame = **current;
  if (frame.stream_pending) {
    return Status::FailedPrecondition(
        "the frame's stream stage is pending: call AdvanceStream before committing it");
  }
  if (!frame.valid) return StoreInvalid(frame, metadata);
  // Checked before writing: a batch the index then refused would leave an unindexed place.
  const DatabaseConfig& config = info_.options.database;
  if (frame.static_features.type() != config.feature_type) {
    return Status::InvalidArgument(std::string("frame's features are ") +
                                   FeatureTypeName(frame.static_features.type()) +
                                   ", the map's are " + FeatureTypeName(config.feature_type));
  }
  if (frame.direct.levels_up != config.verification.levels_up) {
    return Status::InvalidArgument("frame's direct index is at level " +
                                   std::to_string(frame.direct.levels_up) + ", the map uses " +
                                   std::to_string(config.verification.levels_up));
  }
  Stopwatch store;
  PlaceRecord record;
  record.id = database_->ReserveId();
  record.metadata = metadata;
  record.counts = frame.counts;
  record.boxes_used = frame.boxes_used;
  const std::string key = PlaceKey(record.id);
  rocksdb::WriteBatch batch;
  batch.Put(storage_->cf(kPlaces), key, EncodePlaceRecord(record));
  batch.Put(storage_->cf(kBow), key, storage_->BowValue(frame.bow, frame.direct));
  batch.Put(storage_->cf(kFeatures), key,
            EncodeLocalFeatures(frame.static_features, frame.direct, frame.geometry));
  if (storage_->dynamics) storage_->AddDynamics(&batch, record.id, FrameDynamics(frame, metadata));
  if (frame.thumbnail && info_.options.thumbnails.enabled) {
    batch.Put(storage_->cf(kThumbnails), key, EncodeThumbnail(*frame.thumbnail));
  }
  for (LoopConstraint& constraint : found) constraint.query_place = record.id;
  PLACEDB_RETURN_IF_ERROR(loops_->Write(&found, &batch, [&] {
    return storage_->Write(&batch, "storing place " + std::to_string(record.id),
                           MapStorage::Kind::kAddition, record.id);
  }));
  // Durable: now make it searchable.
  auto id = database_->Insert(frame, metadata, record.id);
  if (!id.ok()) return id.status();
  AddResult result;
  result.stored = true;
  result.id = *id;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  result.depth_state = frame.depth_state;
  result.timings.store_ms = store.ElapsedMs();
  result.timings.total_ms += result.timings.store_ms;
  return result;
}

Result<bool> PlaceMap::ApplyAt(uint64_t sequence, const MapLogRecord& record) {
  const SequencedRecord one{sequence, &record};
  auto applied = ApplyBatch(std::span<const SequencedRecord>(&one, 1));
  if (!applied.ok()) return applied.status();
  return *applied == 1;
}

Result<size_t> PlaceMap::ApplyBatch(std::span<const SequencedRecord> records) {
  MutexLock apply(apply_mutex_);
  size_t applied = 0;
  // Runs of records between switches of vocabulary: a switch holds the map its own way.
  while (!records.empty()) {
    size_t run = 0;
    while (run < records.size() &&
           records[run].record->kind != MapLogRecord::Kind::kSwitchVocabulary) {
      ++run;
    }
    if (run > 0) {
      auto done = ApplyRun(records.first(run));
      if (!done.ok()) return done.status();
      applied += *done;
    }
    if (run < records.size()) {
      const SequencedRecord& change = records[run];
      if (change.sequence > applied_sequence_.load()) {
        PLACEDB_RETURN_IF_ERROR(ApplySwitch(change.sequence, *change.record));
        ++applied;
      }
      ++run;
    }
    records = records.subspan(run);
  }
  return applied;
}

Result<size_t> PlaceMap::ApplyRun(std::span<const SequencedRecord> records) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  const DatabaseConfig& config = info_.options.database;
  size_t applied = 0;
  // The run being gathered: one RocksDB batch, written and synced once (DeletePlace ends a
  // run: the index's removal writes its own batch).
  rocksdb::WriteBatch batch;
  std::vector<SequencedRecord> run;
  // An AddPlace frame as this map's vocabulary makes it (the record's own, or a copy
  // transformed again, kept until the run is indexed), by the record's position in `run`.
  std::vector<const ProcessedFrame*> run_frames;
  std::deque<ProcessedFrame> transformed;
  std::unordered_set<PlaceId> run_places;  // places the run adds: a CountObservation may name one
  PlaceId run_max_place = 0;
  std::vector<LoopConstraint> run_loops;  // the run's loop constraints, logged with it
  auto flush = [&]() -> Status {
    if (run.empty()) return Status::Ok();
    const uint64_t first = run.front().sequence, last = run.back().sequence;
    const std::string what =
        run.size() == 1 ? "applying record " + std::to_string(last)
                        : "applying records " + std::to_string(first) + ".." + std::to_string(last);
    batch.Put(storage_->cf(kMeta), kAppliedSequenceKey, U64Key(last));
    PLACEDB_RETURN_IF_ERROR(loops_->Write(&run_loops, &batch, [&] {
      return storage_->Write(&batch, what, MapStorage::Kind::kAddition, run_max_place, run.size());
    }));
    // Durable: now make the places searchable and count what was counted. The applied sequence
    // moves only after that: a reader that waited for it (a shard's read with a minimum
    // sequence) must find every place up to it.
    Status indexed;
    for (size_t i = 0; i < run.size(); ++i) {
      const SequencedRecord& r = run[i];
      const MapLogRecord& record = *r.record;
      if (record.kind == MapLogRecord::Kind::kAddPlace) {
        auto id = database_->Insert(*run_frames[i], record.metadata, PlaceId(r.sequence));
        if (!id.ok()) {
          indexed = id.status().WithContext("applying record " + std::to_string(r.sequence));
          break;
        }
      } else if (record.kind == MapLogRecord::Kind::kInvalidFrame) {
        if (info_.options.store_invalid) {
          ++storage_->invalid_stored;
          uint64_t next = storage_->next_invalid_serial.load();
          while (next <= r.sequence &&
                 !storage_->next_invalid_serial.compare_exchange_weak(next, r.sequence + 1)) {
          }
        }
        database_->CountInvalid();
      }
    }
    // Ids follow the stream: the next place id is above every sequence applied.
    database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(last + 1, kMaxPlaceId)));
    // Stored is applied, also when the index refused a place (reported: the replica stops).
    applied_sequence_ = last;
    PLACEDB_RETURN_IF_ERROR(indexed);
    applied += run.size();
    run.clear();
    run_frames.clear();
    transformed.clear();
    run_places.clear();
    run_max_place = 0;
    run_loops.clear();
    batch.Clear();
    return Status::Ok();
  };
  uint64_t last = applied_sequence_.load();
  for (const SequencedRecord& r : records) {
    if (r.sequence <= last) continue;  // applied before (or repeated in `records`)
    const uint64_t sequence = r.sequence;
    const MapLogRecord& record = *r.record;
    const std::string what = "applying record " + std::to_string(sequence);
    // A record the map cannot take: the run before it is applied, it and the rest are not.
    auto refuse = [&](const std::string& why) -> Status {
      PLACEDB_RETURN_IF_ERROR(flush());
      return Status::InvalidArgument(what + ": " + why);
    };
    const ProcessedFrame* indexed_frame = &record.frame;
    switch (record.kind) {
      case MapLogRecord::Kind::kAddPlace: {
        // Checked before writing: a batch the index then refused would leave an unindexed place.
        if (sequence >= kMaxPlaceId) return refuse("sequence beyond the place-id range");
        if (!record.frame.valid) return refuse("AddPlace of an invalid frame");
        if (record.frame.vocabulary_checksum != 0 && !database_->OfThisVocabulary(record.frame)) {
          // Processed with the vocabulary before a switch (a worker that had not seen it yet).
          transformed.push_back(record.frame);
          if (Status again = database_->Retransform(&transformed.back()); !again.ok()) {
            return refuse(again.message());
          }
          indexed_frame = &transformed.back();
        }
        const ProcessedFrame& frame = *indexed_frame;
        if (frame.static_features.type() != config.feature_type) {
          return refuse("frame's features are " +
                        std::string(FeatureTypeName(frame.static_features.type())) +
                        ", the map's are " + FeatureTypeName(config.feature_type));
        }
        if (frame.direct.levels_up != config.verification.levels_up) {
          return refuse("frame's direct index is at level " +
                        std::to_string(frame.direct.levels_up) + ", the map uses " +
                        std::to_string(config.verification.levels_up));
        }
        PlaceRecord stored;
        stored.id = PlaceId(sequence);
        stored.metadata = record.metadata;
        stored.counts = frame.counts;
        stored.boxes_used = frame.boxes_used;
        const std::string key = PlaceKey(stored.id);
        batch.Put(storage_->cf(kPlaces), key, EncodePlaceRecord(stored));
        batch.Put(storage_->cf(kBow), key, storage_->BowValue(frame.bow, frame.direct));
        batch.Put(storage_->cf(kFeatures), key,
                  EncodeLocalFeatures(frame.static_features, frame.direct, frame.geometry));
        if (storage_->dynamics && record.dynamics) {
          storage_->AddDynamics(&batch, stored.id, *record.dynamics);
        }
        if (frame.thumbnail && info_.options.thumbnails.enabled) {
          batch.Put(storage_->cf(kThumbnails), key, EncodeThumbnail(*frame.thumbnail));
        }
        run_places.insert(stored.id);
        run_max_place = stored.id;
        break;
      }
      case MapLogRecord::Kind::kDeletePlace: {
        PLACEDB_RETURN_IF_ERROR(flush());
        const std::string applied_value = U64Key(sequence);
        if (record.place != 0 && database_->Get(record.place)) {
          // The removal's own batch carries the applied sequence (RocksPayloadStore::Erase).
          t_applying_sequence = &applied_value;
          Status removed = database_->Remove(record.place);
          t_applying_sequence = nullptr;
          PLACEDB_RETURN_IF_ERROR(removed.WithContext(what));
        } else {
          rocksdb::WriteBatch alone;
          alone.Put(storage_->cf(kMeta), kAppliedSequenceKey, applied_value);
          PLACEDB_RETURN_IF_ERROR(storage_->Write(&alone, what, MapStorage::Kind::kRemoval));
        }
        applied_sequence_ = sequence;
        database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(sequence + 1, kMaxPlaceId)));
        ++applied;
        last = sequence;
        continue;  // not part of a run
      }
      case MapLogRecord::Kind::kCountObservation:
        if (storage_->dynamics && record.dynamics) {
          const bool known =
              record.place != 0 && (run_places.count(record.place) || database_->Get(record.place));
          storage_->AddDynamics(&batch, known ? record.place : 0, *record.dynamics);
        }
        break;
      case MapLogRecord::Kind::kInvalidFrame: {
        batch.Merge(storage_->cf(kMeta), kInvalidCountKey, CounterOperand(1));
        if (storage_->dynamics && record.dynamics) {
          storage_->AddInvalidDynamics(&batch, *record.dynamics);
        }
        if (info_.options.store_invalid) {
          // The sequence is the serial: the same on every replica, in arrival order.
          InvalidObservation observation;
          observation.serial = sequence;
          observation.metadata = record.metadata;
          observation.counts = record.frame.counts;
          observation.boxes_used = record.frame.boxes_used;
          observation.reason = record.frame.rejection;
          batch.Put(storage_->cf(kInvalid), U64Key(sequence),
                    EncodeInvalidObservation(observation));
        }
        break;
      }
      case MapLogRecord::Kind::kVocabularyPart: {
        const MapLogRecord::VocabularyPart& part = record.vocabulary_part;
        if (part.count == 0 || part.index >= part.count) {
          return refuse("vocabulary part " + std::to_string(part.index) + " of " +
                        std::to_string(part.count));
        }
        batch.Put(storage_->cf(kMeta), VocabularyPartKey(part.checksum, part.index), part.bytes);
        break;
      }
      case MapLogRecord::Kind::kPrepareVocabulary:
        break;  // built by PrepareVocabularySwitch, on the host's thread
      case MapLogRecord::Kind::kLoopConstraints:
        for (const LoopConstraint& found : record.loops) {
          LoopConstraint& logged = run_loops.emplace_back(found);
          if (auto place = database_->Get(logged.place)) logged.place_metadata = place->metadata;
        }
        break;
      case MapLogRecord::Kind::kSwitchVocabulary:
        return refuse("a switch of vocabulary inside a run");  // ApplyBatch splits runs there
    }
    run.push_back(r);
    run_frames.push_back(indexed_frame);
    last = sequence;
  }
  PLACEDB_RETURN_IF_ERROR(flush());
  return applied;
}

Result<StoredPlace> PlaceMap::GetPlace(PlaceId id) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  auto record = database_->Get(id);
  if (!record)
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  RocksPayloadStore payloads(storage_.get(), info_.options.database.feature_type);
  auto payload = payloads.Get(id);
  if (!payload.ok()) {
    // A corrupt block is DATA_LOSS naming the file, relative to the data directory.
    return Status(payload.status().code(),
                  RelativeTo(payload.status().message(), path_, info_.name));
  }
  return StoredPlace{*record, **payload};
}

Result<BowVector> PlaceMap::GetBow(PlaceId id) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (!database_->Get(id)) {
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  }
  RocksPayloadStore payloads(storage_.get(), info_.options.database.feature_type);
  auto bow = payloads.GetBow(id);
  if (!bow.ok()) {
    return Status(bow.status().code(), RelativeTo(bow.status().message(), path_, info_.name));
  }
  return bow;
}

Status PlaceMap::RemovePlace(PlaceId id) {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  return database_->Remove(id);
}

std::vector<InvalidObservation> PlaceMap::InvalidObservations(size_t limit) const {
  std::vector<InvalidObservation> out;
  ReaderLock alive(lifecycle_);
  if (closed_) return out;
  std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator({}, storage_->cf(kInvalid)));
  for (it->SeekToFirst(); it->Valid() && out.size() < limit; it->Next()) {
    auto decoded = DecodeInvalidObservation(it->value().ToStringView());
    if (decoded.ok()) out.push_back(std::move(decoded).value());
  }
  return out;
}

Result<std::optional<std::string>> PlaceMap::ReadPlaceValue(PlaceId id, size_t family,
                                                            const std::string& what) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (!database_->Get(id)) {
    return Status::NotFound("place " + std::to_string(id) + " not found in map '" + info_.name +
                            "'");
  }
  std::string value;
  auto s = storage_->db->Get({}, storage_->cf(Cf(family)), PlaceKey(id), &value);
  if (s.IsNotFound()) return std::optional<std::string>();
  if (Status read = FromRocks(s, "reading the " + what + " of place " + std::to_string(id));
      !read.ok()) {
    return Status(read.code(), RelativeTo(read.message(), path_, info_.name));
  }
  return std::optional<std::string>(std::move(value));
}

Result<PlaceDynamics> PlaceMap::GetDynamics(PlaceId id) const {
  auto value = ReadPlaceValue(id, kDynamics, "statistics");
  if (!value.ok()) return value.status();
  if (!*value) return PlaceDynamics();
  auto decoded = DecodeDynamics(**value);
  if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(id));
  return decoded;
}

Result<std::optional<Thumbnail>> PlaceMap::GetThumbnail(PlaceId id) const {
  auto value = ReadPlaceValue(id, kThumbnails, "thumbnail");
  if (!value.ok()) return value.status();
  if (!*value) return std::optional<Thumbnail>();
  auto decoded = DecodeThumbnail(**value);
  if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(id));
  return std::optional<Thumbnail>(std::move(decoded).value());
}

Result<PlaceDynamics> PlaceMap::ReadAggregate(const char* key, const std::string& what) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  std::string value;
  auto s = storage_->db->Get({}, storage_->cf(kDynamics), key, &value);
  if (s.IsNotFound()) return PlaceDynamics();
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading " + what));
  auto decoded = DecodeDynamics(value);
  if (!decoded.ok()) return decoded.status().WithContext("map '" + info_.name + "': " + what);
  return decoded;
}

Result<PlaceDynamics> PlaceMap::MapDynamics() const {
  return ReadAggregate(kMapDynamicsKey, "the map's statistics");
}

Result<PlaceDynamics> PlaceMap::InvalidDynamics() const {
  return ReadAggregate(kInvalidDynamicsKey, "the invalid frames' statistics");
}

Status PlaceMap::ForEachPlaceDynamics(
    const std::function<bool(PlaceId, const PlaceDynamics&)>& visit) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  rocksdb::ReadOptions options;
  options.fill_cache = false;
  std::unique_ptr<rocksdb::Iterator> it(
      storage_->db->NewIterator(options, storage_->cf(kDynamics)));
  for (it->SeekToFirst(); it->Valid(); it->Next()) {
    if (IsAggregateKey(it->key())) continue;
    auto id = DecodePlaceKey(it->key().ToStringView());
    if (!id.ok()) return id.status().WithContext("statistics key");
    if (!database_->Get(*id)) continue;  // removed while a merged frame was being counted
    auto decoded = DecodeDynamics(it->value().ToStringView());
    if (!decoded.ok()) return decoded.status().WithContext("place " + std::to_string(*id));
    if (!visit(*id, *decoded)) return Status::Ok();
  }
  return FromRocks(it->status(), "scanning statistics");
}

MapStats PlaceMap::Stats() const {
  MapStats stats;
  stats.database = database_->Stats();
  stats.invalid_stored = storage_->invalid_stored;
  ReaderLock alive(lifecycle_);
  if (closed_) return stats;
  stats.bytes_on_disk = DirectoryBytes(path_);
  uint64_t memtables = 0;
  storage_->db->GetAggregatedIntProperty(rocksdb::DB::Properties::kCurSizeAllMemTables, &memtables);
  stats.bytes_in_memory = stats.database.index_bytes + stats.database.record_bytes +
                          stats.database.payload_bytes + memtables;
  return stats;
}

Status PlaceMap::Checkpoint(const std::string& directory) const {
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  if (fs::exists(directory)) {
    return Status::AlreadyExists("checkpoint directory " + directory + " already exists");
  }
  rocksdb::Checkpoint* raw = nullptr;
  PLACEDB_RETURN_IF_ERROR(
      FromRocks(rocksdb::Checkpoint::Create(storage_->db.get(), &raw), "creating a checkpoint"));
  std::unique_ptr<rocksdb::Checkpoint> checkpoint(raw);
  // log_size_for_flush = 0: flush memtables so the checkpoint needs no WAL replay.
  return FromRocks(checkpoint->CreateCheckpoint(directory, 0), "checkpoint into " + directory);
}

}  // namespace placedb
