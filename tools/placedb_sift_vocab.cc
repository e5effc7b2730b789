// placedb-sift-vocab: trains the SIFT vocabulary on Debian's sample images (opencv-doc, darknet;
// never on ../shared/data) and saves it, or with --if-missing keeps an existing one that loads.
//
//   placedb-sift-vocab --out var/vocabulary/sift-debian.pdbfv [--if-missing]
//       [--k 10] [--L 4] [--seed 1] [--threads 2] [--features 1000]
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

#include "core/base/timing.h"
#include "tools/rgbd_data.h"

int main(int argc, char** argv) {
  std::string out;
  bool if_missing = false;
  placedb::rgbd::SiftVocabularyOptions options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "placedb-sift-vocab: %s needs a value\n", arg.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--out") {
      out = value();
    } else if (arg == "--if-missing") {
      if_missing = true;
    } else if (arg == "--k") {
      options.branching = std::atoi(value().c_str());
    } else if (arg == "--L") {
      options.depth = std::atoi(value().c_str());
    } else if (arg == "--seed") {
      options.seed = std::strtoull(value().c_str(), nullptr, 10);
    } else if (arg == "--threads") {
      options.threads = std::atoi(value().c_str());
    } else if (arg == "--features") {
      options.features_per_image = std::atoi(value().c_str());
    } else {
      std::fprintf(stderr,
                   "usage: placedb-sift-vocab --out PATH [--if-missing] [--k K] [--L L] "
                   "[--seed S] [--threads T] [--features N]\n");
      return 2;
    }
  }
  if (out.empty()) {
    std::fprintf(stderr, "placedb-sift-vocab: --out is required\n");
    return 2;
  }
  if (if_missing && std::filesystem::exists(out)) {
    auto loaded = placedb::FloatVocabulary::Load(out);
    if (loaded.ok()) {
      std::printf("placedb-sift-vocab: %s loads (%u words, checksum %s); nothing to do\n",
                  out.c_str(), (*loaded)->word_count(), (*loaded)->checksum_hex().c_str());
      return 0;
    }
    std::fprintf(stderr, "placedb-sift-vocab: %s does not load (%s); rebuilding it\n", out.c_str(),
                 loaded.status().ToString().c_str());
  }
  placedb::Stopwatch watch;
  size_t descriptors = 0;
  auto vocabulary = placedb::rgbd::TrainDebianSiftVocabulary(options, &descriptors);
  if (!vocabulary.ok()) {
    std::fprintf(stderr, "placedb-sift-vocab: %s\n", vocabulary.status().ToString().c_str());
    return 1;
  }
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(out).parent_path(), ec);
  const placedb::Status saved = (*vocabulary)->Save(out);
  if (!saved.ok()) {
    std::fprintf(stderr, "placedb-sift-vocab: %s\n", saved.ToString().c_str());
    return 1;
  }
  std::printf("placedb-sift-vocab: %s: %zu descriptors, k=%d L=%d, %u words, checksum %s, %.1f s\n",
              out.c_str(), descriptors, options.branching, options.depth,
              (*vocabulary)->word_count(), (*vocabulary)->checksum_hex().c_str(),
              watch.ElapsedMs() / 1000.0);
  return 0;
}
