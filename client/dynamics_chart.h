// The picture `placedb dynamics --png` writes (issue 16): a map's dynamic-object coverage by hour
// of day, as a weekday x hour heat map, and its top places as bars, each with its thumbnail
// (GetPlace include_thumbnail) when the map keeps one, else a placeholder. Drawn with OpenCV from
// the API's messages only; no network here.
#pragma once

#include <cstdint>
#include <map>
#include <opencv2/core.hpp>
#include <string>

#include "proto/placedb.pb.h"

namespace placedb::client {

// The chart's fixed size in pixels, whatever the data (so scripts and tests can rely on it).
inline constexpr int kDynamicsChartWidth = 960;
inline constexpr int kDynamicsChartHeight = 960;
// Bars drawn at most: the first places of `page` (best first).
inline constexpr int kDynamicsChartMaxBars = 8;

// A BGR image of kDynamicsChartWidth x kDynamicsChartHeight. `title` heads it (the map's name);
// `measure` names what the bars show ("mean coverage", "share of frames with car", ...).
// `thumbnails`: decoded thumbnails by place id; a place without one gets a placeholder.
// Hours with no observation are drawn grey, not as zero coverage.
cv::Mat DrawDynamicsChart(const std::string& title, const std::string& measure,
                          const v1::GetDynamicsResponse& page,
                          const std::map<uint32_t, cv::Mat>& thumbnails);

}  // namespace placedb::client
