// Real images seen anew, for the benchmarks' synthetic maps: Debian's sample images (opencv-doc,
// darknet) and, when asked, every third CamVid frame, each view a seeded random crop, rotation,
// scale and brightness/contrast change at 640x480, with ORB 1000 extracted. Seeded by the view's
// number, so a run's views are the same in every run.
#pragma once

#include <algorithm>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "core/base/files.h"
#include "core/features/orb_features.h"

namespace placedb::bench {

// The source images; `camvid` adds every third CamVid frame of `shared`.
inline std::vector<std::string> SourceImages(const std::string& shared, bool camvid) {
  std::vector<std::string> paths;
  auto add_dir = [&](const std::string& dir, size_t every) {
    auto found = ListImageFiles(dir);
    if (!found.ok()) return;
    for (size_t i = 0; i < found->size(); i += every) paths.push_back((*found)[i]);
  };
  add_dir("/usr/share/doc/opencv-doc/examples/data", 1);
  add_dir("/usr/share/darknet/data", 1);
  if (camvid) add_dir(shared + "/data/camvid/images", 3);
  return paths;
}

// A seeded random view of `image`: crop, rotation, scale, brightness/contrast, at 640x480.
inline cv::Mat RandomView(const cv::Mat& image, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> angle(-15, 15), scale(1.0, 1.4), gain(0.7, 1.3),
      bias(-30, 30), shift(-0.1, 0.1);
  cv::Mat base;
  cv::resize(image, base, cv::Size(640, 480));
  const cv::Point2f centre(320 + float(shift(rng) * 640), 240 + float(shift(rng) * 480));
  cv::Mat warp = cv::getRotationMatrix2D(centre, angle(rng), scale(rng));
  cv::Mat view;
  cv::warpAffine(base, view, warp, base.size(), cv::INTER_LINEAR, cv::BORDER_REFLECT);
  view.convertTo(view, -1, gain(rng), bias(rng));
  return view;
}

// `view_count` views cycling over `sources` (view v of source v mod sources), ORB 1000, on every
// core; views under 100 descriptors dropped.
inline std::vector<FeatureSet> ExtractViews(const std::vector<std::string>& sources,
                                            size_t view_count) {
  OrbConfig orb;
  orb.max_features = 1000;
  std::vector<FeatureSet> views(view_count);
  std::vector<std::thread> workers;
  const unsigned threads = std::max(1u, std::thread::hardware_concurrency());
  for (unsigned t = 0; t < threads; ++t) {
    workers.emplace_back([&, t] {
      for (size_t v = t; v < view_count; v += threads) {
        std::mt19937_64 rng(v);
        cv::Mat image = cv::imread(sources[v % sources.size()], cv::IMREAD_GRAYSCALE);
        if (image.empty()) continue;
        auto features = ExtractOrb(RandomView(image, rng), orb);
        if (features.ok()) views[v] = std::move(features).value();
      }
    });
  }
  for (auto& worker : workers) worker.join();
  std::erase_if(views, [](const FeatureSet& f) { return f.size() < 100; });
  return views;
}

}  // namespace placedb::bench
