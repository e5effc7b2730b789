#include "core/filter/depth_filter.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

namespace placedb {

namespace {

bool Finite(double v) {
  return std::isfinite(v);
}

// Same aspect ratio within 1 %: the depth image may be a scaled version of the colour frame.
bool SameAspect(int w0, int h0, int w1, int h1) {
  const double a = double(w0) / double(h0);
  const double b = double(w1) / double(h1);
  return std::abs(a - b) <= 0.01 * std::max(a, b);
}

Status CheckMetres(const cv::Mat& metres) {
  if (metres.empty() || metres.dims != 2 || metres.type() != CV_32FC1) {
    return Status::InvalidArgument(
        "depth must be a non-empty single-channel CV_32F image in metres");
  }
  return Status::Ok();
}

// Histogram of the valid depths (> 0) of `metres` inside `roi`, bins of `bin_m` from 0.
std::vector<uint32_t> DepthHistogram(const cv::Mat& metres, const cv::Rect& roi, float bin_m,
                                     uint32_t* valid) {
  std::vector<uint32_t> hist;
  *valid = 0;
  for (int r = roi.y; r < roi.y + roi.height; ++r) {
    const float* row = metres.ptr<float>(r);
    for (int c = roi.x; c < roi.x + roi.width; ++c) {
      const float d = row[c];
      if (!(d > 0)) continue;
      const size_t b = size_t(d / bin_m);
      if (b >= hist.size()) hist.resize(b + 1, 0);
      ++hist[b];
      ++*valid;
    }
  }
  return hist;
}

float Median(std::vector<float>* values) {
  const size_t mid = values->size() / 2;
  std::nth_element(values->begin(), values->begin() + std::ptrdiff_t(mid), values->end());
  float upper = (*values)[mid];
  if (values->size() % 2 == 1) return upper;
  const float lower = *std::max_element(values->begin(), values->begin() + std::ptrdiff_t(mid));
  return 0.5f * (lower + upper);
}

// `metres` brought to width x height (nearest neighbour) when it has another resolution.
cv::Mat AtImageSize(const cv::Mat& metres, int width, int height) {
  if (metres.cols == width && metres.rows == height) return metres;
  cv::Mat resized;
  cv::resize(metres, resized, cv::Size(width, height), 0, 0, cv::INTER_NEAREST);
  return resized;
}

}  // namespace

// ---- Depth images ----------------------------------------------------------------------------

Status ValidateDepthFormat(const DepthFormat& format) {
  if (!(format.metres_per_unit > 0) || !Finite(format.metres_per_unit)) {
    return Status::InvalidArgument("depth.metres_per_unit must be positive, got " +
                                   std::to_string(format.metres_per_unit));
  }
  if (!(format.float_metres_per_unit > 0) || !Finite(format.float_metres_per_unit)) {
    return Status::InvalidArgument("depth.float_metres_per_unit must be positive, got " +
                                   std::to_string(format.float_metres_per_unit));
  }
  if (!(format.min_depth_m >= 0) || !(format.max_depth_m > format.min_depth_m) ||
      !Finite(format.max_depth_m)) {
    return Status::InvalidArgument(
        "depth range must satisfy 0 <= min_depth_m < max_depth_m, got [" +
        std::to_string(format.min_depth_m) + ", " + std::to_string(format.max_depth_m) + "]");
  }
  return Status::Ok();
}

Status ValidateIntrinsics(const CameraIntrinsics& k, int width, int height) {
  if (!(k.fx > 0) || !(k.fy > 0) || !Finite(k.fx) || !Finite(k.fy)) {
    return Status::InvalidArgument("intrinsics.fx and fy must be positive and finite");
  }
  if (!Finite(k.cx) || !Finite(k.cy) || k.cx < 0 || k.cy < 0 || k.cx > width || k.cy > height) {
    return Status::InvalidArgument("intrinsics principal point (" + std::to_string(k.cx) + ", " +
                                   std::to_string(k.cy) + ") lies outside the " +
                                   std::to_string(width) + "x" + std::to_string(height) + " image");
  }
  return Status::Ok();
}

Result<cv::Mat> DepthToMetres(const cv::Mat& raw, const DepthFormat& format) {
  PLACEDB_RETURN_IF_ERROR(ValidateDepthFormat(format));
  if (raw.empty() || raw.dims != 2) return Status::InvalidArgument("depth image is empty");
  if (raw.channels() != 1) {
    return Status::InvalidArgument("depth image must have one channel, got " +
                                   std::to_string(raw.channels()));
  }
  double scale = 0;
  if (raw.depth() == CV_16U) {
    scale = format.metres_per_unit;
  } else if (raw.depth() == CV_32F) {
    scale = format.float_metres_per_unit;
  } else {
    return Status::InvalidArgument("depth image must be CV_16U (raw units) or CV_32F (metres)");
  }
  cv::Mat metres;
  raw.convertTo(metres, CV_32F, scale);
  // The bounds are inclusive; a relative epsilon keeps a reading of exactly max_depth_m (e.g.
  // 12000 mm * 0.001 = 12.000001f) valid.
  const float lo = format.min_depth_m * (1.0f - 1e-6f);
  const float hi = format.max_depth_m * (1.0f + 1e-6f);
  for (int r = 0; r < metres.rows; ++r) {
    float* row = metres.ptr<float>(r);
    for (int c = 0; c < metres.cols; ++c) {
      const float d = row[c];
      if (!(d >= lo && d <= hi) || d <= 0) row[c] = 0;  // NaN fails the comparison too
    }
  }
  return metres;
}

// ---- Feature depths and bands ----------------------------------------------------------------

std::vector<float> SampleFeatureDepths(const cv::Mat& metres, int image_width, int image_height,
                                       const std::vector<Keypoint>& keypoints, int window_radius,
                                       const CameraIntrinsics* range_intrinsics) {
  std::vector<float> out(keypoints.size(), 0.0f);
  if (metres.empty() || image_width <= 0 || image_height <= 0) return out;
  const double sx = double(metres.cols) / double(image_width);
  const double sy = double(metres.rows) / double(image_height);
  const int radius = std::max(0, window_radius);
  std::vector<float> window;
  window.reserve(size_t((2 * radius + 1) * (2 * radius + 1)));
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const int col = int(std::floor(keypoints[i].x * sx + 0.5 * (sx - 1) + 0.5));
    const int row = int(std::floor(keypoints[i].y * sy + 0.5 * (sy - 1) + 0.5));
    window.clear();
    for (int r = std::max(0, row - radius); r <= std::min(metres.rows - 1, row + radius); ++r) {
      const float* line = metres.ptr<float>(r);
      for (int c = std::max(0, col - radius); c <= std::min(metres.cols - 1, col + radius); ++c) {
        if (line[c] > 0) window.push_back(line[c]);
      }
    }
    if (window.empty()) continue;
    float z = Median(&window);
    if (range_intrinsics != nullptr) {
      const double u = (keypoints[i].x - range_intrinsics->cx) / range_intrinsics->fx;
      const double v = (keypoints[i].y - range_intrinsics->cy) / range_intrinsics->fy;
      z = float(z * std::sqrt(1.0 + u * u + v * v));
    }
    out[i] = z;
  }
  return out;
}

double MeanDepth(const cv::Mat& metres, MeanDepthMode mode, double* valid_fraction) {
  double sum = 0;
  size_t valid = 0;
  for (int r = 0; r < metres.rows; ++r) {
    const float* row = metres.ptr<float>(r);
    for (int c = 0; c < metres.cols; ++c) {
      if (row[c] > 0) {
        sum += row[c];
        ++valid;
      }
    }
  }
  const double total = double(metres.total());
  if (valid_fraction != nullptr) *valid_fraction = total > 0 ? double(valid) / total : 0;
  if (mode == MeanDepthMode::kAllPixels) return total > 0 ? sum / total : 0;
  return valid > 0 ? sum / double(valid) : 0;
}

Status ValidateNearestLayerConfig(const NearestLayerConfig& c) {
  if (!(c.bin_m > 0.001f && c.bin_m <= 1.0f)) {
    return Status::InvalidArgument("nearest_layer.bin_m must be in (0.001, 1]");
  }
  if (!(c.bin_noise_fraction >= 0 && c.bin_noise_fraction < 0.1f)) {
    return Status::InvalidArgument("nearest_layer.bin_noise_fraction must be in [0, 0.1)");
  }
  if (!(c.min_gap_m >= c.bin_m && c.min_gap_m <= 5)) {
    return Status::InvalidArgument("nearest_layer.min_gap_m must be in [bin_m, 5]");
  }
  if (!(c.max_extent_m > 0 && c.max_extent_m <= 20)) {
    return Status::InvalidArgument("nearest_layer.max_extent_m must be in (0, 20]");
  }
  if (!(c.min_layer_fraction >= 0 && c.min_layer_fraction < c.max_layer_fraction &&
        c.max_layer_fraction <= 1)) {
    return Status::InvalidArgument(
        "nearest_layer fractions must satisfy 0 <= min_layer_fraction < max_layer_fraction <= 1");
  }
  return Status::Ok();
}

std::optional<DepthBand> FindNearestLayer(const cv::Mat& metres, const NearestLayerConfig& config,
                                          float below_m) {
  if (metres.empty() || metres.type() != CV_32FC1) return std::nullopt;
  uint32_t valid = 0;
  const auto hist =
      DepthHistogram(metres, cv::Rect(0, 0, metres.cols, metres.rows), config.bin_m, &valid);
  if (valid == 0) return std::nullopt;
  const double noise = double(config.bin_noise_fraction) * double(valid);
  size_t start = 0;
  while (start < hist.size() && double(hist[start]) <= noise) ++start;
  if (start >= hist.size()) return std::nullopt;
  const size_t gap_bins = size_t(std::ceil(config.min_gap_m / config.bin_m - 1e-6));
  const size_t max_bins = size_t(std::ceil(config.max_extent_m / config.bin_m));
  size_t run = 0;
  uint64_t mass = 0;
  for (size_t b = start; b < hist.size(); ++b) {
    if (b - start > max_bins + gap_bins) return std::nullopt;
    if (double(hist[b]) <= noise) {
      if (++run >= gap_bins) {
        const size_t end = b + 1 - run;  // first bin of the gap
        const double fraction = double(mass) / double(valid);
        const float far = float(end) * config.bin_m;
        if (end - start > max_bins || fraction < config.min_layer_fraction ||
            fraction > config.max_layer_fraction || far > below_m) {
          return std::nullopt;
        }
        return DepthBand{0.0f, far + 0.5f * float(gap_bins) * config.bin_m};
      }
    } else {
      // Bins inside a short gap belong to the layer (their mass was below the noise level).
      run = 0;
    }
    mass += hist[b];
  }
  return std::nullopt;  // no gap: the nearest depths run on into the scene
}

Status ValidateAppearedLayerConfig(const AppearedLayerConfig& c) {
  if (!(c.bin_m > 0.001f && c.bin_m <= 1.0f)) {
    return Status::InvalidArgument("appeared_layer.bin_m must be in (0.001, 1]");
  }
  if (!(c.min_bin_excess > 0 && c.min_bin_excess < 1)) {
    return Status::InvalidArgument("appeared_layer.min_bin_excess must be in (0, 1)");
  }
  if (!(c.merge_gap_m >= 0 && c.merge_gap_m <= 5)) {
    return Status::InvalidArgument("appeared_layer.merge_gap_m must be in [0, 5]");
  }
  if (!(c.min_layer_fraction >= 0 && c.min_layer_fraction <= 1)) {
    return Status::InvalidArgument("appeared_layer.min_layer_fraction must be in [0, 1]");
  }
  if (!(c.margin_m >= 0 && c.margin_m <= 5)) {
    return Status::InvalidArgument("appeared_layer.margin_m must be in [0, 5]");
  }
  return Status::Ok();
}

std::vector<float> DepthFractions(const cv::Mat& metres, float bin_m, float max_depth_m) {
  const size_t bins = size_t(std::ceil(max_depth_m / bin_m)) + 1;
  std::vector<uint32_t> counts(bins, 0);
  for (int r = 0; r < metres.rows; ++r) {
    const float* row = metres.ptr<float>(r);
    for (int c = 0; c < metres.cols; ++c) {
      const float d = row[c];
      if (d > 0) ++counts[std::min(bins - 1, size_t(d / bin_m))];
    }
  }
  std::vector<float> fractions(bins, 0.0f);
  const double total = double(std::max<size_t>(metres.total(), 1));
  for (size_t b = 0; b < bins; ++b) fractions[b] = float(double(counts[b]) / total);
  return fractions;
}

std::optional<DepthBand> FindAppearedLayer(const std::vector<float>& current,
                                           const std::vector<float>& reference,
                                           const AppearedLayerConfig& config) {
  const size_t n = std::min(current.size(), reference.size());
  if (n == 0) return std::nullopt;
  // Excess per bin, smoothed over three bins (a layer's depth jitters by a bin or so).
  std::vector<double> excess(n);
  for (size_t b = 0; b < n; ++b) excess[b] = double(current[b]) - double(reference[b]);
  std::vector<double> smooth(n);
  for (size_t b = 0; b < n; ++b) {
    double s = excess[b];
    if (b > 0) s += excess[b - 1];
    if (b + 1 < n) s += excess[b + 1];
    smooth[b] = s / 3.0;
  }
  const size_t merge_bins = size_t(std::lround(config.merge_gap_m / config.bin_m));
  for (size_t b = 0; b < n;) {
    if (smooth[b] <= config.min_bin_excess) {
      ++b;
      continue;
    }
    // A run starting at b, merged across short holes.
    size_t end = b;  // last bin above the threshold
    double mass = 0;
    for (size_t j = b; j < n && j <= end + merge_bins; ++j) {
      if (smooth[j] > config.min_bin_excess) end = j;
    }
    for (size_t j = b; j <= end; ++j) mass += std::max(0.0, excess[j]);
    if (mass >= config.min_layer_fraction) {
      const float near = std::max(0.0f, float(b) * config.bin_m - config.margin_m);
      const float far = float(end + 1) * config.bin_m + config.margin_m;
      return DepthBand{near, far};
    }
    b = end + 1;
  }
  return std::nullopt;
}

void SplitByBand(const std::vector<float>& feature_depth_m, const DepthBand& band,
                 bool remove_without_depth, std::vector<uint32_t>* kept,
                 std::vector<uint32_t>* removed) {
  kept->clear();
  removed->clear();
  for (size_t i = 0; i < feature_depth_m.size(); ++i) {
    const float d = feature_depth_m[i];
    const bool out = d > 0 ? band.Contains(d) : remove_without_depth;
    (out ? removed : kept)->push_back(uint32_t(i));
  }
}

// ---- Algorithm 1 -----------------------------------------------------------------------------

const char* BandPolicyName(BandPolicy policy) {
  switch (policy) {
    case BandPolicy::kFixed:
      return "fixed";
    case BandPolicy::kNearestLayer:
      return "nearest_layer";
    case BandPolicy::kAppearedLayer:
      return "appeared_layer";
  }
  return "unknown";
}

Result<BandPolicy> ParseBandPolicy(const std::string& name) {
  if (name == "fixed") return BandPolicy::kFixed;
  if (name == "nearest_layer") return BandPolicy::kNearestLayer;
  if (name == "appeared_layer") return BandPolicy::kAppearedLayer;
  return Status::InvalidArgument("unknown band policy \"" + name +
                                 "\" (expected fixed, nearest_layer or appeared_layer)");
}

const char* MeanDepthModeName(MeanDepthMode mode) {
  return mode == MeanDepthMode::kAllPixels ? "all_pixels" : "valid_pixels";
}

Result<MeanDepthMode> ParseMeanDepthMode(const std::string& name) {
  if (name == "valid_pixels") return MeanDepthMode::kValidPixels;
  if (name == "all_pixels") return MeanDepthMode::kAllPixels;
  return Status::InvalidArgument("unknown mean depth mode \"" + name +
                                 "\" (expected valid_pixels or all_pixels)");
}

DepthFilterConfig DepthFilterConfig::PaperLiteral() {
  DepthFilterConfig config;
  config.mean_mode = MeanDepthMode::kAllPixels;
  config.band_policy = BandPolicy::kFixed;
  return config;
}

Status ValidateDepthFilterConfig(const DepthFilterConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateDepthFormat(config.format));
  if (!(config.threshold_m > 0) || !Finite(config.threshold_m)) {
    return Status::InvalidArgument("threshold_m must be positive, got " +
                                   std::to_string(config.threshold_m));
  }
  if (config.persistence < 0 || config.persistence > 10000) {
    return Status::InvalidArgument("persistence must be in [0, 10000], got " +
                                   std::to_string(config.persistence));
  }
  if (config.static_window < 1 || config.static_window > 10000) {
    return Status::InvalidArgument("static_window must be in [1, 10000], got " +
                                   std::to_string(config.static_window));
  }
  if (config.warmup_frames < 1 || config.warmup_frames > config.static_window) {
    return Status::InvalidArgument("warmup_frames must be in [1, static_window], got " +
                                   std::to_string(config.warmup_frames));
  }
  for (const auto& [name, band] :
       {std::pair{"rise_band", config.rise_band}, std::pair{"fall_band", config.fall_band}}) {
    if (!Finite(band.near_m) || !Finite(band.far_m) || band.near_m < 0 || band.empty()) {
      return Status::InvalidArgument(
          std::string(name) + " must satisfy 0 <= near_m <= far_m, got [" +
          std::to_string(band.near_m) + ", " + std::to_string(band.far_m) + "]");
    }
  }
  PLACEDB_RETURN_IF_ERROR(ValidateNearestLayerConfig(config.nearest_layer));
  PLACEDB_RETURN_IF_ERROR(ValidateAppearedLayerConfig(config.appeared_layer));
  if (config.feature_window_radius < 0 || config.feature_window_radius > 32) {
    return Status::InvalidArgument("feature_window_radius must be in [0, 32]");
  }
  if (config.rebaseline_after < 0) return Status::InvalidArgument("rebaseline_after must be >= 0");
  return Status::Ok();
}

Result<DepthStreamFilter> DepthStreamFilter::Create(const DepthFilterConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateDepthFilterConfig(config));
  return DepthStreamFilter(config);
}

void DepthStreamFilter::Reset() {
  window_.clear();
  window_sum_ = 0;
  window_hist_.clear();
  hist_sum_.clear();
  v_last_ = 0;
  sign_last_ = 0;
  count_ = 0;
  deviating_run_ = 0;
  frames_ = 0;
}

DepthFrameState DepthStreamFilter::Observe(const cv::Mat& metres) {
  DepthFrameState state;
  state.frame = frames_++;
  state.mean_depth_m = MeanDepth(metres, config_.mean_mode, &state.valid_fraction);
  const double v = state.mean_depth_m;
  state.change_m = state.frame == 0 ? 0.0 : v - v_last_;
  v_last_ = v;
  const bool use_hist = config_.band_policy == BandPolicy::kAppearedLayer;
  std::vector<float> hist;
  if (use_hist) {
    hist = DepthFractions(metres, config_.appeared_layer.bin_m, config_.format.max_depth_m);
  }
  auto push_static = [&](double value) {
    window_.push_back(value);
    window_sum_ += value;
    if (use_hist) {
      if (hist_sum_.size() < hist.size()) hist_sum_.resize(hist.size(), 0.0);
      for (size_t b = 0; b < hist.size(); ++b) hist_sum_[b] += hist[b];
      window_hist_.push_back(hist);
    }
    while (int(window_.size()) > config_.static_window) {
      window_sum_ -= window_.front();
      window_.pop_front();
      if (use_hist) {
        const auto& old = window_hist_.front();
        for (size_t b = 0; b < old.size(); ++b) hist_sum_[b] -= old[b];
        window_hist_.pop_front();
      }
    }
  };
  if (int(window_.size()) < config_.warmup_frames) {
    state.warming_up = true;
    push_static(v);
    state.count = count_;
    return state;
  }
  const double level = window_sum_ / double(window_.size());
  state.static_level_m = level;
  state.difference_m = v - level;
  state.sign = state.difference_m > 0 ? 1 : (state.difference_m < 0 ? -1 : 0);
  state.deviating = std::abs(state.difference_m) > config_.threshold_m;
  if (state.deviating) {
    // Algorithm 1 lines 5-14: COUNT > 5 and the same sign as the last frame: eliminate; else
    // COUNT++. Sign_last is the previous frame's sign (the pseudo-code never updates it).
    state.removing = count_ > config_.persistence && state.sign == sign_last_;
    if (!state.removing) ++count_;
    sign_last_ = state.sign;
    ++deviating_run_;
    if (config_.rebaseline_after > 0 && deviating_run_ >= config_.rebaseline_after) {
      // The change lasted: it is the scene now, not an object.
      window_.clear();
      window_sum_ = 0;
      window_hist_.clear();
      hist_sum_.clear();
      push_static(v);
      count_ = 0;
      sign_last_ = 0;
      deviating_run_ = 0;
    }
  } else {
    count_ = 0;
    sign_last_ = 0;
    deviating_run_ = 0;
    push_static(v);
  }
  state.count = count_;
  if (state.removing) {
    // Line 7: V_current > meandepth_normal (= V_static) picks the rise band.
    const bool rise = state.sign > 0;
    state.band = rise ? config_.rise_band : config_.fall_band;
    state.band_source = rise ? "rise" : "fall";
    if (config_.band_policy == BandPolicy::kNearestLayer) {
      if (auto layer = FindNearestLayer(metres, config_.nearest_layer, float(level))) {
        state.band = *layer;
        state.band_source = "nearest_layer";
      }
    } else if (config_.band_policy == BandPolicy::kAppearedLayer && !window_hist_.empty()) {
      std::vector<float> reference(hist_sum_.size());
      for (size_t b = 0; b < reference.size(); ++b) {
        reference[b] = float(hist_sum_[b] / double(window_hist_.size()));
      }
      if (auto layer = FindAppearedLayer(hist, reference, config_.appeared_layer)) {
        state.band = *layer;
        state.band_source = "appeared_layer";
      }
    }
  }
  return state;
}

Status CheckDepthRegistration(int depth_width, int depth_height, int image_width,
                              int image_height) {
  if (image_width <= 0 || image_height <= 0) {
    return Status::InvalidArgument("image size must be positive");
  }
  if (!SameAspect(depth_width, depth_height, image_width, image_height)) {
    return Status::InvalidArgument("depth image " + std::to_string(depth_width) + "x" +
                                   std::to_string(depth_height) + " is not registered to the " +
                                   std::to_string(image_width) + "x" +
                                   std::to_string(image_height) + " image (aspect ratios differ)");
  }
  return Status::Ok();
}

Result<DepthFilterResult> DepthStreamFilter::Process(
    const cv::Mat& depth, int image_width, int image_height, const std::vector<Keypoint>& keypoints,
    const std::optional<CameraIntrinsics>& intrinsics) {
  if (image_width <= 0 || image_height <= 0) {
    return Status::InvalidArgument("image size must be positive");
  }
  auto metres = DepthToMetres(depth, config_.format);
  if (!metres.ok()) return metres.status();
  PLACEDB_RETURN_IF_ERROR(
      CheckDepthRegistration(metres->cols, metres->rows, image_width, image_height));
  if (intrinsics) {
    PLACEDB_RETURN_IF_ERROR(ValidateIntrinsics(*intrinsics, image_width, image_height));
  } else if (config_.use_range) {
    return Status::InvalidArgument("use_range needs camera intrinsics");
  }
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const Keypoint& kp = keypoints[i];
    if (!(kp.x >= 0 && kp.y >= 0 && kp.x < float(image_width) && kp.y < float(image_height))) {
      return Status::InvalidArgument("keypoints[" + std::to_string(i) + "] lies outside the " +
                                     std::to_string(image_width) + "x" +
                                     std::to_string(image_height) + " image");
    }
  }
  DepthFilterResult result;
  result.state = Observe(*metres);
  result.feature_depth_m = SampleFeatureDepths(
      *metres, image_width, image_height, keypoints, config_.feature_window_radius,
      config_.use_range && intrinsics ? &*intrinsics : nullptr);
  if (result.state.removing) {
    SplitByBand(result.feature_depth_m, result.state.band, config_.remove_features_without_depth,
                &result.kept, &result.removed);
  } else {
    result.kept.resize(keypoints.size());
    for (size_t i = 0; i < keypoints.size(); ++i) result.kept[i] = uint32_t(i);
  }
  return result;
}

// ---- Depth-refined dynamic masks -------------------------------------------------------------

Status ValidateRefineConfig(const RefineConfig& c) {
  if (!(c.bin_m > 0.001f && c.bin_m <= 1.0f)) {
    return Status::InvalidArgument("refine.bin_m must be in (0.001, 1]");
  }
  if (!(c.min_mode_fraction >= 0 && c.min_mode_fraction <= 1)) {
    return Status::InvalidArgument("refine.min_mode_fraction must be in [0, 1]");
  }
  if (!(c.edge_ratio >= 0 && c.edge_ratio < 1)) {
    return Status::InvalidArgument("refine.edge_ratio must be in [0, 1)");
  }
  if (!(c.min_half_extent_m >= 0 && c.max_half_extent_m >= c.min_half_extent_m &&
        c.max_half_extent_m <= 10)) {
    return Status::InvalidArgument(
        "refine extents must satisfy 0 <= min_half_extent_m <= max_half_extent_m <= 10");
  }
  if (!(c.min_component_fraction >= 0 && c.min_component_fraction < 1)) {
    return Status::InvalidArgument("refine.min_component_fraction must be in [0, 1)");
  }
  if (c.dilate_px < 0 || c.dilate_px > 64) {
    return Status::InvalidArgument("refine.dilate_px must be in [0, 64]");
  }
  if (!(c.min_valid_fraction >= 0 && c.min_valid_fraction <= 1)) {
    return Status::InvalidArgument("refine.min_valid_fraction must be in [0, 1]");
  }
  return Status::Ok();
}

Result<RefinedObjects> RefineDynamicObjects(const DynamicObjects& objects, const cv::Mat& metres,
                                            int width, int height, const RefineConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateRefineConfig(config));
  PLACEDB_RETURN_IF_ERROR(CheckMetres(metres));
  if (width <= 0 || height <= 0) return Status::InvalidArgument("image size must be positive");
  if (!SameAspect(metres.cols, metres.rows, width, height)) {
    return Status::InvalidArgument(
        "depth image is not registered to the image (aspect ratios differ)");
  }
  if (!objects.mask.empty() && (objects.mask.type() != CV_8UC1 || objects.mask.cols != width ||
                                objects.mask.rows != height)) {
    return Status::InvalidArgument("mask must be CV_8U and " + std::to_string(width) + "x" +
                                   std::to_string(height));
  }
  const cv::Mat depth = AtImageSize(metres, width, height);
  RefinedObjects out;
  cv::Mat mask =
      objects.mask.empty() ? cv::Mat::zeros(height, width, CV_8U) : cv::Mat(objects.mask != 0);
  for (size_t i = 0; i < objects.boxes.size(); ++i) {
    const DynamicBox& box = objects.boxes[i];
    const cv::Rect2f& r = box.rect;
    if (!Finite(r.x) || !Finite(r.y) || !Finite(r.width) || !Finite(r.height) || r.width < 0 ||
        r.height < 0) {
      return Status::InvalidArgument("boxes[" + std::to_string(i) + "] is not a finite rectangle");
    }
    RefinedBox refined;
    refined.box = box;
    const cv::Rect roi = BoxPixelRect(r, width, height);
    if (roi.area() == 0) {
      refined.dynamic_fraction = 0;
      out.boxes.push_back(refined);
      continue;
    }
    uint32_t valid = 0;
    const auto hist = DepthHistogram(depth, roi, config.bin_m, &valid);
    if (double(valid) < double(config.min_valid_fraction) * roi.area()) {
      mask(roi).setTo(255);
      out.boxes.push_back(refined);
      continue;
    }
    // Smoothed histogram and +-0.15 m window mass.
    const size_t n = hist.size();
    std::vector<double> smooth(n, 0.0);
    for (size_t b = 0; b < n; ++b) {
      double s = hist[b];
      if (b > 0) s += hist[b - 1];
      if (b + 1 < n) s += hist[b + 1];
      smooth[b] = s / 3.0;
    }
    const size_t half_window = size_t(std::lround(0.15 / config.bin_m));
    auto window_mass = [&](size_t b) {
      uint64_t m = 0;
      for (size_t j = b > half_window ? b - half_window : 0; j <= std::min(n - 1, b + half_window);
           ++j) {
        m += hist[j];
      }
      return double(m);
    };
    size_t peak = n;
    for (size_t b = 0; b < n; ++b) {
      const bool local_max =
          (b == 0 || smooth[b] >= smooth[b - 1]) && (b + 1 >= n || smooth[b] >= smooth[b + 1]);
      if (local_max && smooth[b] > 0 &&
          window_mass(b) >= double(config.min_mode_fraction) * double(valid)) {
        peak = b;
        break;
      }
    }
    if (peak == n) peak = size_t(std::max_element(smooth.begin(), smooth.end()) - smooth.begin());
    const double floor_level = double(config.edge_ratio) * smooth[peak];
    const size_t max_bins = size_t(std::floor(config.max_half_extent_m / config.bin_m));
    size_t lo = peak, hi = peak;
    while (lo > 0 && peak - (lo - 1) <= max_bins && smooth[lo - 1] >= floor_level) --lo;
    while (hi + 1 < n && (hi + 1) - peak <= max_bins && smooth[hi + 1] >= floor_level) ++hi;
    const float centre = (float(peak) + 0.5f) * config.bin_m;
    refined.layer.near_m =
        std::max(0.0f, std::min(float(lo) * config.bin_m, centre - config.min_half_extent_m));
    refined.layer.far_m = std::max(float(hi + 1) * config.bin_m, centre + config.min_half_extent_m);
    refined.refined = true;

    cv::Mat layer = cv::Mat::zeros(roi.size(), CV_8U);
    for (int y = 0; y < roi.height; ++y) {
      const float* d = depth.ptr<float>(roi.y + y) + roi.x;
      uint8_t* m = layer.ptr<uint8_t>(y);
      for (int x = 0; x < roi.width; ++x) m[x] = d[x] > 0 && refined.layer.Contains(d[x]) ? 255 : 0;
    }
    // Drop stray components at the same depth, then close holes and cover silhouette edges.
    cv::Mat labels, stats, centroids;
    const int count = cv::connectedComponentsWithStats(layer, labels, stats, centroids, 8, CV_32S);
    const double min_area = double(config.min_component_fraction) * roi.area();
    std::vector<uint8_t> keep(size_t(count), 0);
    for (int c = 1; c < count; ++c)
      keep[size_t(c)] = stats.at<int>(c, cv::CC_STAT_AREA) >= min_area;
    for (int y = 0; y < roi.height; ++y) {
      const int* l = labels.ptr<int>(y);
      uint8_t* m = layer.ptr<uint8_t>(y);
      for (int x = 0; x < roi.width; ++x) m[x] = keep[size_t(l[x])] ? 255 : 0;
    }
    if (config.dilate_px > 0) {
      const cv::Mat kernel = cv::getStructuringElement(
          cv::MORPH_ELLIPSE, cv::Size(2 * config.dilate_px + 1, 2 * config.dilate_px + 1));
      cv::morphologyEx(layer, layer, cv::MORPH_CLOSE, kernel);
      cv::dilate(layer, layer, kernel);
    }
    refined.dynamic_fraction = double(cv::countNonZero(layer)) / double(roi.area());
    cv::Mat target = mask(roi);
    cv::bitwise_or(target, layer, target);
    out.boxes.push_back(refined);
  }
  out.objects.mask = mask;
  return out;
}

}  // namespace placedb
