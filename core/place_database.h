// PlaceDatabase: one in-memory place database (a "map") and the frame pipeline in front of it.
//
// A frame goes: extract (ORB, or the caller's precomputed features) -> filter (DC/SC by the
// dynamic objects) -> validity (|SC| > placeThreshold) -> transform (SC-only BoW vector and
// direct index) -> store or search -> verify. An invalid frame is neither stored nor matched;
// the result says why. DC descriptors are counted and dropped, never kept.
//
// Thread safety: any number of concurrent Query() calls together with Add()/Remove(). The
// expensive stages run outside any lock; only index mutation takes the writer lock and
// searching takes the reader lock. Verification reads immutable, shared place records.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <shared_mutex>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/bow.h"
#include "core/dynamic_filter.h"
#include "core/features.h"
#include "core/geometric_verifier.h"
#include "core/place_index.h"
#include "core/scoring.h"
#include "core/status.h"
#include "core/timing.h"
#include "core/vocabulary.h"

namespace placedb {

struct DatabaseConfig {
  OrbConfig orb;
  FilterConfig filter;
  // Boxes of these COCO classes at or above this confidence count as dynamic objects.
  std::vector<int> dynamic_classes = {0, 1, 2, 3, 5, 7};
  float min_box_confidence = 0.2f;
  ScoringType scoring = ScoringType::kL1;
  VerificationConfig verification;
};

Status ValidateDatabaseConfig(const DatabaseConfig& config);

struct Pose {
  std::array<double, 3> position{};               // x y z
  std::array<double, 4> orientation{0, 0, 0, 1};  // qx qy qz qw
  bool operator==(const Pose&) const = default;
};

struct PlaceMetadata {
  std::string agent_id;
  uint64_t sequence = 0;
  int64_t timestamp_ns = 0;
  std::optional<Pose> pose;
  bool operator==(const PlaceMetadata&) const = default;
};

// One frame as the engine sees it: an image, or precomputed features, plus dynamic objects.
struct Observation {
  cv::Mat image;                       // 8-bit gray or BGR; used when `features` is empty
  std::optional<FeatureSet> features;  // precomputed keypoints + descriptors (validated)
  DynamicObjects dynamic;
  PlaceMetadata metadata;
};

struct FrameCounts {
  uint32_t total = 0;           // descriptors extracted / given
  uint32_t dynamic = 0;         // DC: dropped
  uint32_t static_ = 0;         // SC: kept
  double dynamic_coverage = 0;  // fraction of the image's pixels on dynamic objects
};

// The outcome of extract + filter + transform for one frame.
struct ProcessedFrame {
  FrameCounts counts;
  bool valid = false;
  std::string rejection;       // why the frame is invalid; empty when valid
  FeatureSet static_features;  // SC only
  BowVector bow;               // SC only, normalised for the database's scoring
  DirectIndex direct;          // SC only, at verification.levels_up
  std::vector<DynamicBox> boxes_used;
  StageTimings timings;
};

// What the database keeps in memory per place: small, immutable once stored.
struct PlaceRecord {
  PlaceId id = 0;
  PlaceMetadata metadata;
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
};

// The bulky part of a place: what verification and removal need. Kept by a PayloadStore, so a
// persistent map can leave it on disk and read it only for the candidates it verifies.
struct PlacePayload {
  FeatureSet features;  // SC keypoints + descriptors
  DirectIndex direct;   // at the database's verification.levels_up
  BowVector bow;        // normalised for the database's scoring
};

// Where PlaceDatabase keeps payloads. Implementations must allow concurrent Get() calls with
// one Put()/Erase() at a time.
class PayloadStore {
 public:
  virtual ~PayloadStore() = default;
  // Called when a place is inserted. A persistent store that already wrote the payload (in the
  // same atomic batch as the place) may just cache or ignore it.
  virtual Status Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) = 0;
  // NOT_FOUND when the place is unknown (e.g. removed meanwhile).
  virtual Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const = 0;
  virtual Status Erase(PlaceId id) = 0;
  virtual size_t MemoryBytes() const = 0;
};

// The default: payloads in memory.
class InMemoryPayloadStore final : public PayloadStore {
 public:
  Status Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) override;
  Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const override;
  Status Erase(PlaceId id) override;
  size_t MemoryBytes() const override;

 private:
  mutable std::shared_mutex mutex_;
  std::unordered_map<PlaceId, std::shared_ptr<const PlacePayload>> payloads_;
  size_t bytes_ = 0;
};

size_t PayloadBytes(const PlacePayload& payload);

struct AddResult {
  bool stored = false;
  PlaceId id = 0;         // valid when stored
  std::string rejection;  // why not stored
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  StageTimings timings;
};

struct QueryOptions {
  size_t top_k = 10;
  bool verified_only = false;  // drop candidates that fail verification
  // Optional extra filter on candidates (e.g. exclude the agent's own recent places).
  std::function<bool(const PlaceRecord&)> accept;
};

struct Match {
  PlaceId place = 0;
  double score = 0;
  int inliers = 0;        // 0 when verification is disabled or not reached
  bool verified = false;  // true when inliers >= min_inliers (always false when disabled)
  PlaceMetadata metadata;
};

struct QueryResult {
  bool valid = false;
  std::string rejection;
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  std::vector<Match> matches;  // best first
  StageTimings timings;
};

struct DatabaseStats {
  size_t places = 0;
  uint64_t descriptors_kept = 0;     // SC descriptors of stored places
  uint64_t descriptors_dropped = 0;  // DC descriptors of stored places
  uint64_t invalid_rejected = 0;     // frames refused by Add() as invalid
  size_t index_bytes = 0;            // inverted index (postings + tables)
  size_t record_bytes = 0;           // in-memory place records (metadata, counts, boxes)
  size_t payload_bytes = 0;          // payloads the PayloadStore holds in memory
};

class PlaceDatabase {
 public:
  // INVALID_ARGUMENT for a bad config; the vocabulary is shared, never copied. Without a
  // payload store, payloads stay in memory.
  static Result<std::unique_ptr<PlaceDatabase>> Create(
      std::shared_ptr<const Vocabulary> vocabulary, DatabaseConfig config,
      std::shared_ptr<PayloadStore> payloads = nullptr);

  const DatabaseConfig& config() const { return config_; }
  const std::shared_ptr<const Vocabulary>& vocabulary() const { return vocabulary_; }

  // Extract, filter, validate and transform without touching the database.
  Result<ProcessedFrame> Process(const Observation& observation) const;

  // Processes and, when valid, stores the frame under a new id.
  Result<AddResult> Add(const Observation& observation);
  // Stores an already processed valid frame. With `id` given (restoring from storage) that id is
  // used: ALREADY_EXISTS if taken. Returns the id.
  Result<PlaceId> Insert(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                         std::optional<PlaceId> id = std::nullopt);
  // Re-indexes a stored place as a persistent map reloads it: the payload stays in the
  // PayloadStore, only the record and BoW vector are needed.
  Status Restore(PlaceRecord record, const BowVector& bow);
  // Reserves the id the next Insert() without an explicit id would take.
  PlaceId ReserveId();
  // Makes sure future ids are >= `next` (a reopened map never reuses a deleted place's id).
  void ReserveIdsBelow(PlaceId next);
  Status Remove(PlaceId id);  // NOT_FOUND if absent
  // Counts a frame refused as invalid (Add() does this itself).
  void CountInvalid(uint64_t frames = 1);

  Result<QueryResult> Query(const Observation& observation, const QueryOptions& options) const;
  // Searches with an already processed frame (used by ingest-with-matches).
  QueryResult Search(const ProcessedFrame& frame, const QueryOptions& options) const;

  std::shared_ptr<const PlaceRecord> Get(PlaceId id) const;  // nullptr if absent
  std::vector<PlaceId> ListPlaces() const;                   // ascending
  DatabaseStats Stats() const;
  PlaceId next_id() const;

 private:
  PlaceDatabase(std::shared_ptr<const Vocabulary> vocabulary, DatabaseConfig config,
                std::shared_ptr<PayloadStore> payloads);
  // Adds the record and its postings; caller holds the writer lock.
  Status InsertLocked(std::shared_ptr<const PlaceRecord> record, const BowVector& bow);
  void UndoInsertLocked(PlaceId id, const BowVector& bow);
  std::vector<DynamicBox> SelectBoxes(const std::vector<DynamicBox>& boxes) const;

  const std::shared_ptr<const Vocabulary> vocabulary_;
  const DatabaseConfig config_;
  const std::shared_ptr<PayloadStore> payloads_;

  mutable std::shared_mutex mutex_;
  InvertedIndex index_;
  std::unordered_map<PlaceId, std::shared_ptr<const PlaceRecord>> records_;
  PlaceId next_id_ = 1;
  uint64_t descriptors_kept_ = 0;
  uint64_t descriptors_dropped_ = 0;
  uint64_t invalid_rejected_ = 0;
  size_t record_bytes_ = 0;
};

}  // namespace placedb
