#include "eval/revisits.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <optional>
#include <set>

#include "core/detect/detector.h"
#include "eval/adapters.h"

namespace fs = std::filesystem;

namespace placedb::eval {

namespace {

// SplitMix64: tiny, fully specified, so the same seed gives the same numbers on any platform
// (std::uniform_real_distribution is not specified bit-for-bit).
class Rng {
 public:
  explicit Rng(uint64_t seed) : state_(seed) {}
  uint64_t Next() {
    uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  double Uniform(double lo, double hi) { return lo + (hi - lo) * double(Next() >> 11) * 0x1p-53; }
  size_t Below(size_t n) { return n ? size_t(Next() % n) : 0; }

 private:
  uint64_t state_;
};

uint64_t StreamSeed(uint64_t seed, uint64_t a, uint64_t b) {
  Rng mix(seed ^ (a * 0xD1B54A32D192ED03ull) ^ (b * 0xABC98388FB8FAC03ull));
  return mix.Next();
}

struct Frame {
  CamVidFrame info;
  cv::Mat labels;  // CV_8U CamVid class ids
  double coverage = 0;
};

struct DonorObject {
  size_t frame = 0;  // index into frames
  int label = 0;     // CamVid class
  cv::Rect rect;     // in the donor frame
  cv::Mat patch;     // BGR crop of rect
  cv::Mat mask;      // CV_8U 255 on the component within rect
  int area = 0;
  std::string name;  // "0016E5_05130#3"
};

cv::Mat DynamicOf(const cv::Mat& labels) {
  cv::Mat dynamic = cv::Mat::zeros(labels.size(), CV_8U);
  for (int label : CamVidDynamicLabels()) dynamic |= labels == label;
  return dynamic;
}

// RANSAC inliers of a fundamental matrix between two frames' ORB features (cross-checked
// brute-force matches); 0 when too few matches.
int SharedInliers(const std::vector<cv::KeyPoint>& ka, const cv::Mat& da,
                  const std::vector<cv::KeyPoint>& kb, const cv::Mat& db) {
  if (da.rows < 8 || db.rows < 8) return 0;
  cv::BFMatcher matcher(cv::NORM_HAMMING, /*crossCheck=*/true);
  std::vector<cv::DMatch> matches;
  matcher.match(da, db, matches);
  std::vector<cv::Point2f> pa, pb;
  for (const cv::DMatch& m : matches) {
    if (m.distance > 64) continue;
    pa.push_back(ka[m.queryIdx].pt);
    pb.push_back(kb[m.trainIdx].pt);
  }
  if (pa.size() < 8) return 0;
  std::vector<uchar> inliers;
  cv::Mat f = cv::findFundamentalMat(pa, pb, cv::FM_RANSAC, 2.0, 0.99, inliers);
  if (f.empty()) return 0;
  return cv::countNonZero(inliers);
}

// Gain, bias, gamma per channel, an optional blur, then Gaussian sensor noise.
void Photometric(cv::Mat& image, Rng& rng, const RevisitOptions& options) {
  const double strength = options.photometric;
  if (strength <= 0) return;
  const double gain =
      rng.Uniform(1 - options.gain_range * strength, 1 + options.gain_range * strength);
  const double bias = rng.Uniform(-options.bias_range * strength, options.bias_range * strength);
  const double gamma = std::exp(
      rng.Uniform(-options.log_gamma_range * strength, options.log_gamma_range * strength));
  cv::Mat lut(1, 256, CV_8UC3);
  for (int c = 0; c < 3; ++c) {
    const double channel_gain = gain * rng.Uniform(1 - 0.05 * strength, 1 + 0.05 * strength);
    for (int v = 0; v < 256; ++v) {
      const double out = 255.0 * std::pow(v / 255.0, gamma) * channel_gain + bias;
      lut.at<cv::Vec3b>(0, v)[c] = cv::saturate_cast<uchar>(std::lround(out));
    }
  }
  cv::LUT(image, lut, image);
  if (options.max_blur_sigma > 0) {  // no draw otherwise: the default stream stays as it was
    const double blur = rng.Uniform(0, options.max_blur_sigma * strength);
    if (blur >= 0.05) cv::GaussianBlur(image, image, cv::Size(0, 0), blur);
  }
  const double sigma = rng.Uniform(0, options.max_noise_sigma * strength);
  cv::RNG noise_rng(rng.Next());
  cv::Mat noise(image.size(), CV_16SC3);
  noise_rng.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(sigma));
  cv::Mat wide;
  image.convertTo(wide, CV_16SC3);
  wide += noise;
  wide.convertTo(image, CV_8UC3);
}

// ---- Random placement (the hard variant) ---------------------------------------------------

constexpr int kRoad = 3;
constexpr int kPavement = 4;

// Where the horizon is, roughly: the first row whose ground (Road, Pavement) covers 2 % of the
// width (the street's far end), kept within [0.35, 0.75] of the height; half the height when
// there is no ground. Too low where something hides the far end: sizes below are bounded.
int HorizonRow(const cv::Mat& labels) {
  const int lo = int(0.35 * labels.rows), hi = int(0.75 * labels.rows);
  for (int r = 0; r < labels.rows; ++r) {
    const uchar* row = labels.ptr<uchar>(r);
    int ground = 0;
    for (int c = 0; c < labels.cols; ++c) ground += row[c] == kRoad || row[c] == kPavement;
    if (ground >= labels.cols / 50) return std::clamp(r, lo, hi);
  }
  return labels.rows / 2;
}

// An object to paste: a BGR patch, its binary shape, its COCO class and, for a CamVid object,
// where it stood in its own frame (its perspective).
struct Cutout {
  cv::Mat patch;  // BGR
  cv::Mat mask;   // CV_8U 255 = the object
  int area = 0;   // of mask
  int coco = 0;
  bool vehicle = false;  // stands on Road (cars, bicycles); people on Road or Pavement
  bool upright = false;  // a person (walking or cycling): about 1.7 m tall
  bool from_video = false;
  std::string name;
  int source_bottom = 0;   // CamVid: the row below the object's last row in its frame
  int source_horizon = 0;  // CamVid: HorizonRow of its frame
  bool cut_left = false, cut_right = false, cut_bottom = false;  // by its frame's edges
};

// A planned paste: the scaled object, 1-pixel padded, and where it goes.
struct Placement {
  const Cutout* cutout = nullptr;
  double scale = 1;
  cv::Mat patch;    // BGR, padded
  cv::Mat alpha;    // CV_32F, padded: 3x3 mean of the binary shape
  cv::Rect placed;  // padded, in frame coordinates (may extend past the frame)
  int bottom = 0;   // the row below the object's last row: its ground line (painter's order)
};

// The padded patch and feathered alpha of `cutout` at `size` (the same 1-pixel feathering as
// the near-original placement; the shape is resized linearly and re-binarised).
void Scaled(const Cutout& cutout, cv::Size size, cv::Mat* patch, cv::Mat* alpha) {
  cv::Mat shape;
  cv::resize(cutout.patch, *patch, size, 0, 0, cv::INTER_LINEAR);
  cv::resize(cutout.mask, shape, size, 0, 0, cv::INTER_LINEAR);
  cv::threshold(shape, shape, 127, 255, cv::THRESH_BINARY);
  cv::Mat padded;
  cv::copyMakeBorder(shape, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, 0);
  cv::copyMakeBorder(*patch, *patch, 1, 1, 1, 1, cv::BORDER_REPLICATE);
  padded.convertTo(*alpha, CV_32F, 1.0 / 255);
  cv::blur(*alpha, *alpha, cv::Size(3, 3), cv::Point(-1, -1), cv::BORDER_CONSTANT);
}

// Does the object's bottom row stand on the ground of the (warped) background labels? Three
// points of the bottom row (a quarter, half and three quarters of the width, within the frame)
// on Road or Pavement, the middle one on Road for vehicles.
bool OnGround(const cv::Mat& labels, int x, int width, int bottom, bool vehicle) {
  const int row = std::min(bottom, labels.rows) - 1;
  if (row < 0) return false;
  for (int quarter = 1; quarter <= 3; ++quarter) {
    const int col = std::clamp(x + quarter * width / 4, 0, labels.cols - 1);
    const int label = labels.at<uchar>(row, col);
    if (label != kRoad && label != kPavement) return false;
    if (vehicle && quarter == 2 && label != kRoad) return false;
  }
  return true;
}

struct PasteResult {
  cv::Mat painted;                // CV_8U 255 = a pixel a pasted object changed
  std::vector<DynamicBox> boxes;  // the visible part of each pasted object
  std::string names;
  int objects = 0, video_objects = 0;  // visible
};

// Every pasted object stays mostly visible: at most this share of its footprint hidden or
// shared, and at most this share of any planned object's footprint shared with it.
constexpr double kMaxOverlap = 0.4;

// The background's own objects with their bottom rows: one whose bottom is below a pasted
// object's (nearer to the camera) hides it.
struct Occluders {
  cv::Mat components;       // CV_32S component of the background's dynamic mask, 0 = none
  std::vector<int> bottom;  // per component: the row below its last row

  bool Hides(int component, int ground_line) const {
    return component > 0 && bottom[size_t(component)] > ground_line;
  }
};

Occluders FindOccluders(const cv::Mat& background_dynamic) {
  Occluders occluders;
  cv::Mat stats, centroids;
  const int count = cv::connectedComponentsWithStats(background_dynamic, occluders.components,
                                                     stats, centroids, 8);
  occluders.bottom.assign(size_t(std::max(count, 1)), 0);
  for (int c = 1; c < count; ++c) {
    occluders.bottom[size_t(c)] =
        stats.at<int>(c, cv::CC_STAT_TOP) + stats.at<int>(c, cv::CC_STAT_HEIGHT);
  }
  return occluders;
}

// The objects planned for one visit so far.
struct PastePlan {
  cv::Mat owner;       // CV_16U: 1 + index of the first plan whose footprint covers a pixel
  cv::Mat will_paint;  // CV_8U: marked already, or changed by the drawing
  std::vector<Placement> plans;
  std::vector<int> footprints;  // per plan: pixels under its alpha, within the frame
  double coverage = 0;          // of will_paint: exactly the final mask's
};

// Of a few random unused objects of `pool`, the largest that fits what is left (fewer, larger
// objects, as in a real street), else the smallest; null when every draw was used.
const Cutout* PickCutout(const std::vector<const Cutout*>& pool,
                         const std::set<const Cutout*>& used, double need, double pixels,
                         Rng& rng) {
  const Cutout* pick = nullptr;
  for (int draw = 0; draw < 8; ++draw) {
    const Cutout* c = pool[rng.Below(pool.size())];
    if (used.count(c)) continue;
    const bool fits = c->area / pixels <= need;
    const bool pick_fits = pick && pick->area / pixels <= need;
    if (!pick || (fits && (!pick_fits || c->area > pick->area)) ||
        (!fits && !pick_fits && c->area < pick->area)) {
      pick = c;
    }
  }
  return pick;
}

// A random scale for `cutout` covering at most `need` of the frame; none when what is left is
// too little (a person of the video below the minimum height, a CamVid object below its lowest
// scale). A person of the video gets a height in [min, max] of the frame; an object cut by the
// bottom edge is not shrunk much (it stays on that edge).
std::optional<double> DrawScale(const Cutout& cutout, double need, cv::Size size,
                                const RevisitOptions& options, Rng& rng) {
  const double pixels = double(size.area());
  const double h0 = cutout.mask.rows, w0 = cutout.mask.cols;
  double scale;
  if (cutout.from_video) {
    scale = rng.Uniform(options.video_min_height, options.video_max_height) * size.height / h0;
    if (cutout.area * scale * scale / pixels > need) {
      scale = std::sqrt(need * pixels / cutout.area);
    }
    if (h0 * scale < options.video_min_height * size.height) return std::nullopt;
  } else {
    const double lowest = cutout.cut_bottom ? std::max(options.min_scale, 0.9) : options.min_scale;
    scale = rng.Uniform(lowest, std::max(lowest, options.max_scale));
    if (cutout.area * scale * scale / pixels > need) {
      scale = std::sqrt(need * pixels / cutout.area);
    }
    scale = std::min(scale, size.width / w0);
    if (scale < lowest) return std::nullopt;
  }
  return scale;
}

// The pixels under `placement`'s alpha within the frame when it fits beside the plan: at most
// kMaxOverlap of them hidden by nearer objects of the background or shared with planned objects,
// and at most kMaxOverlap of any planned object's footprint shared with it; 0 when it does not.
// (Standing in front of the background's own objects is fine: a passing bus hides a parked car.)
int FootprintIfFits(const Placement& placement, const cv::Rect& visible, const PastePlan& plan,
                    const Occluders& occluders) {
  int area = 0, hidden = 0, on_planned = 0;
  std::map<int, int> per_plan;
  for (int r = visible.y; r < visible.br().y; ++r) {
    const float* a =
        placement.alpha.ptr<float>(r - placement.placed.y) + (visible.x - placement.placed.x);
    const uint16_t* o = plan.owner.ptr<uint16_t>(r) + visible.x;
    const int* comp = occluders.components.ptr<int>(r) + visible.x;
    for (int c = 0; c < visible.width; ++c) {
      if (a[c] <= 0) continue;
      ++area;
      hidden += occluders.Hides(comp[c], placement.bottom);
      if (o[c]) {
        ++on_planned;
        ++per_plan[o[c] - 1];
      }
    }
  }
  bool fits = area > 0 && hidden + on_planned <= kMaxOverlap * area;
  for (const auto& [k, n] : per_plan) {
    fits = fits && n <= kMaxOverlap * plan.footprints[size_t(k)];
  }
  return fits ? area : 0;
}

// Adds `placement` to the plan: claims the unowned pixels of its footprint and counts the
// pixels it will change (not marked yet, not hidden by a nearer object of the background).
void AddToPlan(Placement placement, const cv::Rect& visible, int footprint,
               const Occluders& occluders, double pixels, PastePlan* plan) {
  const uint16_t id = uint16_t(plan->plans.size() + 1);
  int added = 0;
  for (int r = visible.y; r < visible.br().y; ++r) {
    const float* a =
        placement.alpha.ptr<float>(r - placement.placed.y) + (visible.x - placement.placed.x);
    uint16_t* o = plan->owner.ptr<uint16_t>(r) + visible.x;
    uchar* w = plan->will_paint.ptr<uchar>(r) + visible.x;
    const int* comp = occluders.components.ptr<int>(r) + visible.x;
    for (int c = 0; c < visible.width; ++c) {
      if (a[c] <= 0) continue;
      if (!o[c]) o[c] = id;
      if (w[c] || occluders.Hides(comp[c], placement.bottom)) continue;
      w[c] = 255;
      ++added;
    }
  }
  plan->coverage += added / pixels;
  plan->footprints.push_back(footprint);
  plan->plans.push_back(std::move(placement));
}

// Up to 12 random placements of `cutout` on the ground of `labels`; adds the first that fits to
// the plan. False when none did or what is left is too little for it.
bool PlaceCutout(const Cutout& cutout, double need, const cv::Mat& labels, cv::Size size,
                 int horizon, const Occluders& occluders, const RevisitOptions& options, Rng& rng,
                 PastePlan* plan) {
  const cv::Rect frame(0, 0, size.width, size.height);
  const double h0 = cutout.mask.rows, w0 = cutout.mask.cols;
  for (int draw = 0; draw < 12; ++draw) {
    // Ground line by perspective: on flat ground, an object's height in pixels is proportional
    // to its bottom's distance below the horizon. People (video, CamVid pedestrians and
    // cyclists) stand where a camera at 0.7-0.9 of their height sees them; a CamVid vehicle
    // keeps the height / distance-below-the-horizon ratio it had in its own frame (bounded to
    // [0.6, 2.5]: cars to buses); an object cut by the bottom edge stays on it.
    const std::optional<double> drawn = DrawScale(cutout, need, size, options, rng);
    if (!drawn) return false;
    const double scale = *drawn;
    double ratio;  // height / distance of the bottom below the horizon
    if (cutout.upright) {
      ratio = 1 / rng.Uniform(0.7, 0.9);
    } else {
      ratio = std::clamp(h0 / std::max(1, cutout.source_bottom - cutout.source_horizon), 0.6, 2.5);
    }
    int bottom = cutout.cut_bottom ? size.height : horizon + int(std::lround(h0 * scale / ratio));
    const int sw = std::max(1, int(std::lround(w0 * scale)));
    const int sh = std::max(1, int(std::lround(h0 * scale)));
    const int top = bottom - sh;
    // In the frame, the bottom in its lower 3/4 and below the horizon.
    if (top < 0 || bottom > size.height || bottom < size.height / 4 || bottom <= horizon) {
      continue;
    }
    int x = int(rng.Below(size_t(std::max(0, size.width - sw) + 1)));
    if (cutout.cut_left && !cutout.cut_right) x = 0;
    if (cutout.cut_right && !cutout.cut_left) x = size.width - sw;
    if (!OnGround(labels, x, sw, bottom, cutout.vehicle)) continue;

    Placement placement;
    placement.cutout = &cutout;
    placement.scale = scale;
    placement.bottom = bottom;
    placement.placed = cv::Rect(x - 1, top - 1, sw + 2, sh + 2);
    Scaled(cutout, cv::Size(sw, sh), &placement.patch, &placement.alpha);
    const cv::Rect visible = placement.placed & frame;
    const int footprint = FootprintIfFits(placement, visible, *plan, occluders);
    if (footprint == 0) continue;
    AddToPlan(std::move(placement), visible, footprint, occluders, double(size.area()), plan);
    return true;
  }
  return false;
}

// Draws the planned objects far to near into `image`, each hidden where a nearer object of the
// background stands; the result's boxes and names follow the planning order.
PasteResult DrawPlan(const std::vector<Placement>& plans, const Occluders& occluders,
                     cv::Mat& image) {
  const cv::Size size = image.size();
  const cv::Rect frame(0, 0, size.width, size.height);
  std::vector<size_t> order(plans.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return plans[a].bottom < plans[b].bottom; });
  PasteResult result;
  result.painted = cv::Mat::zeros(size, CV_8U);
  cv::Mat shown = cv::Mat::zeros(size, CV_16U);  // 1 + plan index of the object drawn last
  for (size_t i : order) {
    const Placement& plan = plans[i];
    const cv::Rect visible = plan.placed & frame;
    for (int r = visible.y; r < visible.br().y; ++r) {
      const int lr = r - plan.placed.y, lc = visible.x - plan.placed.x;
      const float* a = plan.alpha.ptr<float>(lr) + lc;
      const cv::Vec3b* p = plan.patch.ptr<cv::Vec3b>(lr) + lc;
      cv::Vec3b* o = image.ptr<cv::Vec3b>(r) + visible.x;
      uchar* m = result.painted.ptr<uchar>(r) + visible.x;
      uint16_t* s = shown.ptr<uint16_t>(r) + visible.x;
      const int* comp = occluders.components.ptr<int>(r) + visible.x;
      for (int c = 0; c < visible.width; ++c) {
        if (a[c] <= 0) continue;
        if (occluders.Hides(comp[c], plan.bottom)) continue;
        for (int k = 0; k < 3; ++k) {
          o[c][k] = cv::saturate_cast<uchar>(a[c] * p[c][k] + (1 - a[c]) * o[c][k]);
        }
        m[c] = 255;
        s[c] = uint16_t(i + 1);
      }
    }
  }
  // Boxes of what is visible of each object (at least 20 pixels), in planning order.
  for (size_t i = 0; i < plans.size(); ++i) {
    const cv::Mat mine = shown == int(i + 1);
    const int visible_pixels = cv::countNonZero(mine);
    const Cutout& cutout = *plans[i].cutout;
    char name[128];
    std::snprintf(name, sizeof(name), "%s%s x%.2f%s", result.names.empty() ? "" : ", ",
                  cutout.name.c_str(), plans[i].scale, visible_pixels < 20 ? " (hidden)" : "");
    result.names += name;
    if (visible_pixels < 20) continue;
    DynamicBox box;
    box.class_id = cutout.coco;
    box.confidence = 1.0f;
    box.rect = cv::Rect2f(cv::boundingRect(mine));
    result.boxes.push_back(box);
    ++result.objects;
    result.video_objects += cutout.from_video;
  }
  return result;
}

// Random placement of one visit (RevisitOptions::random_placement): plans objects until the
// coverage of `mask` (what is already marked) plus what they will change reaches the target,
// then draws them far to near, each hidden where a nearer object of the background stands.
PasteResult PasteAtRandom(cv::Mat& image, const cv::Mat& labels, const cv::Mat& background_dynamic,
                          const cv::Mat& mask, const std::vector<const Cutout*>& still,
                          const std::vector<const Cutout*>& video, std::set<const Cutout*>& used,
                          double target, const RevisitOptions& options, Rng& rng) {
  const cv::Size size = image.size();
  const double pixels = double(size.area());
  const int horizon = HorizonRow(labels);
  const Occluders occluders = FindOccluders(background_dynamic);
  PastePlan plan;
  plan.owner = cv::Mat::zeros(size, CV_16U);
  plan.will_paint = mask.clone();
  plan.coverage = cv::countNonZero(plan.will_paint) / pixels;
  for (int attempt = 0; attempt < 800 && plan.coverage < target - 0.005; ++attempt) {
    const double need = target - plan.coverage;
    const bool from_video = !video.empty() && rng.Uniform(0, 1) < options.video_share;
    const std::vector<const Cutout*>& pool = from_video ? video : still;
    if (pool.empty()) continue;
    const Cutout* pick = PickCutout(pool, used, need, pixels, rng);
    if (!pick) continue;
    if (PlaceCutout(*pick, need, labels, size, horizon, occluders, options, rng, &plan)) {
      used.insert(pick);
    }
  }
  return DrawPlan(plan.plans, occluders, image);
}

Status WriteImage(const std::string& path, const cv::Mat& image, const std::vector<int>& params) {
  if (!cv::imwrite(path, image, params)) return Status::IoError("cannot write " + path);
  return Status::Ok();
}

}  // namespace

RevisitOptions HardRevisitOptions() {
  RevisitOptions options;
  options.max_background_coverage = 0.25;
  options.min_ground_fraction = 0.22;
  options.mask_background_objects = false;
  options.random_placement = true;
  options.min_scale = 0.5;
  options.max_scale = 1.6;
  options.donors_from_other_sequences = true;
  options.video_people = kDebianVtestPath;
  options.video_share = 0.5;
  options.viewpoint_margin = 0.125;  // corners 5-20 % in from each edge
  options.viewpoint_jitter = 0.075;
  options.gain_range = 0.4;
  options.bias_range = 30;
  options.log_gamma_range = 0.35;
  options.max_noise_sigma = 4;
  options.max_blur_sigma = 1;
  return options;
}

Result<std::vector<VideoCutout>> SegmentVideoPeople(const std::string& video_path,
                                                    const VideoPeopleOptions& options) {
  if (options.median_every < 1 || options.every < 1 || options.threshold < 1 ||
      !(options.min_aspect > 0 && options.min_aspect <= options.max_aspect)) {
    return Status::InvalidArgument("video people: bad segmentation options");
  }
  std::error_code ec;
  if (!fs::exists(video_path, ec)) {
    return Status::NotFound(video_path +
                            " does not exist (OpenCV's vtest.avi comes with the Debian package "
                            "opencv-doc: apt-get install opencv-doc)");
  }
  cv::VideoCapture capture(video_path);
  if (!capture.isOpened()) return Status::NotFound("cannot open the video " + video_path);
  // One pass: keep the frames the median needs and the frames people are cut from.
  std::vector<cv::Mat> sampled;
  std::vector<std::pair<int, cv::Mat>> cut_frames;
  cv::Mat frame;
  for (int index = 0; capture.read(frame); ++index) {
    if (frame.empty() || frame.type() != CV_8UC3) continue;
    if (index % options.median_every == 0) sampled.push_back(frame.clone());
    if (index % options.every == 0) cut_frames.emplace_back(index, frame.clone());
  }
  if (sampled.size() < 3) return Status::FailedPrecondition(video_path + ": too few frames");
  const cv::Size size = sampled[0].size();
  for (const cv::Mat& f : sampled) {
    if (f.size() != size) return Status::FailedPrecondition(video_path + ": frame size changes");
  }

  // Per-pixel, per-channel temporal median: the empty scene.
  cv::Mat background(size, CV_8UC3);
  const size_t values = size_t(size.area()) * 3, n = sampled.size();
  std::vector<const uchar*> planes;
  for (const cv::Mat& f : sampled) planes.push_back(f.ptr<uchar>(0));
  std::vector<uchar> samples(n);
  uchar* out = background.ptr<uchar>(0);
  for (size_t v = 0; v < values; ++v) {
    for (size_t k = 0; k < n; ++k) samples[k] = planes[k][v];
    std::nth_element(samples.begin(), samples.begin() + std::ptrdiff_t(n / 2), samples.end());
    out[v] = samples[n / 2];
  }

  const cv::Mat open_kernel = cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(3, 3));
  const cv::Mat close_kernel = cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(9, 9));
  std::vector<VideoCutout> cutouts;
  for (const auto& [index, image] : cut_frames) {
    if (image.size() != size) continue;
    cv::Mat difference, channels[3];
    cv::absdiff(image, background, difference);
    cv::split(difference, channels);
    cv::Mat largest = cv::max(cv::max(channels[0], channels[1]), channels[2]);
    cv::Mat foreground = largest > options.threshold;
    // Cast shadows are not the person: darker than the background by a similar factor in every
    // channel (the colour stays, the light drops).
    for (int r = 0; r < size.height; ++r) {
      const cv::Vec3b* f = image.ptr<cv::Vec3b>(r);
      const cv::Vec3b* b = background.ptr<cv::Vec3b>(r);
      uchar* m = foreground.ptr<uchar>(r);
      for (int c = 0; c < size.width; ++c) {
        if (!m[c]) continue;
        double lo = 2, hi = 0;
        for (int k = 0; k < 3; ++k) {
          const double ratio = (f[c][k] + 1.0) / (b[c][k] + 1.0);
          lo = std::min(lo, ratio);
          hi = std::max(hi, ratio);
        }
        if (lo >= options.shadow_min_ratio && hi <= options.shadow_max_ratio &&
            hi - lo <= options.shadow_max_spread) {
          m[c] = 0;
        }
      }
    }
    cv::morphologyEx(foreground, foreground, cv::MORPH_OPEN, open_kernel);
    cv::morphologyEx(foreground, foreground, cv::MORPH_CLOSE, close_kernel);
    // Holes filled: a person's clothes that happen to match the ground are still the person.
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(foreground, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
    cv::Mat filled = cv::Mat::zeros(size, CV_8U);
    cv::drawContours(filled, contours, -1, cv::Scalar(255), cv::FILLED, cv::LINE_8);
    // One pixel off the outline: the outline's pixels blend the person with the ground.
    cv::erode(filled, filled, open_kernel);
    cv::Mat components, stats, centroids;
    const int count = cv::connectedComponentsWithStats(filled, components, stats, centroids, 8);
    int number = 0;
    for (int c = 1; c < count; ++c) {
      const cv::Rect rect(stats.at<int>(c, cv::CC_STAT_LEFT), stats.at<int>(c, cv::CC_STAT_TOP),
                          stats.at<int>(c, cv::CC_STAT_WIDTH),
                          stats.at<int>(c, cv::CC_STAT_HEIGHT));
      const int area = stats.at<int>(c, cv::CC_STAT_AREA);
      const double aspect = double(rect.height) / rect.width;
      if (area < options.min_area || rect.height < options.min_height ||
          aspect < options.min_aspect || aspect > options.max_aspect ||
          area < options.min_fill * rect.area() || rect.x == 0 || rect.y == 0 ||
          rect.br().x >= size.width || rect.br().y >= size.height) {
        continue;
      }
      VideoCutout cutout;
      char name[64];
      std::snprintf(name, sizeof(name), "vtest_f%05d#%d", index, ++number);
      cutout.name = name;
      cutout.frame = index;
      cutout.rect = rect;
      cutout.patch = image(rect).clone();
      cutout.mask = components(rect) == c;
      cutouts.push_back(std::move(cutout));
    }
  }
  // A fixed camera over flat ground: a person's height in pixels is close to a linear function
  // of the row their feet are on. Fit it (least squares, then again without the outliers) and
  // keep the components within `max_height_deviation` of it: two people one behind the other,
  // or a person cut in two, are not one person.
  if (options.max_height_deviation > 0 && cutouts.size() >= 8) {
    std::vector<bool> keep(cutouts.size(), true);
    for (int round = 0; round < 2; ++round) {
      double n = 0, sx = 0, sy = 0, sxx = 0, sxy = 0;
      for (size_t i = 0; i < cutouts.size(); ++i) {
        if (!keep[i]) continue;
        const double x = cutouts[i].rect.br().y, y = cutouts[i].rect.height;
        n += 1;
        sx += x;
        sy += y;
        sxx += x * x;
        sxy += x * y;
      }
      const double denominator = n * sxx - sx * sx;
      if (n < 3 || denominator <= 0) break;
      const double slope = (n * sxy - sx * sy) / denominator;
      const double intercept = (sy - slope * sx) / n;
      for (size_t i = 0; i < cutouts.size(); ++i) {
        const double expected = intercept + slope * cutouts[i].rect.br().y;
        keep[i] = expected > 0 && std::abs(cutouts[i].rect.height - expected) <=
                                      options.max_height_deviation * expected;
      }
    }
    std::vector<VideoCutout> kept;
    for (size_t i = 0; i < cutouts.size(); ++i) {
      if (keep[i]) kept.push_back(std::move(cutouts[i]));
    }
    cutouts = std::move(kept);
  }
  return cutouts;
}

// ---- BuildRevisits, step by step -----------------------------------------------------------

namespace {

Status ValidateRevisitOptions(const RevisitOptions& options) {
  if (options.places < 1) return Status::InvalidArgument("places must be at least 1");
  if (options.visits < 2) return Status::InvalidArgument("visits must be at least 2");
  if (!(options.min_coverage >= 0 && options.min_coverage <= options.max_coverage &&
        options.max_coverage <= 0.6)) {
    return Status::InvalidArgument("coverage: need 0 <= min_coverage <= max_coverage <= 0.6");
  }
  if (options.out_dir.empty()) return Status::InvalidArgument("out_dir is required");
  if (!(options.min_scale > 0 && options.min_scale <= options.max_scale)) {
    return Status::InvalidArgument("scale: need 0 < min_scale <= max_scale");
  }
  if (!(options.video_share >= 0 && options.video_share <= 1) ||
      !(options.video_min_height > 0 && options.video_min_height <= options.video_max_height &&
        options.video_max_height <= 1)) {
    return Status::InvalidArgument(
        "video people: need video_share in [0, 1] and 0 < video_min_height <= video_max_height "
        "<= 1");
  }
  if (!options.video_people.empty() && !options.random_placement) {
    return Status::InvalidArgument("video people are pasted with random_placement only");
  }
  if (!(options.viewpoint_margin >= 0 && options.viewpoint_jitter >= 0 &&
        options.viewpoint_margin + options.viewpoint_jitter < 0.45) ||
      !(options.max_blur_sigma >= 0 && options.max_noise_sigma >= 0)) {
    return Status::InvalidArgument("viewpoint / photometric ranges out of bounds");
  }
  return Status::Ok();
}

// People of the fixed-camera video, segmented by background subtraction; none without a video.
Result<std::vector<Cutout>> VideoCutouts(const RevisitOptions& options) {
  std::vector<Cutout> cutouts;
  if (options.video_people.empty()) return cutouts;
  std::error_code exists_error;
  if (!fs::exists(options.video_people, exists_error)) {
    return Status::FailedPrecondition(
        options.video_people +
        " does not exist: the hard revisits paste people of OpenCV's vtest.avi, which comes "
        "with the Debian package opencv-doc (apt-get install opencv-doc); or leave it out "
        "(--no-vtest)");
  }
  auto people = SegmentVideoPeople(options.video_people);
  if (!people.ok()) return people.status();
  if (people->empty()) {
    return Status::FailedPrecondition("no people found in " + options.video_people);
  }
  for (VideoCutout& person : *people) {
    Cutout cutout;
    cutout.patch = std::move(person.patch);
    cutout.mask = std::move(person.mask);
    cutout.area = cv::countNonZero(cutout.mask);
    cutout.coco = 0;  // person
    cutout.upright = true;
    cutout.from_video = true;
    cutout.name = person.name;
    cutouts.push_back(std::move(cutout));
  }
  return cutouts;
}

// Every frame's labels and coverage.
Result<std::vector<Frame>> ReadFrames(const std::vector<CamVidFrame>& listed) {
  std::vector<Frame> frames;
  frames.reserve(listed.size());
  for (const CamVidFrame& info : listed) {
    Frame frame;
    frame.info = info;
    frame.labels = cv::imread(info.label_path, cv::IMREAD_GRAYSCALE);
    if (frame.labels.empty()) return Status::NotFound("cannot read labels " + info.label_path);
    frame.coverage = cv::countNonZero(DynamicOf(frame.labels)) / double(frame.labels.total());
    frames.push_back(std::move(frame));
  }
  return frames;
}

// Backgrounds: low coverage, enough ground, far apart and visually distinct (too few shared
// ORB inliers), drawn in a seeded random order.
Result<std::vector<size_t>> ChooseBackgrounds(const std::vector<Frame>& frames, cv::Size size,
                                              const RevisitOptions& options) {
  Rng rng(StreamSeed(options.seed, 0xB6, 0));
  std::vector<size_t> candidates;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (frames[i].coverage <= options.max_background_coverage && frames[i].labels.size() == size &&
        (options.min_ground_fraction <= 0 ||
         cv::countNonZero((frames[i].labels == kRoad) | (frames[i].labels == kPavement)) >=
             options.min_ground_fraction * double(frames[i].labels.total()))) {
      candidates.push_back(i);
    }
  }
  for (size_t i = candidates.size(); i > 1; --i)
    std::swap(candidates[i - 1], candidates[rng.Below(i)]);
  auto orb = cv::ORB::create(500);
  struct Orb {
    std::vector<cv::KeyPoint> keypoints;
    cv::Mat descriptors;
  };
  std::map<size_t, Orb> orb_cache;
  auto features_of = [&](size_t i) -> const Orb& {
    auto it = orb_cache.find(i);
    if (it != orb_cache.end()) return it->second;
    Orb f;
    cv::Mat gray = cv::imread(frames[i].info.image_path, cv::IMREAD_GRAYSCALE);
    if (!gray.empty()) orb->detectAndCompute(gray, cv::noArray(), f.keypoints, f.descriptors);
    return orb_cache.emplace(i, std::move(f)).first->second;
  };
  std::vector<size_t> backgrounds;
  for (size_t candidate : candidates) {
    if (int(backgrounds.size()) >= options.places) break;
    bool distinct = true;
    for (size_t chosen : backgrounds) {
      if (frames[chosen].info.sequence == frames[candidate].info.sequence &&
          std::abs(frames[chosen].info.frame - frames[candidate].info.frame) <
              options.min_separation_frames) {
        distinct = false;
        break;
      }
    }
    for (size_t b = 0; distinct && b < backgrounds.size(); ++b) {
      const Orb& a = features_of(candidate);
      const Orb& c = features_of(backgrounds[b]);
      if (SharedInliers(a.keypoints, a.descriptors, c.keypoints, c.descriptors) >=
          options.max_shared_inliers) {
        distinct = false;
      }
    }
    if (distinct) backgrounds.push_back(candidate);
  }
  if (int(backgrounds.size()) < options.places) {
    return Status::FailedPrecondition(
        "only " + std::to_string(backgrounds.size()) +
        " distinct CamVid backgrounds with at most " +
        std::to_string(options.max_background_coverage) + " dynamic coverage, " +
        (options.min_ground_fraction > 0
             ? "at least " + std::to_string(options.min_ground_fraction) + " Road + Pavement, "
             : std::string()) +
        std::to_string(options.min_separation_frames) + " frames apart; asked for " +
        std::to_string(options.places) +
        " places (lower places, or raise max_background_coverage / lower min_separation_frames)");
  }
  return backgrounds;
}

// Donor objects: the dynamic components of every frame that is not a background.
Result<std::vector<DonorObject>> CollectDonors(const std::vector<Frame>& frames,
                                               const std::vector<size_t>& backgrounds,
                                               const RevisitOptions& options) {
  const std::set<size_t> background_set(backgrounds.begin(), backgrounds.end());
  std::vector<DonorObject> donors;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (background_set.count(i) || frames[i].coverage == 0) continue;
    cv::Mat image;
    int component_number = 0;
    for (int label : CamVidDynamicLabels()) {
      cv::Mat mask = frames[i].labels == label;
      if (cv::countNonZero(mask) < options.min_object_area) continue;
      cv::Mat components, stats, centroids;
      const int count = cv::connectedComponentsWithStats(mask, components, stats, centroids, 8);
      for (int c = 1; c < count; ++c) {
        const int area = stats.at<int>(c, cv::CC_STAT_AREA);
        if (area < options.min_object_area) continue;
        if (image.empty()) image = cv::imread(frames[i].info.image_path, cv::IMREAD_COLOR);
        if (image.empty() || image.size() != frames[i].labels.size()) break;
        DonorObject donor;
        donor.frame = i;
        donor.label = label;
        donor.rect =
            cv::Rect(stats.at<int>(c, cv::CC_STAT_LEFT), stats.at<int>(c, cv::CC_STAT_TOP),
                     stats.at<int>(c, cv::CC_STAT_WIDTH), stats.at<int>(c, cv::CC_STAT_HEIGHT));
        donor.patch = image(donor.rect).clone();
        donor.mask = components(donor.rect) == c;
        donor.area = area;
        donor.name = frames[i].info.stem + "#" + std::to_string(++component_number);
        donors.push_back(std::move(donor));
      }
    }
  }
  if (donors.empty() && options.max_coverage > 0) {
    return Status::FailedPrecondition("no dynamic objects of at least " +
                                      std::to_string(options.min_object_area) +
                                      " pixels to paste in " + options.camvid_dir);
  }
  return donors;
}

// For random placement: every donor as a cutout that remembers its perspective and the frame
// edges that cut it (one per donor, same index).
std::vector<Cutout> StillCutouts(const std::vector<DonorObject>& donors,
                                 const std::vector<Frame>& frames) {
  std::vector<Cutout> cutouts;
  std::map<size_t, int> horizons;
  for (const DonorObject& donor : donors) {
    const cv::Mat& labels = frames[donor.frame].labels;
    if (!horizons.count(donor.frame)) horizons[donor.frame] = HorizonRow(labels);
    Cutout cutout;
    cutout.patch = donor.patch;
    cutout.mask = donor.mask;
    cutout.area = donor.area;
    cutout.coco = CamVidLabelToCoco(donor.label);
    cutout.vehicle = donor.label != kCamVidPedestrian;
    cutout.upright = donor.label != kCamVidCar;
    cutout.name = donor.name;
    cutout.source_bottom = donor.rect.y + donor.rect.height;
    cutout.source_horizon = horizons[donor.frame];
    cutout.cut_left = donor.rect.x == 0;
    cutout.cut_right = donor.rect.x + donor.rect.width >= labels.cols;
    cutout.cut_bottom = cutout.source_bottom >= labels.rows;
    cutouts.push_back(std::move(cutout));
  }
  return cutouts;
}

// The original variant: background objects marked, near-original placement, no video people.
bool IsOriginalVariant(const RevisitOptions& options) {
  return options.mask_background_objects && !options.random_placement &&
         options.video_people.empty();
}

std::string DatasetDescription(const RevisitOptions& options) {
  char description[1024];
  if (IsOriginalVariant(options)) {
    std::snprintf(description, sizeof(description),
                  "Synthetic revisits of %d real CamVid places (seed %llu): %d visits each with a "
                  "random homography, a photometric change and real CamVid dynamic objects from "
                  "other frames pasted to a coverage in [%.2f, %.2f]. Database = visit 0, queries "
                  "= the other visits, ground truth = the same place's visit 0.",
                  options.places, static_cast<unsigned long long>(options.seed), options.visits,
                  options.min_coverage, options.max_coverage);
  } else {
    std::snprintf(
        description, sizeof(description),
        "Hard synthetic revisits of %d real CamVid places (seed %llu), backgrounds with up to "
        "%.0f %% dynamic coverage of their own, %s: %d visits each with a random homography "
        "(corners %.0f-%.0f %% in), a photometric change (gain +-%.2f, bias +-%.0f, log gamma "
        "+-%.2f, noise sigma <= %.1f, blur sigma <= %.1f) and dynamic objects from %s%s%s pasted "
        "%s to a coverage of pasted objects in [%.2f, %.2f]. Database = visit 0, queries = the "
        "other visits, ground truth = the same place's visit 0.",
        options.places, static_cast<unsigned long long>(options.seed),
        options.max_background_coverage * 100,
        options.mask_background_objects
            ? "whose own objects are marked dynamic"
            : "whose own objects stay in every visit and are NOT marked (part of the place; "
              "listed in each entry's source)",
        options.visits, 100 * (options.viewpoint_margin - options.viewpoint_jitter),
        100 * (options.viewpoint_margin + options.viewpoint_jitter), options.gain_range,
        options.bias_range, options.log_gamma_range, options.max_noise_sigma,
        options.max_blur_sigma,
        options.donors_from_other_sequences ? "other CamVid sequences" : "other CamVid frames",
        options.video_people.empty() ? "" : " and people segmented out of ",
        options.video_people.empty() ? "" : fs::path(options.video_people).filename().c_str(),
        options.random_placement ? "at random on the ground, perspective-consistent"
                                 : "near their original position",
        options.min_coverage, options.max_coverage);
  }
  return description;
}

// What every place's visits are made of.
struct Sources {
  cv::Size size;                      // of every background frame
  std::vector<Frame> frames;          // every CamVid frame
  std::vector<size_t> backgrounds;    // one frame per place
  std::vector<DonorObject> donors;    // objects of the other frames
  std::vector<Cutout> still_cutouts;  // random placement: the donors, same index
  std::vector<Cutout> video_cutouts;  // random placement: people of the video
};

// The objects one place's visits may paste, and those its visits used already.
struct PlaceDonors {
  std::vector<size_t> allowed;  // donors from other sequences or far enough in time
  std::set<size_t> used;        // a donor object appears in at most one visit of a place
  // Random placement: the allowed CamVid objects that can be placed by perspective (not cut
  // by the top edge, standing below their frame's horizon), and the video's people.
  std::vector<const Cutout*> still, video;
  std::set<const Cutout*> used_cutouts;
};

PlaceDonors DonorsForPlace(const Sources& sources, const Frame& background,
                           const RevisitOptions& options) {
  PlaceDonors place;
  for (size_t d = 0; d < sources.donors.size(); ++d) {
    const Frame& from = sources.frames[sources.donors[d].frame];
    if (from.info.sequence != background.info.sequence ||
        (!options.donors_from_other_sequences &&
         std::abs(from.info.frame - background.info.frame) >= options.donor_exclusion_frames)) {
      place.allowed.push_back(d);
    }
  }
  if (options.random_placement) {
    for (size_t d : place.allowed) {
      const Cutout& cutout = sources.still_cutouts[d];
      if (sources.donors[d].rect.y == 0) continue;
      if (!cutout.upright && !cutout.cut_bottom &&
          cutout.source_bottom - cutout.source_horizon < 3) {
        continue;
      }
      place.still.push_back(&cutout);
    }
    for (const Cutout& cutout : sources.video_cutouts) place.video.push_back(&cutout);
  }
  return place;
}

// One rendered visit of a place.
struct RenderedVisit {
  cv::Mat homography;                        // background -> visit
  cv::Mat image;                             // BGR
  cv::Mat mask;                              // CV_8U 255 = dynamic
  std::vector<DynamicBox> boxes;             // the dynamic objects
  std::vector<DynamicBox> background_boxes;  // the background's own objects, as warped
  double target = 0, coverage = 0;           // requested and measured coverage of `mask`
  std::string pasted_names;
  int pasted = 0, pasted_video = 0;
};

// Viewpoint: an inner quadrilateral of the frame, its corners jittered, onto the whole frame.
cv::Mat ViewpointHomography(cv::Size size, const RevisitOptions& options, Rng& rng) {
  const double margin = options.viewpoint_margin * options.viewpoint;
  const double jitter = options.viewpoint_jitter * options.viewpoint;
  const float w = float(size.width), h = float(size.height);
  auto inset = [&](double m) { return float(std::max(0.0, m + rng.Uniform(-jitter, jitter))); };
  const cv::Point2f src[4] = {{inset(margin) * w, inset(margin) * h},
                              {w - 1 - inset(margin) * w, inset(margin) * h},
                              {w - 1 - inset(margin) * w, h - 1 - inset(margin) * h},
                              {inset(margin) * w, h - 1 - inset(margin) * h}};
  const cv::Point2f dst[4] = {{0, 0}, {w - 1, 0}, {w - 1, h - 1}, {0, h - 1}};
  return cv::getPerspectiveTransform(src, dst);
}

// Of a few random unused allowed donors, the largest that fits what is left (fewer, larger
// objects, as in a real street), else the smallest; donors.size() when every draw was used.
size_t ChooseDonor(const std::vector<DonorObject>& donors, const PlaceDonors& place, double need,
                   double pixels, Rng& rng) {
  size_t d = donors.size();
  for (int draw = 0; draw < 8; ++draw) {
    const size_t c = place.allowed[rng.Below(place.allowed.size())];
    if (place.used.count(c)) continue;
    const bool fits = donors[c].area / pixels <= need;
    if (d == donors.size()) {
      d = c;
    } else {
      const bool chosen_fits = donors[d].area / pixels <= need;
      if ((fits && (!chosen_fits || donors[c].area > donors[d].area)) ||
          (!fits && !chosen_fits && donors[c].area < donors[d].area)) {
        d = c;
      }
    }
  }
  return d;
}

// Blends `donor` scaled to sw x sh with its top-left at (x, y) into `image` with a feathered
// alpha (the 3x3 mean of the binary mask) and marks every pixel it touches in `mask`. Returns
// how many pixels changed and their bounding box.
int BlendDonor(const DonorObject& donor, int sw, int sh, int x, int y, cv::Mat& image,
               cv::Mat& mask, cv::Rect* changed_box) {
  cv::Mat patch, object_mask;
  cv::resize(donor.patch, patch, cv::Size(sw, sh), 0, 0, cv::INTER_LINEAR);
  cv::resize(donor.mask, object_mask, cv::Size(sw, sh), 0, 0, cv::INTER_NEAREST);
  cv::Mat alpha;
  cv::Mat padded;
  cv::copyMakeBorder(object_mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, 0);
  cv::copyMakeBorder(patch, patch, 1, 1, 1, 1, cv::BORDER_REPLICATE);
  padded.convertTo(alpha, CV_32F, 1.0 / 255);
  cv::blur(alpha, alpha, cv::Size(3, 3), cv::Point(-1, -1), cv::BORDER_CONSTANT);
  const cv::Rect placed(x - 1, y - 1, sw + 2, sh + 2);
  const cv::Rect visible = placed & cv::Rect(0, 0, image.cols, image.rows);
  if (visible.area() == 0) return 0;
  const cv::Rect local = visible - placed.tl();
  int changed = 0;
  for (int r = 0; r < visible.height; ++r) {
    const float* a = alpha.ptr<float>(local.y + r) + local.x;
    const cv::Vec3b* p = patch.ptr<cv::Vec3b>(local.y + r) + local.x;
    cv::Vec3b* o = image.ptr<cv::Vec3b>(visible.y + r) + visible.x;
    uchar* m = mask.ptr<uchar>(visible.y + r) + visible.x;
    for (int c = 0; c < visible.width; ++c) {
      if (a[c] <= 0) continue;
      for (int k = 0; k < 3; ++k) {
        o[c][k] = cv::saturate_cast<uchar>(a[c] * p[c][k] + (1 - a[c]) * o[c][k]);
      }
      m[c] = 255;
      *changed_box |= cv::Rect(visible.x + c, visible.y + r, 1, 1);
      ++changed;
    }
  }
  return changed;
}

// Near-original placement (the original variant): pastes unused allowed donors until the
// coverage of the visit's mask reaches its target, each a little scaled with its bottom where
// it stood (on the road) and its centre moved a little, or its cut edge kept on the border.
void PasteNearOriginal(const std::vector<DonorObject>& donors, PlaceDonors* place, Rng& rng,
                       RenderedVisit* visit) {
  const cv::Size size = visit->image.size();
  const double pixels = double(size.area());
  const float w = float(size.width);
  for (int attempt = 0;
       attempt < 400 && visit->coverage < visit->target - 0.005 && !place->allowed.empty();
       ++attempt) {
    const double need = visit->target - visit->coverage;
    const size_t d = ChooseDonor(donors, *place, need, pixels, rng);
    if (d == donors.size()) continue;
    const DonorObject& donor = donors[d];
    double scale = rng.Uniform(0.9, 1.1);
    const double fraction = donor.area / pixels;
    if (fraction * scale * scale > need) scale = std::sqrt(need / fraction);
    if (scale < 0.5) continue;  // too large for what is left: try another object
    const int sw = std::max(1, int(std::lround(donor.rect.width * scale)));
    const int sh = std::max(1, int(std::lround(donor.rect.height * scale)));
    const bool left = donor.rect.x == 0;
    const bool right = donor.rect.x + donor.rect.width >= size.width;
    int x;
    if (left && !right) {
      x = 0;
    } else if (right && !left) {
      x = size.width - sw;
    } else {
      const double cx = donor.rect.x + donor.rect.width / 2.0 + rng.Uniform(-0.15, 0.15) * w;
      x = int(std::lround(cx - sw / 2.0));
    }
    const int y = donor.rect.y + donor.rect.height - sh;
    cv::Rect changed_box;
    if (BlendDonor(donor, sw, sh, x, y, visit->image, visit->mask, &changed_box) == 0) continue;
    place->used.insert(d);
    ++visit->pasted;
    DynamicBox box;
    box.class_id = CamVidLabelToCoco(donor.label);
    box.confidence = 1.0f;
    box.rect = cv::Rect2f(changed_box);
    visit->boxes.push_back(box);
    char name[96];
    std::snprintf(name, sizeof(name), "%s%s x%.2f", visit->pasted_names.empty() ? "" : ", ",
                  donor.name.c_str(), scale);
    visit->pasted_names += name;
    visit->coverage = cv::countNonZero(visit->mask) / pixels;
  }
}

// One visit: the background from a new viewpoint, objects pasted to a random coverage, then a
// photometric change. Every random draw comes from `rng`, in this order.
RenderedVisit RenderVisit(const Sources& sources, const Frame& background,
                          const cv::Mat& background_image, PlaceDonors* place,
                          const RevisitOptions& options, Rng& rng) {
  const cv::Size size = sources.size;
  const double pixels = double(size.area());
  RenderedVisit visit;
  visit.homography = ViewpointHomography(size, options, rng);
  cv::Mat labels;
  cv::warpPerspective(background_image, visit.image, visit.homography, size, cv::INTER_LINEAR,
                      cv::BORDER_REFLECT);
  cv::warpPerspective(background.labels, labels, visit.homography, size, cv::INTER_NEAREST,
                      cv::BORDER_REFLECT);
  const cv::Mat background_dynamic = DynamicOf(labels);
  visit.background_boxes = BoxesFromLabels(labels, 20);
  visit.mask = options.mask_background_objects ? background_dynamic.clone()
                                               : cv::Mat(cv::Mat::zeros(size, CV_8U));
  if (options.mask_background_objects) visit.boxes = visit.background_boxes;

  visit.target = rng.Uniform(options.min_coverage, options.max_coverage);
  visit.coverage = cv::countNonZero(visit.mask) / pixels;
  if (options.random_placement) {
    PasteResult paste =
        PasteAtRandom(visit.image, labels, background_dynamic, visit.mask, place->still,
                      place->video, place->used_cutouts, visit.target, options, rng);
    visit.mask |= paste.painted;
    visit.boxes.insert(visit.boxes.end(), paste.boxes.begin(), paste.boxes.end());
    visit.pasted_names = paste.names;
    visit.pasted = paste.objects;
    visit.pasted_video = paste.video_objects;
    visit.coverage = cv::countNonZero(visit.mask) / pixels;
  } else {
    PasteNearOriginal(sources.donors, place, rng, &visit);
  }
  Photometric(visit.image, rng, options);
  return visit;
}

// Where an entry's pixels come from: the background, the requested coverage and what was
// pasted; with unmarked background objects, those too (they are part of the place).
std::string VisitSource(const Frame& background, const RenderedVisit& visit,
                        const RevisitOptions& options) {
  char source[160];
  std::snprintf(source, sizeof(source),
                "background %s (own coverage %.3f); requested coverage %.3f; pasted: ",
                background.info.stem.c_str(), background.coverage, visit.target);
  std::string text =
      source + (visit.pasted_names.empty() ? std::string("none") : visit.pasted_names);
  if (!options.mask_background_objects) {
    text += "; background objects (static here, x y w h): ";
    if (visit.background_boxes.empty()) text += "none";
    for (size_t b = 0; b < visit.background_boxes.size(); ++b) {
      const cv::Rect2f& r = visit.background_boxes[b].rect;
      char object[96];
      std::snprintf(object, sizeof(object), "%s%s [%.0f %.0f %.0f %.0f]", b ? ", " : "",
                    CocoClassName(visit.background_boxes[b].class_id), r.x, r.y, r.width, r.height);
      text += object;
    }
  }
  return text;
}

// Writes a visit's image and mask and adds it to the dataset: visit 0 to the database, the
// others to the queries with visit 0 as their ground truth.
Status AddVisit(const RenderedVisit& visit, const Frame& background, int place, int visit_index,
                const RevisitOptions& options, RevisitResult* result) {
  Dataset& dataset = result->dataset;
  char id[32];
  std::snprintf(id, sizeof(id), "p%03d_v%d", place, visit_index);
  Entry entry;
  entry.id = id;
  entry.image = std::string("images/") + id + ".jpg";
  entry.mask = std::string("masks/") + id + ".png";
  entry.boxes = visit.boxes;
  entry.agent = "visit" + std::to_string(visit_index);
  entry.sequence = place;
  entry.timestamp_ns = int64_t(visit_index) * 3600 * 1000000000LL + int64_t(place) * 1000000000LL;
  entry.coverage = visit.coverage;
  entry.source = VisitSource(background, visit, options);
  const std::vector<int> jpeg = {cv::IMWRITE_JPEG_QUALITY, options.jpeg_quality};
  const std::vector<int> png = {cv::IMWRITE_PNG_COMPRESSION, 9};
  PLACEDB_RETURN_IF_ERROR(WriteImage(dataset.Resolve(entry.image), visit.image, jpeg));
  PLACEDB_RETURN_IF_ERROR(WriteImage(dataset.Resolve(entry.mask), visit.mask, png));

  VisitInfo info;
  info.id = id;
  info.place = place;
  info.visit = visit_index;
  info.background = background.info.stem;
  info.requested_coverage = visit.target;
  info.measured_coverage = visit.coverage;
  info.objects = visit.pasted;
  info.video_objects = visit.pasted_video;
  info.background_objects = int(visit.background_boxes.size());
  info.homography = visit.homography;
  result->visits.push_back(info);
  if (visit_index == 0) {
    dataset.database.push_back(std::move(entry));
  } else {
    entry.ground_truth = {dataset.database.back().id};
    dataset.queries.push_back(std::move(entry));
  }
  return Status::Ok();
}

// Every visit of one place, each from its own random stream.
Status BuildPlace(const Sources& sources, int place, const RevisitOptions& options,
                  RevisitResult* result) {
  const Frame& background = sources.frames[sources.backgrounds[size_t(place)]];
  cv::Mat background_image = cv::imread(background.info.image_path, cv::IMREAD_COLOR);
  if (background_image.empty() || background_image.size() != sources.size) {
    return Status::IoError("cannot read background " + background.info.image_path);
  }
  PlaceDonors donors = DonorsForPlace(sources, background, options);
  for (int visit = 0; visit < options.visits; ++visit) {
    Rng rng(StreamSeed(options.seed, uint64_t(place) + 1, uint64_t(visit) + 1));
    const RenderedVisit rendered =
        RenderVisit(sources, background, background_image, &donors, options, rng);
    PLACEDB_RETURN_IF_ERROR(AddVisit(rendered, background, place, visit, options, result));
  }
  return Status::Ok();
}

}  // namespace

Result<RevisitResult> BuildRevisits(const RevisitOptions& options) {
  PLACEDB_RETURN_IF_ERROR(ValidateRevisitOptions(options));
  auto listed = ListCamVid(options.camvid_dir);
  if (!listed.ok()) return listed.status();
  Sources sources;
  auto video = VideoCutouts(options);
  if (!video.ok()) return video.status();
  sources.video_cutouts = std::move(*video);
  auto frames = ReadFrames(*listed);
  if (!frames.ok()) return frames.status();
  sources.frames = std::move(*frames);
  sources.size = sources.frames[0].labels.size();
  auto backgrounds = ChooseBackgrounds(sources.frames, sources.size, options);
  if (!backgrounds.ok()) return backgrounds.status();
  sources.backgrounds = std::move(*backgrounds);
  auto donors = CollectDonors(sources.frames, sources.backgrounds, options);
  if (!donors.ok()) return donors.status();
  sources.donors = std::move(*donors);
  if (options.random_placement)
    sources.still_cutouts = StillCutouts(sources.donors, sources.frames);

  std::error_code ec;
  fs::create_directories(fs::path(options.out_dir) / "images", ec);
  fs::create_directories(fs::path(options.out_dir) / "masks", ec);
  if (ec) return Status::IoError("cannot create " + options.out_dir + ": " + ec.message());
  RevisitResult result;
  result.dataset.directory = options.out_dir;
  result.dataset.name = std::string(IsOriginalVariant(options) ? "revisits-" : "revisits-hard-") +
                        std::to_string(options.places) + "x" + std::to_string(options.visits);
  result.dataset.description = DatasetDescription(options);
  for (int place = 0; place < options.places; ++place) {
    PLACEDB_RETURN_IF_ERROR(BuildPlace(sources, place, options, &result));
  }
  return result;
}

}  // namespace placedb::eval
