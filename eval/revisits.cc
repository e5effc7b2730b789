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
#include <set>

#include "core/detect/detector.h"
#include "eval/adapters.h"
#include "eval/random_placement.h"
#include "eval/revisit_rng.h"

namespace fs = std::filesystem;

namespace placedb::eval {

namespace {

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
         cv::countNonZero((frames[i].labels == kCamVidRoad) |
                          (frames[i].labels == kCamVidPavement)) >=
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
