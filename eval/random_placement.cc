#include "eval/random_placement.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <map>
#include <opencv2/imgproc.hpp>
#include <optional>

namespace placedb::eval {

int HorizonRow(const cv::Mat& labels) {
  const int lo = int(0.35 * labels.rows), hi = int(0.75 * labels.rows);
  for (int r = 0; r < labels.rows; ++r) {
    const uchar* row = labels.ptr<uchar>(r);
    int ground = 0;
    for (int c = 0; c < labels.cols; ++c)
      ground += row[c] == kCamVidRoad || row[c] == kCamVidPavement;
    if (ground >= labels.cols / 50) return std::clamp(r, lo, hi);
  }
  return labels.rows / 2;
}

namespace {

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
    if (label != kCamVidRoad && label != kCamVidPavement) return false;
    if (vehicle && quarter == 2 && label != kCamVidRoad) return false;
  }
  return true;
}

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

}  // namespace

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

}  // namespace placedb::eval
