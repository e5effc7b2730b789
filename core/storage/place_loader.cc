// Opening a map: PlaceMap::Load rebuilds the serving index from the `places` and `bow` column
// families, sequentially or by ranges of ids read and built by worker threads (PlaceLoader).
#include <rocksdb/db.h>

#include <algorithm>
#include <atomic>
#include <functional>
#include <optional>
#include <system_error>
#include <thread>
#include <vector>

#include "core/base/thread_annotations.h"
#include "core/base/timing.h"
#include "core/storage/loop_log.h"
#include "core/storage/map_storage.h"
#include "core/storage/map_store.h"

namespace placedb {

// The storage internals (map_storage.h) and their helpers, unqualified as in the rest of the
// module.
using namespace detail;

namespace {

// One place as Load reads it back: its record and BoW vector, checked against each other.
struct LoadedPlace {
  PlaceRecord record;
  BowVector bow;
};

// Reads the `places` and `bow` families for PlaceMap::Load, with every check Load makes: each
// record has a BoW vector under the same key, its key is its id, no BoW vector lacks a record,
// both decode; an unreadable block is the iterator's error (RocksDB names the file). Either one
// scan of the whole key range restoring place by place (LoadSequential), or ranges of place ids
// read, decoded and built into index segments by worker threads while the calling thread
// installs them in id order (LoadSegments). Both rebuild the same database and stop at the same
// first problem.
class PlaceLoader {
 public:
  using Visit = std::function<Status(LoadedPlace&&)>;

  PlaceLoader(const MapStorage& storage, const std::string& map_name)
      : storage_(storage),
        map_name_(map_name),
        range_ids_(std::min(storage.load_range_ids, PlaceId(1) << InvertedIndex::kSegmentBits)) {
    options_.fill_cache = false;  // a full scan would only evict the verification working set
  }

  // `read_ms` receives the time spent reading and decoding (outside `visit`).
  Status LoadSequential(const Visit& visit, double* read_ms) const {
    Stopwatch clock;
    double visiting = 0;
    const auto timed = [&](LoadedPlace&& place) {
      Stopwatch inside;
      Status status = visit(std::move(place));
      visiting += inside.ElapsedMs();
      return status;
    };
    Iterators its = NewIterators();
    Status status = ReadRange(its, std::nullopt, std::nullopt, timed);
    *read_ms += clock.ElapsedMs() - visiting;
    return status;
  }

  // The bulk path: `workers` threads each read and decode the places of a range of
  // load_range_ids ids (aligned; by default one whole index segment, 2^16 ids) and build its
  // part of the index (PlaceDatabase::PrepareRestore); the calling thread installs the ranges in
  // id order (PlaceDatabase::RestoreRange). At most kRangeWindow ranges are read ahead of the
  // one being installed: a full segment of a 1M-place map is ~370 MB of decoded vectors plus
  // its postings. The first problem in id order is the one reported, as LoadSequential would:
  // a place PrepareRestore refuses comes before the read problem that ended its segment.
  // `read_ms` and `build_ms` receive the workers' times, summed; `install_ms` the calling
  // thread's.
  Status LoadSegments(unsigned workers, PlaceDatabase& database, double* read_ms, double* build_ms,
                      double* install_ms) const {
    std::optional<PlaceId> first, last;
    FirstAndLast(&first, &last);
    const auto restore_one = [&](LoadedPlace&& place) {
      Stopwatch installing;
      Status restored = database.Restore(std::move(place.record), place.bow);
      *install_ms += installing.ElapsedMs();
      return restored;
    };
    // An empty family or a key that is not a place id: one scan reports it as it always has.
    if (!first || !last || *last < *first) return LoadSequential(restore_one, read_ms);
    struct Built {
      Result<PlaceDatabase::RestoredSegment> prepared = Status::Internal("not read");
      Status read_status = Status::Ok();  // the first problem, found after the places read
    };
    std::vector<double> worker_read_ms(workers, 0.0), worker_build_ms(workers, 0.0);
    bool started = false;
    Status status = RunRangesInOrder<Built>(
        *first, *last, range_ids_, workers, kRangeWindow,
        [&](Iterators& its, std::optional<PlaceId> begin, std::optional<PlaceId> end,
            unsigned worker) -> Built {
          Stopwatch clock;
          std::vector<PlaceRecord> records;
          std::vector<BowVector> bows;
          Built built;
          built.read_status = ReadRange(its, begin, end, [&](LoadedPlace&& place) {
            records.push_back(std::move(place.record));
            bows.push_back(std::move(place.bow));
            return Status::Ok();
          });
          worker_read_ms[worker] += clock.ElapsedMs();
          Stopwatch building;
          built.prepared = database.PrepareRestore(std::move(records), bows);
          worker_build_ms[worker] += building.ElapsedMs();
          return built;  // the decoded vectors are freed here: the index holds the postings
        },
        [&](Built&& built) -> Status {
          if (!built.prepared.ok()) return built.prepared.status();
          Stopwatch installing;
          Status installed = database.RestoreRange(std::move(built.prepared).value());
          *install_ms += installing.ElapsedMs();
          PLACEDB_RETURN_IF_ERROR(installed);
          return built.read_status;
        },
        &started);
    if (!started) return LoadSequential(restore_one, read_ms);
    for (double ms : worker_read_ms) *read_ms += ms;
    for (double ms : worker_build_ms) *build_ms += ms;
    return status;
  }

 private:
  // Ranges read and built ahead of the one being installed.
  static constexpr size_t kRangeWindow = 2;

  struct Iterators {
    std::unique_ptr<rocksdb::Iterator> places, bows;
  };

  // The first and last keys of `places` as ids (nullopt: none, or not a place id).
  void FirstAndLast(std::optional<PlaceId>* first, std::optional<PlaceId>* last) const {
    Iterators its = NewIterators();
    its.places->SeekToFirst();
    if (its.places->Valid()) *first = KeyId(its.places->key());
    its.places->SeekToLast();
    if (its.places->Valid()) *last = KeyId(its.places->key());
  }

  // Cuts [first, last] into ranges of `range_ids` aligned ids (the first range has no lower
  // bound and the last no upper bound, so every key is in exactly one range); `workers`
  // threads run `produce(iterators, begin, end, worker)` on them, at most `window` ranges ahead
  // of the one `consume` is taking; `consume` runs on the calling thread, in range order, until
  // it returns an error (returned). `*started` is false when no thread could be started
  // (nothing was consumed then).
  template <typename Produced, typename Produce, typename Consume>
  Status RunRangesInOrder(PlaceId first, PlaceId last, PlaceId range_ids, unsigned workers,
                          size_t window, const Produce& produce, const Consume& consume,
                          bool* started) const {
    const size_t base = first / range_ids;
    const size_t ranges = last / range_ids - base + 1;
    const auto begin_of = [&](size_t r) -> std::optional<PlaceId> {
      if (r == 0 || r >= ranges) return std::nullopt;
      return PlaceId((base + r) * range_ids);
    };
    std::vector<std::optional<Produced>> results(ranges);
    Mutex mutex;
    CondVar changed;
    size_t consuming = 0;  // guarded by mutex
    bool stop = false;     // guarded by mutex
    std::atomic<size_t> next{0};
    const auto work = [&](unsigned worker) {
      Iterators its = NewIterators();
      for (size_t r; (r = next.fetch_add(1)) < ranges;) {
        {
          MutexLock lock(mutex);
          while (!stop && r >= consuming + window) changed.Wait(mutex);
          if (stop) return;
        }
        Produced produced = produce(its, begin_of(r), begin_of(r + 1), worker);
        MutexLock lock(mutex);
        results[r] = std::move(produced);
        changed.NotifyAll();
      }
    };
    std::vector<std::thread> pool;
    for (unsigned w = 0; w < workers; ++w) {
      try {
        pool.emplace_back(work, w);
      } catch (const std::system_error&) {
        break;  // fewer workers than asked: they still take every range
      }
    }
    *started = !pool.empty();
    if (pool.empty()) return Status::Ok();
    Status status = Status::Ok();
    for (size_t r = 0; r < ranges && status.ok(); ++r) {
      std::optional<Produced> produced;
      {
        MutexLock lock(mutex);
        while (!results[r]) changed.Wait(mutex);
        produced = std::move(results[r]);
        results[r].reset();
        consuming = r + 1;
        changed.NotifyAll();
      }
      status = consume(std::move(*produced));
    }
    {
      MutexLock lock(mutex);
      stop = true;
      changed.NotifyAll();
    }
    for (std::thread& thread : pool) thread.join();
    return status;
  }

  Iterators NewIterators() const {
    return {
        std::unique_ptr<rocksdb::Iterator>(
            storage_.db->NewIterator(options_, storage_.cf(kPlaces))),
        std::unique_ptr<rocksdb::Iterator>(storage_.db->NewIterator(options_, storage_.cf(kBow)))};
  }

  static std::optional<PlaceId> KeyId(const rocksdb::Slice& key) {
    auto id = DecodePlaceKey(key.ToStringView());
    if (!id.ok()) return std::nullopt;
    return *id;
  }

  // The places with keys in [begin, end) (nullopt: unbounded), in key order.
  Status ReadRange(Iterators& its, std::optional<PlaceId> begin, std::optional<PlaceId> end,
                   const Visit& visit) const {
    const std::string end_key = end ? PlaceKey(*end) : std::string();
    const auto in_range = [&](const rocksdb::Slice& key) {
      return !end || key.compare(rocksdb::Slice(end_key)) < 0;
    };
    rocksdb::Iterator& places = *its.places;
    rocksdb::Iterator& bows = *its.bows;
    if (begin) {
      const std::string begin_key = PlaceKey(*begin);
      places.Seek(begin_key);
      bows.Seek(begin_key);
    } else {
      places.SeekToFirst();
      bows.SeekToFirst();
    }
    for (; places.Valid() && in_range(places.key()); places.Next(), bows.Next()) {
      // An unreadable block ends an iterator: report it (it names the file), not a missing
      // vector.
      PLACEDB_RETURN_IF_ERROR(FromRocks(bows.status(), "scanning BoW vectors"));
      if (!bows.Valid() || places.key() != bows.key()) {
        return Status::Corruption("map '" + map_name_ + "': place " + places.key().ToString(true) +
                                  " has no BoW vector");
      }
      // A value that does not decode is named by its place (its key, as above).
      auto record = DecodePlaceRecord(places.value().ToStringView());
      if (!record.ok()) {
        return record.status().WithContext("map '" + map_name_ + "': place " +
                                           places.key().ToString(true));
      }
      auto bow = DecodeBow(bows.value().ToStringView());
      if (!bow.ok()) {
        return bow.status().WithContext("map '" + map_name_ + "': place " +
                                        places.key().ToString(true));
      }
      auto key = DecodePlaceKey(places.key().ToStringView());
      if (!key.ok() || *key != record->id) {
        return Status::Corruption("map '" + map_name_ + "': place key and record disagree");
      }
      PLACEDB_RETURN_IF_ERROR(visit({std::move(record).value(), std::move(bow).value()}));
    }
    PLACEDB_RETURN_IF_ERROR(FromRocks(places.status(), "scanning places"));
    if (bows.Valid() && in_range(bows.key())) {
      return Status::Corruption("map '" + map_name_ + "': BoW vector without a place record");
    }
    return FromRocks(bows.status(), "scanning BoW vectors");
  }

  const MapStorage& storage_;
  const std::string& map_name_;
  const PlaceId range_ids_;  // a power of two <= 2^16: a range lies in one index segment
  rocksdb::ReadOptions options_;
};

}  // namespace

Status PlaceMap::Load() {
  Stopwatch total;
  auto loops = LoopLog::Open(storage_->db.get(), storage_->cf(kLoops));
  if (!loops.ok()) return loops.status().WithContext("map '" + info_.name + "'");
  loops_ = std::move(loops).value();
  auto db = PlaceDatabase::Create(
      vocabulary_, info_.options.database,
      std::make_shared<RocksPayloadStore>(storage_.get(), info_.options.database.feature_type));
  if (!db.ok()) return db.status();
  database_ = std::move(db).value();
  rocksdb::ReadOptions options;
  options.fill_cache = false;  // a full scan would only evict the verification working set
  open_timings_ = OpenTimings();
  open_timings_.threads = storage_->load_threads;
  PlaceLoader loader(*storage_, info_.name);
  const auto restore = [&](LoadedPlace&& place) {
    Stopwatch indexing;
    Status restored = database_->Restore(std::move(place.record), place.bow);
    open_timings_.index_ms += indexing.ElapsedMs();
    return restored;
  };
  // More than one thread: whole index segments are read, decoded and built by load_threads
  // workers (the opening thread only installs them); one: the scan of today, place by place.
  PLACEDB_RETURN_IF_ERROR(
      storage_->load_threads > 1
          ? loader.LoadSegments(storage_->load_threads, *database_, &open_timings_.read_decode_ms,
                                &open_timings_.index_ms, &open_timings_.index_ms)
          : loader.LoadSequential(restore, &open_timings_.read_decode_ms));
  open_timings_.total_ms = total.ElapsedMs();

  std::string value;
  if (storage_->db->Get({}, storage_->cf(kMeta), kIdFloorKey, &value).ok()) {
    auto floor = DecodePlaceKey(value);
    if (!floor.ok()) return floor.status().WithContext("map '" + info_.name + "' id floor");
    database_->ReserveIdsBelow(*floor);
  }
  if (storage_->db->Get({}, storage_->cf(kMeta), kAppliedSequenceKey, &value).ok()) {
    auto applied = DecodeU64Key(value);
    if (!applied.ok())
      return applied.status().WithContext("map '" + info_.name + "' applied sequence");
    applied_sequence_ = *applied;
    database_->ReserveIdsBelow(PlaceId(std::min<uint64_t>(*applied + 1, kMaxPlaceId)));
  }
  if (storage_->db->Get({}, storage_->cf(kMeta), kInvalidCountKey, &value).ok()) {
    rocksdb::Slice slice(value);
    database_->CountInvalid(CounterMergeOperator::Decode(&slice));
  }
  std::unique_ptr<rocksdb::Iterator> invalid(
      storage_->db->NewIterator(options, storage_->cf(kInvalid)));
  invalid->SeekToLast();
  if (invalid->Valid()) {
    auto serial = DecodeU64Key(invalid->key().ToStringView());
    if (!serial.ok()) return serial.status().WithContext("invalid-observation log");
    storage_->next_invalid_serial = *serial + 1;
    uint64_t count = 0;
    for (invalid->SeekToFirst(); invalid->Valid(); invalid->Next()) ++count;
    storage_->invalid_stored = count;
  }
  return FromRocks(invalid->status(), "scanning invalid observations");
}

}  // namespace placedb
