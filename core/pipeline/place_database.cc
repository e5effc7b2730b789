#include "core/pipeline/place_database.h"

#include <algorithm>
#include <cctype>
#include <mutex>

#include "core/pipeline/agent_streams.h"

namespace placedb {

Status ValidateDepthConfig(const DepthConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateRefineConfig(config.refine).WithContext("depth.refine"));
  PLACEDB_RETURN_IF_ERROR(ValidateDepthFilterConfig(config.filter).WithContext("depth.filter"));
  return Status::Ok();
}

Status ValidateShortTermConfig(const ShortTermConfig& config) {
  if (config.horizon_ns <= 0) {
    return Status::InvalidArgument("short_term.horizon_ns must be positive");
  }
  if (config.max_places == 0) {
    return Status::InvalidArgument("short_term.max_places must be positive");
  }
  if (!(config.weight > 0.0f && config.weight <= 10.0f)) {
    return Status::InvalidArgument("short_term.weight must be in (0, 10]");
  }
  return Status::Ok();
}

Status ValidateDatabaseConfig(const DatabaseConfig& config) {
  if (config.feature_type != FeatureType::kOrb && config.feature_type != FeatureType::kSift) {
    return Status::InvalidArgument("feature_type " + std::to_string(int(config.feature_type)) +
                                   " is not a feature type");
  }
  PLACEDB_RETURN_IF_ERROR(ValidateOrbConfig(config.orb));
  PLACEDB_RETURN_IF_ERROR(ValidateSiftConfig(config.sift));
  PLACEDB_RETURN_IF_ERROR(ValidateDepthConfig(config.depth));
  PLACEDB_RETURN_IF_ERROR(
      ValidateLoopClosureConfig(config.loop_closure).WithContext("loop_closure"));
  PLACEDB_RETURN_IF_ERROR(ValidateFilterConfig(config.filter));
  PLACEDB_RETURN_IF_ERROR(ValidateBoxRefinementConfig(config.box_refinement));
  PLACEDB_RETURN_IF_ERROR(ValidateShortTermConfig(config.short_term));
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

// "ORB", "SIFT": for messages.
std::string FeatureTypeLabel(FeatureType type) {
  std::string label = FeatureTypeName(type);
  for (char& c : label) c = char(std::toupper(static_cast<unsigned char>(c)));
  return label;
}

// Both images' cameras when both are known: verification then fits the essential matrix.
VerificationCameras CamerasOf(const ProcessedFrame& frame, const PlacePayload& place) {
  if (!frame.geometry.camera.has_value() || !place.geometry.camera.has_value()) return {};
  return {&*frame.geometry.camera, &*place.geometry.camera};
}

// Verification against a place the short-term tier holds: both frames' SC + DC features, so
// the objects both saw are evidence. Collected inlier pairs keep only SC-to-SC ones (the indices
// the frame's static_features and the place's stored features give).
Result<VerificationResult> VerifyWithObjects(
    const ProcessedFrame& frame, const PlacePayload& place,
    const std::pair<LocalFeatures, DirectIndex>& place_objects, const VerificationConfig& config,
    bool collect_inliers) {
  const auto& [objects, objects_direct] = place_objects;
  auto query = LocalFeatures::Concat(frame.static_features, frame.dynamic_features);
  if (!query.ok()) return query.status();
  auto candidate = LocalFeatures::Concat(place.features, objects);
  if (!candidate.ok()) return candidate.status();
  auto verified = VerifyGeometry(
      *query,
      MergeDirectIndices(frame.direct, frame.dynamic_direct,
                         uint32_t(frame.static_features.size())),
      *candidate, MergeDirectIndices(place.direct, objects_direct, uint32_t(place.features.size())),
      config, collect_inliers, CamerasOf(frame, place));
  if (verified.ok() && collect_inliers) {
    std::erase_if(verified->inlier_pairs, [&](const InlierPair& pair) {
      return pair.query >= frame.static_features.size() || pair.candidate >= place.features.size();
    });
  }
  return verified;
}

// What PnP's residuals are weighed by: ORB's pyramid factor; SIFT's octaves double the scale.
double OctaveScaleFactor(const DatabaseConfig& config) {
  return config.feature_type == FeatureType::kOrb ? double(config.orb.scale_factor) : 2.0;
}

// The relative pose of a verified match from verification's inlier pairs (issue 32), or why there
// is none in `pose_unavailable`. Returns the solver's time in ms (0 when it did not run).
double AttachRelativePose(const ProcessedFrame& frame, const PlacePayload& place,
                          const std::vector<InlierPair>& inliers, double octave_scale_factor,
                          Match* match) {
  if (!frame.geometry.camera.has_value()) {
    match->pose_unavailable = "the frame has no camera (observation.camera or depth.intrinsics)";
    return 0;
  }
  if (!place.geometry.camera.has_value()) {
    match->pose_unavailable =
        "place " + std::to_string(match->place) + " was stored without a camera";
    return 0;
  }
  Stopwatch solving;
  std::vector<KeypointMatch> pairs;
  pairs.reserve(inliers.size());
  for (const InlierPair& pair : inliers) pairs.push_back({pair.query, pair.candidate});
  const PoseFrame query{*frame.geometry.camera, frame.static_features.keypoints(),
                        frame.geometry.depth_m};
  const PoseFrame stored{*place.geometry.camera, place.features.keypoints(),
                         place.geometry.depth_m};
  RelativePoseConfig config;
  config.octave_scale_factor = octave_scale_factor;
  auto pose = EstimateRelativePose(query, stored, pairs, config);
  if (pose.ok()) {
    match->relative_pose = std::move(pose).value();
  } else {
    match->pose_unavailable = pose.status().message();
  }
  return solving.ElapsedMs();
}

std::string InvalidReason(const FrameCounts& counts, int place_threshold) {
  std::string depth;
  if (counts.depth_removed > 0) {
    depth = ", " + std::to_string(counts.depth_removed) + " removed by the depth filter";
  }
  return "invalid place representation: " + std::to_string(counts.static_) +
         " static descriptors (" + std::to_string(counts.dynamic) + " of " +
         std::to_string(counts.total) + " dropped as dynamic" + depth +
         ") is not more than placeThreshold " + std::to_string(place_threshold);
}

}  // namespace

size_t PayloadBytes(const PlacePayload& payload) {
  return sizeof(PlacePayload) + payload.features.MemoryBytes() +
         payload.geometry.depth_m.capacity() * sizeof(float) +
         payload.bow.capacity() * sizeof(BowEntry) +
         (payload.direct.node_ids.capacity() + payload.direct.offsets.capacity() +
          payload.direct.feature_ids.capacity()) *
             sizeof(uint32_t);
}

Result<BowVector> PayloadStore::GetBow(PlaceId id) const {
  auto payload = Get(id);
  if (!payload.ok()) return payload.status();
  return (*payload)->bow;
}

Status InMemoryPayloadStore::Put(PlaceId id, std::shared_ptr<const PlacePayload> payload) {
  WriterLock lock(mutex_);
  const size_t bytes = PayloadBytes(*payload);
  if (!payloads_.emplace(id, std::move(payload)).second) {
    return Status::AlreadyExists("payload of place " + std::to_string(id) + " already stored");
  }
  bytes_ += bytes;
  return Status::Ok();
}

Result<std::shared_ptr<const PlacePayload>> InMemoryPayloadStore::Get(PlaceId id) const {
  ReaderLock lock(mutex_);
  auto it = payloads_.find(id);
  if (it == payloads_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  return it->second;
}

Status InMemoryPayloadStore::Erase(PlaceId id) {
  WriterLock lock(mutex_);
  auto it = payloads_.find(id);
  if (it == payloads_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  bytes_ -= PayloadBytes(*it->second);
  payloads_.erase(it);
  return Status::Ok();
}

size_t InMemoryPayloadStore::MemoryBytes() const {
  ReaderLock lock(mutex_);
  // Plus a rough per-entry cost of the hash map node.
  return bytes_ + payloads_.size() * (sizeof(PlaceId) + sizeof(void*) * 4);
}

PlaceDatabase::PlaceDatabase(AnyVocabulary vocabulary, DatabaseConfig config,
                             std::unique_ptr<const FeatureExtractor> extractor,
                             std::shared_ptr<PayloadStore> payloads)
    : vocabulary_(std::move(vocabulary)),
      config_(std::move(config)),
      extractor_(std::move(extractor)),
      payloads_(payloads ? std::move(payloads) : std::make_shared<InMemoryPayloadStore>()),
      streams_(std::make_unique<AgentStreams>()),
      index_(vocabulary_.word_count(), config_.scoring),
      short_term_index_(vocabulary_.word_count(), config_.scoring) {}

PlaceDatabase::~PlaceDatabase() = default;

Result<std::unique_ptr<PlaceDatabase>> PlaceDatabase::Create(
    AnyVocabulary vocabulary, DatabaseConfig config, std::shared_ptr<PayloadStore> payloads) {
  if (!vocabulary) return Status::InvalidArgument("vocabulary is missing");
  PLACEDB_RETURN_IF_ERROR(ValidateDatabaseConfig(config));
  if (vocabulary.feature_type() != config.feature_type) {
    return Status::InvalidArgument(
        std::string("feature_type ") + FeatureTypeName(config.feature_type) + " needs a " +
        VocabularyKindName(config.feature_type) + " vocabulary; this one is " + vocabulary.kind());
  }
  auto extractor = FeatureExtractor::Create(config.feature_type, config.orb, config.sift);
  if (!extractor.ok()) return extractor.status();
  return std::unique_ptr<PlaceDatabase>(new PlaceDatabase(
      std::move(vocabulary), std::move(config), std::move(extractor).value(), std::move(payloads)));
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

Result<LocalFeatures> PlaceDatabase::ExtractFromPixels(
    const Observation& observation, DynamicObjects* dynamic,
    const std::function<Status(int, int)>& refine) const {
  // With dynamic objects known (and no depth, which decides per pixel later), the feature budget
  // is spent on the static pixels: the place then keeps as many static features as a frame
  // without objects. The objects' own features, for the short-term tier, are those a whole-frame
  // extraction finds on them (as many as without the budget).
  const bool budget = config_.static_feature_budget && extractor_->budgets_static_pixels() &&
                      !observation.depth.has_value() &&
                      (!dynamic->boxes.empty() || !dynamic->mask.empty()) &&
                      !observation.image.empty();
  if (budget) PLACEDB_RETURN_IF_ERROR(refine(observation.image.cols, observation.image.rows));
  const cv::Mat region =
      budget ? RasterizeDynamicRegion(*dynamic, observation.image.cols, observation.image.rows)
             : cv::Mat();
  const int dynamic_pixels = region.empty() ? 0 : cv::countNonZero(region);
  cv::Mat static_pixels;
  if (dynamic_pixels > 0) cv::compare(region, 0, static_pixels, cv::CMP_EQ);
  auto extracted = extractor_->Extract(observation.image, static_pixels);
  if (!extracted.ok() || dynamic_pixels == 0 || !config_.short_term.enabled) return extracted;
  auto whole = extractor_->Extract(observation.image);
  if (!whole.ok()) return whole.status();
  std::vector<uint32_t> on_objects;
  for (uint32_t i = 0; i < whole->size(); ++i) {
    const Keypoint& kp = whole->keypoints()[i];
    const int col = std::clamp(int(std::lround(kp.x)), 0, region.cols - 1);
    const int row = std::clamp(int(std::lround(kp.y)), 0, region.rows - 1);
    if (region.at<uint8_t>(row, col) != 0) on_objects.push_back(i);
  }
  return LocalFeatures::Concat(*extracted, whole->Select(on_objects));
}

Result<ProcessedFrame> PlaceDatabase::Process(const Observation& observation, FrameRole role,
                                              const ThumbnailSettings* thumbnail,
                                              bool keep_dropped_keypoints) const {
  ProcessedFrame frame;
  frame.vocabulary_checksum = vocabulary_.checksum();
  Stopwatch total;
  Stopwatch stage;

  // The caller's features must be of the map's feature type.
  if (observation.features.has_value()) {
    if (observation.features->type() != config_.feature_type) {
      const std::string map = FeatureTypeLabel(config_.feature_type);
      return Status::InvalidArgument("this map's features are " + map + ": it takes " + map +
                                     " features or an image, not " +
                                     FeatureTypeLabel(observation.features->type()) + " features");
    }
    PLACEDB_RETURN_IF_ERROR(observation.features->Validate());
  }

  DynamicObjects dynamic;
  dynamic.boxes = SelectBoxes(observation.dynamic.boxes);
  dynamic.mask = observation.dynamic.mask;
  frame.boxes_used = dynamic.boxes;
  // Boxes are narrowed to their objects' pixels on frames without depth (depth refines below).
  bool refined = false;
  auto refine = [&](int width, int height) -> Status {
    refined = true;
    if (observation.depth.has_value() || config_.box_refinement.method == BoxRefinement::kNone ||
        dynamic.boxes.empty()) {
      return Status::Ok();
    }
    Stopwatch watch;
    const bool image_matches = observation.image.cols == width && observation.image.rows == height;
    auto result = RefineBoxesToMasks(dynamic, image_matches ? observation.image : cv::Mat(), width,
                                     height, config_.box_refinement);
    if (!result.ok()) return result.status().WithContext("box refinement");
    for (const BoxMask& box : result->boxes) frame.boxes_refined += box.segmented ? 1 : 0;
    dynamic = std::move(result->objects);
    frame.timings.refine_ms = watch.ElapsedMs();
    return Status::Ok();
  };

  // ---- Extract (or take the caller's features).
  LocalFeatures extracted;
  const LocalFeatures* features = &extracted;
  if (observation.features.has_value()) {
    features = &*observation.features;
  } else {
    auto result = ExtractFromPixels(observation, &dynamic, refine);
    if (!result.ok()) return result.status();
    extracted = std::move(result).value();
  }
  const int width = features->image_width();
  const int height = features->image_height();
  // Box refinement before a budgeted extraction is not extraction time.
  frame.timings.extract_ms = stage.Lap() - frame.timings.refine_ms;

  // ---- Depth: decode, and narrow every dynamic box to its object's depth layer.
  std::optional<CameraIntrinsics> intrinsics;
  if (observation.depth.has_value()) {
    const DepthObservation& depth = *observation.depth;
    DepthFormat format = config_.depth.filter.format;
    if (depth.metres_per_unit.has_value()) {
      format.metres_per_unit = *depth.metres_per_unit;
      format.float_metres_per_unit = *depth.metres_per_unit;
      PLACEDB_RETURN_IF_ERROR(ValidateDepthFormat(format).WithContext("depth"));
    }
    auto metres = DepthToMetres(depth.raw, format);
    if (!metres.ok()) return metres.status().WithContext("depth");
    PLACEDB_RETURN_IF_ERROR(
        CheckDepthRegistration(metres->cols, metres->rows, width, height).WithContext("depth"));
    if (depth.intrinsics.has_value()) {
      PLACEDB_RETURN_IF_ERROR(
          ValidateIntrinsics(*depth.intrinsics, width, height).WithContext("depth.intrinsics"));
      intrinsics = depth.intrinsics;
    }
    frame.depth_m = std::move(metres).value();
    if (config_.depth.refine_boxes && !dynamic.boxes.empty()) {
      auto refined =
          RefineDynamicObjects(dynamic, frame.depth_m, width, height, config_.depth.refine);
      if (!refined.ok()) return refined.status().WithContext("depth refinement");
      for (const RefinedBox& box : refined->boxes) frame.boxes_refined += box.refined ? 1 : 0;
      dynamic = std::move(refined->objects);
    }
    frame.timings.depth_ms += stage.Lap();
  }

  // ---- The camera (issue 32): the observation's, else the depth's intrinsics as a pinhole.
  if (observation.camera.has_value()) {
    Camera camera = *observation.camera;
    if (camera.width == 0 && camera.height == 0) {
      camera.width = width;
      camera.height = height;
    }
    PLACEDB_RETURN_IF_ERROR(camera.Validate("camera"));
    if (camera.width != width || camera.height != height) {
      return Status::InvalidArgument("camera.width/height: " + std::to_string(camera.width) + "x" +
                                     std::to_string(camera.height) + " is not the frame's " +
                                     std::to_string(width) + "x" + std::to_string(height) +
                                     " (0x0 means the frame's size)");
    }
    frame.geometry.camera = std::move(camera);
  } else if (intrinsics.has_value()) {
    frame.geometry.camera = PinholeCamera(width, height, intrinsics->fx, intrinsics->fy,
                                          intrinsics->cx, intrinsics->cy);
  }

  if (!refined) {
    PLACEDB_RETURN_IF_ERROR(refine(width, height));
    stage.Lap();
  }

  // ---- DC/SC.
  auto filtered = ClassifyDescriptors(*features, dynamic, config_.filter);
  if (!filtered.ok()) return filtered.status();
  frame.counts.total = uint32_t(filtered->total());
  frame.counts.dynamic = uint32_t(filtered->dynamic_indices.size());
  frame.counts.static_ = uint32_t(filtered->static_indices.size());
  frame.counts.dynamic_coverage = filtered->frame_dynamic_coverage;
  frame.static_features =
      filtered->dynamic_indices.empty() ? *features : features->Select(filtered->static_indices);
  if (keep_dropped_keypoints) {
    frame.dropped_keypoints.reserve(filtered->dynamic_indices.size());
    for (const uint32_t i : filtered->dynamic_indices) {
      frame.dropped_keypoints.push_back(features->keypoints()[i]);
    }
  }
  frame.timings.filter_ms = stage.Lap();

  // ---- The thumbnail: the reduced frame with boxes_used blurred, and the DC keypoints.
  if (thumbnail && thumbnail->enabled && !observation.features.has_value() &&
      !observation.image.empty()) {
    std::vector<Keypoint> dropped;
    dropped.reserve(filtered->dynamic_indices.size());
    for (uint32_t i : filtered->dynamic_indices) dropped.push_back(features->keypoints()[i]);
    auto made = MakeThumbnail(observation.image, frame.boxes_used, std::move(dropped), *thumbnail,
                              observation.dynamic.mask);
    if (!made.ok()) return made.status().WithContext("thumbnail");
    frame.thumbnail = std::move(made).value();
    stage.Lap();  // counted in total_ms only
  }

  // ---- The short-term tier keeps the DC words (in memory, for recent places).
  if (config_.short_term.enabled && !filtered->dynamic_indices.empty()) {
    LocalFeatures dynamic_features = features->Select(filtered->dynamic_indices);
    const bool keep = extractor_->verifies_dynamic_features();
    PLACEDB_RETURN_IF_ERROR(vocabulary_.Transform(dynamic_features, &frame.dynamic_bow,
                                                  keep ? &frame.dynamic_direct : nullptr,
                                                  config_.verification.levels_up));
    if (keep) frame.dynamic_features = std::move(dynamic_features);
    NormalizeForScoring(&frame.dynamic_bow, config_.scoring);
    frame.timings.transform_ms += stage.Lap();
  }

  // ---- A relative pose needs each stored keypoint's depth (z, as the camera measures it).
  if (!frame.depth_m.empty() && frame.geometry.camera.has_value()) {
    frame.geometry.depth_m =
        SampleFeatureDepths(frame.depth_m, width, height, frame.static_features.keypoints(),
                            config_.depth.filter.feature_window_radius);
    frame.timings.depth_ms += stage.Lap();
  }

  // ---- Algorithm 1 needs the feature depths; the decision itself is per agent stream.
  if (!frame.depth_m.empty() && config_.depth.stream_filter) {
    const DepthFilterConfig& filter = config_.depth.filter;
    if (filter.use_range && !intrinsics) {
      return Status::InvalidArgument(
          "depth.intrinsics: the map measures range (use_range) and "
          "needs the camera intrinsics with every depth image");
    }
    frame.static_depth_m = SampleFeatureDepths(
        frame.depth_m, width, height, frame.static_features.keypoints(),
        filter.feature_window_radius, filter.use_range ? &*intrinsics : nullptr);
    if (role == FrameRole::kStream) {
      frame.stream_pending = true;
      frame.timings.depth_ms += stage.Lap();
      frame.timings.total_ms = total.ElapsedMs();
      return frame;
    }
    // A query applies the agent's current decision without advancing its stream.
    std::optional<DepthFrameState> current;
    if (auto stream = streams_->Find(observation.metadata.agent_id)) {
      MutexLock lock(stream->mutex);
      current = stream->last_depth;
    }
    if (current) ApplyDepthBand(&frame, *current, filter.remove_features_without_depth);
    frame.timings.depth_ms += stage.Lap();
  }
  PLACEDB_RETURN_IF_ERROR(Finish(&frame, &stage));
  frame.timings.total_ms = total.ElapsedMs();
  return frame;
}

void PlaceDatabase::ApplyDepthBand(ProcessedFrame* frame, const DepthFrameState& state,
                                   bool remove_without_depth) {
  frame->depth_state = state;
  if (!state.removing) return;
  std::vector<uint32_t> kept;
  std::vector<uint32_t> removed;
  SplitByBand(frame->static_depth_m, state.band, remove_without_depth, &kept, &removed);
  if (removed.empty()) return;
  frame->static_features = frame->static_features.Select(kept);
  std::vector<float> depths;
  depths.reserve(kept.size());
  for (uint32_t i : kept) depths.push_back(frame->static_depth_m[i]);
  frame->static_depth_m = std::move(depths);
  if (!frame->geometry.depth_m.empty()) {
    std::vector<float> pose_depths;
    pose_depths.reserve(kept.size());
    for (uint32_t i : kept) pose_depths.push_back(frame->geometry.depth_m[i]);
    frame->geometry.depth_m = std::move(pose_depths);
  }
  frame->counts.depth_removed += uint32_t(removed.size());
  frame->counts.static_ -= uint32_t(removed.size());
}

Status PlaceDatabase::Finish(ProcessedFrame* frame, Stopwatch* stage) const {
  frame->stream_pending = false;
  frame->static_depth_m.clear();
  frame->valid = int(frame->counts.static_) > config_.filter.place_threshold;
  if (!frame->valid) {
    // The paper's efficiency gain: an invalid representation is neither transformed, stored
    // nor matched.
    frame->rejection = InvalidReason(frame->counts, config_.filter.place_threshold);
    return Status::Ok();
  }
  PLACEDB_RETURN_IF_ERROR(vocabulary_.Transform(frame->static_features, &frame->bow, &frame->direct,
                                                config_.verification.levels_up));
  NormalizeForScoring(&frame->bow, config_.scoring);
  frame->timings.transform_ms += stage->Lap();
  return Status::Ok();
}

bool PlaceDatabase::OfThisVocabulary(const ProcessedFrame& frame) const {
  return frame.vocabulary_checksum == vocabulary_.checksum();
}

Status PlaceDatabase::Retransform(ProcessedFrame* frame) const {
  if (OfThisVocabulary(*frame)) return Status::Ok();
  if (frame->stream_pending) {
    return Status::FailedPrecondition("a pending stream frame is transformed by AdvanceStream");
  }
  frame->vocabulary_checksum = vocabulary_.checksum();
  frame->bow.clear();
  frame->direct = DirectIndex{};
  if (frame->valid) {
    PLACEDB_RETURN_IF_ERROR(vocabulary_.Transform(frame->static_features, &frame->bow,
                                                  &frame->direct, config_.verification.levels_up));
    NormalizeForScoring(&frame->bow, config_.scoring);
  }
  // The DC words are made again only when the DC features were kept (ORB maps); otherwise the
  // frame goes without the short-term tier.
  frame->dynamic_bow.clear();
  frame->dynamic_direct = DirectIndex{};
  if (!frame->dynamic_features.empty()) {
    PLACEDB_RETURN_IF_ERROR(vocabulary_.Transform(frame->dynamic_features, &frame->dynamic_bow,
                                                  &frame->dynamic_direct,
                                                  config_.verification.levels_up));
    NormalizeForScoring(&frame->dynamic_bow, config_.scoring);
  }
  return Status::Ok();
}

Status PlaceDatabase::AdvanceStream(ProcessedFrame* frame, const std::string& agent_id) {
  if (!frame->stream_pending) return Status::Ok();
  Stopwatch stage;
  const double before = frame->timings.depth_ms + frame->timings.transform_ms;
  {
    auto stream = streams_->Get(agent_id);
    MutexLock lock(stream->mutex);
    if (!stream->depth) {
      auto filter = DepthStreamFilter::Create(config_.depth.filter);
      if (!filter.ok()) return filter.status();
      stream->depth.emplace(std::move(filter).value());
    }
    const DepthFrameState state = stream->depth->Observe(frame->depth_m);
    stream->last_depth = state;
    ApplyDepthBand(frame, state, config_.depth.filter.remove_features_without_depth);
  }
  frame->timings.depth_ms += stage.Lap();
  PLACEDB_RETURN_IF_ERROR(Finish(frame, &stage));
  frame->timings.total_ms += frame->timings.depth_ms + frame->timings.transform_ms - before;
  return Status::Ok();
}

Result<LoopClosureOutcome> PlaceDatabase::CloseLoop(const ProcessedFrame& frame,
                                                    const PlaceMetadata& metadata,
                                                    const std::function<Result<PlaceId>()>& store,
                                                    PlaceSource* source) {
  if (frame.stream_pending) {
    return Status::FailedPrecondition("CloseLoop needs a finished frame: call AdvanceStream first");
  }
  if (!frame.valid) return Status::InvalidArgument("loop closure needs a valid frame");
  auto stream = streams_->Get(metadata.agent_id);
  MutexLock lock(stream->mutex);
  size_t replayed_places = 0;
  double replay_ms = 0;
  Stopwatch replay;
  const bool replay_due = !stream->loop;  // a new detector: the agent's places first
  if (replay_due) {
    LoopClosureConfig config = config_.loop_closure;
    config.scoring = config_.scoring;  // the long-term memory hands back the payloads' vectors
    stream->ltm = std::make_shared<PayloadLongTermMemory>(payloads_);
    auto detector = LoopClosureDetector::Create(vocabulary_.word_count(), config, stream->ltm);
    if (!detector.ok()) return detector.status();
    stream->loop = std::move(detector).value();
  }
  // The source is this call's (it reads at this frame's point of the stream), never kept: the
  // replay's places may move to long-term memory, and the update may retrieve them.
  stream->ltm->set_source(source);
  struct Unset {
    PayloadLongTermMemory* ltm;
    ~Unset() { ltm->set_source(nullptr); }
  } unset{stream->ltm.get()};
  if (replay_due) {
    auto replayed =
        ReplayAgentPlaces(metadata.agent_id, stream->loop.get(), stream->ltm.get(), source);
    if (!replayed.ok()) {
      stream->loop.reset();
      return replayed.status().WithContext("rebuilding the loop-closure memory of agent '" +
                                           metadata.agent_id + "'");
    }
    replayed_places = *replayed;
    replay_ms = replay.ElapsedMs();
  }
  auto update = stream->loop->Update(frame.bow, metadata.sequence);
  if (!update.ok()) return update.status();
  LoopClosureOutcome outcome;
  outcome.replayed = replayed_places;
  outcome.replay_ms = replay_ms;
  outcome.merged = update->merged;
  outcome.candidates = update->candidates;
  outcome.retrieved = update->retrieved.size();
  outcome.transferred = update->transferred.size();
  outcome.update_ms = update->total_ms;
  if (update->loop) {
    const PlaceId target = stream->ltm->Bound(*update->loop);
    bool keep = target != 0;  // else a place whose store had failed: nothing to return to
    if (keep && config_.verify_loops) {
      Match posed;
      posed.place = target;
      auto verified = VerifyLoop(frame, target, source, &posed);
      outcome.loop_inliers = verified.ok() ? *verified : 0;
      keep = verified.ok() && *verified >= config_.verification.min_inliers;
      outcome.loop_pose = std::move(posed.relative_pose);
      outcome.loop_pose_unavailable = std::move(posed.pose_unavailable);
    }
    if (keep) {
      outcome.loop = target;
      outcome.loop_posterior = update->best_posterior;
    } else {
      PLACEDB_RETURN_IF_ERROR(stream->loop->RejectLoop(update->place, *update->loop));
      outcome.loop_rejected = true;
      outcome.rejected_loop = target;
    }
  }
  outcome.best = stream->ltm->Bound(update->best);
  outcome.best_posterior = update->best_posterior;
  if (update->merged) {
    outcome.place = stream->ltm->Bound(update->place);
    return outcome;
  }
  Result<PlaceId> stored = store ? store() : Insert(frame, metadata);
  if (!stored.ok()) return stored.status();
  stream->ltm->Bind(update->place, *stored);
  outcome.place = *stored;
  return outcome;
}

Result<int> PlaceDatabase::VerifyLoop(const ProcessedFrame& frame, PlaceId place,
                                      PlaceSource* source, Match* pose) const {
  auto payload = source ? source->GetPayload(place) : payloads_->Get(place);
  if (!payload.ok()) return payload.status();
  VerificationConfig verification = config_.verification;
  if (verification.mode == VerificationMode::kDisabled) {
    verification.mode = VerificationMode::kExhaustive;
  }
  const bool want_pose = frame.geometry.camera.has_value();
  auto verified =
      VerifyGeometry(frame.static_features, frame.direct, (*payload)->features, (*payload)->direct,
                     verification, want_pose, CamerasOf(frame, **payload));
  if (!verified.ok()) return verified.status();
  if (verified->inliers >= verification.min_inliers) {
    AttachRelativePose(frame, **payload, verified->inlier_pairs, OctaveScaleFactor(config_), pose);
  }
  return verified->inliers;
}

Result<size_t> PlaceDatabase::ReplayAgentPlaces(const std::string& agent_id,
                                                LoopClosureDetector* detector,
                                                PayloadLongTermMemory* ltm,
                                                PlaceSource* source) const {
  // Oldest first: the agent's own order, then the id.
  auto older = [](uint64_t sequence_a, PlaceId a, uint64_t sequence_b, PlaceId b) {
    return sequence_a != sequence_b ? sequence_a < sequence_b : a < b;
  };
  size_t replayed = 0;
  auto replay = [&](const BowVector& bow, uint64_t sequence, PlaceId id) -> Status {
    if (bow.empty()) return Status::Ok();
    auto place = detector->Replay(bow, sequence);
    if (!place.ok()) return place.status();
    ltm->Bind(*place, id);
    ++replayed;
    return Status::Ok();
  };
  if (source) {
    auto places = source->AgentPlaces(agent_id);
    if (!places.ok()) return places.status();
    std::sort(places->begin(), places->end(), [&](const auto& a, const auto& b) {
      return older(a.sequence, a.id, b.sequence, b.id);
    });
    for (const PlaceSource::AgentPlace& place : *places) {
      PLACEDB_RETURN_IF_ERROR(replay(place.bow, place.sequence, place.id));
    }
    return replayed;
  }
  std::vector<std::shared_ptr<const PlaceRecord>> earlier;
  {
    ReaderLock lock(mutex_);
    for (const auto& [id, record] : records_) {
      if (record->metadata.agent_id == agent_id) earlier.push_back(record);
    }
  }
  std::sort(earlier.begin(), earlier.end(), [&](const auto& a, const auto& b) {
    return older(a->metadata.sequence, a->id, b->metadata.sequence, b->id);
  });
  for (const auto& record : earlier) {
    auto bow = payloads_->GetBow(record->id);  // one at a time: only the records in memory
    if (!bow.ok()) {
      if (bow.status().code() == StatusCode::kNotFound) continue;  // removed meanwhile
      return bow.status();
    }
    PLACEDB_RETURN_IF_ERROR(replay(*bow, record->metadata.sequence, record->id));
  }
  return replayed;
}

void PlaceDatabase::ResetLoopClosure(const std::string& agent_id) {
  auto stream = streams_->Find(agent_id);
  if (!stream) return;
  MutexLock lock(stream->mutex);
  stream->loop.reset();
  stream->ltm.reset();
}

Status PlaceDatabase::ResetStream(const std::string& agent_id) {
  if (!streams_->Erase(agent_id)) {
    return Status::NotFound("agent '" + agent_id + "' has no stream state");
  }
  return Status::Ok();
}

Result<LoopClosureStats> PlaceDatabase::LoopStats(const std::string& agent_id) const {
  auto stream = streams_->Find(agent_id);
  if (stream) {
    MutexLock lock(stream->mutex);
    if (stream->loop) return stream->loop->Stats();
  }
  return Status::NotFound("agent '" + agent_id + "' has no loop-closure state");
}

Result<AddResult> PlaceDatabase::Add(const Observation& observation) {
  auto processed = Process(observation, FrameRole::kStream);
  if (!processed.ok()) return processed.status();
  ProcessedFrame& frame = *processed;
  PLACEDB_RETURN_IF_ERROR(AdvanceStream(&frame, observation.metadata.agent_id));
  AddResult result;
  result.depth_state = frame.depth_state;
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
  if (frame.static_features.type() != config_.feature_type) {
    return Status::InvalidArgument("frame's features are not the database's type");
  }
  std::shared_ptr<PlacePayload> payload;
  if (payloads_->KeepsPayloads()) {
    payload = std::make_shared<PlacePayload>();
    payload->features = frame.static_features;
    payload->direct = frame.direct;
    payload->bow = frame.bow;
    payload->geometry = frame.geometry;
  }

  WriterLock lock(mutex_);
  record->id = id.value_or(next_id_);
  const PlaceId place = record->id;
  PLACEDB_RETURN_IF_ERROR(InsertLocked(std::move(record), frame.bow));
  if (Status stored = payloads_->Put(place, payload); !stored.ok()) {
    UndoInsertLocked(place, frame.bow);
    return stored;
  }
  if (config_.short_term.enabled && metadata.timestamp_ns > 0 && !frame.dynamic_bow.empty()) {
    AddShortTermLocked(place, metadata, frame);
  }
  return place;
}

Status PlaceDatabase::Restore(PlaceRecord record, const BowVector& bow) {
  WriterLock lock(mutex_);
  return InsertLocked(std::make_shared<const PlaceRecord>(std::move(record)), bow);
}

Result<PlaceDatabase::RestoredSegment> PlaceDatabase::PrepareRestore(
    std::vector<PlaceRecord> records, std::span<const BowVector> bows) const {
  if (records.size() != bows.size()) {
    return Status::InvalidArgument(std::to_string(records.size()) + " records but " +
                                   std::to_string(bows.size()) + " BoW vectors");
  }
  // Restore's first check. Ids increase, so only the first can be 0 (a later one is out of
  // order, which BuildSegment refuses).
  if (!records.empty() && records.front().id == 0) {
    return Status::InvalidArgument("place id 0 is reserved");
  }
  std::vector<InvertedIndex::BulkPlace> places;
  places.reserve(records.size());
  for (size_t i = 0; i < records.size(); ++i) places.push_back({records[i].id, &bows[i]});
  auto index = InvertedIndex::BuildSegment(vocabulary_.word_count(), places);
  if (!index.ok()) return index.status();
  RestoredSegment segment;
  segment.index = std::move(index).value();
  segment.records.reserve(records.size());
  for (PlaceRecord& record : records) {
    segment.records.push_back(std::make_shared<const PlaceRecord>(std::move(record)));
  }
  return segment;
}

Status PlaceDatabase::RestoreRange(RestoredSegment segment) {
  if (segment.records.empty()) return Status::Ok();
  WriterLock lock(mutex_);
  // The index refuses a segment that holds places; records_ mirrors the index, so checking
  // the records first keeps the refusal free of side effects.
  for (const auto& record : segment.records) {
    if (records_.count(record->id)) {
      return Status::AlreadyExists("place " + std::to_string(record->id) + " already exists");
    }
  }
  PLACEDB_RETURN_IF_ERROR(index_.Install(std::move(segment.index)));
  records_.reserve(records_.size() + segment.records.size());
  for (auto& record : segment.records) {
    descriptors_kept_ += record->counts.static_;
    descriptors_dropped_ += record->counts.dynamic;
    record_bytes_ += RecordBytes(*record);
    next_id_ = std::max(next_id_, record->id + 1);
    const PlaceId place = record->id;
    records_.emplace(place, std::move(record));
  }
  return Status::Ok();
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
  WriterLock lock(mutex_);
  return next_id_++;
}

void PlaceDatabase::ReserveIdsBelow(PlaceId next) {
  WriterLock lock(mutex_);
  next_id_ = std::max(next_id_, next);
}

void PlaceDatabase::CountInvalid(uint64_t frames) {
  WriterLock lock(mutex_);
  invalid_rejected_ += frames;
}

Status PlaceDatabase::Remove(PlaceId id) {
  WriterLock lock(mutex_);
  auto it = records_.find(id);
  if (it == records_.end()) return Status::NotFound("place " + std::to_string(id) + " not found");
  auto payload = payloads_->Get(id);
  if (!payload.ok()) return payload.status().WithContext("removing place " + std::to_string(id));
  // A persistent store makes the removal durable here; if it cannot, the place stays.
  if (Status erased = payloads_->Erase(id); !erased.ok()) return erased;
  PLACEDB_RETURN_IF_ERROR(index_.Remove(id, (*payload)->bow));
  RemoveShortTermLocked(id);
  const PlaceRecord& record = *it->second;
  descriptors_kept_ -= record.counts.static_;
  descriptors_dropped_ -= record.counts.dynamic;
  record_bytes_ -= RecordBytes(record);
  records_.erase(it);  // in-flight queries keep their shared_ptr until they finish
  return Status::Ok();
}

Result<QueryResult> PlaceDatabase::Query(const Observation& observation,
                                         const QueryOptions& options) const {
  auto processed = Process(observation, FrameRole::kQuery);
  if (!processed.ok()) return processed.status();
  if (options.timestamp_ns == 0 && observation.metadata.timestamp_ns != 0) {
    QueryOptions timed = options;
    timed.timestamp_ns = observation.metadata.timestamp_ns;
    return Search(*processed, timed);
  }
  return Search(*processed, options);
}

QueryResult PlaceDatabase::Search(const ProcessedFrame& frame, const QueryOptions& options) const {
  QueryResult result;
  result.valid = frame.valid;
  result.rejection = frame.rejection;
  result.counts = frame.counts;
  result.boxes_used = frame.boxes_used;
  result.timings = frame.timings;
  result.depth_state = frame.depth_state;
  if (!frame.valid || options.top_k == 0) return result;

  Stopwatch stage;
  std::vector<std::pair<ScoredPlace, std::shared_ptr<const PlaceRecord>>> candidates;
  // Per candidate: its DC features when the short-term tier holds them within the horizon.
  std::vector<std::shared_ptr<const std::pair<LocalFeatures, DirectIndex>>> recent_dynamic;
  {
    ReaderLock lock(mutex_);
    std::function<bool(PlaceId)> accept;
    if (options.accept) {
      // index_.Query calls it under this lock.
      accept = [&](PlaceId id) REQUIRES_SHARED(mutex_) {
        auto it = records_.find(id);
        return it != records_.end() && options.accept(*it->second);
      };
    }
    const std::vector<ScoredPlace> bonus = config_.short_term.enabled && !frame.dynamic_bow.empty()
                                               ? ShortTermBonusLocked(frame, options.timestamp_ns)
                                               : std::vector<ScoredPlace>();
    const double word_share =
        index_.place_count() >= options.skip_words_min_places ? options.max_word_share : 1.0;
    const std::vector<ScoredPlace> ranked =
        index_.Query(frame.bow, options.top_k, accept, bonus, options.search_threads, word_share);
    candidates.reserve(ranked.size());
    for (const ScoredPlace& scored : ranked) {
      candidates.emplace_back(scored, records_.at(scored.place));
    }
    if (!frame.dynamic_features.empty() && !short_term_.empty()) {
      const int64_t now = ShortTermNowLocked(options.timestamp_ns);
      recent_dynamic.resize(candidates.size());
      for (size_t i = 0; i < candidates.size(); ++i) {
        auto it = short_term_.find(candidates[i].first.place);
        if (it != short_term_.end() && InHorizon(it->second, now)) {
          recent_dynamic[i] = it->second.dynamic_features;
        }
      }
    }
  }
  result.timings.search_ms = stage.Lap();

  VerificationConfig verification = config_.verification;
  if (options.verified_only && verification.mode == VerificationMode::kDisabled) {
    // Verified matches asked of a map that does not verify by itself: verified on request (as
    // loop closure's VerifyLoop does), not an answer silently emptied of every candidate.
    verification.mode = VerificationMode::kExhaustive;
  }
  const size_t to_verify = verification.mode == VerificationMode::kDisabled
                               ? 0
                               : (verification.candidates > 0
                                      ? std::min(candidates.size(), size_t(verification.candidates))
                                      : candidates.size());
  const bool want_poses = options.relative_poses && frame.geometry.camera.has_value();
  const bool collect_inliers = options.include_correspondences || want_poses;
  const double octave_scale_factor = OctaveScaleFactor(config_);
  double pose_ms = 0;
  for (size_t i = 0; i < candidates.size(); ++i) {
    const auto& [scored, record] = candidates[i];
    Match match;
    match.place = scored.place;
    match.score = scored.score;
    match.metadata = record->metadata;
    if (i < to_verify) {
      auto payload = payloads_->Get(scored.place);
      if (!payload.ok()) continue;  // removed while we searched
      Result<VerificationResult> verified =
          i < recent_dynamic.size() && recent_dynamic[i]
              ? VerifyWithObjects(frame, **payload, *recent_dynamic[i], verification,
                                  collect_inliers)
              : VerifyGeometry(frame.static_features, frame.direct, (*payload)->features,
                               (*payload)->direct, verification, collect_inliers,
                               CamerasOf(frame, **payload));
      if (verified.ok()) {
        match.inliers = verified->inliers;
        match.verified = verified->verified;
        if (match.verified && options.relative_poses) {
          pose_ms += AttachRelativePose(frame, **payload, verified->inlier_pairs,
                                        octave_scale_factor, &match);
        }
        if (match.verified && options.include_correspondences) {
          match.correspondences = std::move(verified->inlier_pairs);
        }
      }
    }
    if (options.verified_only && !match.verified) continue;
    result.matches.push_back(std::move(match));
  }
  if (verification.rerank) {
    // Stable: verified first by inliers, the others keep their BoW order.
    std::stable_sort(result.matches.begin(), result.matches.end(),
                     [](const Match& a, const Match& b) {
                       if (a.verified != b.verified) return a.verified;
                       return a.verified && a.inliers > b.inliers;
                     });
  }
  result.timings.verify_ms = stage.Lap() - pose_ms;
  result.timings.pose_ms = pose_ms;
  result.timings.total_ms +=
      result.timings.search_ms + result.timings.verify_ms + result.timings.pose_ms;
  return result;
}

std::shared_ptr<const PlaceRecord> PlaceDatabase::Get(PlaceId id) const {
  ReaderLock lock(mutex_);
  auto it = records_.find(id);
  return it == records_.end() ? nullptr : it->second;
}

std::vector<PlaceId> PlaceDatabase::ListPlaces() const {
  std::vector<PlaceId> ids;
  {
    ReaderLock lock(mutex_);
    ids.reserve(records_.size());
    for (const auto& [id, record] : records_) ids.push_back(id);
  }
  std::sort(ids.begin(), ids.end());
  return ids;
}

PlacePage PlaceDatabase::ListPlacesBefore(PlaceId before, size_t limit, const PlaceFilter& filter,
                                          size_t max_examined) const {
  const auto passes = [&filter](const PlaceRecord& record) {
    const PlaceMetadata& metadata = record.metadata;
    if (!filter.agent_id.empty() && metadata.agent_id != filter.agent_id) return false;
    if (filter.from_timestamp_ns != 0 && metadata.timestamp_ns < filter.from_timestamp_ns) {
      return false;
    }
    return filter.to_timestamp_ns == 0 || metadata.timestamp_ns < filter.to_timestamp_ns;
  };
  PlacePage page;
  if (limit == 0 || max_examined == 0) {
    page.next_before = before;
    return page;
  }
  ReaderLock lock(mutex_);
  // Ids are handed out ascending and never reused: the walk goes down the id range, so the order
  // is stable while places are added (above) or removed.
  PlaceId id = before == 0 || before > next_id_ ? next_id_ : before;
  size_t examined = 0;
  while (id > 1 && page.places.size() < limit && examined < max_examined) {
    --id;
    ++examined;
    auto it = records_.find(id);
    if (it != records_.end() && passes(*it->second)) page.places.push_back(it->second);
  }
  page.next_before = id > 1 ? id : 0;
  return page;
}

DatabaseStats PlaceDatabase::Stats() const {
  ReaderLock lock(mutex_);
  DatabaseStats stats;
  stats.places = records_.size();
  stats.descriptors_kept = descriptors_kept_;
  stats.descriptors_dropped = descriptors_dropped_;
  stats.invalid_rejected = invalid_rejected_;
  stats.index_bytes = index_.MemoryBytes();
  stats.record_bytes = record_bytes_;
  stats.payload_bytes = payloads_->MemoryBytes();
  stats.short_term_places = short_term_.size();
  stats.short_term_bytes = short_term_index_.MemoryBytes();
  for (const auto& [id, entry] : short_term_) {
    stats.short_term_bytes += sizeof(entry) + entry.dynamic_bow.capacity() * sizeof(BowEntry);
    if (entry.dynamic_features) {
      const auto& [features, direct] = *entry.dynamic_features;
      stats.short_term_bytes +=
          features.MemoryBytes() +
          (direct.node_ids.capacity() + direct.offsets.capacity() + direct.feature_ids.capacity()) *
              sizeof(uint32_t);
    }
  }
  lock.Unlock();
  for (const auto& stream : streams_->All()) {
    ++stats.streams;
    MutexLock stream_lock(stream->mutex);
    if (!stream->loop) continue;
    const LoopClosureStats loop = stream->loop->Stats();
    stats.loop_working_memory += loop.short_term + loop.working;
    stats.loop_long_term += loop.long_term;
    stats.loops_accepted += loop.loops;
    stats.loops_rejected += loop.rejected;
  }
  return stats;
}

namespace {

double DynamicShare(const FrameCounts& counts) {
  return counts.total == 0 ? 0.0 : double(counts.dynamic) / double(counts.total);
}

}  // namespace

void PlaceDatabase::AddShortTermLocked(PlaceId place, const PlaceMetadata& metadata,
                                       const ProcessedFrame& frame) {
  if (!short_term_index_.Add(place, frame.dynamic_bow).ok()) return;
  std::shared_ptr<const std::pair<LocalFeatures, DirectIndex>> features;
  if (!frame.dynamic_features.empty()) {
    features = std::make_shared<const std::pair<LocalFeatures, DirectIndex>>(frame.dynamic_features,
                                                                             frame.dynamic_direct);
  }
  short_term_.emplace(place,
                      ShortTermEntry{metadata.timestamp_ns, metadata.agent_id, frame.dynamic_bow,
                                     DynamicShare(frame.counts), std::move(features)});
  short_term_by_time_.emplace(metadata.timestamp_ns, place);
  TimeOrdered& agent = short_term_by_agent_[metadata.agent_id];
  agent.emplace(metadata.timestamp_ns, place);
  // Evict what left the horizon of the agent's newest observation, then the oldest of all
  // beyond max_places.
  const int64_t newest = agent.rbegin()->first;
  while (agent.begin()->first < newest - config_.short_term.horizon_ns) {
    RemoveShortTermLocked(agent.begin()->second);  // `agent` keeps its newest entry
  }
  while (short_term_.size() > config_.short_term.max_places) {
    RemoveShortTermLocked(short_term_by_time_.begin()->second);
  }
}

int64_t PlaceDatabase::ShortTermNowLocked(int64_t query_timestamp_ns) const {
  return query_timestamp_ns > 0 ? query_timestamp_ns : short_term_by_time_.rbegin()->first;
}

bool PlaceDatabase::InHorizon(const ShortTermEntry& entry, int64_t now) const {
  const int64_t horizon = config_.short_term.horizon_ns;
  return entry.timestamp_ns <= now + horizon && entry.timestamp_ns >= now - horizon;
}

void PlaceDatabase::RemoveShortTermLocked(PlaceId place) {
  auto it = short_term_.find(place);
  if (it == short_term_.end()) return;
  const std::pair<int64_t, PlaceId> key{it->second.timestamp_ns, place};
  (void)short_term_index_.Remove(place, it->second.dynamic_bow);
  short_term_by_time_.erase(key);
  auto agent = short_term_by_agent_.find(it->second.agent_id);
  if (agent != short_term_by_agent_.end()) {
    agent->second.erase(key);
    if (agent->second.empty()) short_term_by_agent_.erase(agent);
  }
  short_term_.erase(it);
}

std::vector<ScoredPlace> PlaceDatabase::ShortTermBonusLocked(const ProcessedFrame& frame,
                                                             int64_t timestamp_ns) const {
  std::vector<ScoredPlace> bonus;
  if (short_term_.empty()) return bonus;
  const int64_t now = ShortTermNowLocked(timestamp_ns);
  const double query_share = DynamicShare(frame.counts);
  for (const ScoredPlace& scored : short_term_index_.Query(frame.dynamic_bow, short_term_.size())) {
    const ShortTermEntry& entry = short_term_.at(scored.place);
    if (!InHorizon(entry, now)) continue;
    const double share = std::min({query_share, entry.dynamic_share, 0.9});
    bonus.push_back(
        {scored.place, double(config_.short_term.weight) * scored.score * share / (1.0 - share)});
  }
  return bonus;
}

PlaceId PlaceDatabase::next_id() const {
  ReaderLock lock(mutex_);
  return next_id_;
}

}  // namespace placedb
