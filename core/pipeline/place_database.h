// PlaceDatabase: one in-memory place database (a "map") and the frame pipeline in front of it.
//
// A frame goes: extract (the map's FeatureExtractor, ORB or SIFT, or the caller's precomputed
// LocalFeatures) -> [depth: refine the dynamic boxes to the objects' depth layers] -> filter (DC/SC
// by the dynamic objects) -> [depth, stream frames: Algorithm 1 of Deng et al. for the agent's
// stream, AdvanceStream()] -> validity (|SC| > placeThreshold) -> transform (SC-only BoW vector
// and direct index) -> store or search -> verify -> [loop closure for the agent's stream,
// CloseLoop()]. An invalid frame is neither stored nor matched; the result says why. DC
// descriptors, and those Algorithm 1 removes, are counted and dropped, never kept.
//
// Per-agent state (core/pipeline/agent_streams.h): Algorithm 1 and the Bayesian loop-closure
// detector need the agent's frames in order, so they run in AdvanceStream() / CloseLoop(), which
// the caller invokes in each agent's sequence order; everything else is stateless and parallel.
//
// Thread safety: any number of concurrent Query() calls together with Add()/Remove(). The
// expensive stages run outside any lock; only index mutation takes the writer lock and
// searching takes the reader lock. Verification reads immutable, shared place records. Calls
// for one agent stream serialise on that stream's own mutex.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "core/base/timing.h"
#include "core/features/local_features.h"
#include "core/filter/box_masks.h"
#include "core/filter/depth_filter.h"
#include "core/filter/dynamic_filter.h"
#include "core/pose/camera.h"
#include "core/pose/relative_pose.h"
#include "core/search/geometric_verifier.h"
#include "core/search/loop_closure.h"
#include "core/search/place_index.h"
#include "core/search/scoring.h"
#include "core/thumbnail/thumbnail.h"
#include "core/vocabulary/any_vocabulary.h"
#include "core/vocabulary/bow.h"
#include "core/vocabulary/vocabulary.h"

namespace placedb {

// What a map does with depth (docs/rgbd.md). Only frames that carry depth are affected.
struct DepthConfig {
  // Inside a dynamic box only the object's own depth layer is dynamic (beyond the paper).
  bool refine_boxes = true;
  RefineConfig refine;
  // Algorithm 1 on each agent's stream of frames with depth (AdvanceStream()).
  bool stream_filter = true;
  DepthFilterConfig filter;  // filter.format: default scale and valid range of depth images
};

Status ValidateDepthConfig(const DepthConfig& config);

// The short-term tier: Munoz & Dexter's own limit (their Figs. 8-9) is that the objects the filter
// drops are often still there on a short revisit (parked cars, a queue of people), where they are
// evidence of the place. The tier keeps each place's DC (dynamic) words, in memory only and never
// on disk (the durable map keeps SC alone), for a horizon. A query scores a place observed within
// the horizon of the query's timestamp on its SC words plus `weight` x the similarity of the two
// frames' DC words, each set normalised on its own, so different objects add only noise while
// the same objects add evidence. The DC similarity counts as much as the DC descriptors' share
// of the frames would give it in one joint vector (x b / (1 - b), b = the smaller of the two
// frames' DC shares): a frame with a few DC descriptors gets a small bonus, however alike they
// are. Verification against a place inside the horizon matches the SC and DC features of both
// frames (ORB maps): objects both frames saw add inliers, different objects add none. Older
// places, and frames without a timestamp, are scored and verified on SC words alone. The tier holds
// each agent's places of the last `horizon_ns` (counted back from that agent's newest timestamp),
// at most `max_places` in all (the oldest leave first); it starts empty when a map is opened.
struct ShortTermConfig {
  bool enabled = true;
  int64_t horizon_ns = 60'000'000'000;  // 60 s
  uint32_t max_places = 5000;
  float weight = 1.0f;
};

Status ValidateShortTermConfig(const ShortTermConfig& config);

struct DatabaseConfig {
  // The map's feature type; must be the vocabulary's (binary -> ORB, float -> SIFT).
  FeatureType feature_type = FeatureType::kOrb;
  OrbConfig orb;
  SiftConfig sift;
  FilterConfig filter;
  // Boxes are narrowed to their objects' pixels before filtering (frames without depth; with
  // depth, `depth.refine_boxes` applies instead).
  BoxRefinementConfig box_refinement;
  // ORB from pixels with dynamic objects known (no depth): detect `orb.max_features` on the
  // static pixels (plus an area share on the objects for the short-term tier) instead of on the
  // whole frame, so filtering does not shrink the place's static features.
  bool static_feature_budget = true;
  ShortTermConfig short_term;
  // Boxes of these COCO classes at or above this confidence count as dynamic objects.
  std::vector<int> dynamic_classes = {0, 1, 2, 3, 5, 7};
  float min_box_confidence = 0.2f;
  ScoringType scoring = ScoringType::kL1;
  VerificationConfig verification;
  DepthConfig depth;
  // The Bayesian loop closure of CloseLoop(); its scoring is always the database's.
  LoopClosureConfig loop_closure;
  // A loop the filter accepts is kept only if the frame verifies geometrically against the
  // loop's stored place (`verification`, exhaustive when its mode is disabled; min_inliers).
  bool verify_loops = true;
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

// A depth image registered to the colour image (same aspect ratio; it may be smaller).
struct DepthObservation {
  cv::Mat raw;  // CV_16U (units of metres_per_unit) or CV_32F
  // Overrides the map's depth format for this frame (metres per unit of `raw`).
  std::optional<double> metres_per_unit;
  std::optional<CameraIntrinsics> intrinsics;  // of the colour image
};

// One frame as the engine sees it: an image, or precomputed features, plus dynamic objects and
// optionally depth and the camera.
struct Observation {
  cv::Mat image;  // 8-bit gray or BGR; used when no precomputed features are given
  // Precomputed features (validated), of the map's feature type.
  std::optional<LocalFeatures> features;
  std::optional<DepthObservation> depth;
  DynamicObjects dynamic;
  PlaceMetadata metadata;
  // The camera that took the frame (issue 32): what a match's relative pose needs. Width and
  // height 0 mean the frame's size; otherwise they must be the frame's. Without it, the depth's
  // intrinsics (a pinhole camera) are used when given.
  std::optional<Camera> camera;
};

// What a relative pose needs of a frame or a stored place besides its keypoints (issue 32): the
// camera, and the depth (z along the optical axis, metres; 0 = none) of each SC keypoint, in
// static_features order. A place stored without a camera has none; without depth, `depth_m` is
// empty (a monocular place: its pose is the essential matrix's rotation and direction).
struct FrameGeometry {
  std::optional<Camera> camera;
  std::vector<float> depth_m;
  bool empty() const { return !camera.has_value() && depth_m.empty(); }
  bool operator==(const FrameGeometry&) const = default;
};

struct FrameCounts {
  uint32_t total = 0;           // descriptors extracted / given
  uint32_t dynamic = 0;         // DC: dropped
  uint32_t static_ = 0;         // SC: kept
  double dynamic_coverage = 0;  // fraction of the image's pixels on dynamic objects
  // Of the non-DC descriptors, removed by Algorithm 1 (an approaching object seen in depth);
  // total = dynamic + depth_removed + static_.
  uint32_t depth_removed = 0;
};

// Which per-agent state a frame may use.
enum class FrameRole {
  kQuery,   // stateless; Algorithm 1's current decision for the agent applies, unchanged
  kStream,  // the agent's next frame: AdvanceStream() must follow, in the agent's order
};

// The outcome of extract + filter + transform for one frame.
struct ProcessedFrame {
  FrameCounts counts;
  bool valid = false;
  std::string rejection;          // why the frame is invalid; empty when valid
  LocalFeatures static_features;  // SC only, of the map's feature type
  // The DC keypoints (the filter's dropped split), only when Process() was asked to keep them.
  std::vector<Keypoint> dropped_keypoints;
  BowVector bow;       // SC only, normalised for the database's scoring
  DirectIndex direct;  // SC only, at verification.levels_up
  std::vector<DynamicBox> boxes_used;
  StageTimings timings;
  // The checksum of the vocabulary `bow`, `direct` and the DC vectors were made with: a map that
  // switched vocabularies (issue 29) transforms a frame processed before the switch again.
  uint64_t vocabulary_checksum = 0;
  // The short-term tier (config.short_term.enabled): the DC descriptors' BoW vector, normalised
  // for the database's scoring, and (ORB maps: FeatureExtractor::verifies_dynamic_features) the
  // DC features with their direct index, so that verification against a recent place can use the
  // objects both frames saw; empty without DC descriptors.
  BowVector dynamic_bow;
  LocalFeatures dynamic_features;
  DirectIndex dynamic_direct;

  // RGB-D. `depth_m` is the frame's depth in metres (CV_32F, 0 = invalid), empty without depth.
  cv::Mat depth_m;
  size_t boxes_refined = 0;           // boxes narrowed to their object's depth layer or segmented
  std::vector<float> static_depth_m;  // per SC feature while Algorithm 1 is pending
  bool stream_pending = false;        // Process(kStream) left Algorithm 1 to AdvanceStream()
  std::optional<DepthFrameState> depth_state;  // Algorithm 1's decision for this frame
  // The camera and each SC keypoint's depth (kept aligned with static_features), for poses.
  FrameGeometry geometry;

  // The frame's thumbnail (Process() with thumbnail settings, a frame with pixels): the reduced
  // JPEG only, never the full image, travels on to the commit.
  std::optional<Thumbnail> thumbnail;
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
  LocalFeatures features;  // SC keypoints + descriptors, of the map's feature type
  DirectIndex direct;      // at the database's verification.levels_up
  BowVector bow;           // normalised for the database's scoring
  FrameGeometry geometry;  // camera and keypoint depths, when the frame had them
};

// Where PlaceDatabase keeps payloads. Implementations must allow concurrent Get() calls with
// one Put()/Erase() at a time.
class PayloadStore {
 public:
  virtual ~PayloadStore() = default;
  // Called when a place is inserted. A persistent store that already wrote the payload (in the
  // same atomic batch as the place) may just cache or ignore it.
  virtual Status Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) = 0;
  // False for a store whose Put() ignores the payload (it wrote it itself): Insert() then copies
  // no features into one.
  virtual bool KeepsPayloads() const { return true; }
  // NOT_FOUND when the place is unknown (e.g. removed meanwhile).
  virtual Result<std::shared_ptr<const PlacePayload>> Get(PlaceId id) const = 0;
  // The place's BoW vector alone (loop closure's long-term memory reads it back). By default
  // from Get(); a persistent store reads just the vector.
  virtual Result<BowVector> GetBow(PlaceId id) const;
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
  mutable SharedMutex mutex_;
  std::unordered_map<PlaceId, std::shared_ptr<const PlacePayload>> payloads_ GUARDED_BY(mutex_);
  size_t bytes_ GUARDED_BY(mutex_) = 0;
};

size_t PayloadBytes(const PlacePayload& payload);

// Where CloseLoop() reads the places its detector needs when the database does not hold them
// itself: a cluster worker's local copy of a map holds no places (they live on the map's
// replicas, docs/cluster.md), so the server implements this over its replicas. Without a source
// (a single node) CloseLoop reads the database's own payload store.
// Called only from CloseLoop(), on its caller's thread, under the agent stream's mutex.
class PlaceSource {
 public:
  struct AgentPlace {
    PlaceId id = 0;
    uint64_t sequence = 0;  // PlaceMetadata::sequence: the replay's order
    BowVector bow;          // normalised for the database's scoring, as stored
  };
  virtual ~PlaceSource() = default;
  // A stored place's BoW vector (long-term memory retrieval). NOT_FOUND when absent.
  virtual Result<BowVector> GetBow(PlaceId place) = 0;
  // A stored place's features and direct index (loop verification). NOT_FOUND when absent.
  virtual Result<std::shared_ptr<const PlacePayload>> GetPayload(PlaceId place) = 0;
  // Every stored place of `agent_id`, in any order (a new detector's replay sorts them).
  virtual Result<std::vector<AgentPlace>> AgentPlaces(const std::string& agent_id) = 0;
};

struct AddResult {
  bool stored = false;
  PlaceId id = 0;         // valid when stored
  std::string rejection;  // why not stored
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  StageTimings timings;
  std::optional<DepthFrameState> depth_state;
};

struct QueryOptions {
  size_t top_k = 10;
  // Drop candidates that fail verification. On a map whose verification is disabled the
  // candidates are then verified on request (exhaustive matching, the map's other settings).
  bool verified_only = false;
  // The query's observation time, for the short-term tier; 0 = the newest place's time.
  int64_t timestamp_ns = 0;
  // Optional extra filter on candidates (e.g. exclude the agent's own recent places).
  std::function<bool(const PlaceRecord&)> accept;
  // Fill Match::correspondences for verified matches (costs a copy of their inliers).
  bool include_correspondences = false;
  // The relative pose of each verified match whose frame and place both have a camera
  // (Match::relative_pose; about 1 ms per verified match at 1000 ORB, docs/poses.md).
  bool relative_poses = true;
  // Threads this one query may use to search the inverted index (it splits the work by
  // segments of 65536 place ids, so only maps past that use more than one; the result is the
  // same for every value). 1 by default: a server answers concurrent queries and ingests on a
  // few cores, where a second thread per query only queues behind other work; 2 roughly halves
  // a large map's search time on an otherwise idle machine.
  int search_threads = 1;
  // < 1: skip the query's words held by more than this share of the map's places (see
  // InvertedIndex::Query): faster on large maps, no longer the exact ranking (docs/index.md has
  // the measured agreement; on small maps it changes the top 1 often). 1: exact, the default.
  double max_word_share = 1.0;
  // max_word_share applies only to maps of at least this many places. A frequent word's run is
  // long only in a large map: that is where skipping it saves time, while in a small one a word
  // held by a few places still tells them apart (and skipping it changes the top 1).
  size_t skip_words_min_places = 0;
};

struct Match {
  PlaceId place = 0;
  double score = 0;
  int inliers = 0;        // 0 when verification is disabled or not reached
  bool verified = false;  // true when inliers >= min_inliers (always false when disabled)
  PlaceMetadata metadata;
  // With QueryOptions::include_correspondences, verified matches only: the geometric inliers as
  // (index into the frame's static_features, index into the place's stored features). Against
  // a place in the short-term tier the inliers on both frames' objects (DC features) are left
  // out: neither side keeps them, so there may be fewer pairs than `inliers`.
  std::vector<InlierPair> correspondences;
  // Verified matches, with QueryOptions::relative_poses: T_place_query from verification's inlier
  // pairs (core/pose/relative_pose.h: metric with depth on either side, rotation and direction
  // without). Empty when none could be made; `pose_unavailable` then says why ("the place was
  // stored without a camera", the solver's FAILED_PRECONDITION, ...).
  std::optional<RelativePose> relative_pose;
  std::string pose_unavailable;
};

struct QueryResult {
  bool valid = false;
  std::string rejection;
  FrameCounts counts;
  std::vector<DynamicBox> boxes_used;
  std::vector<Match> matches;  // best first
  StageTimings timings;
  std::optional<DepthFrameState> depth_state;
};

// The loop-closure answer for one stream frame (CloseLoop()), in database place ids.
struct LoopClosureOutcome {
  bool merged = false;          // rehearsal: the frame was merged into `place`, not stored
  PlaceId place = 0;            // the place the frame became (stored) or was merged into
  std::optional<PlaceId> loop;  // accepted loop closure: the revisited place
  double loop_posterior = 0;    // posterior of the accepted loop (0 without one)
  // With verify_loops: the accepted loop's inliers, and whether verification took it back
  // (`loop` is then empty and `rejected_loop` names the place).
  int loop_inliers = 0;
  bool loop_rejected = false;
  PlaceId rejected_loop = 0;
  // With verify_loops, an accepted loop's relative pose T_loop_frame (as Match::relative_pose:
  // cameras on both sides), else why there is none.
  std::optional<RelativePose> loop_pose;
  std::string loop_pose_unavailable;
  PlaceId best = 0;  // best hypothesis, accepted or not (0: none, or unbound)
  double best_posterior = 0;
  size_t candidates = 0;   // places in the agent's working memory that were searched
  size_t retrieved = 0;    // long-term -> working memory in this update
  size_t transferred = 0;  // working -> long-term memory in this update
  double update_ms = 0;    // the detector's update alone
  // The agent's earlier places replayed into a new detector by this call (first loop-closure
  // frame of the agent since the map was opened or its stream reset), else 0.
  size_t replayed = 0;
  double replay_ms = 0;  // the replay's time (reading the places included), 0 without one
};

struct DatabaseStats {
  size_t places = 0;
  uint64_t descriptors_kept = 0;     // SC descriptors of stored places
  uint64_t descriptors_dropped = 0;  // DC descriptors of stored places
  uint64_t invalid_rejected = 0;     // frames refused by Add() as invalid
  size_t index_bytes = 0;            // inverted index (postings + tables)
  size_t record_bytes = 0;           // in-memory place records (metadata, counts, boxes)
  size_t payload_bytes = 0;          // payloads the PayloadStore holds in memory
  size_t short_term_places = 0;      // places whose DC words the short-term tier holds
  size_t short_term_bytes = 0;       // the tier's index and vectors
  // Agent streams with per-agent state, and their loop-closure memory (summed over agents).
  size_t streams = 0;
  size_t loop_working_memory = 0;  // places searched by loop closure (STM + WM)
  size_t loop_long_term = 0;       // places in long-term memory (in the payload store, unsearched)
  uint64_t loops_accepted = 0;
  uint64_t loops_rejected = 0;  // accepted by the filter, failed geometric verification
};

// Which places PlaceDatabase::ListPlacesBefore returns.
struct PlaceFilter {
  std::string agent_id;           // only this agent's places; empty = every agent's
  int64_t from_timestamp_ns = 0;  // observed at or after this; 0 = no lower bound
  int64_t to_timestamp_ns = 0;    // observed before this; 0 = no upper bound
};

// One page of a newest-first walk over a map's places.
struct PlacePage {
  std::vector<std::shared_ptr<const PlaceRecord>> places;  // highest id first
  PlaceId next_before = 0;  // pass as `before` for the next page; 0 = nothing left below
};

class AgentStreams;
class PayloadLongTermMemory;

class PlaceDatabase {
 public:
  // INVALID_ARGUMENT for a bad config or a vocabulary of the wrong kind for
  // config.feature_type; the vocabulary is shared, never copied. Without a payload store,
  // payloads stay in memory.
  static Result<std::unique_ptr<PlaceDatabase>> Create(
      AnyVocabulary vocabulary, DatabaseConfig config,
      std::shared_ptr<PayloadStore> payloads = nullptr);
  ~PlaceDatabase();

  const DatabaseConfig& config() const { return config_; }
  const AnyVocabulary& vocabulary() const { return vocabulary_; }

  // Extract, filter, validate and transform without touching the database. With kStream and
  // depth (and config.depth.stream_filter), Algorithm 1, validity and transform are left to
  // AdvanceStream() (`stream_pending`). With `thumbnail` enabled and an observation that carries
  // pixels, the frame's thumbnail is made too (core/thumbnail: boxes_used blurred, the DC
  // keypoints kept); precomputed features have no pixels, hence no thumbnail.
  // `keep_dropped_keypoints` fills `dropped_keypoints`.
  Result<ProcessedFrame> Process(const Observation& observation, FrameRole role = FrameRole::kQuery,
                                 const ThumbnailSettings* thumbnail = nullptr,
                                 bool keep_dropped_keypoints = false) const;
  // Whether `frame` was transformed with this database's vocabulary (ProcessedFrame::
  // vocabulary_checksum). Retransform makes its BoW vectors and direct indices again with it
  // from the frame's features (the DC vector only when the DC features were kept: ORB maps);
  // nothing when it already is. FAILED_PRECONDITION for a frame still pending AdvanceStream.
  bool OfThisVocabulary(const ProcessedFrame& frame) const;
  Status Retransform(ProcessedFrame* frame) const;
  // Finishes a kStream frame: Algorithm 1 with the agent's stream state (frames of one agent
  // must arrive here in order), then validity and transform. No-op unless `stream_pending`.
  Status AdvanceStream(ProcessedFrame* frame, const std::string& agent_id);

  // Loop closure for an agent's stream (frames in order): updates the agent's detector with a
  // valid frame, then, unless rehearsal merged the frame into the previous place, calls `store`
  // (which persists the frame and returns its place id) and binds the detector's place to it.
  // With `store` null, Insert() is used. The agent's places in long-term memory are read back
  // from the payload store when retrieved. The agent's first call (since the database was
  // created or opened, or its stream reset) replays the places it stored earlier, oldest first,
  // into the new detector (their weights and loop links are not kept), so loops can close on
  // them after a restart. With `source`, every place the detector reads (long-term memory, the
  // loop target's features for verify_loops, the replay) comes from it instead of this database
  // (cluster mode's worker); its errors are CloseLoop's (the replay's, a verification's), except
  // a retrieval's, which the detector carries in its update as without a source.
  Result<LoopClosureOutcome> CloseLoop(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                                       const std::function<Result<PlaceId>()>& store = nullptr,
                                       PlaceSource* source = nullptr);
  // Forgets an agent's stream state (Algorithm 1 and loop closure); NOT_FOUND if none.
  Status ResetStream(const std::string& agent_id);
  // Forgets the agent's loop-closure detector only (Algorithm 1 stays): its next CloseLoop()
  // starts a new one and replays the agent's places. Nothing when it has none.
  void ResetLoopClosure(const std::string& agent_id);
  // The agent's loop-closure statistics; NOT_FOUND when it has no detector yet.
  Result<LoopClosureStats> LoopStats(const std::string& agent_id) const;

  // Processes (as the agent's next stream frame) and, when valid, stores the frame.
  Result<AddResult> Add(const Observation& observation);
  // Stores an already processed valid frame. With `id` given (restoring from storage) that id is
  // used: ALREADY_EXISTS if taken. Returns the id.
  Result<PlaceId> Insert(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                         std::optional<PlaceId> id = std::nullopt);
  // Re-indexes a stored place as a persistent map reloads it: the payload stays in the
  // PayloadStore, only the record and BoW vector are needed.
  Status Restore(PlaceRecord record, const BowVector& bow);
  // Restore in bulk, a range of ids within one index segment at a time (PlaceMap::Load):
  // PrepareRestore checks the places and builds their segment off the database
  // (InvertedIndex::BuildSegment), then RestoreRange installs it. Together they leave the database
  // exactly as Restore of each place in id order would (same answers; the index takes no more
  // memory).
  struct RestoredSegment {
    std::vector<std::shared_ptr<const PlaceRecord>> records;  // increasing ids
    InvertedIndex::DetachedSegment index;
  };
  // `records[i]` with vector `bows[i]`, ids increasing and all in one index segment (id >>
  // InvertedIndex::kSegmentBits). The first place Restore would refuse decides the error, with
  // Restore's message (id 0 is reserved; the vector checks of InvertedIndex::Add);
  // INVALID_ARGUMENT for ids out of order or across segments. Reads only what is fixed at
  // construction: thread-safe, concurrently with anything, changes nothing.
  Result<RestoredSegment> PrepareRestore(std::vector<PlaceRecord> records,
                                         std::span<const BowVector> bows) const;
  // Installs a prepared segment (InvertedIndex::Install: moved into an empty index segment,
  // appended above the places of a non-empty one). ALREADY_EXISTS if the database holds one of
  // its places, FAILED_PRECONDITION if its index segment holds or held an id at or above its
  // lowest; nothing changes on error. Takes the writer lock.
  Status RestoreRange(RestoredSegment segment);
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
  // The places with ids below `before` (0, or past the newest id: from the newest) that pass
  // `filter`, highest id first, at most `limit`. Bounded work: the walk examines at most
  // `max_examined` ids (stored, deleted or never used alike) and stops there, so a filter that
  // matches rarely costs a bounded call; the page may then hold fewer than `limit` places (even
  // none) while next_before != 0. Walking every page from before = 0 until next_before == 0
  // visits every place that existed throughout, exactly once. Takes the reader lock only.
  PlacePage ListPlacesBefore(PlaceId before, size_t limit, const PlaceFilter& filter,
                             size_t max_examined) const;
  DatabaseStats Stats() const;
  PlaceId next_id() const;

 private:
  PlaceDatabase(AnyVocabulary vocabulary, DatabaseConfig config,
                std::unique_ptr<const FeatureExtractor> extractor,
                std::shared_ptr<PayloadStore> payloads);
  // Extracts the map's features from the observation's pixels. With dynamic objects known and
  // no depth, an extractor that budgets_static_pixels() spends its budget on the static pixels,
  // after `refine(width, height)` has narrowed `dynamic`'s boxes to their objects.
  Result<LocalFeatures> ExtractFromPixels(const Observation& observation, DynamicObjects* dynamic,
                                          const std::function<Status(int, int)>& refine) const;
  // Validity, then the BoW vector and direct index of the SC features.
  Status Finish(ProcessedFrame* frame, Stopwatch* stage) const;
  // Geometric verification of a loop: the frame against the stored place; the inlier count.
  // `source`: read the place from it (else the payload store). A verified loop's relative pose
  // (or why there is none) goes to `pose`'s relative_pose / pose_unavailable.
  Result<int> VerifyLoop(const ProcessedFrame& frame, PlaceId place, PlaceSource* source,
                         Match* pose) const;
  // Replays the agent's stored places (this database's, or `source`'s), oldest first, into a new
  // detector and binds them.
  Result<size_t> ReplayAgentPlaces(const std::string& agent_id, LoopClosureDetector* detector,
                                   PayloadLongTermMemory* ltm, PlaceSource* source) const
      EXCLUDES(mutex_);
  // Removes the SC features whose depth lies in Algorithm 1's band (when it is removing).
  static void ApplyDepthBand(ProcessedFrame* frame, const DepthFrameState& state,
                             bool remove_without_depth);
  // Adds the record and its postings; caller holds the writer lock.
  Status InsertLocked(std::shared_ptr<const PlaceRecord> record, const BowVector& bow)
      REQUIRES(mutex_);
  void UndoInsertLocked(PlaceId id, const BowVector& bow) REQUIRES(mutex_);
  std::vector<DynamicBox> SelectBoxes(const std::vector<DynamicBox>& boxes) const;
  // The short-term tier; callers hold the writer lock.
  void AddShortTermLocked(PlaceId place, const PlaceMetadata& metadata, const ProcessedFrame& frame)
      REQUIRES(mutex_);
  void RemoveShortTermLocked(PlaceId place) REQUIRES(mutex_);
  // The tier's clock for a query: its own timestamp, else the newest place's (tier not empty).
  int64_t ShortTermNowLocked(int64_t query_timestamp_ns) const REQUIRES_SHARED(mutex_);
  struct ShortTermEntry;
  bool InHorizon(const ShortTermEntry& entry, int64_t now) const;
  // The tier's score bonuses for a query (reader lock held).
  std::vector<ScoredPlace> ShortTermBonusLocked(const ProcessedFrame& frame,
                                                int64_t timestamp_ns) const REQUIRES_SHARED(mutex_);

  // Set at construction and never reassigned: read without a lock. The payload store and the
  // streams lock inside.
  const AnyVocabulary vocabulary_;
  const DatabaseConfig config_;
  const std::unique_ptr<const FeatureExtractor> extractor_;  // of config_.feature_type
  const std::shared_ptr<PayloadStore> payloads_;
  const std::unique_ptr<AgentStreams> streams_;

  // Taken after a stream's mutex (CloseLoop's store callback runs under it), never before.
  mutable SharedMutex mutex_;
  InvertedIndex index_ GUARDED_BY(mutex_);
  std::unordered_map<PlaceId, std::shared_ptr<const PlaceRecord>> records_ GUARDED_BY(mutex_);
  PlaceId next_id_ GUARDED_BY(mutex_) = 1;
  uint64_t descriptors_kept_ GUARDED_BY(mutex_) = 0;
  uint64_t descriptors_dropped_ GUARDED_BY(mutex_) = 0;
  uint64_t invalid_rejected_ GUARDED_BY(mutex_) = 0;
  size_t record_bytes_ GUARDED_BY(mutex_) = 0;

  struct ShortTermEntry {
    int64_t timestamp_ns = 0;
    std::string agent_id;
    BowVector dynamic_bow;
    double dynamic_share = 0;  // DC descriptors / all descriptors of the frame
    // The DC features and their direct index, for verification (when the family keeps them).
    std::shared_ptr<const std::pair<LocalFeatures, DirectIndex>> dynamic_features;
  };
  InvertedIndex short_term_index_ GUARDED_BY(mutex_);
  std::unordered_map<PlaceId, ShortTermEntry> short_term_ GUARDED_BY(mutex_);
  using TimeOrdered = std::set<std::pair<int64_t, PlaceId>>;  // oldest first
  TimeOrdered short_term_by_time_ GUARDED_BY(mutex_);
  // Each agent's places: the horizon counts back from the agent's own newest observation, so
  // agents whose clocks differ (or that paused) keep their recent places.
  std::unordered_map<std::string, TimeOrdered> short_term_by_agent_ GUARDED_BY(mutex_);
};

}  // namespace placedb
