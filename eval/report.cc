#include "eval/report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>

namespace fs = std::filesystem;
using json = nlohmann::json;

namespace placedb::eval {

namespace {

std::string Fixed(double value, int decimals) {
  if (!std::isfinite(value)) return "n/a";
  char buffer[64];
  std::snprintf(buffer, sizeof(buffer), "%.*f", decimals, value);
  return buffer;
}

std::string Signed(double value, int decimals) {
  if (!std::isfinite(value)) return "n/a";
  char buffer[64];
  std::snprintf(buffer, sizeof(buffer), "%+.*f", decimals, value);
  return buffer;
}

// p-values: three decimals, or two significant digits below 0.001.
std::string PValue(double p) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), p < 0.001 ? "%.1e" : "%.3f", p);
  return buffer;
}

std::string Confidence(float confidence) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%.2f", confidence);
  return buffer;
}

// The DO variants of a run: distinct confidences of its BoBW+DO runs, in order.
std::vector<float> DoConfidences(const RunResults& results) {
  std::vector<float> confidences;
  for (const MethodRun& run : results.runs) {
    if (run.method == kBoBWDO &&
        std::find(confidences.begin(), confidences.end(), run.confidence) == confidences.end()) {
      confidences.push_back(run.confidence);
    }
  }
  return confidences;
}

// The variant the plots show: the confidence closest to the paper's 0.2.
float PrimaryConfidence(const RunResults& results) {
  const std::vector<float> confidences = DoConfidences(results);
  if (confidences.empty()) return 0;
  return *std::min_element(confidences.begin(), confidences.end(), [](float a, float b) {
    return std::abs(a - 0.2f) < std::abs(b - 0.2f);
  });
}

const MethodRun* FindRun(const RunResults& results, int features, int geom,
                         const std::string& method, float confidence) {
  for (const MethodRun& run : results.runs) {
    if (run.features == features && run.geom == geom && run.method == method &&
        (method == kBoBW || run.confidence == confidence)) {
      return &run;
    }
  }
  return nullptr;
}

// Grid points in run order: (features, geom) pairs.
std::vector<std::pair<int, int>> GridPoints(const RunResults& results) {
  std::vector<std::pair<int, int>> points;
  for (const MethodRun& run : results.runs) {
    const std::pair<int, int> point{run.features, run.geom};
    if (std::find(points.begin(), points.end(), point) == points.end()) points.push_back(point);
  }
  return points;
}

std::vector<int> Distinct(const std::vector<std::pair<int, int>>& points, bool first) {
  std::vector<int> values;
  for (const auto& point : points) {
    const int v = first ? point.first : point.second;
    if (std::find(values.begin(), values.end(), v) == values.end()) values.push_back(v);
  }
  return values;
}

// ---- Drawing ------------------------------------------------------------------------------

const cv::Scalar kWhite(255, 255, 255);
const cv::Scalar kBlack(0, 0, 0);
const cv::Scalar kGrid(225, 225, 225);
const cv::Scalar kAxis(90, 90, 90);
const cv::Scalar kRed(40, 40, 210);    // BoBW (BGR)
const cv::Scalar kGreen(40, 150, 40);  // BoBW+DO
const int kFont = cv::FONT_HERSHEY_SIMPLEX;

// align: 0 left, 1 centre, 2 right; the point is the text's baseline.
void Text(cv::Mat& canvas, const std::string& text, cv::Point at, double scale,
          const cv::Scalar& colour = kBlack, int align = 0, int thickness = 1) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  if (align == 1) at.x -= size.width / 2;
  if (align == 2) at.x -= size.width;
  cv::putText(canvas, text, at, kFont, scale, colour, thickness, cv::LINE_AA);
}

// Round tick step giving at most `max_ticks` ticks over [0, top].
double NiceStep(double top, int max_ticks) {
  if (top <= 0) return 1;
  const double raw = top / max_ticks;
  const double magnitude = std::pow(10.0, std::floor(std::log10(raw)));
  for (double m : {1.0, 2.0, 2.5, 5.0, 10.0}) {
    if (m * magnitude >= raw) return m * magnitude;
  }
  return 10 * magnitude;
}

std::string TickLabel(double value) {
  char buffer[32];
  if (std::abs(value - std::round(value)) < 1e-9) {
    std::snprintf(buffer, sizeof(buffer), "%.0f", value);
  } else {
    std::snprintf(buffer, sizeof(buffer), "%.1f", value);
  }
  return buffer;
}

struct Axes {
  cv::Rect area;  // plotting area in pixels
  double y_top = 100;
  int Y(double value) const {
    return area.y + area.height - int(std::lround(value / y_top * area.height));
  }
};

// Horizontal grid, y ticks and labels, and the frame.
void DrawYAxis(cv::Mat& canvas, const Axes& axes, double step, const std::string& label) {
  for (double v = 0; v <= axes.y_top + 1e-9; v += step) {
    const int y = axes.Y(v);
    cv::line(canvas, {axes.area.x, y}, {axes.area.x + axes.area.width, y}, kGrid, 1);
    Text(canvas, TickLabel(v), {axes.area.x - 5, y + 4}, 0.35, kAxis, 2);
  }
  cv::rectangle(canvas, axes.area, kAxis, 1);
  if (!label.empty()) Text(canvas, label, {axes.area.x, axes.area.y - 6}, 0.38, kAxis);
}

void Triangle(cv::Mat& canvas, cv::Point c, int r, const cv::Scalar& colour) {
  std::vector<cv::Point> points = {{c.x, c.y - r}, {c.x - r, c.y + r - 1}, {c.x + r, c.y + r - 1}};
  cv::fillConvexPoly(canvas, points, colour, cv::LINE_AA);
}

void Legend(cv::Mat& canvas, cv::Point at, const std::string& bobw, const std::string& with_do,
            bool markers) {
  if (markers) {
    Triangle(canvas, {at.x + 6, at.y - 4}, 5, kRed);
    cv::circle(canvas, {at.x + 186, at.y - 4}, 5, kGreen, cv::FILLED, cv::LINE_AA);
  } else {
    cv::rectangle(canvas, cv::Rect(at.x, at.y - 10, 12, 12), kRed, cv::FILLED);
    cv::rectangle(canvas, cv::Rect(at.x + 180, at.y - 10, 12, 12), kGreen, cv::FILLED);
  }
  Text(canvas, bobw, {at.x + 18, at.y}, 0.45);
  Text(canvas, with_do, {at.x + 198, at.y}, 0.45);
}

Status Save(const std::string& path, const cv::Mat& canvas) {
  if (!cv::imwrite(path, canvas, {cv::IMWRITE_PNG_COMPRESSION, 9})) {
    return Status::IoError("cannot write " + path);
  }
  return Status::Ok();
}

std::string DoLabel(const RunResults& results, float confidence) {
  std::string label = "BoBW+DO";
  if (results.options.boxes == BoxInput::kDetector) label += " @" + Confidence(confidence);
  return label;
}

// Grouped bars (BoBW red, DO green) per grid point, with optional whiskers.
struct BarGroup {
  std::string top_label, bottom_label;
  double bobw = 0, with_do = 0;
  double bobw_low = -1, bobw_high = -1, do_low = -1, do_high = -1;  // whiskers when >= 0
};

cv::Mat DrawBars(const std::vector<BarGroup>& groups, const std::string& title,
                 const std::string& y_label, const std::string& note, const std::string& do_label,
                 bool percent_labels) {
  const int group_width = 56, left = 70, right = 20, top = 70, plot_height = 330;
  int baseline = 0;
  const int note_width = cv::getTextSize(note, kFont, 0.38, 1, &baseline).width;
  const int width =
      std::max({640, left + right + int(groups.size()) * group_width, left + note_width + 20});
  const int height = top + plot_height + 80;
  cv::Mat canvas(height, width, CV_8UC3, kWhite);
  Text(canvas, title, {left, 26}, 0.6, kBlack, 0, 1);
  Legend(canvas, {left, 50}, "BoBW", do_label, false);
  double top_value = 0;
  for (const BarGroup& g : groups) {
    top_value = std::max({top_value, g.bobw, g.with_do, g.bobw_high, g.do_high});
  }
  Axes axes;
  axes.area = cv::Rect(left, top, width - left - right, plot_height);
  const double step = NiceStep(top_value * 1.08, 6);
  axes.y_top = std::max(step, std::ceil(top_value * 1.08 / step) * step);
  DrawYAxis(canvas, axes, step, y_label);
  for (size_t i = 0; i < groups.size(); ++i) {
    const BarGroup& g = groups[i];
    const int x0 = axes.area.x + int(i) * group_width + 8;
    const int bar = (group_width - 16) / 2;
    const double values[2] = {g.bobw, g.with_do};
    const double lows[2] = {g.bobw_low, g.do_low};
    const double highs[2] = {g.bobw_high, g.do_high};
    for (int m = 0; m < 2; ++m) {
      const cv::Rect rect(x0 + m * bar, axes.Y(values[m]), bar - 2,
                          axes.area.y + axes.area.height - axes.Y(values[m]));
      cv::rectangle(canvas, rect, m == 0 ? kRed : kGreen, cv::FILLED);
      if (lows[m] >= 0 && highs[m] >= 0) {
        const int cx = rect.x + rect.width / 2;
        cv::line(canvas, {cx, axes.Y(lows[m])}, {cx, axes.Y(highs[m])}, kBlack, 1, cv::LINE_AA);
        cv::line(canvas, {cx - 3, axes.Y(highs[m])}, {cx + 3, axes.Y(highs[m])}, kBlack, 1);
        cv::line(canvas, {cx - 3, axes.Y(lows[m])}, {cx + 3, axes.Y(lows[m])}, kBlack, 1);
      }
    }
    if (percent_labels && g.bobw > 0) {
      const double change = RelativeChange(g.bobw, g.with_do);
      Text(canvas, Fixed(change, 0) + "%", {x0 + bar, axes.Y(std::max(g.bobw, g.with_do)) - 4},
           0.32, kAxis, 1);
    }
    const int label_y = axes.area.y + axes.area.height;
    Text(canvas, g.top_label, {x0 + bar, label_y + 16}, 0.38, kBlack, 1);
    Text(canvas, g.bottom_label, {x0 + bar, label_y + 32}, 0.34, kAxis, 1);
  }
  Text(canvas, note, {left, height - 14}, 0.38, kAxis);
  return canvas;
}

}  // namespace

double RelativeChange(double bobw, double with_do) {
  if (bobw == 0) return std::numeric_limits<double>::quiet_NaN();
  return (with_do - bobw) / bobw * 100.0;
}

PairedComparison ComparePaired(const RunResults& results, const MethodRun& bobw,
                               const MethodRun& with_do, const CoverageBin& bin) {
  PairedComparison paired;
  const size_t n = std::min(bobw.queries.size(), with_do.queries.size());
  for (size_t q = 0; q < n; ++q) {
    if (!results.query_has_truth[q]) continue;
    if (bin.above >= 0 && !(results.query_coverage[q] > bin.above)) continue;
    const bool a = bobw.queries[q].correct, b = with_do.queries[q].correct;
    paired.do_only += b && !a;
    paired.bobw_only += a && !b;
  }
  const int discordant = paired.do_only + paired.bobw_only;
  if (discordant > 0) {
    // 2 * P(X <= min(b, c)) for X ~ Binomial(discordant, 1/2), summed in log space.
    const int k = std::min(paired.do_only, paired.bobw_only);
    double tail = 0;
    for (int i = 0; i <= k; ++i) {
      tail += std::exp(std::lgamma(discordant + 1.0) - std::lgamma(i + 1.0) -
                       std::lgamma(discordant - i + 1.0) - discordant * std::log(2.0));
    }
    paired.p_value = std::min(1.0, 2 * tail);
  }
  return paired;
}

std::string ResultsCsv(const RunResults& results) {
  std::ostringstream out;
  out << "dataset,backend,dynamic_source,features,geom,confidence,method,bin,queries,correct,"
         "accuracy,recall_at_1,recall_at_5,recall_at_10,invalid_queries,no_truth_queries,"
         "no_truth_accepted,db_places,db_invalid,db_descriptors_kept,db_descriptors_dropped,"
         "db_encoded_bytes,db_memory_bytes,db_disk_bytes,db_build_s,latency_mean_ms,"
         "latency_p50_ms,latency_p90_ms,match_mean_ms,extract_mean_ms,detect_mean_ms,do_only_"
         "correct,"
         "bobw_only_correct,mcnemar_p\n";
  for (const MethodRun& run : results.runs) {
    for (const CoverageBin& bin : PaperBins()) {
      const Summary s = Summarize(results, run, bin);
      const auto extract = results.extract_mean_ms.find(run.features);
      out << CsvField(results.dataset_name) << "," << CsvField(results.backend) << ","
          << CsvField(results.dynamic_source) << "," << run.features << "," << GeomName(run.geom)
          << "," << Confidence(run.confidence) << "," << run.method << "," << bin.name << ","
          << s.queries << "," << s.correct << "," << Fixed(s.accuracy, 2) << ","
          << Fixed(s.recall_at_1, 2) << "," << Fixed(s.recall_at_5, 2) << ","
          << Fixed(s.recall_at_10, 2) << "," << s.invalid << "," << s.no_truth << ","
          << s.no_truth_accepted << "," << run.database.places << "," << run.database.invalid << ","
          << run.database.descriptors_kept << "," << run.database.descriptors_dropped << ","
          << run.database.encoded_bytes << "," << run.database.memory_bytes << ","
          << run.database.disk_bytes << "," << Fixed(run.database.build_seconds, 3) << ","
          << Fixed(s.latency_mean_ms, 3) << "," << Fixed(s.latency_p50_ms, 3) << ","
          << Fixed(s.latency_p90_ms, 3) << "," << Fixed(s.match_mean_ms, 3) << ","
          << Fixed(extract == results.extract_mean_ms.end() ? 0.0 : extract->second, 3) << ","
          << Fixed(results.detect_mean_ms, 3) << ",";
      // The paired comparison, on the BoBW+DO rows (against BoBW of the same grid point).
      const MethodRun* bobw = FindRun(results, run.features, run.geom, kBoBW, 0);
      if (run.method == kBoBWDO && bobw) {
        const PairedComparison paired = ComparePaired(results, *bobw, run, bin);
        out << paired.do_only << "," << paired.bobw_only << "," << PValue(paired.p_value);
      } else {
        out << ",,";
      }
      out << "\n";
    }
  }
  return out.str();
}

std::string QueriesCsv(const RunResults& results, const Dataset& dataset) {
  std::ostringstream out;
  out << "features,geom,confidence,method,query_id,coverage,has_truth,valid,top1_id,score,"
         "verified,inliers,truth_rank,correct,latency_ms,match_ms,kept,dropped\n";
  for (const MethodRun& run : results.runs) {
    for (size_t q = 0; q < run.queries.size() && q < dataset.queries.size(); ++q) {
      const QueryOutcome& o = run.queries[q];
      const std::string top1 = o.top1 >= 0 && size_t(o.top1) < dataset.database.size()
                                   ? dataset.database[size_t(o.top1)].id
                                   : "";
      out << run.features << "," << GeomName(run.geom) << "," << Confidence(run.confidence) << ","
          << run.method << "," << CsvField(dataset.queries[q].id) << ","
          << Fixed(results.query_coverage[q], 4) << "," << int(results.query_has_truth[q]) << ","
          << int(o.valid) << "," << CsvField(top1) << "," << Fixed(o.score, 5) << ","
          << int(o.verified) << "," << o.inliers << "," << o.truth_rank << "," << int(o.correct)
          << "," << Fixed(o.latency_ms, 3) << "," << Fixed(o.match_ms, 3) << "," << o.kept << ","
          << o.dropped << "\n";
    }
  }
  return out.str();
}

std::string MarkdownReport(const RunResults& results, const std::string& title) {
  std::ostringstream md;
  const std::vector<CoverageBin> bins = PaperBins();
  md << "# " << title << "\n\n";
  // Query counts per bin (with ground truth).
  std::vector<int> per_bin(bins.size(), 0);
  int no_truth = 0;
  for (size_t q = 0; q < results.query_coverage.size(); ++q) {
    if (!results.query_has_truth[q]) {
      ++no_truth;
      continue;
    }
    for (size_t b = 0; b < bins.size(); ++b) {
      if (bins[b].above < 0 || results.query_coverage[q] > bins[b].above) ++per_bin[b];
    }
  }
  md << "- dataset: `" << results.dataset_name << "`: " << results.database_size
     << " database entries, " << results.query_coverage.size() << " queries (with ground truth: ";
  for (size_t b = 0; b < bins.size(); ++b) {
    md << (b ? ", " : "") << bins[b].name << " " << per_bin[b];
  }
  md << (no_truth ? "; " + std::to_string(no_truth) + " without" : "") << ")\n";
  md << "- backend: " << results.backend << "; BoBW+DO dynamic input: " << results.dynamic_source
     << "\n";
  for (const MethodRun& run : results.runs) {
    if (run.database.learned_words == 0 || run.geom != results.runs.front().geom) continue;
    md << "- the " << run.method << " database at " << run.features << " features"
       << (run.method == kBoBWDO ? " (boxes >= " + Fixed(run.confidence, 2) + ")" : "") << ": ";
    if (run.database.learned_depth == 0) {  // incremental words
      md << run.database.learned_words << " words grown from its stored descriptors\n";
      continue;
    }
    md << "learned " << run.database.learned_words << " words, L=" << run.database.learned_depth
       << ", from " << run.database.learned_from_descriptors << " stored descriptors in "
       << Fixed(run.database.learn_seconds, 2) << " s\n";
  }
  md << "- top-1 accuracy (%): the best-ranked place is a ground-truth place and, with "
        "verification (only the best candidate is verified; >= "
     << results.options.min_inliers
     << " RANSAC inliers), passed it. +- = relative change (BoBW+DO - BoBW) / BoBW in %.\n\n";

  const std::vector<std::pair<int, int>> points = GridPoints(results);
  for (float confidence : DoConfidences(results)) {
    md << "## Top-1 accuracy (%), " << DoLabel(results, confidence) << "\n\n";
    md << "| keys | Geom |";
    for (const CoverageBin& bin : bins) {
      const std::string name = bin.name == "All" ? "All" : bin.name + " dyn.";
      md << " " << name << " BoBW | " << name << " BoBW+DO | +- |";
    }
    md << "\n|---:|---|";
    for (size_t b = 0; b < bins.size(); ++b) md << "---:|---:|---:|";
    md << "\n";
    for (const auto& [features, geom] : points) {
      const MethodRun* bobw = FindRun(results, features, geom, kBoBW, 0);
      const MethodRun* with_do = FindRun(results, features, geom, kBoBWDO, confidence);
      if (!bobw || !with_do) continue;
      md << "| " << features << " | " << GeomName(geom) << " |";
      for (const CoverageBin& bin : bins) {
        const Summary a = Summarize(results, *bobw, bin), b = Summarize(results, *with_do, bin);
        if (a.queries == 0) {
          md << " - | - | - |";
          continue;
        }
        md << " " << Fixed(a.accuracy, 1) << " | " << Fixed(b.accuracy, 1) << " | "
           << Signed(RelativeChange(a.accuracy, b.accuracy), 1) << " |";
      }
      md << "\n";
    }
    md << "\n";

    md << "### Recall@k (%, BoW ranking, no verification) and paired top-1 comparison, all "
          "queries, " +
              DoLabel(results, confidence) + "\n\n";
    md << "| keys | Geom | R@1 BoBW | R@1 BoBW+DO | R@5 BoBW | R@5 BoBW+DO | R@10 BoBW | R@10 "
          "BoBW+DO | invalid queries BoBW / DO | top-1 right only with DO / only without "
          "(McNemar p) |";
    if (no_truth) md << " no-truth accepted BoBW / DO |";
    md << "\n|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|" << (no_truth ? "---:|" : "")
       << "\n";
    for (const auto& [features, geom] : points) {
      const MethodRun* bobw = FindRun(results, features, geom, kBoBW, 0);
      const MethodRun* with_do = FindRun(results, features, geom, kBoBWDO, confidence);
      if (!bobw || !with_do) continue;
      const Summary a = Summarize(results, *bobw, bins[0]),
                    b = Summarize(results, *with_do, bins[0]);
      md << "| " << features << " | " << GeomName(geom) << " | " << Fixed(a.recall_at_1, 1) << " | "
         << Fixed(b.recall_at_1, 1) << " | " << Fixed(a.recall_at_5, 1) << " | "
         << Fixed(b.recall_at_5, 1) << " | " << Fixed(a.recall_at_10, 1) << " | "
         << Fixed(b.recall_at_10, 1) << " | " << a.invalid << " / " << b.invalid << " |";
      const PairedComparison paired = ComparePaired(results, *bobw, *with_do, bins[0]);
      md << " " << paired.do_only << " / " << paired.bobw_only << " (" << PValue(paired.p_value)
         << ") |";
      if (no_truth) md << " " << a.no_truth_accepted << " / " << b.no_truth_accepted << " |";
      md << "\n";
    }
    md << "\n";

    md << "### Database size and query latency, " << DoLabel(results, confidence) << "\n\n";
    // In-process runs know the encoded sizes; server runs the map's files on disk.
    const bool encoded = results.runs.front().database.encoded_bytes > 0;
    const std::string size = encoded ? "encoded MB" : "on-disk MB";
    md << "| keys | Geom | places BoBW / DO | descriptors kept BoBW / DO | " << size << " BoBW | "
       << size << " BoBW+DO | +- | latency mean ms BoBW / DO | p50 BoBW / DO | p90 BoBW / DO | "
       << "search + verify mean ms BoBW / DO |\n";
    md << "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n";
    for (const auto& [features, geom] : points) {
      const MethodRun* bobw = FindRun(results, features, geom, kBoBW, 0);
      const MethodRun* with_do = FindRun(results, features, geom, kBoBWDO, confidence);
      if (!bobw || !with_do) continue;
      const Summary a = Summarize(results, *bobw, bins[0]),
                    b = Summarize(results, *with_do, bins[0]);
      auto megabytes = [&](const MethodRun* run) {
        return double(encoded ? run->database.encoded_bytes : run->database.disk_bytes) / 1e6;
      };
      const double mb_a = megabytes(bobw), mb_b = megabytes(with_do);
      md << "| " << features << " | " << GeomName(geom) << " | " << bobw->database.places << " / "
         << with_do->database.places << " | " << bobw->database.descriptors_kept << " / "
         << with_do->database.descriptors_kept << " | " << Fixed(mb_a, 3) << " | " << Fixed(mb_b, 3)
         << " | " << Signed(RelativeChange(mb_a, mb_b), 1) << " |";
      md << " " << Fixed(a.latency_mean_ms, 2) << " / " << Fixed(b.latency_mean_ms, 2) << " | "
         << Fixed(a.latency_p50_ms, 2) << " / " << Fixed(b.latency_p50_ms, 2) << " | "
         << Fixed(a.latency_p90_ms, 2) << " / " << Fixed(b.latency_p90_ms, 2) << " | "
         << Fixed(a.match_mean_ms, 3) << " / " << Fixed(b.match_mean_ms, 3) << " |\n";
    }
    md << "\n";
  }
  if (!results.runs.empty() && results.runs.front().database.encoded_bytes > 0) {
    md << "Encoded MB = the bytes a durable map writes for the stored places (record + BoW + "
          "static features + direct index + keys, core/storage/codec.h), before RocksDB's own "
          "overhead.";
  } else {
    md << "On-disk MB = the map's files on the server after ingestion (MapStats.bytes_on_disk).";
  }
  if (results.backend == "in-process") {
    md << " Latency = the engine's filter + transform + search + verification per query "
          "(features precomputed); ORB extraction per frame: ";
    bool first = true;
    for (const auto& [features, ms] : results.extract_mean_ms) {
      md << (first ? "" : ", ") << features << ": " << Fixed(ms, 1) << " ms";
      first = false;
    }
    md << ".";
  } else {
    md << " Latency = the client's round trip of a Query RPC (decode, extraction, filter, "
          "transform, search, verification, transport).";
  }
  if (results.detect_mean_ms > 0) {
    md << " Object detection per frame: " << Fixed(results.detect_mean_ms, 1) << " ms.";
  }
  md << "\n";
  return md.str();
}

std::string RunJson(const RunResults& results) {
  json j;
  j["dataset"] = results.dataset_name;
  j["backend"] = results.backend;
  j["dynamic_source"] = results.dynamic_source;
  j["database_entries"] = results.database_size;
  j["queries"] = results.query_coverage.size();
  const RunOptions& o = results.options;
  j["options"] = {{"features", o.features},
                  {"geoms", o.geoms},
                  {"filter", FilterMethodName(o.filter)},
                  {"place_threshold", o.place_threshold},
                  {"min_inliers", o.min_inliers},
                  {"top_k", o.top_k},
                  {"threads", o.threads}};
  // Only what applied: the sensitivity is exact_coverage's threshold, the confidences threshold
  // detector boxes.
  if (o.filter == FilterMethod::kExactCoverage) j["options"]["sensitivity"] = o.sensitivity;
  if (o.boxes == BoxInput::kDetector) j["options"]["confidences"] = o.confidences;
  json extract = json::object();
  for (const auto& [features, ms] : results.extract_mean_ms) extract[std::to_string(features)] = ms;
  j["extract_mean_ms"] = extract;
  j["detect_mean_ms"] = results.detect_mean_ms;
  j["written_unix_s"] = int64_t(std::time(nullptr));
  return j.dump(2) + "\n";
}

Status PlotAccuracyVsCoverage(const RunResults& results, const std::string& path) {
  const std::vector<std::pair<int, int>> points = GridPoints(results);
  const std::vector<int> features = Distinct(points, true);
  const std::vector<int> geoms = Distinct(points, false);
  const float confidence = PrimaryConfidence(results);
  // Disjoint 5 % bins from the smallest to the largest coverage (10 % bins past 60 %).
  double min_coverage = 1, max_coverage = 0;
  for (size_t q = 0; q < results.query_coverage.size(); ++q) {
    if (!results.query_has_truth[q]) continue;
    min_coverage = std::min(min_coverage, results.query_coverage[q]);
    max_coverage = std::max(max_coverage, results.query_coverage[q]);
  }
  if (min_coverage > max_coverage) min_coverage = max_coverage = 0;
  const double bin_width = max_coverage > 0.6 ? 0.1 : 0.05;
  const int first_bin = int(min_coverage / bin_width);
  const int bin_count = std::max(1, int(max_coverage / bin_width) - first_bin + 1);
  auto bin_of = [&](double coverage) {
    return std::clamp(int(coverage / bin_width) - first_bin, 0, bin_count - 1);
  };
  std::vector<int> bin_queries(size_t(bin_count), 0);
  for (size_t q = 0; q < results.query_coverage.size(); ++q) {
    if (results.query_has_truth[q]) ++bin_queries[size_t(bin_of(results.query_coverage[q]))];
  }

  const int panel_w = 250, panel_h = 170, left = 90, top = 90, gap_x = 45, gap_y = 50;
  const std::string title =
      "Top-1 accuracy (%) vs dynamic coverage of the query: " + results.dataset_name + " (" +
      std::to_string(results.query_coverage.size()) + " queries)";
  const std::string do_label = DoLabel(results, confidence) + " (" + results.dynamic_source + ")";
  const std::string note = "x: dynamic coverage of the query (%), disjoint " +
                           std::to_string(int(std::lround(bin_width * 100))) +
                           " % bins; n = queries per bin; y: top-1 accuracy (%)";
  int baseline = 0;
  const int text_width = std::max({cv::getTextSize(title, kFont, 0.55, 1, &baseline).width,
                                   198 + cv::getTextSize(do_label, kFont, 0.45, 1, &baseline).width,
                                   cv::getTextSize(note, kFont, 0.4, 1, &baseline).width});
  const int width =
      std::max(left + int(geoms.size()) * (panel_w + gap_x) + 10, left + text_width + 20);
  const int height = top + int(features.size()) * (panel_h + gap_y) + 40;
  cv::Mat canvas(height, width, CV_8UC3, kWhite);
  Text(canvas, title, {left, 26}, 0.55);
  Legend(canvas, {left, 56}, "BoBW", do_label, true);
  for (size_t r = 0; r < features.size(); ++r) {
    Text(canvas, "ORB", {12, top + int(r) * (panel_h + gap_y) + panel_h / 2 - 4}, 0.45);
    Text(canvas, std::to_string(features[r]),
         {12, top + int(r) * (panel_h + gap_y) + panel_h / 2 + 14}, 0.45);
    for (size_t c = 0; c < geoms.size(); ++c) {
      Axes axes;
      axes.area = cv::Rect(left + int(c) * (panel_w + gap_x), top + int(r) * (panel_h + gap_y),
                           panel_w, panel_h);
      axes.y_top = 100;
      DrawYAxis(canvas, axes, 25, r == 0 ? GeomName(geoms[c]) : "");
      auto x_of = [&](int bin) {
        return axes.area.x + int((bin + 0.5) * axes.area.width / bin_count);
      };
      // x: bin edges labelled in percent; the query counts under the bottom row.
      const int bottom = axes.area.y + axes.area.height;
      for (int b = 0; b <= bin_count; ++b) {
        const int x = axes.area.x + b * axes.area.width / bin_count;
        cv::line(canvas, {x, bottom}, {x, bottom + 3}, kAxis, 1);
        if (bin_count > 10 && b % 2) continue;
        Text(canvas, std::to_string(int(std::lround((first_bin + b) * bin_width * 100))),
             {x, bottom + 14}, 0.32, kAxis, 1);
      }
      if (r + 1 == features.size()) {
        Text(canvas, "n", {axes.area.x - 5, bottom + 28}, 0.32, kAxis, 2);
        for (int b = 0; b < bin_count; ++b) {
          Text(canvas, std::to_string(bin_queries[size_t(b)]), {x_of(b), bottom + 28}, 0.3, kAxis,
               1);
        }
      }
      for (int m = 0; m < 2; ++m) {
        const MethodRun* run =
            FindRun(results, features[r], geoms[c], m == 0 ? kBoBW : kBoBWDO, confidence);
        if (!run) continue;
        std::vector<int> correct(size_t(bin_count), 0), total(size_t(bin_count), 0);
        for (size_t q = 0; q < run->queries.size(); ++q) {
          if (!results.query_has_truth[q]) continue;
          const int b = bin_of(results.query_coverage[q]);
          ++total[size_t(b)];
          correct[size_t(b)] += run->queries[q].correct;
        }
        cv::Point previous(-1, -1);
        const cv::Scalar colour = m == 0 ? kRed : kGreen;
        for (int b = 0; b < bin_count; ++b) {
          if (total[size_t(b)] == 0) continue;
          const cv::Point p(x_of(b) + (m == 0 ? -2 : 2),
                            axes.Y(100.0 * correct[size_t(b)] / total[size_t(b)]));
          if (previous.x >= 0) cv::line(canvas, previous, p, colour, 1, cv::LINE_AA);
          previous = p;
        }
        for (int b = 0; b < bin_count; ++b) {
          if (total[size_t(b)] == 0) continue;
          const cv::Point p(x_of(b) + (m == 0 ? -2 : 2),
                            axes.Y(100.0 * correct[size_t(b)] / total[size_t(b)]));
          if (m == 0) {
            Triangle(canvas, p, 4, colour);
          } else {
            cv::circle(canvas, p, 4, colour, cv::FILLED, cv::LINE_AA);
          }
        }
      }
    }
  }
  Text(canvas, note, {left, height - 12}, 0.4, kAxis);
  return Save(path, canvas);
}

Status PlotDatabaseSize(const RunResults& results, const std::string& path) {
  const float confidence = PrimaryConfidence(results);
  std::vector<BarGroup> groups;
  double largest = 0;
  const bool encoded = !results.runs.empty() && results.runs.front().database.encoded_bytes > 0;
  for (const auto& [features, geom] : GridPoints(results)) {
    const MethodRun* a = FindRun(results, features, geom, kBoBW, 0);
    const MethodRun* b = FindRun(results, features, geom, kBoBWDO, confidence);
    if (!a || !b) continue;
    // The server backend knows the map's files, not the encoded sizes.
    auto bytes = [&](const MethodRun* run) {
      return double(encoded ? run->database.encoded_bytes : run->database.disk_bytes);
    };
    largest = std::max(largest, bytes(a));
    groups.push_back({std::to_string(features), GeomName(geom), bytes(a), bytes(b)});
  }
  const bool megabytes = largest >= 1e6;
  for (BarGroup& g : groups) {
    g.bobw /= megabytes ? 1e6 : 1e3;
    g.with_do /= megabytes ? 1e6 : 1e3;
  }
  const cv::Mat canvas = DrawBars(
      groups, "Database size per configuration: " + results.dataset_name,
      std::string(megabytes ? "MB" : "kB") + (encoded ? " (encoded)" : " (on disk)"),
      encoded ? "bars: bytes a durable map writes for its places (record, BoW, static features, "
                "direct index); labels: BoBW+DO change"
              : "bars: the map's files on the server (MapStats.bytes_on_disk); labels: BoBW+DO "
                "change",
      DoLabel(results, confidence), true);
  return Save(path, canvas);
}

Status PlotLatency(const RunResults& results, const std::string& path) {
  const float confidence = PrimaryConfidence(results);
  std::vector<BarGroup> groups;
  for (const auto& [features, geom] : GridPoints(results)) {
    const MethodRun* a = FindRun(results, features, geom, kBoBW, 0);
    const MethodRun* b = FindRun(results, features, geom, kBoBWDO, confidence);
    if (!a || !b) continue;
    const Summary sa = Summarize(results, *a, PaperBins()[0]);
    const Summary sb = Summarize(results, *b, PaperBins()[0]);
    BarGroup g{std::to_string(features), GeomName(geom), sa.latency_mean_ms, sb.latency_mean_ms};
    g.bobw_low = sa.latency_p50_ms;
    g.bobw_high = sa.latency_p90_ms;
    g.do_low = sb.latency_p50_ms;
    g.do_high = sb.latency_p90_ms;
    groups.push_back(g);
  }
  const std::string what = results.backend == "in-process"
                               ? "filter + transform + search + verify, features precomputed"
                               : "client round trip of a Query RPC";
  const cv::Mat canvas = DrawBars(
      groups, "Query latency per configuration: " + results.dataset_name, "ms",
      "bars: mean; whiskers: p50 to p90 (" + what + ")", DoLabel(results, confidence), false);
  return Save(path, canvas);
}

Status WriteReport(const RunResults& results, const Dataset& dataset, const std::string& directory,
                   const std::string& title) {
  std::error_code ec;
  fs::create_directories(directory, ec);
  if (ec) return Status::IoError("cannot create " + directory + ": " + ec.message());
  auto write = [&](const std::string& name, const std::string& contents) -> Status {
    const std::string path = directory + "/" + name;
    std::ofstream out(path, std::ios::trunc);
    if (!out) return Status::IoError("cannot write " + path);
    out << contents;
    if (!out.flush()) return Status::IoError("cannot write " + path);
    return Status::Ok();
  };
  PLACEDB_RETURN_IF_ERROR(write("results.csv", ResultsCsv(results)));
  PLACEDB_RETURN_IF_ERROR(write("queries.csv", QueriesCsv(results, dataset)));
  PLACEDB_RETURN_IF_ERROR(write("table3.md", MarkdownReport(results, title)));
  PLACEDB_RETURN_IF_ERROR(write("run.json", RunJson(results)));
  PLACEDB_RETURN_IF_ERROR(
      PlotAccuracyVsCoverage(results, directory + "/fig5_accuracy_vs_coverage.png"));
  PLACEDB_RETURN_IF_ERROR(PlotDatabaseSize(results, directory + "/fig6_database_size.png"));
  PLACEDB_RETURN_IF_ERROR(PlotLatency(results, directory + "/fig7_latency.png"));
  return Status::Ok();
}

}  // namespace placedb::eval
