// The wire library (proto/): every enum value named, parsed and mapped both ways, every status
// code both ways, every MapConfig field through the configuration conversion and back, and
// precomputed features of both families out as results and back in as observations.
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include <functional>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "core/detect/detector.h"
#include "core/filter/box_masks.h"
#include "core/filter/depth_filter.h"
#include "core/filter/dynamic_filter.h"
#include "core/search/geometric_verifier.h"
#include "core/vocabulary/any_vocabulary.h"
#include "core/vocabulary/weighting.h"
#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/convert_result.h"
#include "proto/names.h"
#include "proto/status.h"

namespace placedb::wire {
namespace {

using google::protobuf::EnumDescriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::util::MessageDifferencer;

// ---- Names --------------------------------------------------------------------------------------

// Every enum the API declares.
std::vector<const EnumDescriptor*> ApiEnums() {
  std::vector<const EnumDescriptor*> enums;
  const google::protobuf::FileDescriptor* file = v1::MapConfig::descriptor()->file();
  for (int i = 0; i < file->enum_type_count(); ++i) enums.push_back(file->enum_type(i));
  return enums;
}

TEST(Names, EveryValueOfEveryApiEnumRoundTrips) {
  const std::vector<const EnumDescriptor*> enums = ApiEnums();
  ASSERT_GE(enums.size(), 8u);
  for (const EnumDescriptor* type : enums) {
    for (int i = 0; i < type->value_count(); ++i) {
      const int number = type->value(i)->number();
      if (number == 0) continue;
      const std::string name = EnumValueName(type, number);
      SCOPED_TRACE(type->value(i)->name() + " -> " + name);
      auto parsed = ParseEnumValue(type, name);
      ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
      EXPECT_EQ(*parsed, number);
      // The proto3 JSON spelling parses too.
      auto full = ParseEnumValue(type, type->value(i)->name());
      ASSERT_TRUE(full.ok()) << full.status().ToString();
      EXPECT_EQ(*full, number);
    }
  }
}

TEST(Names, CanonicalNamesAreTheCoresNames) {
  EXPECT_EQ(EnumNames<v1::Scoring>(),
            (std::vector<std::string>{"l1", "l2", "chi2", "kl", "bhattacharyya", "dot"}));
  EXPECT_EQ(EnumNames<v1::VerificationMode>(),
            (std::vector<std::string>{"disabled", "direct", "exhaustive"}));
  EXPECT_EQ(
      EnumNames<v1::FilterMethod>(),
      (std::vector<std::string>{"none", "keypoint_in_box", "corner_distance", "exact_coverage"}));
  EXPECT_EQ(EnumNames<v1::BoxSource>(), (std::vector<std::string>{"agent", "server", "both"}));
  EXPECT_EQ(EnumNames<v1::BoxRefinement>(), (std::vector<std::string>{"none", "shape", "grabcut"}));
  EXPECT_EQ(EnumNames<v1::FeatureType>(), (std::vector<std::string>{"orb", "sift"}));
  EXPECT_EQ(EnumNames<v1::BandPolicy>(),
            (std::vector<std::string>{"fixed", "nearest_layer", "appeared_layer"}));
  EXPECT_EQ(EnumNames<v1::PixelFormat>(), (std::vector<std::string>{"gray8", "bgr8", "rgb8"}));

  // Each core value's name is the name of the proto value it maps to.
  for (ScoringType t : {ScoringType::kL1, ScoringType::kL2, ScoringType::kChiSquare,
                        ScoringType::kKL, ScoringType::kBhattacharyya, ScoringType::kDotProduct}) {
    EXPECT_EQ(EnumName(ScoringToProto(t)), ScoringName(t));
  }
  for (VerificationMode m : {VerificationMode::kDisabled, VerificationMode::kDirectIndex,
                             VerificationMode::kExhaustive}) {
    EXPECT_EQ(EnumName(VerificationToProto(m)), VerificationModeName(m));
  }
  for (FilterMethod m : {FilterMethod::kNone, FilterMethod::kKeypointInBox,
                         FilterMethod::kCornerDistance, FilterMethod::kExactCoverage}) {
    EXPECT_EQ(EnumName(FilterToProto(m)), FilterMethodName(m));
  }
  for (BoxSource s : {BoxSource::kAgent, BoxSource::kServer, BoxSource::kBoth}) {
    EXPECT_EQ(EnumName(BoxSourceToProto(s)), BoxSourceName(s));
  }
  for (BoxRefinement r : {BoxRefinement::kNone, BoxRefinement::kShape, BoxRefinement::kGrabCut}) {
    EXPECT_EQ(EnumName(BoxRefinementToProto(r)), BoxRefinementName(r));
  }
  for (FeatureType t : {FeatureType::kOrb, FeatureType::kSift}) {
    EXPECT_EQ(EnumName(FeatureTypeToProto(t)), FeatureTypeName(t));
  }
  for (BandPolicy p : {BandPolicy::kFixed, BandPolicy::kNearestLayer, BandPolicy::kAppearedLayer}) {
    EXPECT_EQ(EnumName(BandPolicyToProto(p)), BandPolicyName(p));
  }
}

// The spellings client/cli.cc's flags accepted before the names were derived keep parsing.
TEST(Names, OldSpellingsParse) {
  EXPECT_EQ(*ParseEnum<v1::Scoring>("chi_square"), v1::SCORING_CHI_SQUARE);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("dot_product"), v1::SCORING_DOT_PRODUCT);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("chi2"), v1::SCORING_CHI_SQUARE);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("dot"), v1::SCORING_DOT_PRODUCT);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("l1"), v1::SCORING_L1);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("l2"), v1::SCORING_L2);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("kl"), v1::SCORING_KL);
  EXPECT_EQ(*ParseEnum<v1::Scoring>("bhattacharyya"), v1::SCORING_BHATTACHARYYA);
  EXPECT_EQ(*ParseEnum<v1::VerificationMode>("disabled"), v1::VERIFICATION_MODE_DISABLED);
  EXPECT_EQ(*ParseEnum<v1::VerificationMode>("direct"), v1::VERIFICATION_MODE_DIRECT_INDEX);
  EXPECT_EQ(*ParseEnum<v1::VerificationMode>("direct_index"), v1::VERIFICATION_MODE_DIRECT_INDEX);
  EXPECT_EQ(*ParseEnum<v1::VerificationMode>("exhaustive"), v1::VERIFICATION_MODE_EXHAUSTIVE);
  EXPECT_EQ(*ParseEnum<v1::FilterMethod>("none"), v1::FILTER_METHOD_NONE);
  EXPECT_EQ(*ParseEnum<v1::FilterMethod>("keypoint_in_box"), v1::FILTER_METHOD_KEYPOINT_IN_BOX);
  EXPECT_EQ(*ParseEnum<v1::FilterMethod>("corner_distance"), v1::FILTER_METHOD_CORNER_DISTANCE);
  EXPECT_EQ(*ParseEnum<v1::FilterMethod>("exact_coverage"), v1::FILTER_METHOD_EXACT_COVERAGE);
  EXPECT_EQ(*ParseEnum<v1::FeatureType>("orb"), v1::FEATURE_TYPE_ORB);
  EXPECT_EQ(*ParseEnum<v1::FeatureType>("sift"), v1::FEATURE_TYPE_SIFT);
  EXPECT_EQ(*ParseEnum<v1::BandPolicy>("fixed"), v1::BAND_POLICY_FIXED);
  EXPECT_EQ(*ParseEnum<v1::BandPolicy>("nearest_layer"), v1::BAND_POLICY_NEAREST_LAYER);
  EXPECT_EQ(*ParseEnum<v1::BandPolicy>("appeared_layer"), v1::BAND_POLICY_APPEARED_LAYER);
  EXPECT_EQ(*ParseEnum<v1::BoxSource>("agent"), v1::BOX_SOURCE_AGENT);
  EXPECT_EQ(*ParseEnum<v1::BoxSource>("server"), v1::BOX_SOURCE_SERVER);
  EXPECT_EQ(*ParseEnum<v1::BoxSource>("both"), v1::BOX_SOURCE_BOTH);
  EXPECT_EQ(*ParseEnum<v1::BoxRefinement>("none"), v1::BOX_REFINEMENT_NONE);
  EXPECT_EQ(*ParseEnum<v1::BoxRefinement>("shape"), v1::BOX_REFINEMENT_SHAPE);
  EXPECT_EQ(*ParseEnum<v1::BoxRefinement>("grabcut"), v1::BOX_REFINEMENT_GRABCUT);

  // A flag's choices: the names, then the other spellings.
  EXPECT_EQ(EnumSpellings<v1::Scoring>(),
            (std::vector<std::string>{"l1", "l2", "chi2", "kl", "bhattacharyya", "dot",
                                      "chi_square", "dot_product"}));
  EXPECT_EQ(EnumSpellings<v1::VerificationMode>(),
            (std::vector<std::string>{"disabled", "direct", "exhaustive", "direct_index"}));
  EXPECT_EQ(EnumSpellings<v1::BoxSource>(), EnumNames<v1::BoxSource>());
}

// UNSPECIFIED prints as the value the server takes it for, and is never a choice.
TEST(Names, UnspecifiedPrintsItsDefaultAndDoesNotParse) {
  EXPECT_EQ(EnumName(v1::FILTER_METHOD_UNSPECIFIED), "keypoint_in_box");
  EXPECT_EQ(EnumName(v1::SCORING_UNSPECIFIED), "l1");
  EXPECT_EQ(EnumName(v1::VERIFICATION_MODE_UNSPECIFIED), "disabled");
  EXPECT_EQ(EnumName(v1::BOX_SOURCE_UNSPECIFIED), "agent");
  EXPECT_EQ(EnumName(v1::BOX_REFINEMENT_UNSPECIFIED), "shape");
  EXPECT_EQ(EnumName(v1::BAND_POLICY_UNSPECIFIED), "appeared_layer");
  EXPECT_EQ(EnumName(v1::FEATURE_TYPE_UNSPECIFIED), "unspecified");
  EXPECT_EQ(EnumName(v1::PIXEL_FORMAT_UNSPECIFIED), "unspecified");
  // The default's name parses as the value itself, not as UNSPECIFIED.
  EXPECT_EQ(*ParseEnum<v1::Scoring>("l1"), v1::SCORING_L1);
  EXPECT_FALSE(ParseEnum<v1::FeatureType>("unspecified").ok());
  EXPECT_FALSE(ParseEnum<v1::Scoring>("SCORING_UNSPECIFIED").ok());
}

TEST(Names, UnknownNamesAndNumbers) {
  auto bad = ParseEnum<v1::Scoring>("cosine");
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(bad.status().message(),
            "unknown scoring 'cosine' (expected l1, l2, chi2, kl, bhattacharyya or dot)");
  EXPECT_EQ(ParseEnum<v1::VerificationMode>("Direct").status().message(),
            "unknown verification mode 'Direct' (expected disabled, direct or exhaustive)");
  // Proto3 enums are open: a newer peer's value still gets a name.
  EXPECT_EQ(EnumName(v1::Scoring(17)), "scoring_17");
  EXPECT_EQ(EnumName(v1::FilterMethod(9)), "filter_method_9");
}

// ---- Enum mappings ------------------------------------------------------------------------------

// Every proto value maps to a core value that maps back to it; UNSPECIFIED to the documented
// default; a value outside the enum is INVALID_ARGUMENT naming the field.
template <typename P, typename C>
void ExpectMapping(Result<C> (*from)(P, const std::string&), P (*to)(C), P unspecified,
                   P default_value) {
  const EnumDescriptor* type = google::protobuf::GetEnumDescriptor<P>();
  for (int i = 0; i < type->value_count(); ++i) {
    const P value = P(type->value(i)->number());
    SCOPED_TRACE(type->value(i)->name());
    auto core = from(value, "config.x");
    ASSERT_TRUE(core.ok()) << core.status().ToString();
    EXPECT_EQ(to(*core), value == unspecified ? default_value : value);
  }
  auto bad = from(P(99), "config.x");
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(bad.status().message(), "config.x: unknown value 99");
}

TEST(EnumMappings, EveryValueBothWays) {
  ExpectMapping(&FilterFromProto, &FilterToProto, v1::FILTER_METHOD_UNSPECIFIED,
                v1::FILTER_METHOD_KEYPOINT_IN_BOX);
  ExpectMapping(&BoxRefinementFromProto, &BoxRefinementToProto, v1::BOX_REFINEMENT_UNSPECIFIED,
                v1::BOX_REFINEMENT_SHAPE);
  ExpectMapping(&ScoringFromProto, &ScoringToProto, v1::SCORING_UNSPECIFIED, v1::SCORING_L1);
  ExpectMapping(&VerificationFromProto, &VerificationToProto, v1::VERIFICATION_MODE_UNSPECIFIED,
                v1::VERIFICATION_MODE_DISABLED);
  ExpectMapping(&BoxSourceFromProto, &BoxSourceToProto, v1::BOX_SOURCE_UNSPECIFIED,
                v1::BOX_SOURCE_AGENT);
  ExpectMapping(&BandPolicyFromProto, &BandPolicyToProto, v1::BAND_POLICY_UNSPECIFIED,
                v1::BAND_POLICY_APPEARED_LAYER);
}

// ---- Status -------------------------------------------------------------------------------------

const StatusCode kCoreCodes[] = {StatusCode::kOk,
                                 StatusCode::kInvalidArgument,
                                 StatusCode::kNotFound,
                                 StatusCode::kAlreadyExists,
                                 StatusCode::kFailedPrecondition,
                                 StatusCode::kResourceExhausted,
                                 StatusCode::kCorruption,
                                 StatusCode::kIoError,
                                 StatusCode::kInternal,
                                 StatusCode::kCancelled};

TEST(StatusMapping, EveryCoreCodeRoundTrips) {
  std::set<int> grpc_codes;
  for (StatusCode code : kCoreCodes) {
    SCOPED_TRACE(StatusCodeName(code));
    const grpc::StatusCode wire = ToGrpcCode(code);
    grpc_codes.insert(int(wire));
    EXPECT_EQ(FromGrpcCode(wire), code);
    if (code == StatusCode::kOk) continue;
    const Status status(code, "map 'x' not found");
    const grpc::Status sent = ToGrpc(status, "GetMap");
    EXPECT_EQ(sent.error_code(), wire);
    EXPECT_EQ(sent.error_message(), "GetMap: map 'x' not found");
    const Status received = FromGrpc(ToGrpc(status));
    EXPECT_EQ(received.code(), code);
    EXPECT_EQ(received.message(), "map 'x' not found");
  }
  EXPECT_EQ(grpc_codes.size(), std::size(kCoreCodes));  // 1:1
  EXPECT_EQ(ToGrpcCode(StatusCode::kCorruption), grpc::StatusCode::DATA_LOSS);
  EXPECT_EQ(ToGrpcCode(StatusCode::kIoError), grpc::StatusCode::UNAVAILABLE);
  EXPECT_TRUE(ToGrpc(Status::Ok(), "GetMap").ok());
  EXPECT_TRUE(FromGrpc(grpc::Status::OK, "GetMap").ok());
}

TEST(StatusMapping, EveryGrpcCodeMapsAndKeepsItsName) {
  const std::vector<std::pair<grpc::StatusCode, StatusCode>> expected = {
      {grpc::StatusCode::OK, StatusCode::kOk},
      {grpc::StatusCode::CANCELLED, StatusCode::kCancelled},
      {grpc::StatusCode::UNKNOWN, StatusCode::kInternal},
      {grpc::StatusCode::INVALID_ARGUMENT, StatusCode::kInvalidArgument},
      {grpc::StatusCode::DEADLINE_EXCEEDED, StatusCode::kCancelled},
      {grpc::StatusCode::NOT_FOUND, StatusCode::kNotFound},
      {grpc::StatusCode::ALREADY_EXISTS, StatusCode::kAlreadyExists},
      {grpc::StatusCode::PERMISSION_DENIED, StatusCode::kFailedPrecondition},
      {grpc::StatusCode::RESOURCE_EXHAUSTED, StatusCode::kResourceExhausted},
      {grpc::StatusCode::FAILED_PRECONDITION, StatusCode::kFailedPrecondition},
      {grpc::StatusCode::ABORTED, StatusCode::kFailedPrecondition},
      {grpc::StatusCode::OUT_OF_RANGE, StatusCode::kInvalidArgument},
      {grpc::StatusCode::UNIMPLEMENTED, StatusCode::kInternal},
      {grpc::StatusCode::INTERNAL, StatusCode::kInternal},
      {grpc::StatusCode::UNAVAILABLE, StatusCode::kIoError},
      {grpc::StatusCode::DATA_LOSS, StatusCode::kCorruption},
      {grpc::StatusCode::UNAUTHENTICATED, StatusCode::kFailedPrecondition}};
  for (const auto& [code, core] : expected) {
    SCOPED_TRACE(GrpcCodeName(code));
    EXPECT_EQ(FromGrpcCode(code), core);
    if (code == grpc::StatusCode::OK) continue;
    const Status status = FromGrpc(grpc::Status(code, "late"), "Query q1");
    EXPECT_EQ(status.code(), core);
    // A code the core folds into another keeps its gRPC name in the message.
    const bool folded = ToGrpcCode(core) != code;
    EXPECT_EQ(status.message(), folded ? "Query q1: " + GrpcCodeName(code) + ": late"
                                       : std::string("Query q1: late"));
  }
  EXPECT_EQ(FromGrpcCode(99), StatusCode::kInternal);

  v1::ErrorStatus error;
  error.set_code(int(grpc::StatusCode::RESOURCE_EXHAUSTED));
  error.set_message("observation.boxes: 300 boxes exceed limits.max_boxes_per_frame = 256");
  const Status frame = FromProto(error, "ingesting frame_7");
  EXPECT_EQ(frame.code(), StatusCode::kResourceExhausted);
  EXPECT_EQ(frame.message(),
            "ingesting frame_7: observation.boxes: 300 boxes exceed limits.max_boxes_per_frame = "
            "256");
  error.set_code(99);
  EXPECT_EQ(FromProto(error, "x").message(), "x: CODE_99: " + error.message());
}

TEST(StatusMapping, ClientMessagesHideServerPaths) {
  const std::string dir = "/srv/placedb/data";
  EXPECT_EQ(HidePaths("IO error: While appending to file: /srv/placedb/data/maps/m1/000012.log: "
                      "No space left on device",
                      dir),
            "IO error: While appending to file: maps/m1/000012.log: No space left on device");
  EXPECT_EQ(HidePaths("cannot open /srv/placedb/data.", dir), "cannot open <data_dir>.");
  EXPECT_EQ(HidePaths("data directory /srv/placedb/data/: gone", dir),
            "data directory <data_dir>: gone");
  // Any other absolute path: its file name.
  EXPECT_EQ(HidePaths("model_path '/opt/models/yolox_nano.onnx' does not exist", dir),
            "model_path 'yolox_nano.onnx' does not exist");
  EXPECT_EQ(HidePaths("(/usr/share/placedb/default.pdbv)", dir), "(default.pdbv)");
  EXPECT_EQ(HidePaths("/usr/share/placedb/vocabularies/", dir), "vocabularies");
  // A data directory spelled with a trailing slash or dots still matches.
  EXPECT_EQ(HidePaths("at /srv/placedb/data/maps/m1/LOCK", "/srv/placedb/./data/"),
            "at maps/m1/LOCK");
  // Not paths: slashes inside words, fractions, a lone slash.
  for (const std::string& text :
       {std::string("observation.features.image_width/image_height: must be in [1, 100000]"),
        std::string("1 / 2"), std::string("a/b"), std::string("/"), std::string("")}) {
    EXPECT_EQ(HidePaths(text, dir), text);
  }
  const grpc::Status hidden = HidePaths(
      grpc::Status(grpc::StatusCode::UNAVAILABLE, "write /srv/placedb/data/maps/m/x failed"), dir);
  EXPECT_EQ(hidden.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(hidden.error_message(), "write maps/m/x failed");
}

TEST(StatusMapping, CodeNamesAndLabels) {
  const char* const names[] = {"OK",
                               "CANCELLED",
                               "UNKNOWN",
                               "INVALID_ARGUMENT",
                               "DEADLINE_EXCEEDED",
                               "NOT_FOUND",
                               "ALREADY_EXISTS",
                               "PERMISSION_DENIED",
                               "RESOURCE_EXHAUSTED",
                               "FAILED_PRECONDITION",
                               "ABORTED",
                               "OUT_OF_RANGE",
                               "UNIMPLEMENTED",
                               "INTERNAL",
                               "UNAVAILABLE",
                               "DATA_LOSS",
                               "UNAUTHENTICATED"};
  for (int code = 0; code < int(std::size(names)); ++code) {
    EXPECT_EQ(GrpcCodeName(code), names[code]);
  }
  EXPECT_EQ(GrpcCodeName(17), "CODE_17");
  EXPECT_EQ(GrpcCodeName(-2), "CODE_-2");
  EXPECT_EQ(GrpcCodeLabel(grpc::StatusCode::INVALID_ARGUMENT), "invalid_argument");
  EXPECT_EQ(GrpcCodeLabel(grpc::StatusCode::OK), "ok");
}

// ---- Map configuration --------------------------------------------------------------------------

constexpr uint32_t kMaxDescriptors = 10000;

// The effective configuration of a map created with nothing set.
v1::MapConfig DefaultConfig() {
  v1::MapConfig config;
  MapConfigToProto(MapOptions{}, ServiceMapSettings{}, "default", &config);
  return config;
}

struct FieldCase {
  std::string path;  // the leaf field it sets, "depth.rise_band.near_m"
  std::function<void(v1::MapConfig*)> set;
  FeatureType vocabulary = FeatureType::kOrb;
  bool may_be_default = false;  // the enum cases go through every value, the default's too
};

// One non-default, valid value for every leaf field of MapConfig, and every value of its enums.
std::vector<FieldCase> FieldCases() {
  std::vector<FieldCase> cases = {
      {"vocabulary", [](v1::MapConfig* c) { c->set_vocabulary("indoor"); }},
      {"feature_type", [](v1::MapConfig* c) { c->set_feature_type(v1::FEATURE_TYPE_SIFT); },
       FeatureType::kSift},
      {"orb.max_features", [](v1::MapConfig* c) { c->mutable_orb()->set_max_features(500); }},
      {"orb.scale_factor", [](v1::MapConfig* c) { c->mutable_orb()->set_scale_factor(1.5f); }},
      {"orb.levels", [](v1::MapConfig* c) { c->mutable_orb()->set_levels(6); }},
      {"orb.edge_threshold", [](v1::MapConfig* c) { c->mutable_orb()->set_edge_threshold(40); }},
      {"orb.patch_size", [](v1::MapConfig* c) { c->mutable_orb()->set_patch_size(25); }},
      {"orb.fast_threshold", [](v1::MapConfig* c) { c->mutable_orb()->set_fast_threshold(12); }},
      {"sift.max_features", [](v1::MapConfig* c) { c->mutable_sift()->set_max_features(700); }},
      {"sift.octave_layers", [](v1::MapConfig* c) { c->mutable_sift()->set_octave_layers(4); }},
      {"sift.contrast_threshold",
       [](v1::MapConfig* c) { c->mutable_sift()->set_contrast_threshold(0.03); }},
      {"sift.edge_threshold", [](v1::MapConfig* c) { c->mutable_sift()->set_edge_threshold(12); }},
      {"sift.sigma", [](v1::MapConfig* c) { c->mutable_sift()->set_sigma(1.4); }},
      {"depth.refine_boxes", [](v1::MapConfig* c) { c->mutable_depth()->set_refine_boxes(false); }},
      {"depth.stream_filter",
       [](v1::MapConfig* c) { c->mutable_depth()->set_stream_filter(false); }},
      {"depth.scale", [](v1::MapConfig* c) { c->mutable_depth()->set_scale(0.0002f); }},
      {"depth.min_depth_m", [](v1::MapConfig* c) { c->mutable_depth()->set_min_depth_m(0.3f); }},
      {"depth.max_depth_m", [](v1::MapConfig* c) { c->mutable_depth()->set_max_depth_m(8.5f); }},
      {"depth.mean_all_pixels",
       [](v1::MapConfig* c) { c->mutable_depth()->set_mean_all_pixels(true); }},
      {"depth.threshold_m", [](v1::MapConfig* c) { c->mutable_depth()->set_threshold_m(0.25f); }},
      {"depth.persistence", [](v1::MapConfig* c) { c->mutable_depth()->set_persistence(3); }},
      {"depth.static_window", [](v1::MapConfig* c) { c->mutable_depth()->set_static_window(14); }},
      {"depth.rise_band.near_m",
       [](v1::MapConfig* c) { c->mutable_depth()->mutable_rise_band()->set_near_m(1.5f); }},
      {"depth.rise_band.far_m",
       [](v1::MapConfig* c) { c->mutable_depth()->mutable_rise_band()->set_far_m(5.0f); }},
      {"depth.fall_band.near_m",
       [](v1::MapConfig* c) { c->mutable_depth()->mutable_fall_band()->set_near_m(0.25f); }},
      {"depth.fall_band.far_m",
       [](v1::MapConfig* c) { c->mutable_depth()->mutable_fall_band()->set_far_m(0.75f); }},
      {"depth.remove_features_without_depth",
       [](v1::MapConfig* c) { c->mutable_depth()->set_remove_features_without_depth(true); }},
      {"depth.use_range", [](v1::MapConfig* c) { c->mutable_depth()->set_use_range(true); }},
      {"depth.rebaseline_after",
       [](v1::MapConfig* c) { c->mutable_depth()->set_rebaseline_after(50); }},
      {"loop_closure.loop_threshold",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_loop_threshold(0.3); }},
      {"loop_closure.rehearsal_threshold",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_rehearsal_threshold(0.5); }},
      {"loop_closure.short_term_memory",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_short_term_memory(20); }},
      {"loop_closure.max_working_memory",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_max_working_memory(100); }},
      {"loop_closure.time_budget_ms",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_time_budget_ms(5); }},
      {"loop_closure.min_candidates",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_min_candidates(3); }},
      {"loop_closure.verify",
       [](v1::MapConfig* c) { c->mutable_loop_closure()->set_verify(false); }},
      // Detection off selects no class: the effective configuration lists none.
      {"detection.enabled",
       [](v1::MapConfig* c) {
         c->mutable_detection()->set_enabled(false);
         c->mutable_detection()->clear_classes();
       }},
      {"detection.classes",
       [](v1::MapConfig* c) {
         c->mutable_detection()->clear_classes();
         c->mutable_detection()->add_classes("person");
         c->mutable_detection()->add_classes("dog");
       }},
      {"detection.min_confidence",
       [](v1::MapConfig* c) { c->mutable_detection()->set_min_confidence(0.5f); }},
      {"filter.sensitivity_threshold",
       [](v1::MapConfig* c) { c->mutable_filter()->set_sensitivity_threshold(0.4f); }},
      {"filter.place_threshold",
       [](v1::MapConfig* c) { c->mutable_filter()->set_place_threshold(30); }},
      {"filter.static_feature_budget",
       [](v1::MapConfig* c) { c->mutable_filter()->set_static_feature_budget(false); }},
      {"filter.short_term.enabled",
       [](v1::MapConfig* c) { c->mutable_filter()->mutable_short_term()->set_enabled(false); }},
      {"filter.short_term.horizon_s",
       [](v1::MapConfig* c) { c->mutable_filter()->mutable_short_term()->set_horizon_s(30.5); }},
      {"filter.short_term.max_places",
       [](v1::MapConfig* c) { c->mutable_filter()->mutable_short_term()->set_max_places(100); }},
      {"filter.short_term.weight",
       [](v1::MapConfig* c) { c->mutable_filter()->mutable_short_term()->set_weight(0.5f); }},
      {"verification.levels_up",
       [](v1::MapConfig* c) { c->mutable_verification()->set_levels_up(3); }},
      {"verification.min_inliers",
       [](v1::MapConfig* c) { c->mutable_verification()->set_min_inliers(20); }},
      {"verification.candidates",
       [](v1::MapConfig* c) { c->mutable_verification()->set_candidates(5); }},
      {"verification.rerank",
       [](v1::MapConfig* c) { c->mutable_verification()->set_rerank(false); }},
      {"store_invalid", [](v1::MapConfig* c) { c->set_store_invalid(true); }},
      {"thumbnails.enabled", [](v1::MapConfig* c) { c->mutable_thumbnails()->set_enabled(true); }},
      {"thumbnails.max_side", [](v1::MapConfig* c) { c->mutable_thumbnails()->set_max_side(640); }},
      {"thumbnails.jpeg_quality",
       [](v1::MapConfig* c) { c->mutable_thumbnails()->set_jpeg_quality(90); }},
      {"dynamics.count_query_hits_above",
       [](v1::MapConfig* c) { c->mutable_dynamics()->set_count_query_hits_above(0.25); }},
      {"vocabulary_policy.adapt_after_descriptors",
       [](v1::MapConfig* c) {
         c->mutable_vocabulary_policy()->set_adapt_after_descriptors(50000);
       }},
      {"vocabulary_policy.regrow_factor",
       [](v1::MapConfig* c) { c->mutable_vocabulary_policy()->set_regrow_factor(2.5); }},
  };
  // Every specified value of the enum fields (the defaults come back as themselves).
  auto each = [&](const EnumDescriptor* type, const std::string& path,
                  std::function<void(v1::MapConfig*, int)> set) {
    for (int i = 0; i < type->value_count(); ++i) {
      const int number = type->value(i)->number();
      if (number == 0) continue;
      cases.push_back(
          {path, [set, number](v1::MapConfig* c) { set(c, number); }, FeatureType::kOrb, true});
    }
  };
  each(v1::BandPolicy_descriptor(), "depth.band_policy",
       [](v1::MapConfig* c, int v) { c->mutable_depth()->set_band_policy(v1::BandPolicy(v)); });
  each(v1::BoxSource_descriptor(), "detection.box_source",
       [](v1::MapConfig* c, int v) { c->mutable_detection()->set_box_source(v1::BoxSource(v)); });
  each(v1::FilterMethod_descriptor(), "filter.method",
       [](v1::MapConfig* c, int v) { c->mutable_filter()->set_method(v1::FilterMethod(v)); });
  each(v1::BoxRefinement_descriptor(), "filter.box_refinement", [](v1::MapConfig* c, int v) {
    c->mutable_filter()->set_box_refinement(v1::BoxRefinement(v));
  });
  each(v1::Scoring_descriptor(), "scoring",
       [](v1::MapConfig* c, int v) { c->set_scoring(v1::Scoring(v)); });
  each(v1::VerificationMode_descriptor(), "verification.mode", [](v1::MapConfig* c, int v) {
    c->mutable_verification()->set_mode(v1::VerificationMode(v));
  });
  return cases;
}

void LeafPaths(const google::protobuf::Descriptor* message, const std::string& prefix,
               std::set<std::string>* out) {
  for (int i = 0; i < message->field_count(); ++i) {
    const FieldDescriptor* field = message->field(i);
    const std::string path = prefix + field->name();
    if (field->type() == FieldDescriptor::TYPE_MESSAGE) {
      LeafPaths(field->message_type(), path + ".", out);
    } else {
      out->insert(path);
    }
  }
}

// A field added to MapConfig without a case here fails this test.
TEST(MapConfigConversion, EveryFieldHasACase) {
  std::set<std::string> leaves;
  LeafPaths(v1::MapConfig::descriptor(), "", &leaves);
  std::set<std::string> covered;
  for (const FieldCase& c : FieldCases()) covered.insert(c.path);
  EXPECT_EQ(covered, leaves);
}

TEST(MapConfigConversion, EveryFieldComesBack) {
  const v1::MapConfig defaults = DefaultConfig();
  for (const FieldCase& field : FieldCases()) {
    v1::MapConfig config = defaults;
    field.set(&config);
    SCOPED_TRACE(field.path + " = " + config.ShortDebugString());
    if (!field.may_be_default) {
      ASSERT_FALSE(MessageDifferencer::Equals(config, defaults)) << "the value is the default";
    }
    ServiceMapSettings settings;
    auto options = MapOptionsFromProto(config, kMaxDescriptors,
                                       MapVocabulary{"test", field.vocabulary}, &settings);
    ASSERT_TRUE(options.ok()) << options.status().ToString();
    v1::MapConfig back;
    MapConfigToProto(*options, settings, config.vocabulary(), &back);
    std::string differences;
    MessageDifferencer differencer;
    differencer.ReportDifferencesToString(&differences);
    EXPECT_TRUE(differencer.Compare(config, back)) << differences;
  }
}

TEST(MapConfigConversion, UnsetFieldsTakeTheDefaults) {
  ServiceMapSettings settings;
  auto options =
      MapOptionsFromProto(v1::MapConfig(), kMaxDescriptors, MapVocabulary{"default"}, &settings);
  ASSERT_TRUE(options.ok()) << options.status().ToString();
  v1::MapConfig back;
  MapConfigToProto(*options, settings, "default", &back);
  EXPECT_TRUE(MessageDifferencer::Equals(back, DefaultConfig())) << back.ShortDebugString();
  EXPECT_EQ(settings, ServiceMapSettings{});
}

TEST(MapConfigConversion, FeatureBudgetIsTheServersLimit) {
  v1::MapConfig config;
  config.mutable_orb()->set_max_features(2000);
  ServiceMapSettings settings;
  auto refused = MapOptionsFromProto(config, 1000, MapVocabulary{"default"}, &settings);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), StatusCode::kResourceExhausted);
  EXPECT_EQ(refused.status().message(),
            "config.orb.max_features = 2000 exceeds limits.max_descriptors_per_frame = 1000");
  // SIFT's "all" is the limit.
  config.Clear();
  config.mutable_sift()->set_max_features(0);
  auto all =
      MapOptionsFromProto(config, 1000, MapVocabulary{"sift", FeatureType::kSift}, &settings);
  ASSERT_TRUE(all.ok()) << all.status().ToString();
  EXPECT_EQ(all->database.sift.max_features, 1000);
}

TEST(MapConfigConversion, ThumbnailSettingsOutOfRangeNameTheirField) {
  ServiceMapSettings settings;
  for (const auto& [side, quality, field] :
       std::vector<std::tuple<uint32_t, uint32_t, std::string>>{
           {15, 0, "config.thumbnails.max_side"},
           {1025, 0, "config.thumbnails.max_side"},
           {0, 101, "config.thumbnails.jpeg_quality"}}) {
    v1::MapConfig config;
    config.mutable_thumbnails()->set_max_side(side);
    config.mutable_thumbnails()->set_jpeg_quality(quality);
    auto refused =
        MapOptionsFromProto(config, kMaxDescriptors, MapVocabulary{"default"}, &settings);
    ASSERT_FALSE(refused.ok()) << field;
    EXPECT_EQ(refused.status().code(), StatusCode::kInvalidArgument);
    EXPECT_EQ(refused.status().message().rfind(field, 0), 0u) << refused.status().message();
  }
  v1::MapConfig config;
  config.mutable_thumbnails()->set_enabled(true);
  auto options = MapOptionsFromProto(config, kMaxDescriptors, MapVocabulary{"default"}, &settings);
  ASSERT_TRUE(options.ok());
  EXPECT_EQ(options->thumbnails, (ThumbnailSettings{true, 320, 75}));
}

TEST(MatchOptionsConversion, DefaultsAndCap) {
  v1::MatchOptions options;
  EXPECT_EQ(QueryOptionsFromProto(options, "a").top_k, 10u);
  options.set_top_k(5000);
  options.set_verified_only(true);
  QueryOptions out = QueryOptionsFromProto(options, "a");
  EXPECT_EQ(out.top_k, 1000u);
  EXPECT_TRUE(out.verified_only);
  EXPECT_FALSE(out.accept);
  options.set_exclude_same_agent(true);
  out = QueryOptionsFromProto(options, "a");
  ASSERT_TRUE(out.accept);
  PlaceRecord mine, theirs;
  mine.metadata.agent_id = "a";
  theirs.metadata.agent_id = "b";
  EXPECT_FALSE(out.accept(mine));
  EXPECT_TRUE(out.accept(theirs));
}

// ---- Frames and results -------------------------------------------------------------------------

constexpr FrameLimits kFrameLimits{.max_image_pixels = 4096 * 4096,
                                   .max_descriptors_per_frame = 10000,
                                   .max_boxes_per_frame = 256};

std::vector<Keypoint> SomeKeypoints() {
  std::vector<Keypoint> keypoints;
  for (int i = 0; i < 4; ++i) {
    keypoints.push_back(Keypoint{.x = 3.5f + float(i) * 11,
                                 .y = 40.25f - float(i) * 9,
                                 .size = 31 + float(i),
                                 .angle = i == 0 ? -1.0f : float(i) * 90,
                                 .response = 0.001f * float(i + 1),
                                 .octave = i});
  }
  return keypoints;
}

TEST(FrameConversion, OrbFeaturesComeBackAsSent) {
  FeatureSet sent{
      .image_width = 64, .image_height = 48, .keypoints = SomeKeypoints(), .descriptors = {}};
  for (size_t i = 0; i < sent.keypoints.size(); ++i) {
    uint8_t bytes[Descriptor256::kBytes];
    for (int b = 0; b < Descriptor256::kBytes; ++b) bytes[b] = uint8_t(i * 37 + size_t(b) * 11);
    sent.descriptors.push_back(Descriptor256::FromBytes(bytes));
  }
  v1::Observation observation;
  FeaturesToProto(sent, observation.mutable_features());
  auto decoded = DecodeObservation(observation, kFrameLimits, /*color=*/false, "observation");
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  ASSERT_TRUE(decoded->observation.features.has_value());
  const FeatureSet* back = decoded->observation.features->orb();
  ASSERT_NE(back, nullptr);
  EXPECT_FALSE(decoded->has_pixels);
  EXPECT_EQ(back->image_width, 64);
  EXPECT_EQ(back->image_height, 48);
  EXPECT_EQ(back->keypoints, sent.keypoints);
  EXPECT_EQ(back->descriptors, sent.descriptors);
}

TEST(FrameConversion, SiftFeaturesComeBackAsSent) {
  FloatFeatureSet sent{
      .image_width = 64, .image_height = 48, .keypoints = SomeKeypoints(), .descriptors = {}};
  for (size_t i = 0; i < sent.keypoints.size() * size_t(kSiftDimensions); ++i) {
    sent.descriptors.push_back(float(i % 97) * 0.125f - 5.0f);
  }
  v1::Observation observation;
  SiftFeaturesToProto(sent, observation.mutable_sift_features());
  EXPECT_EQ(observation.sift_features().descriptors().size(), sent.keypoints.size() * 512);
  auto decoded = DecodeObservation(observation, kFrameLimits, /*color=*/false, "observation");
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  ASSERT_TRUE(decoded->observation.features.has_value());
  const FloatFeatureSet* back = decoded->observation.features->sift();
  ASSERT_NE(back, nullptr);
  EXPECT_EQ(back->image_width, 64);
  EXPECT_EQ(back->image_height, 48);
  EXPECT_EQ(back->keypoints, sent.keypoints);
  EXPECT_EQ(back->descriptors, sent.descriptors);
}

TEST(FrameConversion, AgentBoxesComeBackAsSent) {
  FeatureSet features{
      .image_width = 64, .image_height = 48, .keypoints = SomeKeypoints(), .descriptors = {}};
  features.descriptors.resize(features.keypoints.size());
  const std::vector<DynamicBox> sent = {
      {.class_id = 0, .confidence = 0.75f, .rect = cv::Rect2f(2.5f, 3.25f, 20.0f, 30.5f)},
      {.class_id = 2, .confidence = 1.0f, .rect = cv::Rect2f(-4.0f, 10.0f, 80.0f, 12.0f)}};
  v1::Observation observation;
  FeaturesToProto(features, observation.mutable_features());
  for (const DynamicBox& box : sent) AgentBoxToProto(box, observation.add_boxes());
  auto decoded = DecodeObservation(observation, kFrameLimits, /*color=*/false, "observation");
  ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
  ASSERT_EQ(decoded->agent_boxes.size(), sent.size());
  for (size_t i = 0; i < sent.size(); ++i) {
    EXPECT_EQ(decoded->agent_boxes[i].class_id, sent[i].class_id) << i;
    EXPECT_EQ(decoded->agent_boxes[i].confidence, sent[i].confidence) << i;
    EXPECT_EQ(decoded->agent_boxes[i].rect, sent[i].rect) << i;
  }
}

TEST(FrameConversion, KeypointsOverTheLimitAreNamed) {
  FeatureSet sent{
      .image_width = 64, .image_height = 48, .keypoints = SomeKeypoints(), .descriptors = {}};
  sent.descriptors.resize(sent.keypoints.size());
  v1::Observation observation;
  FeaturesToProto(sent, observation.mutable_features());
  FrameLimits limits = kFrameLimits;
  limits.max_descriptors_per_frame = 3;
  auto decoded = DecodeObservation(observation, limits, /*color=*/false, "observation");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().code(), StatusCode::kResourceExhausted);
  EXPECT_EQ(decoded.status().message(),
            "observation.features.keypoints: 4 keypoints exceed "
            "limits.max_descriptors_per_frame = 3");
}

// Sizes arrive as uint32: each is checked and reported as sent, before any product or narrowing
// (4000000000 was once reported as -294967296).
TEST(FrameConversion, SizesAreReportedAsSentAndCheckedBeforeArithmetic) {
  const std::vector<uint32_t> bad_sides = {0u, 100001u, 1u << 31, 4'000'000'000u, 0xFFFFFFFFu};
  for (uint32_t side : bad_sides) {
    const std::string sent = std::to_string(side);
    v1::Observation features;
    features.mutable_features()->set_image_width(side);
    features.mutable_features()->set_image_height(1);
    auto decoded = DecodeObservation(features, kFrameLimits, /*color=*/false, "observation");
    ASSERT_FALSE(decoded.ok()) << side;
    EXPECT_EQ(decoded.status().code(), StatusCode::kInvalidArgument);
    EXPECT_EQ(decoded.status().message(),
              "observation.features.image_width/image_height: must be in [1, 100000], got " + sent +
                  "x1");

    v1::Observation sift;
    sift.mutable_sift_features()->set_image_width(7);
    sift.mutable_sift_features()->set_image_height(side);
    decoded = DecodeObservation(sift, kFrameLimits, /*color=*/false, "observation");
    ASSERT_FALSE(decoded.ok()) << side;
    EXPECT_EQ(decoded.status().message(),
              "observation.sift_features.image_width/image_height: must be in [1, 100000], got 7x" +
                  sent);

    v1::Observation raw;
    raw.mutable_raw_image()->set_width(side);
    raw.mutable_raw_image()->set_height(side);
    raw.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_GRAY8);
    decoded = DecodeObservation(raw, kFrameLimits, /*color=*/false, "observation");
    ASSERT_FALSE(decoded.ok()) << side;
    EXPECT_EQ(
        decoded.status().message(),
        "observation.raw_image.width/height: must be in [1, 100000], got " + sent + "x" + sent);

    v1::Observation depth;
    depth.mutable_raw_image()->set_width(64);
    depth.mutable_raw_image()->set_height(48);
    depth.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_GRAY8);
    depth.mutable_raw_image()->set_data(std::string(64 * 48, '\x40'));
    depth.mutable_depth()->mutable_raw_float32()->set_width(side);
    depth.mutable_depth()->mutable_raw_float32()->set_height(3);
    decoded = DecodeObservation(depth, kFrameLimits, /*color=*/false, "observation");
    ASSERT_FALSE(decoded.ok()) << side;
    EXPECT_EQ(
        decoded.status().message(),
        "observation.depth.raw_float32.width/height: must be in [1, 100000], got " + sent + "x3");
  }
}

// Every raw pixel format decodes to what the pipeline takes: gray, or BGR for server-side
// detection (color). GRAY8 with color came out as one channel (found by fuzz_observation); the
// detector takes three.
TEST(FrameConversion, EveryRawFormatDecodesToGrayOrBgrAsAsked) {
  for (const auto& [format, channels] :
       {std::pair{v1::PIXEL_FORMAT_GRAY8, 1}, std::pair{v1::PIXEL_FORMAT_BGR8, 3},
        std::pair{v1::PIXEL_FORMAT_RGB8, 3}}) {
    v1::Observation raw;
    raw.mutable_raw_image()->set_width(8);
    raw.mutable_raw_image()->set_height(6);
    raw.mutable_raw_image()->set_format(format);
    raw.mutable_raw_image()->set_data(std::string(size_t(8 * 6 * channels), '\x50'));
    for (const bool color : {false, true}) {
      auto decoded = DecodeObservation(raw, kFrameLimits, color, "observation");
      ASSERT_TRUE(decoded.ok()) << decoded.status().ToString();
      const cv::Mat& image = decoded->observation.image;
      EXPECT_EQ(image.type(), color ? CV_8UC3 : CV_8UC1) << int(format) << " color " << color;
      EXPECT_EQ(image.cols, 8);
      EXPECT_EQ(image.rows, 6);
      EXPECT_EQ(image.at<uint8_t>(0, 0), 0x50) << int(format) << " color " << color;
    }
  }
}

TEST(FrameConversion, PixelCountsAndByteCountsUse64Bits) {
  // 100000 x 100000 passes the side check; its 10^10 pixels do not fit in 32 bits.
  v1::Observation raw;
  raw.mutable_raw_image()->set_width(100000);
  raw.mutable_raw_image()->set_height(100000);
  raw.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_BGR8);
  raw.mutable_raw_image()->set_data("abc");
  auto decoded = DecodeObservation(raw, kFrameLimits, /*color=*/false, "observation");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().code(), StatusCode::kResourceExhausted);
  EXPECT_EQ(decoded.status().message(),
            "observation.raw_image: 100000x100000 = 10000000000 pixels exceed "
            "limits.max_image_pixels = 16777216");
  // With no pixel limit, the byte count (3 * 10^10) is exact, and the data must match it.
  FrameLimits unlimited = kFrameLimits;
  unlimited.max_image_pixels = UINT64_MAX;
  decoded = DecodeObservation(raw, unlimited, /*color=*/false, "observation");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(decoded.status().message(),
            "observation.raw_image.data: 3 bytes, expected 100000x100000 x 3 = 30000000000");
  v1::Observation depth;
  depth.mutable_features()->set_image_width(100000);
  depth.mutable_features()->set_image_height(100000);
  depth.mutable_depth()->mutable_raw_float32()->set_width(100000);
  depth.mutable_depth()->mutable_raw_float32()->set_height(100000);
  decoded = DecodeObservation(depth, unlimited, /*color=*/false, "observation");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().message(),
            "observation.depth.raw_float32.data: 0 bytes, expected 100000x100000 x 4 = "
            "40000000000");
  // One byte short of an exact raw image is refused, the exact count is accepted.
  v1::Observation exact;
  exact.mutable_raw_image()->set_width(64);
  exact.mutable_raw_image()->set_height(48);
  exact.mutable_raw_image()->set_format(v1::PIXEL_FORMAT_RGB8);
  exact.mutable_raw_image()->set_data(std::string(64 * 48 * 3 - 1, '\x20'));
  EXPECT_EQ(DecodeObservation(exact, kFrameLimits, false, "observation").status().message(),
            "observation.raw_image.data: 9215 bytes, expected 64x48 x 3 = 9216");
  exact.mutable_raw_image()->mutable_data()->push_back('\x20');
  EXPECT_TRUE(DecodeObservation(exact, kFrameLimits, false, "observation").ok());
}

TEST(FrameConversion, FeaturesOfTheOtherFamilyAreRefusedWithTheField) {
  v1::Observation orb;
  orb.mutable_features();
  v1::Observation sift;
  sift.mutable_sift_features();
  v1::Observation pixels;
  pixels.mutable_encoded_image();

  const Status orb_into_sift = CheckFeatureType(orb, FeatureType::kSift, "m", "observation");
  EXPECT_EQ(orb_into_sift.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(orb_into_sift.message(),
            "observation.features: map 'm' is a SIFT map (feature_type SIFT): send sift_features "
            "or pixels (encoded_image, raw_image), not ORB features");
  const Status sift_into_orb = CheckFeatureType(sift, FeatureType::kOrb, "m", "observation");
  EXPECT_EQ(sift_into_orb.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(sift_into_orb.message(),
            "observation.sift_features: map 'm' is an ORB map (feature_type ORB): send features "
            "or pixels (encoded_image, raw_image), not SIFT features");

  EXPECT_TRUE(CheckFeatureType(orb, FeatureType::kOrb, "m", "observation").ok());
  EXPECT_TRUE(CheckFeatureType(sift, FeatureType::kSift, "m", "observation").ok());
  EXPECT_TRUE(CheckFeatureType(pixels, FeatureType::kOrb, "m", "observation").ok());
  EXPECT_TRUE(CheckFeatureType(pixels, FeatureType::kSift, "m", "observation").ok());
}

}  // namespace
}  // namespace placedb::wire
