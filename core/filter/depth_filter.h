// Depth for dynamic scenes: depth images, Deng et al.'s Algorithm 1 as a per-stream state
// machine, and depth-refined dynamic-object masks. docs/rgbd.md explains the reading of the paper
// implemented here and every parameter.
//
// 1. Depth images. A depth image is CV_16U (raw units, default millimetres) or CV_32F (metres),
//    converted by DepthToMetres() into CV_32F metres where 0 marks an invalid pixel (0, NaN,
//    outside [min_depth_m, max_depth_m]). It must be registered to the colour image; it may have
//    another resolution with the same aspect ratio (keypoints are scaled onto it).
//
// 2. Algorithm 1 (DepthStreamFilter, one per agent stream). Every frame: V_current = mean depth;
//    V_difference = V_current - V_static, where V_static is the mean of a sliding window over the
//    stream's recent *static* frames; a frame deviates when |V_difference| > threshold. A run of
//    deviating frames is counted (COUNT); once COUNT > persistence and the sign of the deviation
//    equals the previous frame's, the frame's features inside a depth band are removed: the
//    paper's "rise" band when V_current > V_static, the "fall" band otherwise, or (beyond the
//    paper, the default) the depth layer that appeared since the static frames. A frame back within
//    the threshold resets COUNT (the paper: fluctuations that "return to stability quickly" prove
//    nothing) and joins the static window; deviating frames never do.
//
// 3. Depth-refined masks (beyond the paper). Inside a detected dynamic box, only the pixels on the
//    object's own depth layer are dynamic, so the background seen inside a person's box keeps its
//    features. RefineDynamicObjects() turns boxes into such a mask for dynamic_filter.h.
#pragma once

#include <cstdint>
#include <deque>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/features/orb_features.h"
#include "core/filter/dynamic_filter.h"

namespace placedb {

// ---- Depth images ----------------------------------------------------------------------------

struct DepthFormat {
  // Metres per unit of a CV_16U image: 0.001 for millimetres (Kinect, RealSense, the rgbd-people
  // and slambook2 data), 0.0002 for TUM's 1/5000 m. For a CV_32F image: metres per unit (1).
  double metres_per_unit = 0.001;
  double float_metres_per_unit = 1.0;
  // Readings outside [min_depth_m, max_depth_m] are invalid (sensor limits).
  float min_depth_m = 0.1f;
  float max_depth_m = 12.0f;
};

Status ValidateDepthFormat(const DepthFormat& format);

struct CameraIntrinsics {
  double fx = 0, fy = 0;  // focal lengths, pixels
  double cx = 0, cy = 0;  // principal point, pixels
};

// fx, fy > 0 and finite; the principal point inside the width x height image.
Status ValidateIntrinsics(const CameraIntrinsics& intrinsics, int width, int height);

// CV_16U or CV_32F (single channel, non-empty) -> CV_32F metres, 0 = invalid.
Result<cv::Mat> DepthToMetres(const cv::Mat& raw, const DepthFormat& format);

// INVALID_ARGUMENT unless a depth image of `depth_width` x `depth_height` can be registered to an
// `image_width` x `image_height` colour image (the same aspect ratio within 1 %).
Status CheckDepthRegistration(int depth_width, int depth_height, int image_width, int image_height);

// ---- Feature depths and bands ----------------------------------------------------------------

struct DepthBand {
  float near_m = 0;
  float far_m = 0;  // inclusive; an empty band has far_m < near_m
  bool Contains(float d) const { return d >= near_m && d <= far_m; }
  bool empty() const { return !(far_m >= near_m); }
  bool operator==(const DepthBand&) const = default;
};

// Depth of every keypoint in metres: the median of the valid pixels in a (2r+1)^2 window around
// it on `metres` (keypoints scaled when the depth image has another resolution than
// image_width x image_height), 0 when none is valid. With `range_intrinsics` the Euclidean
// distance from the camera centre is returned instead of z.
std::vector<float> SampleFeatureDepths(const cv::Mat& metres, int image_width, int image_height,
                                       const std::vector<Keypoint>& keypoints, int window_radius,
                                       const CameraIntrinsics* range_intrinsics = nullptr);

enum class MeanDepthMode {
  kValidPixels,  // mean over valid pixels (the default: a depth level, not a validity ratio)
  kAllPixels,    // the paper's "average pixel value of the depth image": invalid pixels count 0
};

// The frame's mean depth; `valid_fraction` (optional) receives the fraction of valid pixels.
double MeanDepth(const cv::Mat& metres, MeanDepthMode mode, double* valid_fraction = nullptr);

// The nearest depth layer of a frame, found in its depth histogram: starting at the nearest
// populated bin, the layer ends at the first gap (bins almost empty) at least min_gap_m wide.
struct NearestLayerConfig {
  float bin_m = 0.05f;
  float bin_noise_fraction = 0.0005f;  // bins holding less than this fraction of valid pixels
                                       // are empty (flying pixels, sensor noise)
  float min_gap_m = 0.15f;
  float max_extent_m = 1.5f;         // a layer deeper than this is the scene, not an object
  float min_layer_fraction = 0.01f;  // of the valid pixels
  float max_layer_fraction = 0.7f;
};

Status ValidateNearestLayerConfig(const NearestLayerConfig& config);

// The band [0, cut] of the nearest layer, cut in the middle of the gap behind it, or nullopt
// when there is no separated layer nearer than `below_m` holding the configured fraction.
std::optional<DepthBand> FindNearestLayer(const cv::Mat& metres, const NearestLayerConfig& config,
                                          float below_m);

// The depth layer that appeared: where the frame's depth histogram (fractions of all pixels)
// exceeds the mean histogram of the static window's frames. Runs of bins with an excess above
// min_bin_excess, merged across holes up to merge_gap_m, holding at least min_layer_fraction of
// the image in excess; the nearest such run, widened by margin_m each way.
struct AppearedLayerConfig {
  float bin_m = 0.05f;
  float min_bin_excess = 0.002f;
  float merge_gap_m = 0.1f;
  float min_layer_fraction = 0.01f;
  float margin_m = 0.1f;
};

Status ValidateAppearedLayerConfig(const AppearedLayerConfig& config);

// Depth histogram of `metres` as fractions of all its pixels (invalid pixels count in the total
// but in no bin), bins of bin_m up to max_depth_m.
std::vector<float> DepthFractions(const cv::Mat& metres, float bin_m, float max_depth_m);

// The appeared layer of `current` against `reference` (both from DepthFractions with the same
// bins), or nullopt when nothing appeared.
std::optional<DepthBand> FindAppearedLayer(const std::vector<float>& current,
                                           const std::vector<float>& reference,
                                           const AppearedLayerConfig& config);

// ---- Algorithm 1 -----------------------------------------------------------------------------

enum class BandPolicy {
  kFixed,          // the paper: rise_band when the mean rose above V_static, fall_band otherwise
  kNearestLayer,   // the frame's nearest separated layer (FindNearestLayer)
  kAppearedLayer,  // the layer that appeared since the static frames (FindAppearedLayer)
};
// kNearestLayer and kAppearedLayer fall back to the fixed band of the deviation's sign when they
// find no layer.

const char* BandPolicyName(BandPolicy policy);
// "fixed", "nearest_layer", "appeared_layer"
Result<BandPolicy> ParseBandPolicy(const std::string& name);
const char* MeanDepthModeName(MeanDepthMode mode);
Result<MeanDepthMode> ParseMeanDepthMode(const std::string& name);  // "valid_pixels", "all_pixels"

struct DepthFilterConfig {
  DepthFormat format;
  MeanDepthMode mean_mode = MeanDepthMode::kValidPixels;
  // threshold_depthdifference: |V_current - V_static| above this (metres) is a deviation. The
  // paper gives no value; 0.15 m is a person of ~10 % of the image ~1.5 m nearer than a room.
  float threshold_m = 0.15f;
  // Removal needs COUNT > persistence (the paper's 5): the 7th consecutive deviating frame.
  int persistence = 5;
  int static_window = 10;  // frames averaged into V_static (the paper's sliding window)
  int warmup_frames = 3;   // frames that only build V_static (no decision before)
  BandPolicy band_policy = BandPolicy::kAppearedLayer;
  // Algorithm 1 lines 8 and 10. (The prose says 1.5-2 m for the rising case.)
  DepthBand rise_band{1.8f, 4.5f};
  DepthBand fall_band{0.0f, 0.8f};
  NearestLayerConfig nearest_layer;
  AppearedLayerConfig appeared_layer;
  int feature_window_radius = 2;  // see SampleFeatureDepths
  // Features without a valid depth cannot be placed in a band: kept unless this is set.
  bool remove_features_without_depth = false;
  // Measure a feature's distance as Euclidean range (needs intrinsics) instead of z.
  bool use_range = false;
  // After this many consecutive deviating frames the level is taken as the new static level
  // (a genuine change of scene); 0 = never, as the paper.
  int rebaseline_after = 0;

  // The paper read literally: mean over all pixels (invalid = 0), fixed bands 1.8-4.5 m / 0-0.8 m.
  static DepthFilterConfig PaperLiteral();
};

Status ValidateDepthFilterConfig(const DepthFilterConfig& config);

// What Algorithm 1 decided for one frame.
struct DepthFrameState {
  uint64_t frame = 0;         // 0-based index in the stream
  double mean_depth_m = 0;    // V_current
  double valid_fraction = 0;  // of the frame's pixels
  double static_level_m = 0;  // V_static (the window's mean before this frame); 0 in warm-up
  double difference_m = 0;    // V_current - V_static
  double change_m = 0;        // V_current - V_last (the paper's "changing rate"; reported only)
  int sign = 0;               // sign(V_difference)
  int count = 0;              // COUNT after this frame
  bool warming_up = false;
  bool deviating = false;
  bool removing = false;    // features in `band` are removed from this frame
  DepthBand band{0, -1};    // empty unless removing
  std::string band_source;  // "rise", "fall", "nearest_layer", "appeared_layer" or ""
};

struct DepthFilterResult {
  DepthFrameState state;
  std::vector<uint32_t> kept;          // indices into the keypoints, ascending
  std::vector<uint32_t> removed;       // ascending
  std::vector<float> feature_depth_m;  // per keypoint, 0 = no valid depth
};

// Splits keypoints by a band: removed when their depth is in `band` (or, with
// `remove_without_depth`, when they have none).
void SplitByBand(const std::vector<float>& feature_depth_m, const DepthBand& band,
                 bool remove_without_depth, std::vector<uint32_t>* kept,
                 std::vector<uint32_t>* removed);

// Algorithm 1 for one stream. Not thread-safe: one instance per agent stream, frames in order.
class DepthStreamFilter {
 public:
  static Result<DepthStreamFilter> Create(const DepthFilterConfig& config);

  // Updates the stream with one frame's depth (CV_16U or CV_32F, see DepthFormat) and classifies
  // its keypoints (coordinates in the image_width x image_height colour image). `intrinsics` is
  // required when config.use_range is set.
  Result<DepthFilterResult> Process(const cv::Mat& depth, int image_width, int image_height,
                                    const std::vector<Keypoint>& keypoints,
                                    const std::optional<CameraIntrinsics>& intrinsics = {});

  // The state update alone, on a depth image already in metres (CV_32F, 0 = invalid).
  DepthFrameState Observe(const cv::Mat& metres);

  void Reset();
  const DepthFilterConfig& config() const { return config_; }
  uint64_t frames() const { return frames_; }

 private:
  explicit DepthStreamFilter(const DepthFilterConfig& config) : config_(config) {}

  DepthFilterConfig config_;
  std::deque<double> window_;  // recent static frames' mean depths
  double window_sum_ = 0;
  // Their depth histograms (kAppearedLayer only) and the running sum of those.
  std::deque<std::vector<float>> window_hist_;
  std::vector<double> hist_sum_;
  double v_last_ = 0;
  int sign_last_ = 0;
  int count_ = 0;
  int deviating_run_ = 0;
  uint64_t frames_ = 0;
};

// ---- Depth-refined dynamic masks -------------------------------------------------------------

struct RefineConfig {
  float bin_m = 0.05f;
  // The object's layer is the nearest histogram mode (within the box) holding at least this
  // fraction of the box's valid pixels within +-0.15 m.
  float min_mode_fraction = 0.15f;
  // The layer extends from the mode while the smoothed histogram stays above this fraction of
  // the mode's height, at least min_half_extent_m and at most max_half_extent_m each way.
  float edge_ratio = 0.1f;
  float min_half_extent_m = 0.25f;
  float max_half_extent_m = 0.6f;
  // Layer components smaller than this fraction of the box are dropped (stray pixels at the
  // same depth); the rest are closed and dilated by dilate_px to cover silhouette edges, where
  // depth is missing or mixed.
  float min_component_fraction = 0.02f;
  int dilate_px = 4;
  // A box with fewer valid depth pixels than this fraction stays dynamic as a whole.
  float min_valid_fraction = 0.2f;
};

Status ValidateRefineConfig(const RefineConfig& config);

struct RefinedBox {
  DynamicBox box;
  bool refined = false;         // false: too little depth, the whole box stays dynamic
  DepthBand layer{0, -1};       // the object's depth layer when refined
  double dynamic_fraction = 1;  // of the box's pixels
};

struct RefinedObjects {
  DynamicObjects objects;  // no boxes: the refined mask (union with the input mask)
  std::vector<RefinedBox> boxes;
};

// Refines every box of `objects` against `metres` (CV_32F, image-sized as width x height, or of
// another resolution with the same aspect ratio). The input mask, if any, is kept as is.
Result<RefinedObjects> RefineDynamicObjects(const DynamicObjects& objects, const cv::Mat& metres,
                                            int width, int height, const RefineConfig& config);

}  // namespace placedb
