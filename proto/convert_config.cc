#include "proto/convert_config.h"

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/base/text.h"
#include "proto/field_errors.h"

namespace placedb::wire {

using internal::Invalid;
using internal::Num;

// ---- Enums -------------------------------------------------------------------------------------

v1::FeatureType FeatureTypeToProto(FeatureType type) {
  return type == FeatureType::kSift ? v1::FEATURE_TYPE_SIFT : v1::FEATURE_TYPE_ORB;
}

Result<FilterMethod> FilterFromProto(v1::FilterMethod method, const std::string& field) {
  switch (method) {
    case v1::FILTER_METHOD_UNSPECIFIED:
    case v1::FILTER_METHOD_KEYPOINT_IN_BOX:
      return FilterMethod::kKeypointInBox;
    case v1::FILTER_METHOD_NONE:
      return FilterMethod::kNone;
    case v1::FILTER_METHOD_CORNER_DISTANCE:
      return FilterMethod::kCornerDistance;
    case v1::FILTER_METHOD_EXACT_COVERAGE:
      return FilterMethod::kExactCoverage;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(method)));
  }
}

Result<BoxRefinement> BoxRefinementFromProto(v1::BoxRefinement method, const std::string& field) {
  switch (method) {
    case v1::BOX_REFINEMENT_GRABCUT:
      return BoxRefinement::kGrabCut;
    case v1::BOX_REFINEMENT_NONE:
      return BoxRefinement::kNone;
    case v1::BOX_REFINEMENT_UNSPECIFIED:
    case v1::BOX_REFINEMENT_SHAPE:
      return BoxRefinement::kShape;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(method)));
  }
}

v1::BoxRefinement BoxRefinementToProto(BoxRefinement method) {
  switch (method) {
    case BoxRefinement::kNone:
      return v1::BOX_REFINEMENT_NONE;
    case BoxRefinement::kShape:
      return v1::BOX_REFINEMENT_SHAPE;
    case BoxRefinement::kGrabCut:
      return v1::BOX_REFINEMENT_GRABCUT;
  }
  return v1::BOX_REFINEMENT_UNSPECIFIED;
}

v1::FilterMethod FilterToProto(FilterMethod method) {
  switch (method) {
    case FilterMethod::kNone:
      return v1::FILTER_METHOD_NONE;
    case FilterMethod::kKeypointInBox:
      return v1::FILTER_METHOD_KEYPOINT_IN_BOX;
    case FilterMethod::kCornerDistance:
      return v1::FILTER_METHOD_CORNER_DISTANCE;
    case FilterMethod::kExactCoverage:
      return v1::FILTER_METHOD_EXACT_COVERAGE;
  }
  return v1::FILTER_METHOD_UNSPECIFIED;
}

Result<ScoringType> ScoringFromProto(v1::Scoring scoring, const std::string& field) {
  switch (scoring) {
    case v1::SCORING_UNSPECIFIED:
    case v1::SCORING_L1:
      return ScoringType::kL1;
    case v1::SCORING_L2:
      return ScoringType::kL2;
    case v1::SCORING_CHI_SQUARE:
      return ScoringType::kChiSquare;
    case v1::SCORING_KL:
      return ScoringType::kKL;
    case v1::SCORING_BHATTACHARYYA:
      return ScoringType::kBhattacharyya;
    case v1::SCORING_DOT_PRODUCT:
      return ScoringType::kDotProduct;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(scoring)));
  }
}

v1::Scoring ScoringToProto(ScoringType scoring) {
  switch (scoring) {
    case ScoringType::kL1:
      return v1::SCORING_L1;
    case ScoringType::kL2:
      return v1::SCORING_L2;
    case ScoringType::kChiSquare:
      return v1::SCORING_CHI_SQUARE;
    case ScoringType::kKL:
      return v1::SCORING_KL;
    case ScoringType::kBhattacharyya:
      return v1::SCORING_BHATTACHARYYA;
    case ScoringType::kDotProduct:
      return v1::SCORING_DOT_PRODUCT;
  }
  return v1::SCORING_UNSPECIFIED;
}

Result<VerificationMode> VerificationFromProto(v1::VerificationMode mode,
                                               const std::string& field) {
  switch (mode) {
    case v1::VERIFICATION_MODE_UNSPECIFIED:
    case v1::VERIFICATION_MODE_DISABLED:
      return VerificationMode::kDisabled;
    case v1::VERIFICATION_MODE_DIRECT_INDEX:
      return VerificationMode::kDirectIndex;
    case v1::VERIFICATION_MODE_EXHAUSTIVE:
      return VerificationMode::kExhaustive;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(mode)));
  }
}

v1::VerificationMode VerificationToProto(VerificationMode mode) {
  switch (mode) {
    case VerificationMode::kDisabled:
      return v1::VERIFICATION_MODE_DISABLED;
    case VerificationMode::kDirectIndex:
      return v1::VERIFICATION_MODE_DIRECT_INDEX;
    case VerificationMode::kExhaustive:
      return v1::VERIFICATION_MODE_EXHAUSTIVE;
  }
  return v1::VERIFICATION_MODE_UNSPECIFIED;
}

Result<BoxSource> BoxSourceFromProto(v1::BoxSource source, const std::string& field) {
  switch (source) {
    case v1::BOX_SOURCE_UNSPECIFIED:
    case v1::BOX_SOURCE_AGENT:
      return BoxSource::kAgent;
    case v1::BOX_SOURCE_SERVER:
      return BoxSource::kServer;
    case v1::BOX_SOURCE_BOTH:
      return BoxSource::kBoth;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(source)));
  }
}

v1::BoxSource BoxSourceToProto(BoxSource source) {
  switch (source) {
    case BoxSource::kAgent:
      return v1::BOX_SOURCE_AGENT;
    case BoxSource::kServer:
      return v1::BOX_SOURCE_SERVER;
    case BoxSource::kBoth:
      return v1::BOX_SOURCE_BOTH;
  }
  return v1::BOX_SOURCE_UNSPECIFIED;
}

Result<BandPolicy> BandPolicyFromProto(v1::BandPolicy policy, const std::string& field) {
  switch (policy) {
    case v1::BAND_POLICY_UNSPECIFIED:
    case v1::BAND_POLICY_APPEARED_LAYER:
      return BandPolicy::kAppearedLayer;
    case v1::BAND_POLICY_FIXED:
      return BandPolicy::kFixed;
    case v1::BAND_POLICY_NEAREST_LAYER:
      return BandPolicy::kNearestLayer;
    default:
      return Invalid(field, "unknown value " + std::to_string(int(policy)));
  }
}

v1::BandPolicy BandPolicyToProto(BandPolicy policy) {
  switch (policy) {
    case BandPolicy::kFixed:
      return v1::BAND_POLICY_FIXED;
    case BandPolicy::kNearestLayer:
      return v1::BAND_POLICY_NEAREST_LAYER;
    case BandPolicy::kAppearedLayer:
      return v1::BAND_POLICY_APPEARED_LAYER;
  }
  return v1::BAND_POLICY_UNSPECIFIED;
}

// ---- Maps ---------------------------------------------------------------------------------------

namespace {

Result<FeatureType> FeatureTypeFromProto(v1::FeatureType type, const MapVocabulary& vocabulary) {
  FeatureType wanted = vocabulary.feature_type;
  switch (type) {
    case v1::FEATURE_TYPE_UNSPECIFIED:
      return vocabulary.feature_type;
    case v1::FEATURE_TYPE_ORB:
      wanted = FeatureType::kOrb;
      break;
    case v1::FEATURE_TYPE_SIFT:
      wanted = FeatureType::kSift;
      break;
    default:
      return Invalid("config.feature_type", "unknown value " + std::to_string(int(type)));
  }
  if (wanted != vocabulary.feature_type) {
    return Invalid("config.feature_type",
                   v1::FeatureType_Name(FeatureTypeToProto(wanted)) + " needs a " +
                       VocabularyKindName(wanted) + " vocabulary, but vocabulary '" +
                       vocabulary.name + "' is " + VocabularyKindName(vocabulary.feature_type) +
                       ": name one of the server's " + VocabularyKindName(wanted) +
                       " vocabularies in config.vocabulary (GetServerInfo lists them)");
  }
  return wanted;
}

Status BandFromProto(const v1::DepthBand& band, const std::string& field, DepthBand* out) {
  if (!std::isfinite(band.near_m()) || !std::isfinite(band.far_m()) || band.near_m() < 0 ||
      band.far_m() < band.near_m()) {
    return Invalid(field, "must satisfy 0 <= near_m <= far_m, got [" + Num(band.near_m()) + ", " +
                              Num(band.far_m()) + "]");
  }
  *out = DepthBand{band.near_m(), band.far_m()};
  return Status::Ok();
}

// The map's depth handling (docs/rgbd.md); messages name the proto fields.
Status DepthSettingsFromProto(const v1::DepthSettings& s, DepthConfig* depth) {
  const std::string at = "config.depth.";
  if (s.has_refine_boxes()) depth->refine_boxes = s.refine_boxes();
  if (s.has_stream_filter()) depth->stream_filter = s.stream_filter();
  DepthFilterConfig& f = depth->filter;
  if (s.has_scale()) {
    if (!std::isfinite(s.scale()) || !(s.scale() > 0)) {
      return Invalid(at + "scale",
                     "must be positive (metres per png16 unit), got " + Num(s.scale()));
    }
    f.format.metres_per_unit = s.scale();
  }
  if (s.has_min_depth_m()) {
    if (!std::isfinite(s.min_depth_m()) || s.min_depth_m() < 0) {
      return Invalid(at + "min_depth_m", "must be >= 0, got " + Num(s.min_depth_m()));
    }
    f.format.min_depth_m = s.min_depth_m();
  }
  if (s.has_max_depth_m()) {
    if (!std::isfinite(s.max_depth_m()) || !(s.max_depth_m() > 0)) {
      return Invalid(at + "max_depth_m", "must be positive, got " + Num(s.max_depth_m()));
    }
    f.format.max_depth_m = s.max_depth_m();
  }
  if (!(f.format.max_depth_m > f.format.min_depth_m)) {
    return Invalid(at + (s.has_max_depth_m() ? "max_depth_m" : "min_depth_m"),
                   "the valid range must satisfy min_depth_m < max_depth_m, got [" +
                       Num(f.format.min_depth_m) + ", " + Num(f.format.max_depth_m) + "]");
  }
  if (s.has_mean_all_pixels()) {
    f.mean_mode = s.mean_all_pixels() ? MeanDepthMode::kAllPixels : MeanDepthMode::kValidPixels;
  }
  if (s.has_threshold_m()) {
    if (!std::isfinite(s.threshold_m()) || !(s.threshold_m() > 0)) {
      return Invalid(at + "threshold_m", "must be positive, got " + Num(s.threshold_m()));
    }
    f.threshold_m = s.threshold_m();
  }
  if (s.has_persistence()) {
    if (s.persistence() < 0 || s.persistence() > 10000) {
      return Invalid(at + "persistence",
                     "must be in [0, 10000], got " + std::to_string(s.persistence()));
    }
    f.persistence = s.persistence();
  }
  if (s.has_static_window()) {
    if (s.static_window() < 1 || s.static_window() > 10000) {
      return Invalid(at + "static_window",
                     "must be in [1, 10000], got " + std::to_string(s.static_window()));
    }
    f.static_window = s.static_window();
    // The warm-up (not exposed) builds the window: it cannot be longer than the window.
    f.warmup_frames = std::min(f.warmup_frames, f.static_window);
  }
  auto policy = BandPolicyFromProto(s.band_policy(), at + "band_policy");
  if (!policy.ok()) return policy.status();
  f.band_policy = *policy;
  if (s.has_rise_band()) {
    PLACEDB_RETURN_IF_ERROR(BandFromProto(s.rise_band(), at + "rise_band", &f.rise_band));
  }
  if (s.has_fall_band()) {
    PLACEDB_RETURN_IF_ERROR(BandFromProto(s.fall_band(), at + "fall_band", &f.fall_band));
  }
  if (s.has_remove_features_without_depth()) {
    f.remove_features_without_depth = s.remove_features_without_depth();
  }
  if (s.has_use_range()) f.use_range = s.use_range();
  if (s.has_rebaseline_after()) {
    if (s.rebaseline_after() < 0) {
      return Invalid(at + "rebaseline_after",
                     "must be >= 0 (0 = never), got " + std::to_string(s.rebaseline_after()));
    }
    f.rebaseline_after = s.rebaseline_after();
  }
  return Status::Ok();
}

Status LoopClosureSettingsFromProto(const v1::LoopClosureSettings& s, LoopClosureConfig* c,
                                    bool* verify_loops) {
  if (s.has_verify()) *verify_loops = s.verify();
  const std::string at = "config.loop_closure.";
  if (s.has_loop_threshold()) {
    if (!(s.loop_threshold() >= 0 && s.loop_threshold() <= 1)) {
      return Invalid(at + "loop_threshold", "must be in [0, 1], got " + Num(s.loop_threshold()));
    }
    c->loop_threshold = s.loop_threshold();
  }
  if (s.has_rehearsal_threshold()) {
    if (!std::isfinite(s.rehearsal_threshold()) || !(s.rehearsal_threshold() >= 0)) {
      return Invalid(at + "rehearsal_threshold", "must be >= 0 (above 1 disables rehearsal), got " +
                                                     Num(s.rehearsal_threshold()));
    }
    c->rehearsal_threshold = s.rehearsal_threshold();
  }
  if (s.has_short_term_memory()) {
    if (s.short_term_memory() < 0 || s.short_term_memory() > 100000) {
      return Invalid(at + "short_term_memory",
                     "must be in [0, 100000], got " + std::to_string(s.short_term_memory()));
    }
    c->short_term_memory = s.short_term_memory();
  }
  if (s.has_max_working_memory()) c->max_working_memory = s.max_working_memory();
  if (s.has_time_budget_ms()) {
    if (!std::isfinite(s.time_budget_ms()) || !(s.time_budget_ms() >= 0)) {
      return Invalid(at + "time_budget_ms",
                     "must be >= 0 (0 = no budget), got " + Num(s.time_budget_ms()));
    }
    c->time_budget_ms = s.time_budget_ms();
  }
  if (s.has_min_candidates()) {
    if (s.min_candidates() < 1 || s.min_candidates() > 100000) {
      return Invalid(at + "min_candidates",
                     "must be in [1, 100000], got " + std::to_string(s.min_candidates()));
    }
    c->min_candidates = s.min_candidates();
  }
  return Status::Ok();
}

Status CheckBudget(const char* field, int max_features, uint32_t max_descriptors_per_frame) {
  if (uint64_t(max_features) > max_descriptors_per_frame) {
    return Status::ResourceExhausted(
        std::string(field) + " = " + std::to_string(max_features) +
        " exceeds limits.max_descriptors_per_frame = " + std::to_string(max_descriptors_per_frame));
  }
  return Status::Ok();
}

}  // namespace

Result<MapOptions> MapOptionsFromProto(const v1::MapConfig& c, uint32_t max_descriptors_per_frame,
                                       const MapVocabulary& vocabulary,
                                       ServiceMapSettings* settings) {
  MapOptions options;
  DatabaseConfig& d = options.database;
  auto feature_type = FeatureTypeFromProto(c.feature_type(), vocabulary);
  if (!feature_type.ok()) return feature_type.status();
  d.feature_type = *feature_type;

  const v1::OrbSettings& orb = c.orb();
  if (orb.has_max_features()) d.orb.max_features = orb.max_features();
  if (orb.has_scale_factor()) d.orb.scale_factor = orb.scale_factor();
  if (orb.has_levels()) d.orb.levels = orb.levels();
  if (orb.has_edge_threshold()) d.orb.edge_threshold = orb.edge_threshold();
  if (orb.has_patch_size()) d.orb.patch_size = orb.patch_size();
  if (orb.has_fast_threshold()) d.orb.fast_threshold = orb.fast_threshold();

  const v1::SiftSettings& sift = c.sift();
  if (sift.has_max_features()) d.sift.max_features = sift.max_features();
  if (sift.has_octave_layers()) d.sift.octave_layers = sift.octave_layers();
  if (sift.has_contrast_threshold()) d.sift.contrast_threshold = sift.contrast_threshold();
  if (sift.has_edge_threshold()) d.sift.edge_threshold = sift.edge_threshold();
  if (sift.has_sigma()) d.sift.sigma = sift.sigma();

  PLACEDB_RETURN_IF_ERROR(DepthSettingsFromProto(c.depth(), &d.depth));
  PLACEDB_RETURN_IF_ERROR(
      LoopClosureSettingsFromProto(c.loop_closure(), &d.loop_closure, &d.verify_loops));

  const v1::VocabularyPolicy& policy = c.vocabulary_policy();
  if (policy.adapt_after_descriptors() != 0 && policy.adapt_after_descriptors() < 5000) {
    return Invalid("config.vocabulary_policy.adapt_after_descriptors",
                   "must be 0 (never) or at least 5000 (what learning needs), got " +
                       std::to_string(policy.adapt_after_descriptors()));
  }
  if (!(policy.regrow_factor() == 0 ||
        (policy.regrow_factor() > 1 && policy.regrow_factor() <= 1000))) {
    return Invalid("config.vocabulary_policy.regrow_factor",
                   "must be 0 (never) or in (1, 1000], got " + Num(policy.regrow_factor()));
  }
  settings->adapt_after_descriptors = policy.adapt_after_descriptors();
  settings->regrow_factor = policy.regrow_factor();

  const v1::DetectionSettings& det = c.detection();
  settings->detection_enabled = !det.has_enabled() || det.enabled();
  auto source = BoxSourceFromProto(det.box_source(), "config.detection.box_source");
  if (!source.ok()) return source.status();
  settings->box_source = *source;
  if (det.has_min_confidence()) d.min_box_confidence = det.min_confidence();
  if (!(d.min_box_confidence >= 0.0f && d.min_box_confidence <= 1.0f)) {
    return Invalid("config.detection.min_confidence",
                   "must be in [0, 1], got " + Num(det.min_confidence()));
  }
  if (det.classes_size() > 0) {
    d.dynamic_classes.clear();
    for (int i = 0; i < det.classes_size(); ++i) {
      auto id = CocoClassId(det.classes(i));
      if (!id.ok()) {
        return Invalid("config.detection.classes[" + std::to_string(i) + "]",
                       id.status().message());
      }
      if (std::find(d.dynamic_classes.begin(), d.dynamic_classes.end(), *id) ==
          d.dynamic_classes.end()) {
        d.dynamic_classes.push_back(*id);
      }
    }
  }
  // Detection off: no box selects any class, so boxes never reach the filter (a mask still does).
  if (!settings->detection_enabled) d.dynamic_classes.clear();

  const v1::FilterSettings& f = c.filter();
  auto method = FilterFromProto(f.method(), "config.filter.method");
  if (!method.ok()) return method.status();
  d.filter.method = *method;
  if (f.has_sensitivity_threshold()) d.filter.sensitivity_threshold = f.sensitivity_threshold();
  if (f.has_place_threshold()) d.filter.place_threshold = f.place_threshold();
  d.static_feature_budget = !f.has_static_feature_budget() || f.static_feature_budget();
  auto refinement = BoxRefinementFromProto(f.box_refinement(), "config.filter.box_refinement");
  if (!refinement.ok()) return refinement.status();
  d.box_refinement.method = *refinement;
  const v1::ShortTermSettings& st = f.short_term();
  d.short_term.enabled = !st.has_enabled() || st.enabled();
  if (st.has_horizon_s()) {
    if (!(st.horizon_s() > 0 && st.horizon_s() <= 1e9)) {
      return Invalid("config.filter.short_term.horizon_s",
                     "must be in (0, 1e9] seconds, got " + Num(st.horizon_s()));
    }
    d.short_term.horizon_ns = int64_t(st.horizon_s() * 1e9);
  }
  if (st.has_max_places()) d.short_term.max_places = st.max_places();
  if (st.has_weight()) d.short_term.weight = st.weight();

  auto scoring = ScoringFromProto(c.scoring(), "config.scoring");
  if (!scoring.ok()) return scoring.status();
  d.scoring = *scoring;

  const v1::VerificationSettings& v = c.verification();
  auto mode = VerificationFromProto(v.mode(), "config.verification.mode");
  if (!mode.ok()) return mode.status();
  d.verification.mode = *mode;
  if (v.has_levels_up()) d.verification.levels_up = v.levels_up();
  if (v.has_min_inliers()) d.verification.min_inliers = v.min_inliers();
  if (v.has_candidates()) d.verification.candidates = v.candidates();
  d.verification.rerank = !v.has_rerank() || v.rerank();
  if (d.verification.candidates < 0) {
    return Invalid("config.verification.candidates", "must be >= 0");
  }
  options.store_invalid = c.store_invalid();
  // Thumbnails: 0 takes the default; the settings are validated even when off, so that turning
  // them on later needs no other change.
  const v1::ThumbnailSettings& t = c.thumbnails();
  options.thumbnails.enabled = t.enabled();
  options.thumbnails.max_side = t.max_side() == 0 ? kDefaultThumbnailSide : t.max_side();
  options.thumbnails.jpeg_quality =
      t.jpeg_quality() == 0 ? kDefaultThumbnailQuality : t.jpeg_quality();
  if (Status valid = ValidateThumbnailSettings(options.thumbnails); !valid.ok()) {
    return Status::InvalidArgument("config." + valid.message());
  }
  const double hits_above = c.dynamics().count_query_hits_above();
  if (!std::isfinite(hits_above) || hits_above < 0) {
    return Invalid("config.dynamics.count_query_hits_above",
                   "must be a finite score >= 0 (0 = off)");
  }
  options.count_query_hits_above = hits_above;

  // The core's messages name fields relative to the DatabaseConfig ("orb.max_features ...").
  if (Status valid = ValidateDatabaseConfig(d); !valid.ok()) {
    return Status::InvalidArgument("config." + valid.message());
  }
  // The map's feature budget: only its own feature type extracts.
  if (d.feature_type == FeatureType::kSift) {
    // 0 ("all") is capped by the server's limit, so a frame never exceeds it.
    // (The limit is a uint32 of the server's configuration: clamped, never wrapped, to an int.)
    if (d.sift.max_features == 0) {
      d.sift.max_features = int(std::min<uint32_t>(max_descriptors_per_frame, INT32_MAX));
    }
    PLACEDB_RETURN_IF_ERROR(
        CheckBudget("config.sift.max_features", d.sift.max_features, max_descriptors_per_frame));
  } else {
    PLACEDB_RETURN_IF_ERROR(
        CheckBudget("config.orb.max_features", d.orb.max_features, max_descriptors_per_frame));
  }
  return options;
}

void MapConfigToProto(const MapOptions& options, const ServiceMapSettings& settings,
                      const std::string& vocabulary_name, v1::MapConfig* out) {
  const DatabaseConfig& d = options.database;
  out->set_vocabulary(vocabulary_name);
  out->set_feature_type(FeatureTypeToProto(d.feature_type));
  v1::OrbSettings* orb = out->mutable_orb();
  orb->set_max_features(d.orb.max_features);
  orb->set_scale_factor(d.orb.scale_factor);
  orb->set_levels(d.orb.levels);
  orb->set_edge_threshold(d.orb.edge_threshold);
  orb->set_patch_size(d.orb.patch_size);
  orb->set_fast_threshold(d.orb.fast_threshold);
  v1::SiftSettings* sift = out->mutable_sift();
  sift->set_max_features(d.sift.max_features);
  sift->set_octave_layers(d.sift.octave_layers);
  sift->set_contrast_threshold(d.sift.contrast_threshold);
  sift->set_edge_threshold(d.sift.edge_threshold);
  sift->set_sigma(d.sift.sigma);
  const DepthFilterConfig& df = d.depth.filter;
  v1::DepthSettings* depth = out->mutable_depth();
  depth->set_refine_boxes(d.depth.refine_boxes);
  depth->set_stream_filter(d.depth.stream_filter);
  depth->set_scale(float(df.format.metres_per_unit));
  depth->set_min_depth_m(df.format.min_depth_m);
  depth->set_max_depth_m(df.format.max_depth_m);
  depth->set_mean_all_pixels(df.mean_mode == MeanDepthMode::kAllPixels);
  depth->set_threshold_m(df.threshold_m);
  depth->set_persistence(df.persistence);
  depth->set_static_window(df.static_window);
  depth->set_band_policy(BandPolicyToProto(df.band_policy));
  depth->mutable_rise_band()->set_near_m(df.rise_band.near_m);
  depth->mutable_rise_band()->set_far_m(df.rise_band.far_m);
  depth->mutable_fall_band()->set_near_m(df.fall_band.near_m);
  depth->mutable_fall_band()->set_far_m(df.fall_band.far_m);
  depth->set_remove_features_without_depth(df.remove_features_without_depth);
  depth->set_use_range(df.use_range);
  depth->set_rebaseline_after(df.rebaseline_after);
  const LoopClosureConfig& lc = d.loop_closure;
  v1::LoopClosureSettings* loop = out->mutable_loop_closure();
  loop->set_loop_threshold(lc.loop_threshold);
  loop->set_rehearsal_threshold(lc.rehearsal_threshold);
  loop->set_short_term_memory(lc.short_term_memory);
  loop->set_max_working_memory(uint32_t(lc.max_working_memory));
  loop->set_time_budget_ms(lc.time_budget_ms);
  loop->set_min_candidates(lc.min_candidates);
  loop->set_verify(d.verify_loops);
  out->mutable_vocabulary_policy()->set_adapt_after_descriptors(settings.adapt_after_descriptors);
  out->mutable_vocabulary_policy()->set_regrow_factor(settings.regrow_factor);
  v1::DetectionSettings* det = out->mutable_detection();
  det->set_enabled(settings.detection_enabled);
  for (int id : d.dynamic_classes) det->add_classes(CocoClassName(id));
  det->set_min_confidence(d.min_box_confidence);
  det->set_box_source(BoxSourceToProto(settings.box_source));
  v1::FilterSettings* f = out->mutable_filter();
  f->set_method(FilterToProto(d.filter.method));
  f->set_sensitivity_threshold(d.filter.sensitivity_threshold);
  f->set_place_threshold(d.filter.place_threshold);
  f->set_box_refinement(BoxRefinementToProto(d.box_refinement.method));
  f->set_static_feature_budget(d.static_feature_budget);
  v1::ShortTermSettings* st = f->mutable_short_term();
  st->set_enabled(d.short_term.enabled);
  st->set_horizon_s(double(d.short_term.horizon_ns) / 1e9);
  st->set_max_places(d.short_term.max_places);
  st->set_weight(d.short_term.weight);
  out->set_scoring(ScoringToProto(d.scoring));
  v1::VerificationSettings* v = out->mutable_verification();
  v->set_mode(VerificationToProto(d.verification.mode));
  v->set_levels_up(d.verification.levels_up);
  v->set_min_inliers(d.verification.min_inliers);
  v->set_candidates(d.verification.candidates);
  v->set_rerank(d.verification.rerank);
  out->set_store_invalid(options.store_invalid);
  v1::ThumbnailSettings* thumbnails = out->mutable_thumbnails();
  thumbnails->set_enabled(options.thumbnails.enabled);
  thumbnails->set_max_side(options.thumbnails.max_side);
  thumbnails->set_jpeg_quality(options.thumbnails.jpeg_quality);
  out->mutable_dynamics()->set_count_query_hits_above(options.count_query_hits_above);
}

void MapStatsToProto(const MapStats& stats, v1::MapStats* out) {
  out->set_places(stats.database.places);
  out->set_descriptors_kept(stats.database.descriptors_kept);
  out->set_descriptors_dropped(stats.database.descriptors_dropped);
  out->set_invalid_rejected(stats.database.invalid_rejected);
  out->set_invalid_stored(stats.invalid_stored);
  out->set_bytes_on_disk(stats.bytes_on_disk);
  out->set_bytes_in_memory(stats.bytes_in_memory);
  out->set_streams(stats.database.streams);
  out->set_loop_working_memory(stats.database.loop_working_memory);
  out->set_loop_long_term(stats.database.loop_long_term);
  out->set_loops_accepted(stats.database.loops_accepted);
  out->set_loops_rejected(stats.database.loops_rejected);
  out->set_short_term_places(stats.database.short_term_places);
}

void MapDamageToProto(const MapDamage& damage, v1::MapDamage* out) {
  out->set_reason(damage.reason);
  out->set_writes_lost(damage.writes_lost);
  out->set_places_lost(damage.places_lost);
  out->set_first_lost_place(damage.first_lost);
  out->set_last_lost_place(damage.last_lost);
  out->set_recovered_unix_ms(damage.recovered_unix_ms);
  out->set_records_lost(damage.records_lost);
  out->set_bow_lost(damage.bow_lost);
  out->set_features_lost(damage.features_lost);
  out->set_quarantine(damage.quarantine);
}

void ScrubReportToProto(const ScrubReport& report, v1::ScrubReport* out) {
  out->set_places_checked(report.places_checked);
  out->set_files_checked(report.files_checked);
  for (const ScrubReport::Place& place : report.damaged_places) {
    v1::ScrubReport::DamagedPlace* damaged = out->add_damaged_places();
    damaged->set_place_id(place.id);
    damaged->set_reason(place.reason);
  }
  for (const ScrubReport::File& file : report.damaged_files) {
    v1::ScrubReport::DamagedFile* damaged = out->add_damaged_files();
    damaged->set_file(file.file);
    damaged->set_reason(file.reason);
  }
  out->set_clean(report.clean());
}

void VocabularySourceToProto(const VocabularySource& source, v1::VocabularySource* out) {
  out->set_origin(source.origin);
  out->set_checksum(Hex64(source.checksum));
  out->set_branching(source.branching);
  out->set_depth(source.depth);
  out->set_words(source.words);
  out->set_learned_unix_ms(source.learned_unix_ms);
  out->set_places_offered(source.places_offered);
  out->set_descriptors_offered(source.descriptors_offered);
  out->set_places_sampled(source.places_sampled);
  out->set_descriptors_sampled(source.descriptors_sampled);
  out->set_learn_ms(source.learn_ms);
}

Result<VocabularySource> VocabularySourceFromProto(const v1::VocabularySource& source,
                                                   const std::string& field) {
  VocabularySource out;
  const auto checksum = ParseHex64(source.checksum());
  if (!checksum) {
    return Status::InvalidArgument(field + ".checksum: '" + source.checksum() +
                                   "' is not 16 hex digits");
  }
  out.origin = source.origin();
  out.checksum = *checksum;
  out.branching = source.branching();
  out.depth = source.depth();
  out.words = source.words();
  out.learned_unix_ms = source.learned_unix_ms();
  out.places_offered = source.places_offered();
  out.descriptors_offered = source.descriptors_offered();
  out.places_sampled = source.places_sampled();
  out.descriptors_sampled = source.descriptors_sampled();
  out.learn_ms = source.learn_ms();
  return out;
}

Result<VocabularyRecord> VocabularyRecordFromProto(const v1::MapVocabulary& record,
                                                   const std::string& field) {
  VocabularyRecord out;
  out.generation = record.generation();
  auto current = VocabularySourceFromProto(record.current(), field + ".current");
  if (!current.ok()) return current.status();
  out.current = std::move(current).value();
  if (record.has_previous()) {
    auto previous = VocabularySourceFromProto(record.previous(), field + ".previous");
    if (!previous.ok()) return previous.status();
    out.previous = std::move(previous).value();
  }
  out.since_unix_ms = record.since_unix_ms();
  out.places_reindexed = record.places_reindexed();
  out.reindex_ms = record.reindex_ms();
  return out;
}

void VocabularyRecordToProto(const VocabularyRecord& record, bool switching,
                             v1::MapVocabulary* out) {
  out->set_generation(record.generation);
  VocabularySourceToProto(record.current, out->mutable_current());
  if (record.previous) VocabularySourceToProto(*record.previous, out->mutable_previous());
  out->set_since_unix_ms(record.since_unix_ms);
  out->set_places_reindexed(record.places_reindexed);
  out->set_reindex_ms(record.reindex_ms);
  out->set_switching(switching);
}

QueryOptions QueryOptionsFromProto(const v1::MatchOptions& options, const std::string& agent_id) {
  QueryOptions out;
  out.top_k = options.top_k() == 0 ? 10 : std::min<size_t>(options.top_k(), 1000);
  out.verified_only = options.verified_only();
  out.include_correspondences = options.include_correspondences();
  if (options.exclude_same_agent()) {
    out.accept = [agent_id](const PlaceRecord& record) {
      return record.metadata.agent_id != agent_id;
    };
  }
  return out;
}

Result<PlaceListing> PlaceListingFromProto(const v1::ListPlacesRequest& request) {
  constexpr uint32_t kMaxLimit = 1000;
  PlaceListing listing;
  if (request.limit() > kMaxLimit) {
    return Status::InvalidArgument("limit: must be 1-" + std::to_string(kMaxLimit) +
                                   " (0 = 100), got " + std::to_string(request.limit()));
  }
  if (request.from_timestamp_ns() < 0) {
    return Status::InvalidArgument("from_timestamp_ns: must not be negative, got " +
                                   std::to_string(request.from_timestamp_ns()));
  }
  if (request.to_timestamp_ns() < 0) {
    return Status::InvalidArgument("to_timestamp_ns: must not be negative, got " +
                                   std::to_string(request.to_timestamp_ns()));
  }
  if (request.to_timestamp_ns() != 0 && request.to_timestamp_ns() <= request.from_timestamp_ns()) {
    return Status::InvalidArgument("to_timestamp_ns: must be after from_timestamp_ns (" +
                                   std::to_string(request.from_timestamp_ns()) + "), got " +
                                   std::to_string(request.to_timestamp_ns()));
  }
  listing.filter.agent_id = request.agent_id();
  listing.filter.from_timestamp_ns = request.from_timestamp_ns();
  listing.filter.to_timestamp_ns = request.to_timestamp_ns();
  listing.before = request.before_place_id();
  if (request.limit() != 0) listing.limit = request.limit();
  return listing;
}

}  // namespace placedb::wire
