#include "eval/video_people.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <system_error>
#include <utility>

namespace placedb::eval {

namespace fs = std::filesystem;

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

}  // namespace placedb::eval
