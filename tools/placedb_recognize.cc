// placedb-recognize: the core engine from the command line, without a server.
// Builds an in-memory place database from one list of images and queries it with another,
// printing each query's ranked matches, inliers and per-stage timings.
//
//   placedb-recognize --vocabulary FILE --database LIST --queries LIST [options]
// LIST is a directory (images sorted by name, numbers in natural order) or a text file with one
// image path per line.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "core/base/files.h"
#include "core/pipeline/place_database.h"

namespace fs = std::filesystem;
using namespace placedb;

namespace {

void Usage() {
  std::fprintf(
      stderr,
      "usage: placedb-recognize --vocabulary FILE --database LIST --queries LIST\n"
      "         [--features N=1000] [--top-k K=3] [--scoring l1|l2|chi2|kl|bhattacharyya|dot]\n"
      "         [--verify disabled|direct|exhaustive] [--levels-up N=2] [--min-inliers N=12]\n"
      "  LIST: a directory of images or a text file with one image path per line\n");
}

Result<std::vector<std::string>> ReadList(const std::string& list) {
  std::vector<std::string> paths;
  if (fs::is_directory(list)) {
    auto images = ListImageFiles(list);
    if (!images.ok()) return images.status();
    paths = std::move(*images);
  } else {
    std::ifstream in(list);
    if (!in) return Status::NotFound(list + ": no such directory or list file");
    for (std::string line; std::getline(in, line);) {
      if (!line.empty() && line[0] != '#') paths.push_back(line);
    }
  }
  if (paths.empty()) return Status::InvalidArgument(list + ": no images");
  return paths;
}

}  // namespace

int main(int argc, char** argv) {
  std::string vocabulary_path, database_list, query_list;
  DatabaseConfig config;
  QueryOptions options;
  options.top_k = 3;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "-h" || arg == "--help") {
      Usage();
      return 0;
    }
    if (i + 1 >= argc) {
      std::fprintf(stderr, "%s needs a value\n", arg.c_str());
      Usage();
      return 2;
    }
    const std::string value = argv[++i];
    try {
      if (arg == "--vocabulary") {
        vocabulary_path = value;
      } else if (arg == "--database") {
        database_list = value;
      } else if (arg == "--queries") {
        query_list = value;
      } else if (arg == "--features") {
        config.orb.max_features = std::stoi(value);
      } else if (arg == "--top-k") {
        options.top_k = std::stoul(value);
      } else if (arg == "--levels-up") {
        config.verification.levels_up = std::stoi(value);
      } else if (arg == "--min-inliers") {
        config.verification.min_inliers = std::stoi(value);
      } else if (arg == "--scoring") {
        auto scoring = ParseScoring(value);
        if (!scoring.ok()) throw std::invalid_argument(scoring.status().message());
        config.scoring = *scoring;
      } else if (arg == "--verify") {
        auto mode = ParseVerificationMode(value);
        if (!mode.ok()) throw std::invalid_argument(mode.status().message());
        config.verification.mode = *mode;
      } else {
        std::fprintf(stderr, "unknown option %s\n", arg.c_str());
        Usage();
        return 2;
      }
    } catch (const std::exception& e) {
      std::fprintf(stderr, "bad value for %s: %s\n", arg.c_str(), e.what());
      return 2;
    }
  }
  if (vocabulary_path.empty() || database_list.empty() || query_list.empty()) {
    Usage();
    return 2;
  }

  auto vocabulary = Vocabulary::Load(vocabulary_path);
  if (!vocabulary.ok()) {
    std::fprintf(stderr, "%s\n", vocabulary.status().ToString().c_str());
    return 1;
  }
  auto db = PlaceDatabase::Create(*vocabulary, config);
  auto database_paths = ReadList(database_list);
  auto query_paths = ReadList(query_list);
  for (const Status& status : {db.status(), database_paths.status(), query_paths.status()}) {
    if (!status.ok()) {
      std::fprintf(stderr, "%s\n", status.ToString().c_str());
      return 1;
    }
  }
  std::printf("vocabulary %s: k=%d L=%d, %u words, checksum %s\n", vocabulary_path.c_str(),
              (*vocabulary)->branching(), (*vocabulary)->depth(), (*vocabulary)->word_count(),
              (*vocabulary)->checksum_hex().c_str());

  std::vector<std::string> names;
  for (size_t i = 0; i < database_paths->size(); ++i) {
    const std::string& path = (*database_paths)[i];
    Observation observation;
    observation.image = cv::imread(path, cv::IMREAD_GRAYSCALE);
    observation.metadata.sequence = i;
    auto added = (*db)->Add(observation);
    if (!added.ok()) {
      std::fprintf(stderr, "%s: %s\n", path.c_str(), added.status().ToString().c_str());
      return 1;
    }
    names.push_back(fs::path(path).filename().string());
    if (!added->stored) std::printf("not stored %s: %s\n", path.c_str(), added->rejection.c_str());
  }
  const DatabaseStats stats = (*db)->Stats();
  std::printf("database: %zu places, %llu descriptors, index %.1f KB\n\n", stats.places,
              static_cast<unsigned long long>(stats.descriptors_kept), stats.index_bytes / 1024.0);

  for (const std::string& path : *query_paths) {
    Observation observation;
    observation.image = cv::imread(path, cv::IMREAD_GRAYSCALE);
    auto result = (*db)->Query(observation, options);
    if (!result.ok()) {
      std::fprintf(stderr, "%s: %s\n", path.c_str(), result.status().ToString().c_str());
      continue;
    }
    std::printf("%s (%u features)", fs::path(path).filename().string().c_str(),
                result->counts.total);
    if (!result->valid) {
      std::printf(": %s\n", result->rejection.c_str());
      continue;
    }
    for (const Match& match : result->matches) {
      std::printf("  %s %.3f", names[match.metadata.sequence].c_str(), match.score);
      if (config.verification.mode != VerificationMode::kDisabled) {
        std::printf(" [%d inliers%s]", match.inliers, match.verified ? ", verified" : "");
      }
    }
    const StageTimings& t = result->timings;
    std::printf("   | extract %.1f transform %.2f search %.2f verify %.1f total %.1f ms\n",
                t.extract_ms, t.transform_ms, t.search_ms, t.verify_ms, t.total_ms);
  }
  return 0;
}
