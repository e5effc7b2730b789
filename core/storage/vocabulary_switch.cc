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

std::string VocabularyPartKey(uint64_t checksum, uint32_t index) {
  char digits[16];
  std::snprintf(digits, sizeof digits, "%08u", index);
  return kVocabularyPartPrefix + Hex64(checksum) + "." + digits;
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
template <typename T>
Result<T> OnNiceThread(int nice, const std::function<Result<T>()>& work) {
  if (nice <= 0) return work();
  std::optional<Result<T>> result;
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
  return OnNiceThread<VocabularyRecord>(options.nice, [&] { return AdaptVocabularyNow(options); });
}

Result<VocabularyRecord> PlaceMap::RevertVocabulary(const AdaptOptions& options) {
  return OnNiceThread<VocabularyRecord>(options.nice, [&] { return RevertVocabularyNow(options); });
}

Result<MapLearnedVocabulary> PlaceMap::LearnVocabulary(const AdaptOptions& options) const {
  PLACEDB_RETURN_IF_ERROR(ValidateLearningOptions(options.learning));
  return OnNiceThread<MapLearnedVocabulary>(options.nice, [&]() -> Result<MapLearnedVocabulary> {
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
      std::unique_ptr<rocksdb::Iterator> it(
          storage_->db->NewIterator(read, storage_->cf(kFeatures)));
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
    MapLearnedVocabulary out;
    VocabularySource& source = out.source;
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
    out.vocabulary = std::move(learned->vocabulary);
    return out;
  });
}

Result<VocabularyRecord> PlaceMap::AdaptVocabularyNow(const AdaptOptions& options) {
  SwitchGuard guard(switching_);
  PLACEDB_RETURN_IF_ERROR(MaySwitch(guard.held()));
  AdaptOptions here = options;
  here.nice = 0;  // already on this thread
  auto learned = LearnVocabulary(here);
  if (!learned.ok()) return learned.status();
  if (options.on_phase) options.on_phase(VocabularyPhase::kLearned);
  VocabularyRecord record;
  record.current = learned->source;
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

Result<VocabularyRecord> PlaceMap::InstallVocabulary(AnyVocabulary vocabulary,
                                                     VocabularySource source,
                                                     const AdaptOptions& options) {
  if (!vocabulary || vocabulary.checksum() != source.checksum) {
    return Status::InvalidArgument("map '" + info_.name + "': the vocabulary to install is not " +
                                   "the one its source names (" + Hex64(source.checksum) + ")");
  }
  return OnNiceThread<VocabularyRecord>(options.nice, [&]() -> Result<VocabularyRecord> {
    SwitchGuard guard(switching_);
    PLACEDB_RETURN_IF_ERROR(MaySwitch(guard.held()));
    if (options.on_phase) options.on_phase(VocabularyPhase::kLearned);
    VocabularyRecord record;
    record.current = source;
    return SwitchVocabulary(std::move(vocabulary), std::move(record), options);
  });
}

// A switch being built: the new vocabulary, its BoW family and index beside the live ones.
// Dropped before it switched, it drops the family (a half-built family left by a crash is
// dropped by the next open).
struct PlaceMap::PreparedSwitch {
  PlaceMap* map = nullptr;
  AnyVocabulary next;
  std::shared_ptr<RocksPayloadStore> store;
  std::shared_ptr<PlaceDatabase> fresh;
  uint64_t generation = 0;
  rocksdb::ColumnFamilyHandle* family = nullptr;
  bool switched = false;
  double work_ms = 0;  // building and switching (not the wait for a prepared switch's record)
  ~PreparedSwitch() {
    if (switched || !family) return;
    ReaderLock alive(map->lifecycle_);
    if (!map->closed_) (void)DropGenerationFamily(*map->storage_, generation);
  }
};

Result<AnyVocabulary> PlaceMap::StoredVocabularyFor(uint64_t checksum, uint32_t parts,
                                                    const std::string& what) const {
  // The vocabulary's bytes: stored whole (the previous vocabulary: a revert), or its parts.
  std::string bytes;
  {
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    const rocksdb::Status whole =
        storage_->db->Get({}, storage_->cf(kMeta), VocabularyBytesKey(checksum), &bytes);
    if (whole.IsNotFound()) {
      if (parts == 0) return Status::Corruption(what + ": the map does not store that vocabulary");
      bytes.clear();
      for (uint32_t i = 0; i < parts; ++i) {
        std::string part;
        const rocksdb::Status s =
            storage_->db->Get({}, storage_->cf(kMeta), VocabularyPartKey(checksum, i), &part);
        if (s.IsNotFound()) {
          return Status::Corruption(what + ": part " + std::to_string(i) + " of " +
                                    std::to_string(parts) + " is missing");
        }
        PLACEDB_RETURN_IF_ERROR(FromRocks(s, what));
        bytes += part;
      }
    } else {
      PLACEDB_RETURN_IF_ERROR(FromRocks(whole, what));
    }
  }
  auto next = AnyVocabulary::Parse(bytes);
  if (!next.ok()) return Status::Corruption(what + ": " + next.status().message());
  if (next->checksum() != checksum) {
    return Status::Corruption(what + ": its bytes make vocabulary " + next->checksum_hex());
  }
  return next;
}

Status PlaceMap::ApplySwitch(uint64_t sequence, const MapLogRecord& change) {
  const VocabularySource& source = change.vocabulary_source;
  const std::string what = "applying record " + std::to_string(sequence) +
                           " (a switch to vocabulary " + Hex64(source.checksum) + ")";
  auto next = StoredVocabularyFor(source.checksum, change.vocabulary_parts, what);
  if (!next.ok()) return next.status();
  // A switch prepared while the records before this one were applied (PrepareVocabularySwitch):
  // only the places since are caught up now. A preparation still running is waited for.
  MutexLock prepared_lock(prepare_mutex_);
  PreparedSwitchPtr prepared = std::move(prepared_);
  prepared_checksum_ = 0;
  if (prepared && prepared->next.checksum() != source.checksum) prepared.reset();
  SwitchGuard guard(switching_);
  if (!guard.held()) return Status::FailedPrecondition(what + ": another switch is running");
  if (next->checksum() == vocabulary().checksum()) {
    // Already the map's (a repeated switch): only the applied sequence moves.
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::WriteBatch batch;
    batch.Put(storage_->cf(kMeta), kAppliedSequenceKey, U64Key(sequence));
    PLACEDB_RETURN_IF_ERROR(storage_->Write(&batch, what, MapStorage::Kind::kAddition));
    applied_sequence_ = sequence;
    return Status::Ok();
  }
  AdaptOptions options;  // one thread at nice 10, as a single server's switch
  VocabularyRecord record;
  record.current = source;
  auto switched = OnNiceThread<VocabularyRecord>(options.nice, [&]() -> Result<VocabularyRecord> {
    if (prepared) return FinishSwitch(*prepared, std::move(record), options, sequence);
    return SwitchVocabulary(std::move(next).value(), std::move(record), options, sequence);
  });
  return switched.status().WithContext(what);
}

namespace {

// A stored place transformed with the new vocabulary (any thread), then (one thread) put in the
// new family's batch and the new index.
struct Reindexed {
  PlaceId id = 0;
  std::string features;
  std::shared_ptr<const PlaceRecord> record;
  ProcessedFrame frame;
  Status status;
};

void TransformPlace(FeatureType type, const PlaceDatabase& fresh, uint64_t checksum,
                    Reindexed* place) {
  place->status = FrameOfStoredPlace(type, place->features, place->id, &place->frame);
  place->frame.vocabulary_checksum = ~checksum;  // not this vocabulary's yet
  if (place->status.ok()) place->status = fresh.Retransform(&place->frame);
  place->features.clear();
}

Status AddReindexed(const std::string& name, PlaceDatabase& fresh,
                    rocksdb::ColumnFamilyHandle* family, Reindexed* place,
                    rocksdb::WriteBatch* batch) {
  PLACEDB_RETURN_IF_ERROR(place->status.WithContext("map '" + name + "'"));
  batch->Put(family, PlaceKey(place->id),
             EncodeBowWithDirect(place->frame.bow, place->frame.direct));
  return fresh.Restore(*place->record, place->frame.bow);
}

}  // namespace

void PlaceMap::PreparedSwitchDeleter::operator()(PreparedSwitch* build) const {
  delete build;
}

Result<PlaceMap::PreparedSwitchPtr> PlaceMap::BeginSwitch(AnyVocabulary next) {
  const FeatureType type = info_.options.database.feature_type;
  if (!next || next.feature_type() != type) {
    return Status::InvalidArgument("map '" + info_.name + "' needs a " + VocabularyKindName(type) +
                                   " vocabulary");
  }
  PreparedSwitchPtr build(new PreparedSwitch());
  build->map = this;
  // The new index, beside the live one. Its payload store reads the map's families like the
  // live one's, but removes nothing from RocksDB until it is the map's.
  build->store = std::make_shared<RocksPayloadStore>(storage_.get(), type);
  build->store->set_erases(false);
  auto created = PlaceDatabase::Create(next, info_.options.database, build->store);
  if (!created.ok()) return created.status();
  build->fresh = std::move(created).value();
  build->next = std::move(next);
  ReaderLock alive(lifecycle_);
  if (closed_) return Deleted();
  build->generation = storage_->bow_generation.load() + 1;
  auto made = CreateGenerationFamily(*storage_, build->generation);
  if (!made.ok()) return made.status().WithContext("map '" + info_.name + "'");
  build->family = *made;
  return build;
}

Status PlaceMap::CatchUp(PreparedSwitch& build, rocksdb::WriteBatch* batch, size_t limit,
                         size_t* changed) {
  // Places indexed by the live map and not by the new one, and places the new one has that
  // the live map removed since.
  const std::vector<PlaceId> live = database_->ListPlaces();
  const std::vector<PlaceId> built = build.fresh->ListPlaces();
  std::vector<PlaceId> missing, extra;
  std::set_difference(live.begin(), live.end(), built.begin(), built.end(),
                      std::back_inserter(missing));
  std::set_difference(built.begin(), built.end(), live.begin(), live.end(),
                      std::back_inserter(extra));
  *changed = 0;
  for (PlaceId id : extra) {
    if (*changed == limit) return Status::Ok();
    PLACEDB_RETURN_IF_ERROR(build.fresh->Remove(id));
    batch->Delete(build.family, PlaceKey(id));
    ++*changed;
  }
  const FeatureType type = info_.options.database.feature_type;
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
    Reindexed one{id, std::move(features), std::move(place), {}, {}};
    TransformPlace(type, *build.fresh, build.next.checksum(), &one);
    PLACEDB_RETURN_IF_ERROR(AddReindexed(info_.name, *build.fresh, build.family, &one, batch));
    ++*changed;
  }
  return Status::Ok();
}

Status PlaceMap::BuildSwitch(PreparedSwitch& build, const AdaptOptions& options) {
  Stopwatch clock;
  struct Count {
    PreparedSwitch& build;
    Stopwatch& clock;
    ~Count() { build.work_ms += clock.ElapsedMs(); }
  } count{build, clock};
  const FeatureType type = info_.options.database.feature_type;
  const int threads = options.threads > 0 ? options.threads
                                          : int(std::max(1u, std::thread::hardware_concurrency()));
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
    ParallelFor(chunk.size(), threads, [&](size_t i, int) {
      TransformPlace(type, *build.fresh, build.next.checksum(), &chunk[i]);
    });
    rocksdb::WriteBatch batch;
    for (Reindexed& place : chunk) {
      PLACEDB_RETURN_IF_ERROR(AddReindexed(info_.name, *build.fresh, build.family, &place, &batch));
    }
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }
  if (options.on_phase) options.on_phase(VocabularyPhase::kReindexed);

  // 2. Both vocabularies' bytes, before writers are held: the switch's batch then writes only
  // the generation, the record and the info (its sync makes these durable too). Then what
  // changed meanwhile, with writers going on, a chunk per shared hold.
  {
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::WriteBatch batch;
    batch.Put(storage_->cf(kMeta), VocabularyBytesKey(build.next.checksum()),
              build.next.Serialize());
    batch.Put(storage_->cf(kMeta), VocabularyBytesKey(vocabulary_.checksum()),
              vocabulary_.Serialize());
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }
  for (size_t changed = kChunkPlaces; changed == kChunkPlaces;) {
    PLACEDB_RETURN_IF_ERROR(Cancelled(options));
    ReaderLock alive(lifecycle_);
    if (closed_) return Deleted();
    rocksdb::WriteBatch batch;
    PLACEDB_RETURN_IF_ERROR(CatchUp(build, &batch, kChunkPlaces, &changed));
    PLACEDB_RETURN_IF_ERROR(write(&batch));
  }
  return Status::Ok();
}

Result<VocabularyRecord> PlaceMap::SwitchVocabulary(AnyVocabulary next, VocabularyRecord record,
                                                    const AdaptOptions& options,
                                                    std::optional<uint64_t> at_sequence) {
  auto build = BeginSwitch(std::move(next));
  if (!build.ok()) return build.status();
  PLACEDB_RETURN_IF_ERROR(BuildSwitch(**build, options));
  return FinishSwitch(**build, std::move(record), options, at_sequence);
}

Result<VocabularyRecord> PlaceMap::FinishSwitch(PreparedSwitch& build, VocabularyRecord record,
                                                const AdaptOptions& options,
                                                std::optional<uint64_t> at_sequence) {
  Stopwatch clock;
  const VocabularySource previous_source = info().vocabulary.current;
  const std::shared_ptr<PlaceDatabase>& fresh = build.fresh;
  AnyVocabulary& next = build.next;
  const uint64_t generation = build.generation;
  // 3. Writers and readers held: the last places, then the switch in one synced batch.
  std::shared_ptr<PlaceDatabase> retired;  // freed after the hold ends
  PLACEDB_RETURN_IF_ERROR(Cancelled(options));
  WriterLock exclusive(lifecycle_);
  if (closed_) return Deleted();
  rocksdb::WriteBatch batch;
  size_t changed = 0;
  PLACEDB_RETURN_IF_ERROR(CatchUp(build, &batch, SIZE_MAX, &changed));
  fresh->ReserveIdsBelow(database_->next_id());
  fresh->CountInvalid(database_->Stats().invalid_rejected);
  if (options.on_phase) options.on_phase(VocabularyPhase::kCaughtUp);

  record.generation = generation;
  record.previous = previous_source;
  record.since_unix_ms = NowUnixMs();
  record.places_reindexed = fresh->ListPlaces().size();
  record.reindex_ms = build.work_ms + clock.ElapsedMs();
  MapInfo next_info = info();
  next_info.vocabulary_checksum = next.checksum();
  next_info.vocabulary = record;
  batch.Put(storage_->cf(kMeta), kVocabularyGenerationKey, U64Key(generation));
  batch.Put(storage_->cf(kMeta), kVocabularyRecordKey, EncodeVocabularyRecord(record));
  batch.Put(storage_->cf(kMeta), kInfoKey, EncodeInfo(next_info));
  if (at_sequence) {
    batch.Put(storage_->cf(kMeta), kAppliedSequenceKey, U64Key(*at_sequence));
    // Its parts: the vocabulary's bytes are stored whole now.
    const std::string prefix = kVocabularyPartPrefix + Hex64(next.checksum()) + ".";
    std::unique_ptr<rocksdb::Iterator> it(storage_->db->NewIterator({}, storage_->cf(kMeta)));
    for (it->Seek(prefix); it->Valid() && it->key().starts_with(prefix); it->Next()) {
      batch.Delete(storage_->cf(kMeta), it->key());
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(it->status(), "listing the vocabulary's parts"));
  }
  PLACEDB_RETURN_IF_ERROR(storage_->Write(
      &batch, "switching map '" + info_.name + "' to vocabulary " + next.checksum_hex(),
      MapStorage::Kind::kAddition));
  build.switched = true;
  if (options.on_phase) options.on_phase(VocabularyPhase::kSwitched);

  storage_->active_bow = build.family;
  storage_->bow_generation = generation;
  build.store->set_erases(true);
  {
    MutexLock lock(state_mutex_);
    retired = std::move(database_);
    database_ = fresh;
    vocabulary_ = std::move(next);
    // Only the vocabulary's fields: the rest of info_ is read without the mutex.
    info_.vocabulary_checksum = next_info.vocabulary_checksum;
    info_.vocabulary = next_info.vocabulary;
  }
  if (at_sequence) {
    database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(*at_sequence + 1, kMaxPlaceId)));
    applied_sequence_ = *at_sequence;
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

Status PlaceMap::PrepareVocabularySwitch(uint64_t checksum, uint32_t parts) {
  MutexLock apply(prepare_mutex_);
  // The parts, as ApplySwitch reads them.
  auto next = StoredVocabularyFor(checksum, parts, "preparing vocabulary " + Hex64(checksum));
  if (!next.ok()) return next.status();
  SwitchGuard guard(switching_);
  if (!guard.held()) {
    return Status::FailedPrecondition("map '" + info_.name + "' is already switching");
  }
  if (next->checksum() == vocabulary().checksum()) return Status::Ok();
  auto build = BeginSwitch(std::move(next).value());
  if (!build.ok()) return build.status();
  AdaptOptions options;  // one thread at nice 10
  options.cancel = &prepare_cancel_;
  PLACEDB_RETURN_IF_ERROR(OnNiceThread<bool>(options.nice, [&]() -> Result<bool> {
                            PLACEDB_RETURN_IF_ERROR(BuildSwitch(**build, options));
                            return true;
                          }).status());
  prepared_ = std::move(build).value();
  prepared_checksum_ = checksum;
  return Status::Ok();
}

void PlaceMap::CancelPreparedSwitch() {
  prepare_cancel_ = true;
  MutexLock apply(prepare_mutex_);
  prepared_.reset();
  prepared_checksum_ = 0;
  prepare_cancel_ = false;
}

}  // namespace placedb
