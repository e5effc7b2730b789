#include "client/dynamics_chart.h"

#include <algorithm>
#include <array>
#include <cstdio>
#include <opencv2/imgproc.hpp>

namespace placedb::client {

namespace {

const cv::Scalar kWhite(255, 255, 255);
const cv::Scalar kBlack(0, 0, 0);
const cv::Scalar kGrey(200, 200, 200);
const cv::Scalar kDarkGrey(110, 110, 110);
const cv::Scalar kBarColour(180, 110, 40);  // BGR: a blue
constexpr int kLeft = 70;
constexpr int kRight = kDynamicsChartWidth - 30;
constexpr const char* kWeekdays[] = {"Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun"};

std::string Percent(double share) {
  char text[32];
  std::snprintf(text, sizeof text, "%.1f%%", 100.0 * share);
  return text;
}

void Text(cv::Mat& image, const std::string& text, cv::Point at, double scale = 0.45,
          const cv::Scalar& colour = kBlack) {
  cv::putText(image, text, at, cv::FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv::LINE_AA);
}

// Per weekday x hour: observations and mean coverage, from the histogram's non-empty bins.
struct HourBins {
  std::array<std::array<uint64_t, 24>, 7> observations{};
  std::array<std::array<double, 24>, 7> mean{};
};

HourBins ReadBins(const v1::DynamicStatistics& statistics) {
  HourBins bins;
  for (const v1::HourCoverage& bin : statistics.hours()) {
    if (bin.weekday() >= 7 || bin.hour() >= 24) continue;  // not ours to draw
    bins.observations[bin.weekday()][bin.hour()] = bin.observations();
    bins.mean[bin.weekday()][bin.hour()] = bin.mean_coverage();
  }
  return bins;
}

// Mean coverage by hour of day over every weekday (observation-weighted), drawn in `area`.
void DrawHours(cv::Mat& image, const HourBins& bins, const cv::Rect& area) {
  std::array<double, 24> mean{};
  std::array<uint64_t, 24> count{};
  for (int day = 0; day < 7; ++day) {
    for (int hour = 0; hour < 24; ++hour) {
      count[hour] += bins.observations[day][hour];
      mean[hour] += bins.mean[day][hour] * double(bins.observations[day][hour]);
    }
  }
  double top = 0;
  for (int hour = 0; hour < 24; ++hour) {
    if (count[hour] > 0) mean[hour] /= double(count[hour]);
    top = std::max(top, mean[hour]);
  }
  Text(image, "mean dynamic coverage by hour of day (UTC)", {area.x, area.y - 10}, 0.55);
  cv::rectangle(image, area, kDarkGrey);
  Text(image, top > 0 ? Percent(top) : "0%", {5, area.y + 12});
  Text(image, "0%", {5, area.y + area.height});
  const double width = double(area.width) / 24;
  for (int hour = 0; hour < 24; ++hour) {
    const int x0 = area.x + int(hour * width) + 3;
    const int x1 = area.x + int((hour + 1) * width) - 3;
    if (count[hour] == 0) {  // no data: a grey stub, not a zero bar
      cv::rectangle(image, cv::Point(x0, area.y + area.height - 4),
                    cv::Point(x1, area.y + area.height - 1), kGrey, cv::FILLED);
    } else if (top > 0) {
      const int height = int(std::lround(mean[hour] / top * (area.height - 2)));
      cv::rectangle(image, cv::Point(x0, area.y + area.height - height),
                    cv::Point(x1, area.y + area.height - 1), kBarColour, cv::FILLED);
    }
    if (hour % 3 == 0) {
      Text(image, std::to_string(hour), {x0, area.y + area.height + 16}, 0.4);
    }
  }
}

// Weekday x hour heat map of mean coverage; empty bins grey.
void DrawHeatMap(cv::Mat& image, const HourBins& bins, const cv::Rect& area) {
  double top = 0;
  for (int day = 0; day < 7; ++day) {
    for (int hour = 0; hour < 24; ++hour) {
      if (bins.observations[day][hour] > 0) top = std::max(top, bins.mean[day][hour]);
    }
  }
  Text(image,
       "by weekday and hour (UTC; grey = no frames; dark to bright = 0 to " + Percent(top) + ")",
       {area.x, area.y - 10}, 0.55);
  const double width = double(area.width) / 24;
  const double height = double(area.height) / 7;
  cv::Mat level(1, 1, CV_8U);
  cv::Mat colour;
  for (int day = 0; day < 7; ++day) {
    Text(image, kWeekdays[day], {20, area.y + int((day + 0.7) * height)}, 0.4);
    for (int hour = 0; hour < 24; ++hour) {
      const cv::Rect cell(area.x + int(hour * width), area.y + int(day * height), int(width) - 1,
                          int(height) - 1);
      cv::Scalar fill = kGrey;
      if (bins.observations[day][hour] > 0) {
        level.at<uint8_t>(0) =
            top > 0 ? uint8_t(std::lround(255 * bins.mean[day][hour] / top)) : uint8_t(0);
        cv::applyColorMap(level, colour, cv::COLORMAP_VIRIDIS);
        const cv::Vec3b c = colour.at<cv::Vec3b>(0);
        fill = cv::Scalar(c[0], c[1], c[2]);
      }
      cv::rectangle(image, cell, fill, cv::FILLED);
    }
  }
  for (int hour = 0; hour < 24; hour += 3) {
    Text(image, std::to_string(hour), {area.x + int(hour * width) + 3, area.br().y + 16}, 0.4);
  }
}

// The top places: thumbnail (or placeholder), id, a bar for the score and its value.
void DrawBars(cv::Mat& image, const std::string& measure, const v1::GetDynamicsResponse& page,
              const std::map<uint32_t, cv::Mat>& thumbnails, const cv::Rect& area) {
  Text(image, "top places by " + measure, {area.x, area.y - 10}, 0.55);
  const int rows = std::min(page.places_size(), kDynamicsChartMaxBars);
  if (rows == 0) {
    Text(image, "no place ranked", {area.x, area.y + 30});
    return;
  }
  double top = 0;
  for (int i = 0; i < rows; ++i) top = std::max(top, page.places(i).score());
  const int row_height = area.height / kDynamicsChartMaxBars;
  const cv::Size thumb(64, row_height - 8);
  const int bar_left = area.x + thumb.width + 110;
  const int bar_width = area.br().x - bar_left - 80;
  for (int i = 0; i < rows; ++i) {
    const v1::RankedPlace& place = page.places(i);
    const int y = area.y + i * row_height;
    const cv::Rect slot(area.x, y + 4, thumb.width, thumb.height);
    const auto found = thumbnails.find(place.place_id());
    if (found != thumbnails.end() && !found->second.empty()) {
      // Fit inside the slot, keeping the aspect ratio.
      const cv::Mat& t = found->second;
      const double scale = std::min(double(slot.width) / t.cols, double(slot.height) / t.rows);
      cv::Mat resized;
      cv::resize(t, resized,
                 cv::Size(std::max(1, int(t.cols * scale)), std::max(1, int(t.rows * scale))), 0, 0,
                 cv::INTER_AREA);
      if (resized.channels() == 1) cv::cvtColor(resized, resized, cv::COLOR_GRAY2BGR);
      resized.copyTo(image(cv::Rect(slot.x, slot.y, resized.cols, resized.rows)));
    } else {
      cv::rectangle(image, slot, kGrey, cv::FILLED);
      cv::line(image, slot.tl(), slot.br(), kWhite);
      cv::line(image, cv::Point(slot.x, slot.br().y), cv::Point(slot.br().x, slot.y), kWhite);
    }
    Text(image, "place " + std::to_string(place.place_id()),
         {slot.br().x + 10, y + row_height / 2 + 5});
    const int length = top > 0 ? int(std::lround(place.score() / top * bar_width)) : 0;
    if (length > 0) {
      cv::rectangle(image, cv::Point(bar_left, y + 10),
                    cv::Point(bar_left + length, y + row_height - 10), kBarColour, cv::FILLED);
    }
    char value[48];
    std::snprintf(value, sizeof value, "%.3f (%llu fr.)", place.score(),
                  static_cast<unsigned long long>(place.support()));
    Text(image, value, {bar_left + length + 6, y + row_height / 2 + 5}, 0.4);
  }
}

}  // namespace

cv::Mat DrawDynamicsChart(const std::string& title, const std::string& measure,
                          const v1::GetDynamicsResponse& page,
                          const std::map<uint32_t, cv::Mat>& thumbnails) {
  cv::Mat image(kDynamicsChartHeight, kDynamicsChartWidth, CV_8UC3, kWhite);
  const v1::DynamicStatistics& map = page.map();
  Text(image,
       title + ": " + std::to_string(map.observations()) + " frames, mean coverage " +
           Percent(map.mean_coverage()) + ", max " + Percent(map.max_coverage()),
       {20, 30}, 0.65);
  const HourBins bins = ReadBins(map);
  DrawHours(image, bins, cv::Rect(kLeft, 80, kRight - kLeft, 200));
  DrawHeatMap(image, bins, cv::Rect(kLeft, 340, kRight - kLeft, 7 * 22));
  DrawBars(image, measure, page, thumbnails,
           cv::Rect(20, 560, kDynamicsChartWidth - 40, kDynamicsChartHeight - 580));
  return image;
}

}  // namespace placedb::client
