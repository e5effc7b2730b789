// placedb-vocab: trains, converts and inspects vocabularies.
//
//   placedb-vocab train --out FILE [--images DIR]... [--video FILE [--video-every N]]... [options]
//   placedb-vocab convert --in FILE --out FILE [--format binary|dbow2-text]
//   placedb-vocab info FILE
//
// Exit status: 0 success, 1 failure, 2 bad usage.
#include <algorithm>
#include <atomic>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <string>
#include <thread>
#include <vector>

#include "core/base/files.h"
#include "core/base/parallel.h"
#include "core/base/thread_annotations.h"
#include "core/features/orb_features.h"
#include "core/vocabulary/vocabulary.h"
#include "core/vocabulary/vocabulary_trainer.h"

namespace fs = std::filesystem;

namespace placedb {
namespace {

constexpr int kExitFailure = 1;
constexpr int kExitUsage = 2;

constexpr char kUsage[] =
    "usage:\n"
    "  placedb-vocab train --out FILE [--images DIR]... [--video FILE [--video-every N]]...\n"
    "                      [--k 10] [--L 6] [--features 1000] [--seed 1] [--augment 0]\n"
    "                      [--threads 0] [--max-images N]\n"
    "      Extracts ORB from every image in each DIR (not recursive, natural order) and every\n"
    "      Nth frame of each video (--video-every applies to the --video before it; default 1),\n"
    "      adds --augment randomly warped views of each still image, trains a k-branch, L-level\n"
    "      vocabulary and saves it in the binary format. --max-images caps the source images\n"
    "      (stills first, then video frames) before augmentation; --threads 0 uses every core.\n"
    "  placedb-vocab convert --in FILE --out FILE [--format binary|dbow2-text]\n"
    "      Reads a binary or DBoW2 text vocabulary and writes it in --format (default binary).\n"
    "  placedb-vocab info FILE\n"
    "      Prints a vocabulary's parameters, checksum and load time.\n";

// Thrown for bad usage only inside argument parsing; main turns it into exit status 2.
struct UsageError {
  std::string message;
};

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// Walks argv as "--name value" pairs.
class Arguments {
 public:
  Arguments(int argc, char** argv, int first) : args_(argv + first, argv + argc) {}
  bool Done() const { return next_ >= args_.size(); }
  std::string Next() { return args_[next_++]; }
  std::string Value(const std::string& option) {
    if (Done()) throw UsageError{option + " needs a value"};
    return Next();
  }
  int64_t Integer(const std::string& option, int64_t min, int64_t max) {
    const std::string text = Value(option);
    int64_t value = 0;
    const auto [end, error] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (error != std::errc() || end != text.data() + text.size() || value < min || value > max) {
      throw UsageError{option + " must be an integer in [" + std::to_string(min) + ", " +
                       std::to_string(max) + "], got '" + text + "'"};
    }
    return value;
  }

 private:
  std::vector<std::string> args_;
  size_t next_ = 0;
};

// ---- train --------------------------------------------------------------------------------

struct VideoSource {
  std::string path;
  int every = 1;
};

struct TrainOptions {
  std::string out;
  std::vector<std::string> image_dirs;
  std::vector<VideoSource> videos;
  int k = 10;
  int levels = 6;
  int features = 1000;
  uint64_t seed = 1;
  int augment = 0;
  int threads = 0;
  int64_t max_images = -1;
};

TrainOptions ParseTrain(Arguments& args) {
  TrainOptions options;
  while (!args.Done()) {
    const std::string option = args.Next();
    if (option == "--out") {
      options.out = args.Value(option);
    } else if (option == "--images") {
      options.image_dirs.push_back(args.Value(option));
    } else if (option == "--video") {
      options.videos.push_back({args.Value(option), 1});
    } else if (option == "--video-every") {
      if (options.videos.empty()) throw UsageError{"--video-every must follow a --video"};
      options.videos.back().every = int(args.Integer(option, 1, 1000000));
    } else if (option == "--k") {
      options.k = int(args.Integer(option, 2, 64));
    } else if (option == "--L") {
      options.levels = int(args.Integer(option, 1, 10));
    } else if (option == "--features") {
      options.features = int(args.Integer(option, 1, 100000));
    } else if (option == "--seed") {
      options.seed = uint64_t(args.Integer(option, 0, INT64_MAX));
    } else if (option == "--augment") {
      options.augment = int(args.Integer(option, 0, 10000));
    } else if (option == "--threads") {
      options.threads = int(args.Integer(option, 0, 1024));
    } else if (option == "--max-images") {
      options.max_images = args.Integer(option, 1, INT64_MAX);
    } else {
      throw UsageError{"train: unknown option '" + option + "'"};
    }
  }
  if (options.out.empty()) throw UsageError{"train needs --out FILE"};
  if (options.image_dirs.empty() && options.videos.empty()) {
    throw UsageError{"train needs at least one --images DIR or --video FILE"};
  }
  return options;
}

// A random stream for augmentation, keyed by (seed, source, view) so that results do not depend
// on which thread handles which image.
class ViewRandom {
 public:
  ViewRandom(uint64_t seed, uint64_t source, uint64_t view) {
    const uint64_t words[3] = {seed, source, view};
    key_ = Checksum64(words, sizeof(words), 0x5ca1ab1e0ddba11ull);
  }
  double Uniform(double lo, double hi) {
    const uint64_t counter = counter_++;
    const uint64_t bits = Checksum64(&counter, sizeof(counter), key_);
    return lo + (hi - lo) * double(bits >> 11) * 0x1.0p-53;
  }

 private:
  uint64_t key_ = 0;
  uint64_t counter_ = 0;
};

// A randomly cropped, rotated, scaled and re-exposed view of `image` (grayscale).
cv::Mat AugmentedView(const cv::Mat& image, ViewRandom& random) {
  const double angle = random.Uniform(-30.0, 30.0);
  const double scale = random.Uniform(0.7, 1.4);
  const double crop_w = random.Uniform(0.6, 1.0);
  const double crop_h = random.Uniform(0.6, 1.0);
  const double shift_x = random.Uniform(-0.5, 0.5);
  const double shift_y = random.Uniform(-0.5, 0.5);
  const double contrast = random.Uniform(0.7, 1.3);
  const double brightness = random.Uniform(-40.0, 40.0);

  const double scaled_w = image.cols * scale;
  const double scaled_h = image.rows * scale;
  const int out_w = std::max(64, int(std::lround(scaled_w * crop_w)));
  const int out_h = std::max(64, int(std::lround(scaled_h * crop_h)));
  // Map the source centre, moved by the crop offset, to the centre of the output.
  cv::Mat transform = cv::getRotationMatrix2D(
      cv::Point2f(float(image.cols) / 2.0f, float(image.rows) / 2.0f), angle, scale);
  transform.at<double>(0, 2) += out_w / 2.0 - image.cols / 2.0 + shift_x * (scaled_w - out_w);
  transform.at<double>(1, 2) += out_h / 2.0 - image.rows / 2.0 + shift_y * (scaled_h - out_h);
  cv::Mat warped;
  cv::warpAffine(image, warped, transform, cv::Size(out_w, out_h), cv::INTER_LINEAR,
                 cv::BORDER_REFLECT_101);
  cv::Mat adjusted;
  warped.convertTo(adjusted, CV_8U, contrast, brightness);
  return adjusted;
}

// One source image: a still (read from its path by a worker) or a decoded video frame.
struct Source {
  std::string name;
  cv::Mat frame;  // empty for stills
  bool still = true;
};

int RunTrain(const TrainOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  cv::setNumThreads(1);  // parallel over images here; OpenCV's own threads would oversubscribe
  const int threads = options.threads > 0 ? options.threads
                                          : int(std::max(1u, std::thread::hardware_concurrency()));

  std::vector<Source> sources;
  for (const std::string& dir : options.image_dirs) {
    const auto paths = ListImageFiles(dir);
    if (!paths.ok()) throw std::runtime_error(paths.status().message());
    std::printf("images: %zu in %s\n", paths->size(), dir.c_str());
    for (const auto& path : *paths) sources.push_back({path, cv::Mat(), true});
  }
  const auto limit = [&] { return options.max_images > 0 ? size_t(options.max_images) : SIZE_MAX; };
  if (sources.size() > limit()) sources.resize(limit());
  for (const VideoSource& video : options.videos) {
    cv::VideoCapture capture(video.path);
    if (!capture.isOpened()) throw std::runtime_error("cannot open video " + video.path);
    size_t kept = 0;
    cv::Mat frame;
    for (int64_t index = 0; sources.size() < limit() && capture.read(frame); ++index) {
      if (index % video.every != 0) continue;
      cv::Mat gray;
      cv::cvtColor(frame, gray, frame.channels() == 4 ? cv::COLOR_BGRA2GRAY : cv::COLOR_BGR2GRAY);
      sources.push_back({video.path + "#" + std::to_string(index), gray, false});
      ++kept;
    }
    std::printf("video: %zu frames (every %d) from %s\n", kept, video.every, video.path.c_str());
  }
  if (sources.empty()) throw std::runtime_error("no training images found");

  // Extraction, parallel over sources; each view becomes one training image (for idf).
  OrbConfig orb;
  orb.max_features = options.features;
  std::vector<std::vector<std::vector<Descriptor256>>> views(sources.size());
  std::atomic<size_t> finished{0};
  std::atomic<size_t> extracted{0};
  // The workers' warnings, and their progress lines on stdout.
  struct {
    Mutex mutex;
    std::vector<std::string> warnings GUARDED_BY(mutex);
  } printed;
  ParallelFor(sources.size(), threads, [&](size_t s, int) {
    const Source& source = sources[s];
    try {
      cv::Mat image = source.still ? cv::imread(source.name, cv::IMREAD_GRAYSCALE) : source.frame;
      if (image.empty()) {
        MutexLock lock(printed.mutex);
        printed.warnings.push_back("skipped unreadable image " + source.name);
      } else {
        const int view_count = 1 + (source.still ? options.augment : 0);
        for (int view = 0; view < view_count; ++view) {
          cv::Mat input = image;
          if (view > 0) {
            ViewRandom random(options.seed, s, uint64_t(view));
            input = AugmentedView(image, random);
          }
          auto features = ExtractOrb(input, orb);
          if (!features.ok()) {
            MutexLock lock(printed.mutex);
            printed.warnings.push_back(source.name + ": " + features.status().ToString());
            continue;
          }
          extracted += features->descriptors.size();
          views[s].push_back(std::move(features->descriptors));
        }
      }
    } catch (const std::exception& e) {  // cv::Exception, or bad_alloc on a huge image
      MutexLock lock(printed.mutex);
      printed.warnings.push_back("skipped " + source.name + ": " + e.what());
    }
    const size_t done = ++finished;
    if (done % 50 == 0 || done == sources.size()) {
      MutexLock lock(printed.mutex);
      std::printf("extracted %zu/%zu source images, %zu descriptors (%.1f s)\n", done,
                  sources.size(), extracted.load(), SecondsSince(start));
      std::fflush(stdout);
    }
  });
  {
    MutexLock lock(printed.mutex);  // the workers are done: uncontended
    for (const auto& warning : printed.warnings) {
      std::fprintf(stderr, "warning: %s\n", warning.c_str());
    }
  }
  sources.clear();  // the decoded frames are no longer needed

  std::vector<std::vector<Descriptor256>> images;
  size_t descriptors = 0;
  for (auto& source_views : views) {
    for (auto& view : source_views) {
      descriptors += view.size();
      images.push_back(std::move(view));
    }
  }
  views.clear();
  const double extraction_seconds = SecondsSince(start);
  std::printf("training images: %zu, descriptors: %zu (extraction %.1f s)\n", images.size(),
              descriptors, extraction_seconds);
  std::fflush(stdout);

  TrainerConfig config;
  config.branching = options.k;
  config.depth = options.levels;
  config.seed = options.seed;
  config.threads = options.threads;
  int last_percent = -1;
  const auto train_start = std::chrono::steady_clock::now();
  auto trained = TrainVocabulary(images, config, [&](double fraction, const char* phase) {
    const int percent = int(fraction * 100);
    if (percent / 5 == last_percent / 5 && percent != 100) return;
    last_percent = percent;
    std::printf("training: %3d%% %s (%.1f s)\n", percent, phase, SecondsSince(train_start));
    std::fflush(stdout);
  });
  if (!trained.ok()) {
    std::fprintf(stderr, "error: %s\n", trained.status().ToString().c_str());
    return kExitFailure;
  }
  const Vocabulary& vocabulary = **trained;
  const Status saved = vocabulary.SaveBinary(options.out);
  if (!saved.ok()) {
    std::fprintf(stderr, "error: %s\n", saved.ToString().c_str());
    return kExitFailure;
  }
  std::printf(
      "summary: %zu training images, %zu descriptors, k %d, L %d, %u nodes, %u words, "
      "checksum %s, extraction %.1f s, training %.1f s, total %.1f s\n",
      images.size(), descriptors, vocabulary.branching(), vocabulary.depth(),
      vocabulary.node_count(), vocabulary.word_count(), vocabulary.checksum_hex().c_str(),
      extraction_seconds, SecondsSince(train_start), SecondsSince(start));
  std::printf("saved %s\n", options.out.c_str());
  return 0;
}

// ---- convert / info -----------------------------------------------------------------------

bool IsBinaryFile(const std::string& path) {
  char magic[8] = {};
  std::ifstream in(path, std::ios::binary);
  in.read(magic, sizeof(magic));
  return in.gcount() == sizeof(magic) && std::memcmp(magic, "PLDBVOC\0", 8) == 0;
}

int RunConvert(Arguments& args) {
  std::string in;
  std::string out;
  std::string format = "binary";
  while (!args.Done()) {
    const std::string option = args.Next();
    if (option == "--in") {
      in = args.Value(option);
    } else if (option == "--out") {
      out = args.Value(option);
    } else if (option == "--format") {
      format = args.Value(option);
      if (format != "binary" && format != "dbow2-text") {
        throw UsageError{"--format must be binary or dbow2-text, got '" + format + "'"};
      }
    } else {
      throw UsageError{"convert: unknown option '" + option + "'"};
    }
  }
  if (in.empty() || out.empty()) throw UsageError{"convert needs --in FILE and --out FILE"};
  const auto start = std::chrono::steady_clock::now();
  auto loaded = Vocabulary::Load(in);
  if (!loaded.ok()) {
    std::fprintf(stderr, "error: %s\n", loaded.status().ToString().c_str());
    return kExitFailure;
  }
  const double load_seconds = SecondsSince(start);
  const Vocabulary& vocabulary = **loaded;
  const Status saved =
      format == "binary" ? vocabulary.SaveBinary(out) : vocabulary.ExportDbow2Text(out);
  if (!saved.ok()) {
    std::fprintf(stderr, "error: %s\n", saved.ToString().c_str());
    return kExitFailure;
  }
  std::printf("converted %s (%u words, read in %.3f s) to %s %s, checksum %s\n", in.c_str(),
              vocabulary.word_count(), load_seconds, format.c_str(), out.c_str(),
              vocabulary.checksum_hex().c_str());
  return 0;
}

int RunInfo(Arguments& args) {
  if (args.Done()) throw UsageError{"info needs a FILE"};
  const std::string path = args.Next();
  if (!args.Done()) throw UsageError{"info takes one FILE"};
  const auto start = std::chrono::steady_clock::now();
  auto loaded = Vocabulary::Load(path);
  const double load_ms = SecondsSince(start) * 1000.0;
  if (!loaded.ok()) {
    std::fprintf(stderr, "error: %s\n", loaded.status().ToString().c_str());
    return kExitFailure;
  }
  const Vocabulary& v = **loaded;
  std::printf("file:      %s\n", path.c_str());
  std::printf("format:    %s\n", IsBinaryFile(path) ? "binary" : "dbow2-text");
  std::printf("k:         %d\n", v.branching());
  std::printf("L:         %d\n", v.depth());
  std::printf("nodes:     %u\n", v.node_count());
  std::printf("words:     %u\n", v.word_count());
  std::printf("scoring:   %s (%d)\n", ScoringName(v.default_scoring()),
              static_cast<int>(v.default_scoring()));
  std::printf("weighting: %s (%d)\n", WeightingName(v.weighting()),
              static_cast<int>(v.weighting()));
  std::printf("checksum:  %s\n", v.checksum_hex().c_str());
  std::printf("memory:    %.1f MB\n", double(v.memory_bytes()) / 1e6);
  std::printf("load ms:   %.2f\n", load_ms);
  return 0;
}

int Main(int argc, char** argv) {
  if (argc < 2) {
    std::fputs(kUsage, stderr);
    return kExitUsage;
  }
  const std::string command = argv[1];
  if (command == "-h" || command == "--help" || command == "help") {
    std::fputs(kUsage, stdout);
    return 0;
  }
  try {
    Arguments args(argc, argv, 2);
    if (command == "train") return RunTrain(ParseTrain(args));
    if (command == "convert") return RunConvert(args);
    if (command == "info") return RunInfo(args);
    throw UsageError{"unknown command '" + command + "'"};
  } catch (const UsageError& error) {
    std::fprintf(stderr, "placedb-vocab: %s\n\n%s", error.message.c_str(), kUsage);
    return kExitUsage;
  } catch (const cv::Exception& error) {
    std::fprintf(stderr, "error: OpenCV: %s\n", error.what());
  } catch (const std::bad_alloc&) {
    std::fprintf(stderr, "error: out of memory\n");
  } catch (const std::exception& error) {
    std::fprintf(stderr, "error: %s\n", error.what());
  }
  return kExitFailure;
}

}  // namespace
}  // namespace placedb

int main(int argc, char** argv) {
  return placedb::Main(argc, argv);
}
