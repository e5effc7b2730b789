// Outputs of a run (docs/evaluation.md):
//  - results.csv: one row per configuration x method x coverage bin (All, >10%, >20%, >30%);
//  - queries.csv: one row per configuration x method x query (what ranked first, verified, ...);
//  - table3.md: the paper's Table III layout (keys, Geom, then BoBW / BoBW+DO / +- for All and
//    each coverage bin), followed by database size and latency tables;
//  - fig5_accuracy_vs_coverage.png, fig6_database_size.png, fig7_latency.png (OpenCV drawings
//    in the manner of the paper's Figs. 5-7);
//  - run.json: the dataset, backend, options and per-stage means.
#pragma once

#include <string>

#include "core/base/status.h"
#include "eval/runner.h"

namespace placedb::eval {

// +- column: relative change in percent, (do - bobw) / bobw * 100; NaN when bobw is 0.
double RelativeChange(double bobw, double with_do);

// Paired comparison of two runs over the same queries (with ground truth, in `bin`): how many
// only BoBW+DO got right, how many only BoBW, and the exact two-sided McNemar p-value (the
// binomial test on those discordant pairs; 1 when there are none).
struct PairedComparison {
  int do_only = 0;
  int bobw_only = 0;
  double p_value = 1;
};
PairedComparison ComparePaired(const RunResults& results, const MethodRun& bobw,
                               const MethodRun& with_do, const CoverageBin& bin);

std::string ResultsCsv(const RunResults& results);
std::string QueriesCsv(const RunResults& results, const Dataset& dataset);
// The Markdown report: one Table III per BoBW+DO variant (detector confidence), then sizes and
// latencies. `title` heads it.
std::string MarkdownReport(const RunResults& results, const std::string& title);
std::string RunJson(const RunResults& results);

// Plots (PNG). Each returns IO_ERROR when the file cannot be written.
Status PlotAccuracyVsCoverage(const RunResults& results, const std::string& path);
Status PlotDatabaseSize(const RunResults& results, const std::string& path);
Status PlotLatency(const RunResults& results, const std::string& path);

// Everything above into `directory` (created).
Status WriteReport(const RunResults& results, const Dataset& dataset, const std::string& directory,
                   const std::string& title);

}  // namespace placedb::eval
