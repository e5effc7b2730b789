// A map's own vocabulary (issue 29, map_store.h): PlaceMap::AdaptVocabulary and
// RevertVocabulary, the online re-index into a new BoW family beside the live one and the one
// synced batch that switches, the vocabulary record, and reading a stored vocabulary at open.
//
// Layout (docs/storage.md, "A map's own vocabulary"): generation g > 0 keeps each place's BoW
// vector and direct index in the family "bow.<g>"; the meta family holds the generation, the
// vocabulary, the previous vocabulary and the record, all written by the switch's batch together
// with the info's checksum. A crash before that batch is durable leaves generation g - 1 (the
// next open drops the half-built family); after it, generation g (the next open drops or clears
// the previous family if the crash came before that).
#include <rocksdb/db.h>
#include <rocksdb/write_batch.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <functional>
#include <iterator>
#include <nlohmann/json.hpp>
#include <optional>
#include <system_error>
#include <thread>

#include "core/base/parallel.h"
#include "core/base/text.h"
#include "core/base/timing.h"
#include "core/storage/map_storage.h"
#include "core/storage/map_store.h"

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

namespace {

// Places re-indexed per shared hold of the map: holds stay short, so a DeleteMap (or a reader
// queued behind it) waits for one chunk at most.
constexpr size_t kChunkPlaces = 256;

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

nlohmann::json SourceJson(const VocabularySource& source) {
  return {{"origin", source.origin},
          {"checksum", source.checksum},
          {"branching", source.branching},
          {"depth", source.depth},
          {"words", source.words},
          {"learned_unix_ms", source.learned_unix_ms},
          {"places_offered", source.places_offered},
          {"descriptors_offered", source.descriptors_offered},
          {"places_sampled", source.places_sampled},
          {"descriptors_sampled", source.descriptors_sampled},
          {"learn_ms", source.learn_ms}};
}

VocabularySource SourceFromJson(const nlohmann::json& j) {
  VocabularySource source;
  source.origin = j.at("origin").get<std::string>();
  source.checksum = j.at("checksum").get<uint64_t>();
  source.branching = j.at("branching").get<uint32_t>();
  source.depth = j.at("depth").get<uint32_t>();
  source.words = j.at("words").get<uint64_t>();
  source.learned_unix_ms = j.at("learned_unix_ms").get<int64_t>();
  source.places_offered = j.at("places_offered").get<uint64_t>();
  source.descriptors_offered = j.at("descriptors_offered").get<uint64_t>();
  source.places_sampled = j.at("places_sampled").get<uint64_t>();
  source.descriptors_sampled = j.at("descriptors_sampled").get<uint64_t>();
  source.learn_ms = j.at("learn_ms").get<double>();
  return source;
}

// A stored place's features value decoded as a frame the new vocabulary can transform.
Status FrameOfStoredPlace(FeatureType type, std::string_view features, PlaceId id,
                          ProcessedFrame* frame) {
  DirectIndex unused;
  PLACEDB_RETURN_IF_ERROR(DecodeLocalFeatures(features, type, &frame->static_features, &unused)
                              .WithContext("place " + std::to_string(id)));
  frame->valid = true;
  return Status::Ok();
}

}  // namespace

namespace detail {

std::string VocabularyBytesKey(uint64_t checksum) {
  return kVocabularyBytesPrefix + Hex64(checksum);
}

std::string EncodeVocabularyRecord(const VocabularyRecord& record) {
  nlohmann::json j;
  j["generation"] = record.generation;
  j["current"] = SourceJson(record.current);
  if (record.previous) j["previous"] = SourceJson(*record.previous);
  j["since_unix_ms"] = record.since_unix_ms;
  j["places_reindexed"] = record.places_reindexed;
  j["reindex_ms"] = record.reindex_ms;
  return j.dump();
}

Result<VocabularyRecord> DecodeVocabularyRecord(std::string_view json) {
  const nlohmann::json j = nlohmann::json::parse(json, nullptr, false);
  if (j.is_discarded() || !j.is_object()) {
    return Status::Corruption("the vocabulary record is not valid JSON");
  }
  VocabularyRecord record;
  try {
    record.generation = j.at("generation").get<uint64_t>();
    record.current = SourceFromJson(j.at("current"));
    if (j.contains("previous")) record.previous = SourceFromJson(j.at("previous"));
    record.since_unix_ms = j.at("since_unix_ms").get<int64_t>();
    record.places_reindexed = j.at("places_reindexed").get<uint64_t>();
    record.reindex_ms = j.at("reindex_ms").get<double>();
  } catch (const nlohmann::json::exception& e) {
    return Status::Corruption(std::string("the vocabulary record: ") + e.what());
  }
  return record;
}

Status ReadVocabularyRecord(MapStorage& storage, MapInfo* info) {
  std::string value;
  const rocksdb::Status s =
      storage.db->Get({}, storage.handles[kMeta], kVocabularyRecordKey, &value);
  if (s.IsNotFound()) return Status::Ok();  // generation 0: DecodeInfo's default
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the map's vocabulary record"));
  auto record = DecodeVocabularyRecord(value);
  if (!record.ok()) return record.status();
  if (record->current.checksum != info->vocabulary_checksum) {
    return Status::Corruption(
        "the vocabulary record and the map info name different "
        "vocabularies");
  }
  info->vocabulary = std::move(record).value();
  return Status::Ok();
}

Result<std::optional<AnyVocabulary>> ReadStoredVocabulary(MapStorage& storage,
                                                          const MapInfo& info) {
  if (!info.vocabulary.stored()) return std::optional<AnyVocabulary>();
  std::string bytes;
  const rocksdb::Status s = storage.db->Get({}, storage.handles[kMeta],
                                            VocabularyBytesKey(info.vocabulary_checksum), &bytes);
  if (s.IsNotFound()) {
    return Status::Corruption("its vocabulary (generation " +
                              std::to_string(info.vocabulary.generation) + ") is missing");
  }
  PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the map's vocabulary"));
  auto vocabulary = AnyVocabulary::Parse(bytes);
  if (!vocabulary.ok()) {
    return Status::Corruption("its stored vocabulary is damaged: " + vocabulary.status().message());
  }
  if (vocabulary->feature_type() != info.options.database.feature_type ||
      vocabulary->checksum() != info.vocabulary_checksum) {
    return Status::Corruption("its stored vocabulary (" + vocabulary->checksum_hex() +
                              ") is not the one its info names");
  }
  return std::optional<AnyVocabulary>(std::move(vocabulary).value());
}

}  // namespace detail

namespace {

// One switch at a time per map.
class SwitchGuard {
 public:
  explicit SwitchGuard(std::atomic<bool>& flag) : flag_(flag) {
    bool idle = false;
    held_ = flag_.compare_exchange_strong(idle, true);
  }
  ~SwitchGuard() {
    if (held_) flag_ = false;
  }
  bool held() const { return held_; }

 private:
  std::atomic<bool>& flag_;
  bool held_ = false;
};

// Runs `work` on a thread whose nice value is `nice` above the caller's (Linux: per thread; the
// threads it starts inherit it), so that a switch yields the CPU to queries and ingest; on the
// calling thread when no thread can be started or `nice` is 0.
Result<VocabularyRecord> OnNiceThread(int nice,
                                      const std::function<Result<VocabularyRecord>()>& work) {
  if (nice <= 0) return work();
  std::optional<Result<VocabularyRecord>> result;
  try {
    std::thread thread([&] {
      const id_t self = id_t(::syscall(SYS_gettid));
      errno = 0;
      const int current = ::getpriority(PRIO_PROCESS, self);
      if (errno == 0) (void)::setpriority(PRIO_PROCESS, self, std::min(current + nice, 19));
      result.emplace(work());
    });
    thread.join();
  } catch (const std::system_error&) {
    return work();
  }
  return std::move(*result);
}

}  // namespace

Status PlaceMap::MaySwitch(bool only_switch) const {
  if (!only_switch) {
    return Status::FailedPrecondition("map '" + info_.name +
                                      "' is already switching its vocabulary; wait for it");
  }
  if (applied_sequence_.load() > 0) {
    return Status::FailedPrecondition("map '" + info_.name +
                                      "' is a replica of a cluster map: its vocabulary cannot "
                                      "change on one replica");
  }
  return Status::Ok();
}

Status PlaceMap::Cancelled(const AdaptOptions& options) const {
  if (!options.cancel || !options.cancel->load()) return Status::Ok();
  return Status::Cancelled("the vocabulary switch of map '" + info_.name +
                           "' was cancelled; the map keeps its vocabulary");
}

Result<VocabularyRecord> PlaceMap::AdaptVocabulary(const AdaptOptions& options) {
  return OnNiceThread(options.nice, [&] { return AdaptVocabularyNow(options); });
}

Result<VocabularyRecord> PlaceMap::RevertVocabulary(const AdaptOptions& options) {
  return OnNiceThread(options.nice, [&] { return RevertVocabularyNow(options); });
}

Result<VocabularyRecord> PlaceMap::AdaptVocabularyNow(const AdaptOptions& options) {
  PLACEDB_RETURN_IF_ERROR(ValidateLearningOptions(options.learning));
  SwitchGuard guard(switching_);
  PLACEDB_RETURN_IF_ERROR(MaySwitch(guard.held()));
  Stopwatch learning;
  const FeatureType type = info_.options.database.feature_type;
  LearningOptions learning_options = options.learning;
  if (learning_options.threads == 0) learning_options.threads = options.threads;
  VocabularyLearner learner(type, learning_options);
  // Every stored place's features, a chunk per shared hold; a place stored meanwhile may be
  // offered or not (the sample is of the places seen), a removed one is not.
  std::string resume = PlaceKey(0);
  for (bool more = true; more;) {
    PLACEDB_RETURN_IF_ERROR(Cancelled(options));
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::ReadOptions read;
    read.fill_cache = false;  // a full scan would only evict the verification working set
    std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator(read, storage_->cf(kFeatures)));
    size_t n = 0;
    for (it->Seek(resume); it->Valid() && n < kChunkPlaces; it->Next(), ++n) {
      auto id = DecodePlaceKey(it->key().ToStringView());
      if (!id.ok()) return id.status().WithContext("map '" + info_.name + "' features");
      ProcessedFrame frame;
      PLACEDB_RETURN_IF_ERROR(FrameOfStoredPlace(type, it->value().ToStringView(), *id, &frame)
                                  .WithContext("map '" + info_.name + "'"));
      PLACEDB_RETURN_IF_ERROR(learner.Offer(*id, frame.static_features));
      resume = PlaceKey(*id + 1);
      if (*id == kMaxPlaceId) break;
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(it->status(), "scanning features"));
    more = it->Valid() && n == kChunkPlaces;
  }
  PLACEDB_RETURN_IF_ERROR(Cancelled(options));
  auto learned = learner.Learn();
  if (!learned.ok()) return learned.status().WithContext("map '" + info_.name + "'");
  if (options.on_phase) options.on_phase(VocabularyPhase::kLearned);
  VocabularyRecord record;
  VocabularySource& source = record.current;
  source.origin = "learned";
  source.checksum = learned->vocabulary.checksum();
  source.branching = uint32_t(learned->vocabulary.branching());
  source.depth = uint32_t(learned->vocabulary.depth());
  source.words = learned->vocabulary.word_count();
  source.learned_unix_ms = NowUnixMs();
  source.places_offered = learned->places_offered;
  source.descriptors_offered = learned->descriptors_offered;
  source.places_sampled = learned->places_sampled;
  source.descriptors_sampled = learned->descriptors_sampled;
  source.learn_ms = learning.ElapsedMs();
  return SwitchVocabulary(std::move(learned->vocabulary), std::move(record), options);
}

Result<VocabularyRecord> PlaceMap::RevertVocabularyNow(const AdaptOptions& options) {
  SwitchGuard guard(switching_);
  PLACEDB_RETURN_IF_ERROR(MaySwitch(guard.held()));
  const VocabularyRecord now = info().vocabulary;
  if (!now.previous) {
    return Status::FailedPrecondition("map '" + info_.name +
                                      "' has no previous vocabulary: it never switched "
                                      "vocabularies");
  }
  std::string bytes;
  {
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    const rocksdb::Status s = storage_->db->Get({}, storage_->cf(kMeta),
                                                VocabularyBytesKey(now.previous->checksum), &bytes);
    if (s.IsNotFound()) {
      return Status::Corruption("map '" + info_.name + "': its previous vocabulary is missing");
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading the map's previous vocabulary"));
  }
  auto previous = AnyVocabulary::Parse(bytes);
  if (!previous.ok()) {
    return Status::Corruption("map '" + info_.name +
                              "': its stored previous vocabulary is "
                              "damaged: " +
                              previous.status().message());
  }
  if (previous->checksum() != now.previous->checksum) {
    return Status::Corruption("map '" + info_.name + "': its stored previous vocabulary (" +
                              previous->checksum_hex() + ") is not the one its record names");
  }
  if (options.on_phase) options.on_phase(VocabularyPhase::kLearned);
  VocabularyRecord record;
  record.current = *now.previous;
  return SwitchVocabulary(std::move(previous).value(), std::move(record), options);
}

Result<VocabularyRecord> PlaceMap::SwitchVocabulary(AnyVocabulary next, VocabularyRecord record,
                                                    const AdaptOptions& options) {
  Stopwatch clock;
  const FeatureType type = info_.options.database.feature_type;
  const int threads = options.threads > 0 ? options.threads
                                          : int(std::max(1u, std::thread::hardware_concurrency()));
  if (!next || next.feature_type() != type) {
    return Status::InvalidArgument("map '" + info_.name + "' needs a " + VocabularyKindName(type) +
                                   " vocabulary");
  }
  // The new index, beside the live one. Its payload store reads the map's families like the
  // live one's, but removes nothing from RocksDB until it is the map's.
  auto store = std::make_shared<RocksPayloadStore>(storage_.get(), type);
  store->set_erases(false);
  auto created = PlaceDatabase::Create(next, info_.options.database, store);
  if (!created.ok()) return created.status();
  std::shared_ptr<PlaceDatabase> fresh = std::move(created).value();
  // Read while no other switch can change them (this one holds switching_).
  const std::string previous_bytes = vocabulary_.Serialize();
  const std::string next_bytes = next.Serialize();
  const VocabularySource previous_source = info().vocabulary.current;

  uint64_t generation = 0;
  rocksdb::ColumnFamilyHandle* family = nullptr;
  {
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    generation = storage_->bow_generation.load() + 1;
    auto made = CreateGenerationFamily(*storage_, generation);
    if (!made.ok()) return made.status().WithContext("map '" + info_.name + "'");
    family = *made;
  }
  bool switched = false;
  struct Abandon {
    PlaceMap* map;
    uint64_t generation;
    const bool& switched;
    ~Abandon() {
      if (switched) return;
      ReaderLock alive(map->lifecycle_);
      if (!map->closed_) (void)DropGenerationFamily(*map->storage_, generation);
    }
  } abandon{this, generation, switched};

  // A stored place transformed with the new vocabulary (any thread), then (one thread) put in
  // the new family's batch and the new index.
  struct Reindexed {
    PlaceId id = 0;
    std::string features;
    std::shared_ptr<const PlaceRecord> record;
    ProcessedFrame frame;
    Status status;
  };
  const auto transform = [&](Reindexed* place) {
    place->status = FrameOfStoredPlace(type, place->features, place->id, &place->frame);
    place->frame.vocabulary_checksum = ~next.checksum();  // not this vocabulary's yet
    if (place->status.ok()) place->status = fresh->Retransform(&place->frame);
    place->features.clear();
  };
  const auto add = [&](Reindexed* place, rocksdb::WriteBatch* batch) -> Status {
    PLACEDB_RETURN_IF_ERROR(place->status.WithContext("map '" + info_.name + "'"));
    batch->Put(family, PlaceKey(place->id),
               EncodeBowWithDirect(place->frame.bow, place->frame.direct));
    return fresh->Restore(*place->record, place->frame.bow);
  };
  const auto reindex = [&](PlaceId id, std::string_view features, const PlaceRecord& place,
                           rocksdb::WriteBatch* batch) -> Status {
    Reindexed one{id, std::string(features), std::make_shared<const PlaceRecord>(place), {}, {}};
    transform(&one);
    return add(&one, batch);
  };
  const auto write = [&](rocksdb::WriteBatch* batch) -> Status {
    if (batch->Count() == 0) return Status::Ok();
    // Not synced: the switch's synced batch makes everything before it durable.
    return storage_->WriteError(storage_->db->Write(rocksdb::WriteOptions(), batch),
                                "re-indexing map '" + info_.name + "'");
  };

  // 1. Every place stored now, a chunk per shared hold. A place whose features are written but
  // which is not indexed yet (a write in flight) waits for the catch-up.
  std::string resume = PlaceKey(0);
  for (bool more = true; more;) {
    PLACEDB_RETURN_IF_ERROR(Cancelled(options));
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::ReadOptions read;
    read.fill_cache = false;
    std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator(read, storage_->cf(kFeatures)));
    std::vector<Reindexed> chunk;
    size_t n = 0;
    for (it->Seek(resume); it->Valid() && n < kChunkPlaces; it->Next(), ++n) {
      auto id = DecodePlaceKey(it->key().ToStringView());
      if (!id.ok()) return id.status().WithContext("map '" + info_.name + "' features");
      resume = PlaceKey(*id + 1);
      if (auto place = database_->Get(*id)) {
        chunk.push_back({*id, it->value().ToString(), std::move(place), {}, {}});
      }
      if (*id == kMaxPlaceId) break;
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(it->status(), "scanning features"));
    more = it->Valid() && n == kChunkPlaces;
    it.reset();
    ParallelFor(chunk.size(), threads, [&](size_t i, int) { transform(&chunk[i]); });
    rocksdb::WriteBatch batch;
    for (Reindexed& place : chunk) PLACEDB_RETURN_IF_ERROR(add(&place, &batch));
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }
  if (options.on_phase) options.on_phase(VocabularyPhase::kReindexed);

  // 2. What changed meanwhile: places indexed by the live map and not by the new one, and
  // places the new one has that the live map removed since. `batch` receives the new family's
  // changes. At most `limit` places per call.
  const auto catch_up = [&](rocksdb::WriteBatch* batch, size_t limit, size_t* changed)
                            REQUIRES_SHARED(lifecycle_) -> Status {
    const std::vector<PlaceId> live = database_->ListPlaces();
    const std::vector<PlaceId> built = fresh->ListPlaces();
    std::vector<PlaceId> missing, extra;
    std::set_difference(live.begin(), live.end(), built.begin(), built.end(),
                        std::back_inserter(missing));
    std::set_difference(built.begin(), built.end(), live.begin(), live.end(),
                        std::back_inserter(extra));
    *changed = 0;
    for (PlaceId id : extra) {
      if (*changed == limit) return Status::Ok();
      PLACEDB_RETURN_IF_ERROR(fresh->Remove(id));
      batch->Delete(family, PlaceKey(id));
      ++*changed;
    }
    for (PlaceId id : missing) {
      if (*changed == limit) return Status::Ok();
      auto place = database_->Get(id);
      if (!place) continue;  // removed since the listing
      std::string features;
      const rocksdb::Status s =
          storage_->db->Get({}, storage_->cf(kFeatures), PlaceKey(id), &features);
      if (s.IsNotFound()) {
        return Status::Corruption("map '" + info_.name + "': place " + std::to_string(id) +
                                  ": its features are missing (ScrubMap lists the places "
                                  "affected)");
      }
      PLACEDB_RETURN_IF_ERROR(FromRocks(s, "reading features of place " + std::to_string(id)));
      PLACEDB_RETURN_IF_ERROR(reindex(id, features, *place, batch));
      ++*changed;
    }
    return Status::Ok();
  };
  // Both vocabularies' bytes, before writers are held: the switch's batch then writes only the
  // generation, the record and the info (its sync makes these durable too).
  {
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::WriteBatch batch;
    batch.Put(storage_->cf(kMeta), VocabularyBytesKey(next.checksum()), next_bytes);
    batch.Put(storage_->cf(kMeta), VocabularyBytesKey(vocabulary_.checksum()), previous_bytes);
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }
  // Most of it with writers going on; then the rest with them held.
  for (size_t changed = kChunkPlaces; changed == kChunkPlaces;) {
    PLACEDB_RETURN_IF_ERROR(Cancelled(options));
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::WriteBatch batch;
    PLACEDB_RETURN_IF_ERROR(catch_up(&batch, kChunkPlaces, &changed));
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }

  // 3. Writers and readers held: the last places, then the switch in one synced batch.
  std::shared_ptr<PlaceDatabase> retired;  // freed after the hold ends
  PLACEDB_RETURN_IF_ERROR(Cancelled(options));
  WriterLock exclusive(lifecycle_);
  if (closed_) return Deleted();
  rocksdb::WriteBatch batch;
  size_t changed = 0;
  PLACEDB_RETURN_IF_ERROR(catch_up(&batch, SIZE_MAX, &changed));
  fresh->ReserveIdsBelow(database_->next_id());
  fresh->CountInvalid(database_->Stats().invalid_rejected);
  if (options.on_phase) options.on_phase(VocabularyPhase::kCaughtUp);

  record.generation = generation;
  record.previous = previous_source;
  record.since_unix_ms = NowUnixMs();
  record.places_reindexed = fresh->ListPlaces().size();
  record.reindex_ms = clock.ElapsedMs();
  MapInfo next_info = info();
  next_info.vocabulary_checksum = next.checksum();
  next_info.vocabulary = record;
  batch.Put(storage_->cf(kMeta), kVocabularyGenerationKey, U64Key(generation));
  batch.Put(storage_->cf(kMeta), kVocabularyRecordKey, EncodeVocabularyRecord(record));
  batch.Put(storage_->cf(kMeta), kInfoKey, EncodeInfo(next_info));
  PLACEDB_RETURN_IF_ERROR(storage_->Write(
      &batch, "switching map '" + info_.name + "' to vocabulary " + next.checksum_hex(),
      MapStorage::Kind::kAddition));
  switched = true;
  if (options.on_phase) options.on_phase(VocabularyPhase::kSwitched);

  storage_->active_bow = family;
  storage_->bow_generation = generation;
  store->set_erases(true);
  {
    MutexLock lock(state_mutex_);
    retired = std::move(database_);
    database_ = fresh;
    vocabulary_ = std::move(next);
    // Only the vocabulary's fields: the rest of info_ is read without the mutex.
    info_.vocabulary_checksum = next_info.vocabulary_checksum;
    info_.vocabulary = next_info.vocabulary;
  }
  // The previous generation's vectors: no reader can use them any more. A failure here only
  // leaves them for the next open to remove.
  if (generation > 1) {
    (void)DropGenerationFamily(*storage_, generation - 1);
  } else {
    (void)ClearFamily(*storage_, storage_->handles[kBow]);
  }
  // Vocabularies neither current nor previous (the one before the previous; one an interrupted
  // switch left).
  {
    std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator({}, storage_->cf(kMeta)));
    rocksdb::WriteBatch unused;
    const std::string keep[] = {VocabularyBytesKey(record.current.checksum),
                                VocabularyBytesKey(previous_source.checksum)};
    for (it->Seek(kVocabularyBytesPrefix);
         it->Valid() && it->key().starts_with(kVocabularyBytesPrefix); it->Next()) {
      if (it->key() != keep[0] && it->key() != keep[1])
        unused.Delete(storage_->cf(kMeta), it->key());
    }
    if (unused.Count() > 0) (void)storage_->db->Write(rocksdb::WriteOptions(), &unused);
  }
  if (options.on_phase) options.on_phase(VocabularyPhase::kCleaned);
  return record;
}

}  // namespace placedb
