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

// Gain, bias, gamma per channel, then Gaussian sensor noise.
void Photometric(cv::Mat& image, Rng& rng, double strength) {
  if (strength <= 0) return;
  const double gain = rng.Uniform(1 - 0.25 * strength, 1 + 0.25 * strength);
  const double bias = rng.Uniform(-20 * strength, 20 * strength);
  const double gamma = std::exp(rng.Uniform(-0.22 * strength, 0.22 * strength));
  cv::Mat lut(1, 256, CV_8UC3);
  for (int c = 0; c < 3; ++c) {
    const double channel_gain = gain * rng.Uniform(1 - 0.05 * strength, 1 + 0.05 * strength);
    for (int v = 0; v < 256; ++v) {
      const double out = 255.0 * std::pow(v / 255.0, gamma) * channel_gain + bias;
      lut.at<cv::Vec3b>(0, v)[c] = cv::saturate_cast<uchar>(std::lround(out));
    }
  }
  cv::LUT(image, lut, image);
  const double sigma = rng.Uniform(0, 3 * strength);
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

Result<RevisitResult> BuildRevisits(const RevisitOptions& options) {
  if (options.places < 1) return Status::InvalidArgument("places must be at least 1");
  if (options.visits < 2) return Status::InvalidArgument("visits must be at least 2");
  if (!(options.min_coverage >= 0 && options.min_coverage <= options.max_coverage &&
        options.max_coverage <= 0.6)) {
    return Status::InvalidArgument("coverage: need 0 <= min_coverage <= max_coverage <= 0.6");
  }
  if (options.out_dir.empty()) return Status::InvalidArgument("out_dir is required");
  auto listed = ListCamVid(options.camvid_dir);
  if (!listed.ok()) return listed.status();

  // Every frame's labels and coverage.
  std::vector<Frame> frames;
  frames.reserve(listed->size());
  for (const CamVidFrame& info : *listed) {
    Frame frame;
    frame.info = info;
    frame.labels = cv::imread(info.label_path, cv::IMREAD_GRAYSCALE);
    if (frame.labels.empty()) return Status::NotFound("cannot read labels " + info.label_path);
    frame.coverage = cv::countNonZero(DynamicOf(frame.labels)) / double(frame.labels.total());
    frames.push_back(std::move(frame));
  }
  const cv::Size size = frames[0].labels.size();

  // ---- Backgrounds: low coverage, far apart, visually distinct -----------------------------
  Rng rng(StreamSeed(options.seed, 0xB6, 0));
  std::vector<size_t> candidates;
  for (size_t i = 0; i < frames.size(); ++i) {
    if (frames[i].coverage <= options.max_background_coverage && frames[i].labels.size() == size) {
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
        std::to_string(options.min_separation_frames) + " frames apart; asked for " +
        std::to_string(options.places) +
        " places (lower places, or raise max_background_coverage / lower min_separation_frames)");
  }
  const std::set<size_t> background_set(backgrounds.begin(), backgrounds.end());

  // ---- Donor objects: dynamic components of every non-background frame ---------------------
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

  // ---- Visits -------------------------------------------------------------------------------
  std::error_code ec;
  fs::create_directories(fs::path(options.out_dir) / "images", ec);
  fs::create_directories(fs::path(options.out_dir) / "masks", ec);
  if (ec) return Status::IoError("cannot create " + options.out_dir + ": " + ec.message());

  RevisitResult result;
  Dataset& dataset = result.dataset;
  dataset.directory = options.out_dir;
  dataset.name =
      "revisits-" + std::to_string(options.places) + "x" + std::to_string(options.visits);
  char description[512];
  std::snprintf(description, sizeof(description),
                "Synthetic revisits of %d real CamVid places (seed %llu): %d visits each with a "
                "random homography, a photometric change and real CamVid dynamic objects from "
                "other frames pasted to a coverage in [%.2f, %.2f]. Database = visit 0, queries "
                "= the other visits, ground truth = the same place's visit 0.",
                options.places, static_cast<unsigned long long>(options.seed), options.visits,
                options.min_coverage, options.max_coverage);
  dataset.description = description;
  const double pixels = double(size.area());
  const std::vector<int> jpeg = {cv::IMWRITE_JPEG_QUALITY, options.jpeg_quality};
  const std::vector<int> png = {cv::IMWRITE_PNG_COMPRESSION, 9};

  for (int place = 0; place < options.places; ++place) {
    const Frame& background = frames[backgrounds[size_t(place)]];
    cv::Mat background_image = cv::imread(background.info.image_path, cv::IMREAD_COLOR);
    if (background_image.empty() || background_image.size() != size) {
      return Status::IoError("cannot read background " + background.info.image_path);
    }
    // Donors allowed for this place: other sequences or far enough in time.
    std::vector<size_t> allowed;
    for (size_t d = 0; d < donors.size(); ++d) {
      const Frame& from = frames[donors[d].frame];
      if (from.info.sequence != background.info.sequence ||
          std::abs(from.info.frame - background.info.frame) >= options.donor_exclusion_frames) {
        allowed.push_back(d);
      }
    }
    std::set<size_t> used;  // a donor object appears in at most one visit of a place
    std::string first_id;
    for (int visit = 0; visit < options.visits; ++visit) {
      Rng vrng(StreamSeed(options.seed, uint64_t(place) + 1, uint64_t(visit) + 1));
      // Viewpoint: an inner quadrilateral, jittered, onto the whole frame.
      const double margin = 0.08 * options.viewpoint, jitter = 0.05 * options.viewpoint;
      const float w = float(size.width), h = float(size.height);
      auto inset = [&](double m) {
        return float(std::max(0.0, m + vrng.Uniform(-jitter, jitter)));
      };
      const cv::Point2f src[4] = {{inset(margin) * w, inset(margin) * h},
                                  {w - 1 - inset(margin) * w, inset(margin) * h},
                                  {w - 1 - inset(margin) * w, h - 1 - inset(margin) * h},
                                  {inset(margin) * w, h - 1 - inset(margin) * h}};
      const cv::Point2f dst[4] = {{0, 0}, {w - 1, 0}, {w - 1, h - 1}, {0, h - 1}};
      const cv::Mat homography = cv::getPerspectiveTransform(src, dst);
      cv::Mat image, labels;
      cv::warpPerspective(background_image, image, homography, size, cv::INTER_LINEAR,
                          cv::BORDER_REFLECT);
      cv::warpPerspective(background.labels, labels, homography, size, cv::INTER_NEAREST,
                          cv::BORDER_REFLECT);
      cv::Mat mask = DynamicOf(labels);
      std::vector<DynamicBox> boxes = BoxesFromLabels(labels, 20);

      const double target = vrng.Uniform(options.min_coverage, options.max_coverage);
      double coverage = cv::countNonZero(mask) / pixels;
      std::string pasted_names;
      int pasted = 0;
      for (int attempt = 0; attempt < 400 && coverage < target - 0.005 && !allowed.empty();
           ++attempt) {
        // Of a few random unused donors, the largest that fits what is left (fewer, larger
        // objects, as in a real street), else the smallest, scaled down.
        const double need = target - coverage;
        size_t d = donors.size();
        for (int draw = 0; draw < 8; ++draw) {
          const size_t c = allowed[vrng.Below(allowed.size())];
          if (used.count(c)) continue;
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
        if (d == donors.size()) continue;
        const DonorObject& donor = donors[d];
        double scale = vrng.Uniform(0.9, 1.1);
        const double fraction = donor.area / pixels;
        if (fraction * scale * scale > need) scale = std::sqrt(need / fraction);
        if (scale < 0.5) continue;  // too large for what is left: try another object
        const int sw = std::max(1, int(std::lround(donor.rect.width * scale)));
        const int sh = std::max(1, int(std::lround(donor.rect.height * scale)));
        // Anchor: the bottom of the object stays where it was (on the road); horizontally its
        // centre moves a little, or its cut edge stays on the frame border it touched.
        const bool left = donor.rect.x == 0;
        const bool right = donor.rect.x + donor.rect.width >= size.width;
        int x;
        if (left && !right) {
          x = 0;
        } else if (right && !left) {
          x = size.width - sw;
        } else {
          const double cx = donor.rect.x + donor.rect.width / 2.0 + vrng.Uniform(-0.15, 0.15) * w;
          x = int(std::lround(cx - sw / 2.0));
        }
        const int y = donor.rect.y + donor.rect.height - sh;
        cv::Mat patch, object_mask;
        cv::resize(donor.patch, patch, cv::Size(sw, sh), 0, 0, cv::INTER_LINEAR);
        cv::resize(donor.mask, object_mask, cv::Size(sw, sh), 0, 0, cv::INTER_NEAREST);
        // Feathered alpha: the 3x3 mean of the binary mask; every pixel it touches is dynamic.
        cv::Mat alpha;
        cv::Mat padded;
        cv::copyMakeBorder(object_mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, 0);
        cv::copyMakeBorder(patch, patch, 1, 1, 1, 1, cv::BORDER_REPLICATE);
        padded.convertTo(alpha, CV_32F, 1.0 / 255);
        cv::blur(alpha, alpha, cv::Size(3, 3), cv::Point(-1, -1), cv::BORDER_CONSTANT);
        const cv::Rect placed(x - 1, y - 1, sw + 2, sh + 2);
        const cv::Rect visible = placed & cv::Rect(0, 0, size.width, size.height);
        if (visible.area() == 0) continue;
        const cv::Rect local = visible - placed.tl();
        int changed = 0;
        cv::Rect changed_box;
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
            changed_box |= cv::Rect(visible.x + c, visible.y + r, 1, 1);
            ++changed;
          }
        }
        if (changed == 0) continue;
        used.insert(d);
        ++pasted;
        DynamicBox box;
        box.class_id = CamVidLabelToCoco(donor.label);
        box.confidence = 1.0f;
        box.rect = cv::Rect2f(changed_box);
        boxes.push_back(box);
        char name[96];
        std::snprintf(name, sizeof(name), "%s%s x%.2f", pasted_names.empty() ? "" : ", ",
                      donor.name.c_str(), scale);
        pasted_names += name;
        coverage = cv::countNonZero(mask) / pixels;
      }
      Photometric(image, vrng, options.photometric);

      char id[32];
      std::snprintf(id, sizeof(id), "p%03d_v%d", place, visit);
      Entry entry;
      entry.id = id;
      entry.image = std::string("images/") + id + ".jpg";
      entry.mask = std::string("masks/") + id + ".png";
      entry.boxes = boxes;
      entry.agent = "visit" + std::to_string(visit);
      entry.sequence = place;
      entry.timestamp_ns = int64_t(visit) * 3600 * 1000000000LL + int64_t(place) * 1000000000LL;
      entry.coverage = coverage;
      char source[160];
      std::snprintf(source, sizeof(source),
                    "background %s (own coverage %.3f); requested coverage %.3f; pasted: ",
                    background.info.stem.c_str(), background.coverage, target);
      entry.source = source + (pasted_names.empty() ? std::string("none") : pasted_names);
      PLACEDB_RETURN_IF_ERROR(WriteImage(dataset.Resolve(entry.image), image, jpeg));
      PLACEDB_RETURN_IF_ERROR(WriteImage(dataset.Resolve(entry.mask), mask, png));

      VisitInfo info;
      info.id = id;
      info.place = place;
      info.visit = visit;
      info.background = background.info.stem;
      info.requested_coverage = target;
      info.measured_coverage = coverage;
      info.objects = pasted;
      result.visits.push_back(info);
      if (visit == 0) {
        first_id = entry.id;
        dataset.database.push_back(std::move(entry));
      } else {
        entry.ground_truth = {first_id};
        dataset.queries.push_back(std::move(entry));
      }
    }
  }
  return result;
}

}  // namespace placedb::eval
