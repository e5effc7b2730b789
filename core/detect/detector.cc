#include "core/detect/detector.h"

#include <algorithm>
#include <array>
#include <bitset>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <functional>
#include <mutex>
#include <numeric>
#include <opencv2/core/utility.hpp>
#include <opencv2/dnn.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>
#include <thread>
#include <utility>

#include "core/base/files.h"
#include "core/base/thread_annotations.h"
#include "core/detect/onnx_graph.h"

namespace placedb {

namespace {

// ---- COCO names ----------------------------------------------------------------------------

constexpr std::array<const char*, kCocoClassCount> kCocoNames = {
    "person",        "bicycle",      "car",
    "motorcycle",    "airplane",     "bus",
    "train",         "truck",        "boat",
    "traffic light", "fire hydrant", "stop sign",
    "parking meter", "bench",        "bird",
    "cat",           "dog",          "horse",
    "sheep",         "cow",          "elephant",
    "bear",          "zebra",        "giraffe",
    "backpack",      "umbrella",     "handbag",
    "tie",           "suitcase",     "frisbee",
    "skis",          "snowboard",    "sports ball",
    "kite",          "baseball bat", "baseball glove",
    "skateboard",    "surfboard",    "tennis racket",
    "bottle",        "wine glass",   "cup",
    "fork",          "knife",        "spoon",
    "bowl",          "banana",       "apple",
    "sandwich",      "orange",       "broccoli",
    "carrot",        "hot dog",      "pizza",
    "donut",         "cake",         "chair",
    "couch",         "potted plant", "bed",
    "dining table",  "toilet",       "tv",
    "laptop",        "mouse",        "remote",
    "keyboard",      "cell phone",   "microwave",
    "oven",          "toaster",      "sink",
    "refrigerator",  "book",         "clock",
    "vase",          "scissors",     "teddy bear",
    "hair drier",    "toothbrush"};

// darknet's data/coco.names spells six classes the PASCAL VOC way.
constexpr std::array<std::pair<const char*, int>, 6> kDarknetAliases = {{{"motorbike", 3},
                                                                         {"aeroplane", 4},
                                                                         {"sofa", 57},
                                                                         {"pottedplant", 58},
                                                                         {"diningtable", 60},
                                                                         {"tvmonitor", 62}}};

// Lower case, '_' as ' ', surrounding blanks dropped: "Traffic_Light " -> "traffic light".
std::string NormaliseClassName(const std::string& name) {
  std::string out;
  for (char c : name) out += c == '_' ? ' ' : char(std::tolower(static_cast<unsigned char>(c)));
  const auto first = out.find_first_not_of(' ');
  if (first == std::string::npos) return "";
  return out.substr(first, out.find_last_not_of(' ') - first + 1);
}

// ---- Small helpers -------------------------------------------------------------------------

std::string FormatFloat(double value, int decimals) {
  std::ostringstream out;
  out.setf(std::ios::fixed);
  out.precision(decimals);
  out << value;
  return out.str();
}

std::string ShapeString(const cv::Mat& m) {
  std::string s = "[";
  for (int i = 0; i < m.dims; ++i) {
    if (i > 0) s += ',';
    s += std::to_string(m.size[i]);
  }
  return s + "]";
}

// Reads a whole model file. Missing -> NOT_FOUND, a directory -> INVALID_ARGUMENT, empty ->
// FAILED_PRECONDITION, unreadable -> IO_ERROR; `field` names the config field in messages.
Result<std::vector<uchar>> ReadModelFile(const std::string& path, const char* field) {
  namespace fs = std::filesystem;
  if (path.empty()) return Status::InvalidArgument(std::string(field) + " is empty");
  std::error_code ec;
  const fs::file_status status = fs::status(path, ec);
  if (status.type() == fs::file_type::not_found) {
    return Status::NotFound(std::string(field) + " '" + path + "' does not exist");
  }
  if (status.type() == fs::file_type::directory) {
    return Status::InvalidArgument(std::string(field) + " '" + path +
                                   "' is a directory, not a model file");
  }
  auto contents = ReadWholeFile(path);
  if (!contents.ok()) return contents.status().WithContext(std::string(field) + " '" + path + "'");
  if (contents->empty()) {
    return Status::FailedPrecondition(std::string(field) + " '" + path + "' is empty");
  }
  return std::vector<uchar>(contents->begin(), contents->end());
}

// ---- Darknet model preparation -------------------------------------------------------------

std::string Trim(const std::string& s) {
  const auto first = s.find_first_not_of(" \t\r");
  if (first == std::string::npos) return "";
  return s.substr(first, s.find_last_not_of(" \t\r") - first + 1);
}

// OpenCV's YOLO layer zeroes every class score below the layer's `thresh` (default 0.2), which
// would hide detections between a lower configured threshold and 0.2. Rewrites the cfg so that
// every [yolo]/[region] section has thresh=0 (any thresh of its own is dropped): all filtering
// then happens here. Fails when the cfg has no YOLO output layer.
Result<std::vector<uchar>> PrepareDarknetCfg(const std::vector<uchar>& cfg,
                                             const std::string& path) {
  std::istringstream in(std::string(cfg.begin(), cfg.end()));
  std::string out, line;
  bool in_yolo_section = false;
  int yolo_sections = 0;
  while (std::getline(in, line)) {
    const std::string trimmed = Trim(line);
    if (!trimmed.empty() && trimmed.front() == '[') {
      in_yolo_section = trimmed == "[yolo]" || trimmed == "[region]";
      out += line + "\n";
      if (in_yolo_section) {
        ++yolo_sections;
        out += "thresh=0\n";
      }
      continue;
    }
    if (in_yolo_section) {
      const auto eq = trimmed.find('=');
      if (eq != std::string::npos && Trim(trimmed.substr(0, eq)) == "thresh") continue;
    }
    out += line + "\n";
  }
  if (yolo_sections == 0) {
    return Status::FailedPrecondition("config_path '" + path +
                                      "' is not a darknet YOLO cfg: it has no [yolo] section");
  }
  return std::vector<uchar>(out.begin(), out.end());
}

// OpenCV fills whatever weights a short .weights file lacks with garbage and raises no error, so
// the size is checked against the parameters the cfg declares: the file is a header (major,
// minor, revision as int32, then `seen` as int64 from version 0.2 on, int32 before) followed by
// the float32 parameters of every convolution and batch-norm layer.
Status CheckDarknetWeightsSize(cv::dnn::Net& net, const std::vector<uchar>& weights,
                               const std::string& path) {
  size_t parameters = 0;
  for (const std::string& name : net.getLayerNames()) {
    cv::Ptr<cv::dnn::Layer> layer = net.getLayer(net.getLayerId(name));
    if (layer->type != "Convolution" && layer->type != "BatchNorm") continue;
    for (const cv::Mat& blob : layer->blobs) parameters += blob.total();
  }
  if (weights.size() < 12) {
    return Status::FailedPrecondition("model_path '" + path + "' is too short for darknet weights");
  }
  int32_t version[2];
  std::memcpy(version, weights.data(), sizeof(version));
  const size_t header = (version[0] * 10 + version[1] >= 2) ? 20 : 16;
  const size_t needed = header + parameters * sizeof(float);
  if (weights.size() < needed) {
    return Status::FailedPrecondition("model_path '" + path + "' holds " +
                                      std::to_string(weights.size()) + " bytes but its cfg needs " +
                                      std::to_string(needed) + ": truncated or for another cfg");
  }
  return Status::Ok();
}

// ---- Preprocessing -------------------------------------------------------------------------

// How network-input pixels map back to the frame: full = net / scale + offset, per axis.
struct InputMapping {
  double scale_x = 1, scale_y = 1;
  double offset_x = 0, offset_y = 0;
};

// The network input's size for a `frame_size` frame: the square, or with `rectangular` (letterbox
// only) the frame's aspect ratio with each side rounded up to a multiple of 32 (the network's
// largest stride) and at most `size`.
cv::Size NetworkInputSize(cv::Size frame_size, int size, Preprocessing preprocessing,
                          bool rectangular) {
  if (!rectangular || preprocessing != Preprocessing::kLetterbox) return {size, size};
  const double scale = std::min(double(size) / frame_size.width, double(size) / frame_size.height);
  auto side = [&](int length) {
    const int scaled = std::clamp(int(std::lround(length * scale)), 1, size);
    return std::min(size, (scaled + 31) / 32 * 32);
  };
  return {side(frame_size.width), side(frame_size.height)};
}

// The network input (`target` pixels, see NetworkInputSize) for `bgr`, and its mapping. `pad`
// fills the letterbox margin. The letterbox resizes straight into the input, with no
// intermediate image.
cv::Mat MakeNetworkInput(const cv::Mat& bgr, cv::Size target, Preprocessing preprocessing,
                         const cv::Scalar& pad, InputMapping* mapping) {
  const int size = std::max(target.width, target.height);
  auto resize_to = [](const cv::Mat& src, cv::Size dsize) {
    if (src.size() == dsize) return src;
    cv::Mat dst;
    cv::resize(src, dst, dsize, 0, 0, cv::INTER_LINEAR);
    return dst;
  };
  switch (preprocessing) {
    case Preprocessing::kLetterbox: {
      const double scale = std::min(double(size) / bgr.cols, double(size) / bgr.rows);
      const int width = std::clamp(int(std::lround(bgr.cols * scale)), 1, target.width);
      const int height = std::clamp(int(std::lround(bgr.rows * scale)), 1, target.height);
      cv::Mat input(target, CV_8UC3, pad);
      cv::Mat picture = input(cv::Rect(0, 0, width, height));
      if (bgr.size() == picture.size()) {
        bgr.copyTo(picture);
      } else {
        cv::resize(bgr, picture, picture.size(), 0, 0, cv::INTER_LINEAR);  // writes into the ROI
      }
      // The exact per-axis factor of the resize, not the rounded-off `scale`.
      mapping->scale_x = double(width) / bgr.cols;
      mapping->scale_y = double(height) / bgr.rows;
      return input;
    }
    case Preprocessing::kCentreCrop: {
      const int side = std::min(bgr.cols, bgr.rows);
      const cv::Rect crop((bgr.cols - side) / 2, (bgr.rows - side) / 2, side, side);
      mapping->scale_x = mapping->scale_y = double(size) / side;
      mapping->offset_x = crop.x;
      mapping->offset_y = crop.y;
      return resize_to(bgr(crop), target);
    }
    case Preprocessing::kStretch:
      mapping->scale_x = double(size) / bgr.cols;
      mapping->scale_y = double(size) / bgr.rows;
      return resize_to(bgr, target);
  }
  return {};
}

// ---- Decoding ------------------------------------------------------------------------------

constexpr int kRowLength = 5 + kCocoClassCount;  // box (4), objectness, class scores
constexpr std::array<int, 3> kYoloxStrides = {8, 16, 32};

int YoloxExpectedRows(cv::Size input) {
  int rows = 0;
  for (int stride : kYoloxStrides) rows += (input.width / stride) * (input.height / stride);
  return rows;
}

// A detection in network-input pixels, before mapping back.
struct Candidate {
  int class_id;
  float score;
  float cx, cy, w, h;
};

// The best dynamic class of one row, if its score reaches the threshold. Each class score is an
// independent probability (sigmoid outputs), so a row whose overall best class is static (say
// "bench" 0.35) still reports its person score of 0.3: recall on dynamic classes is what counts.
bool BestDynamicClass(const float* class_scores, float objectness,
                      const std::vector<int>& dynamic_ids, float threshold, int* class_id,
                      float* score) {
  float best = -1;
  for (int id : dynamic_ids) {
    const float s = objectness * class_scores[id];
    if (s > best) {
      best = s;
      *class_id = id;
    }
  }
  *score = best;
  return best >= threshold;
}

// YOLOX rows in grid order for strides 8, 16, 32: x = (p0 + gx) * s, y = (p1 + gy) * s,
// w = exp(p2) * s, h = exp(p3) * s; score = p4 * p[5 + c].
void DecodeYolox(const cv::Mat& output, cv::Size input, const std::vector<int>& dynamic_ids,
                 float threshold, std::vector<Candidate>* candidates) {
  const float* row = output.ptr<float>();
  for (int stride : kYoloxStrides) {
    const int grid_width = input.width / stride, grid_height = input.height / stride;
    for (int gy = 0; gy < grid_height; ++gy) {
      for (int gx = 0; gx < grid_width; ++gx, row += kRowLength) {
        const float objectness = row[4];
        if (objectness < threshold) continue;  // score = objectness * class <= objectness
        Candidate c;
        if (!BestDynamicClass(row + 5, objectness, dynamic_ids, threshold, &c.class_id, &c.score))
          continue;
        c.cx = (row[0] + gx) * stride;
        c.cy = (row[1] + gy) * stride;
        c.w = std::exp(row[2]) * stride;
        c.h = std::exp(row[3]) * stride;
        candidates->push_back(c);
      }
    }
  }
}

// OpenCV's darknet YOLO layer rows: [cx, cy, w, h] normalised to the input, objectness, then the
// class scores already multiplied by objectness.
void DecodeDarknet(const std::vector<cv::Mat>& outputs, int input_size,
                   const std::vector<int>& dynamic_ids, float threshold,
                   std::vector<Candidate>* candidates) {
  for (const cv::Mat& output : outputs) {
    for (int r = 0; r < output.rows; ++r) {
      const float* row = output.ptr<float>(r);
      if (row[4] < threshold) continue;
      Candidate c;
      if (!BestDynamicClass(row + 5, 1.0f, dynamic_ids, threshold, &c.class_id, &c.score)) continue;
      c.cx = row[0] * input_size;
      c.cy = row[1] * input_size;
      c.w = row[2] * input_size;
      c.h = row[3] * input_size;
      candidates->push_back(c);
    }
  }
}

// ---- Net pool ------------------------------------------------------------------------------

// cv::dnn::Net keeps per-inference state, so one Net serves one call at a time. The pool hands
// out idle Nets, builds a new one (from the bytes in memory) while fewer than `capacity` exist,
// and otherwise makes the caller wait for one to come back.
class NetPool {
 public:
  using Factory = std::function<Result<cv::dnn::Net>()>;

  NetPool(Factory factory, int capacity) : factory_(std::move(factory)), capacity_(capacity) {}

  void Add(cv::dnn::Net net) {
    MutexLock lock(mutex_);
    idle_.push_back(std::move(net));
    ++created_;
  }

  // Returns a Net for the caller's exclusive use; give it back with Release().
  Result<cv::dnn::Net> Acquire() {
    {
      MutexLock lock(mutex_);
      while (idle_.empty() && created_ >= capacity_) available_.Wait(mutex_);
      if (!idle_.empty()) {
        cv::dnn::Net net = std::move(idle_.back());
        idle_.pop_back();
        return net;
      }
      ++created_;  // reserve the slot; build outside the lock
    }
    Result<cv::dnn::Net> net = factory_();
    if (!net.ok()) {
      MutexLock lock(mutex_);
      --created_;
      available_.NotifyOne();
    }
    return net;
  }

  void Release(cv::dnn::Net net) {
    {
      MutexLock lock(mutex_);
      idle_.push_back(std::move(net));
    }
    available_.NotifyOne();
  }

 private:
  Factory factory_;
  const int capacity_;
  Mutex mutex_;
  CondVar available_;
  std::vector<cv::dnn::Net> idle_ GUARDED_BY(mutex_);
  int created_ GUARDED_BY(mutex_) = 0;
};

// ---- The detector --------------------------------------------------------------------------

class DnnDetector final : public Detector {
 public:
  // `silu_fused`: how many SiLU pairs FuseSiluNodes replaced in `model_bytes` (0: none);
  // `stem`: set when CutFocusStem cut YOLOX's Focus stem from them.
  DnnDetector(DetectorConfig config, std::vector<int> dynamic_ids, std::vector<uchar> model_bytes,
              std::vector<uchar> cfg_bytes, int pool_capacity, int silu_fused,
              std::optional<FocusStem> stem)
      : config_(std::move(config)),
        dynamic_ids_(std::move(dynamic_ids)),
        model_bytes_(std::move(model_bytes)),
        cfg_bytes_(std::move(cfg_bytes)),
        silu_fused_(silu_fused),
        stem_(stem),
        pool_([this] { return BuildNet(); }, pool_capacity) {}

  // Builds the first Net and checks the model's output layout on a blank frame.
  Status Initialise() {
    Result<cv::dnn::Net> net = BuildNet();
    if (!net.ok()) return net.status();
    if (config_.backend == DetectorBackend::kDarknet) {
      PLACEDB_RETURN_IF_ERROR(CheckDarknetWeightsSize(*net, model_bytes_, config_.model_path));
    }
    std::vector<cv::Mat> outputs;
    const cv::Mat blank(config_.input_size, config_.input_size, CV_8UC3, PadColour());
    try {
      RunNet(*net, blank, &outputs);
    } catch (const cv::Exception& e) {
      return Status::FailedPrecondition("model '" + config_.model_path +
                                        "' fails on a blank input: " + e.what());
    }
    PLACEDB_RETURN_IF_ERROR(CheckOutputLayout(outputs, blank.size()));
    pool_.Add(std::move(*net));
    return Status::Ok();
  }

  // No exception leaves Detect: OpenCV may throw from any of its calls (cv::Exception), and a
  // huge frame may exhaust memory.
  Result<std::vector<DynamicBox>> Detect(const cv::Mat& image) const override {
    try {
      return DetectOrThrow(image);
    } catch (const cv::Exception& e) {
      return Status::Internal(std::string("OpenCV failed during detection: ") + e.what());
    } catch (const std::bad_alloc&) {
      return Status::ResourceExhausted("out of memory during detection");
    } catch (const std::exception& e) {
      return Status::Internal(std::string("detection failed: ") + e.what());
    }
  }

  std::string model_name() const override {
    return std::filesystem::path(config_.model_path).filename().string();
  }

  std::string Describe() const override {
    std::string classes;
    for (int id : dynamic_ids_) {
      if (!classes.empty()) classes += ',';
      classes += kCocoNames[size_t(id)];
    }
    return std::string(DetectorBackendName(config_.backend)) + " " + model_name() + ", input " +
           std::to_string(config_.input_size) + "x" + std::to_string(config_.input_size) + " " +
           PreprocessingName(config_.preprocessing) + (rectangular() ? " (rectangular)" : "") +
           (silu_fused_ > 0 ? ", " + std::to_string(silu_fused_) + " SiLU fused" : "") +
           (stem_ ? ", Focus stem in preprocessing" : "") +
           ", confidence >= " + FormatFloat(config_.confidence_threshold, 2) + BoxRules() +
           ", NMS IoU " + FormatFloat(config_.nms_iou_threshold, 2) + ", classes " + classes;
  }

  int input_size() const override { return config_.input_size; }
  const DetectorConfig& config() const override { return config_; }

 private:
  Result<std::vector<DynamicBox>> DetectOrThrow(const cv::Mat& image) const {
    if (image.empty()) return Status::InvalidArgument("image is empty");
    if (image.depth() != CV_8U) {
      return Status::InvalidArgument("image must be 8-bit (got OpenCV depth " +
                                     std::to_string(image.depth()) + ")");
    }
    cv::Mat bgr;
    switch (image.channels()) {
      case 3:
        bgr = image;
        break;
      case 1:
        cv::cvtColor(image, bgr, cv::COLOR_GRAY2BGR);
        break;
      case 4:
        cv::cvtColor(image, bgr, cv::COLOR_BGRA2BGR);
        break;
      default:
        return Status::InvalidArgument("image must have 1, 3 or 4 channels (got " +
                                       std::to_string(image.channels()) + ")");
    }

    InputMapping mapping;
    const cv::Size input_size =
        NetworkInputSize(bgr.size(), config_.input_size, config_.preprocessing, rectangular());
    const cv::Mat input =
        MakeNetworkInput(bgr, input_size, config_.preprocessing, PadColour(), &mapping);

    std::vector<Candidate> candidates;
    {
      Result<cv::dnn::Net> net = pool_.Acquire();
      if (!net.ok()) return net.status();
      // Back to the pool however this scope ends, exceptions included.
      struct ReturnToPool {
        NetPool& pool;
        cv::dnn::Net& net;
        ~ReturnToPool() { pool.Release(std::move(net)); }
      } lease{pool_, *net};
      std::vector<cv::Mat> outputs;
      RunNet(*net, input, &outputs);
      PLACEDB_RETURN_IF_ERROR(CheckOutputLayout(outputs, input.size()));
      Decode(outputs, input.size(), &candidates);
    }

    std::vector<DynamicBox> boxes;
    boxes.reserve(candidates.size());
    for (const Candidate& c : candidates) {
      // exp() of a wild regression output can overflow: such a row is noise, not an object.
      if (!std::isfinite(c.cx) || !std::isfinite(c.cy) || !std::isfinite(c.w) ||
          !std::isfinite(c.h)) {
        continue;
      }
      DynamicBox box;
      box.class_id = c.class_id;
      box.confidence = std::min(c.score, 1.0f);
      const double x0 = (c.cx - c.w / 2) / mapping.scale_x + mapping.offset_x;
      const double y0 = (c.cy - c.h / 2) / mapping.scale_y + mapping.offset_y;
      box.rect = cv::Rect2f(float(x0), float(y0), float(c.w / mapping.scale_x),
                            float(c.h / mapping.scale_y));
      boxes.push_back(box);
    }
    boxes = SuppressNonMaxima(std::move(boxes), config_.nms_iou_threshold);

    // Clip to the frame; drop what lies entirely outside it.
    const cv::Rect2f frame(0, 0, float(image.cols), float(image.rows));
    std::vector<DynamicBox> clipped;
    clipped.reserve(boxes.size());
    for (DynamicBox& box : boxes) {
      box.rect &= frame;
      if (box.rect.width > 0 && box.rect.height > 0) clipped.push_back(box);
    }
    return ApplyBoxRules(std::move(clipped), config_, image.size());
  }

  // ", bus >= 0.40, boxes >= 0.1 % of the frame, boxes > 30 % of the frame >= 0.50", or "".
  std::string BoxRules() const {
    std::string out;
    for (const auto& [name, value] : config_.class_confidence) {
      out += ", " + name + " >= " + FormatFloat(value, 2);
    }
    if (config_.min_box_area > 0) {
      out += ", boxes >= " + FormatFloat(config_.min_box_area * 100, 1) + " % of the frame";
    }
    if (config_.large_box_confidence > 0 && config_.large_box_area < 1) {
      out += ", boxes > " + FormatFloat(config_.large_box_area * 100, 0) +
             " % of the frame >= " + FormatFloat(config_.large_box_confidence, 2);
    }
    return out;
  }

  bool is_yolox() const { return config_.backend == DetectorBackend::kYoloxOnnx; }
  bool rectangular() const {
    return is_yolox() && config_.rectangular_letterbox &&
           config_.preprocessing == Preprocessing::kLetterbox;
  }

  // YOLOX was trained with pad 114; darknet letterboxes with mid grey (0.5).
  cv::Scalar PadColour() const { return is_yolox() ? cv::Scalar::all(114) : cv::Scalar::all(128); }

  Result<cv::dnn::Net> BuildNet() const {
    try {
      cv::dnn::Net net = is_yolox() ? cv::dnn::readNetFromONNX(model_bytes_)
                                    : cv::dnn::readNet("darknet", model_bytes_, cfg_bytes_);
      if (net.empty()) {
        return Status::FailedPrecondition("model '" + config_.model_path + "' has no layers");
      }
      net.setPreferableBackend(cv::dnn::DNN_BACKEND_OPENCV);
      net.setPreferableTarget(cv::dnn::DNN_TARGET_CPU);
      return net;
    } catch (const cv::Exception& e) {
      std::string what = is_yolox() ? "model_path '" + config_.model_path + "' is not an ONNX model"
                                    : "model_path '" + config_.model_path + "' / config_path '" +
                                          config_.config_path + "' are not a darknet model";
      return Status::FailedPrecondition(what + " OpenCV can load: " + e.what());
    }
  }

  void RunNet(cv::dnn::Net& net, const cv::Mat& input, std::vector<cv::Mat>* outputs) const {
    // YOLOX: BGR 0..255 as is (with the stem cut: its 12 phase channels). darknet: RGB scaled to
    // 0..1.
    const cv::Mat blob = stem_        ? SpaceToDepthBlob(input, *stem_)
                         : is_yolox() ? cv::dnn::blobFromImage(input, 1.0, cv::Size(), cv::Scalar(),
                                                               /*swapRB=*/false, /*crop=*/false)
                                      : cv::dnn::blobFromImage(input, 1.0 / 255, cv::Size(),
                                                               cv::Scalar(), true, false);
    net.setInput(blob);
    net.forward(*outputs, net.getUnconnectedOutLayersNames());
  }

  // `input`: the network input's size (YOLOX's row count depends on it).
  Status CheckOutputLayout(const std::vector<cv::Mat>& outputs, cv::Size input) const {
    if (is_yolox()) {
      const int rows = YoloxExpectedRows(input);
      const bool ok = outputs.size() == 1 && outputs[0].dims == 3 && outputs[0].size[0] == 1 &&
                      outputs[0].size[1] == rows && outputs[0].size[2] == kRowLength &&
                      outputs[0].type() == CV_32F && outputs[0].isContinuous();
      if (!ok) {
        std::string got;
        for (const cv::Mat& m : outputs) {
          if (!got.empty()) got += " + ";
          got += ShapeString(m);
        }
        return Status::FailedPrecondition(
            "model '" + config_.model_path + "' is not a raw YOLOX COCO model: its output is " +
            got + ", expected [1," + std::to_string(rows) + "," + std::to_string(kRowLength) +
            "] for a " + std::to_string(input.width) + "x" + std::to_string(input.height) +
            " input");
      }
      return Status::Ok();
    }
    if (outputs.empty()) {
      return Status::FailedPrecondition("darknet model '" + config_.model_path + "' has no output");
    }
    for (const cv::Mat& m : outputs) {
      if (m.dims != 2 || m.cols != kRowLength || m.type() != CV_32F) {
        return Status::FailedPrecondition("darknet model '" + config_.model_path + "' outputs " +
                                          ShapeString(m) + ", expected YOLO rows of " +
                                          std::to_string(kRowLength) + " (a COCO-80 model)");
      }
    }
    return Status::Ok();
  }

  void Decode(const std::vector<cv::Mat>& outputs, cv::Size input,
              std::vector<Candidate>* candidates) const {
    // The lowest threshold any class has: ApplyBoxRules raises it per class afterwards.
    float threshold = config_.confidence_threshold;
    for (const auto& [name, value] : config_.class_confidence)
      threshold = std::min(threshold, value);
    if (is_yolox()) {
      DecodeYolox(outputs[0], input, dynamic_ids_, threshold, candidates);
    } else {
      DecodeDarknet(outputs, config_.input_size, dynamic_ids_, threshold, candidates);
    }
  }

  const DetectorConfig config_;
  const std::vector<int> dynamic_ids_;
  const std::vector<uchar> model_bytes_;  // the .onnx or .weights file, kept to build more Nets
  const std::vector<uchar> cfg_bytes_;    // darknet: the prepared .cfg
  const int silu_fused_;                  // YOLOX: SiLU pairs fused in model_bytes_
  const std::optional<FocusStem> stem_;   // YOLOX: the Focus stem cut from model_bytes_
  mutable NetPool pool_;
};

Result<std::vector<int>> ResolveDynamicClasses(const std::vector<std::string>& names) {
  if (names.empty()) return Status::InvalidArgument("dynamic_classes is empty");
  std::bitset<kCocoClassCount> seen;
  for (size_t i = 0; i < names.size(); ++i) {
    Result<int> id = CocoClassId(names[i]);
    if (!id.ok()) return id.status().WithContext("dynamic_classes[" + std::to_string(i) + "]");
    seen.set(size_t(*id));
  }
  std::vector<int> ids;
  for (int id = 0; id < kCocoClassCount; ++id) {
    if (seen.test(size_t(id))) ids.push_back(id);
  }
  return ids;
}

}  // namespace

// ---- Names ---------------------------------------------------------------------------------

const char* CocoClassName(int class_id) {
  if (class_id < 0 || class_id >= kCocoClassCount) return "unknown";
  return kCocoNames[size_t(class_id)];
}

Result<int> CocoClassId(const std::string& name) {
  const std::string key = NormaliseClassName(name);
  for (int id = 0; id < kCocoClassCount; ++id) {
    if (key == kCocoNames[size_t(id)]) return id;
  }
  for (const auto& [alias, id] : kDarknetAliases) {
    if (key == alias) return id;
  }
  return Status::InvalidArgument("unknown COCO class name '" + name +
                                 "' (expected a COCO-80 name such as person, car, truck)");
}

std::vector<std::string> DefaultDynamicClassNames() {
  return {"person", "bicycle", "car", "motorcycle", "bus", "truck"};
}

const char* DetectorBackendName(DetectorBackend backend) {
  switch (backend) {
    case DetectorBackend::kYoloxOnnx:
      return "yolox_onnx";
    case DetectorBackend::kDarknet:
      return "darknet";
  }
  return "unknown";
}

Result<DetectorBackend> ParseDetectorBackend(const std::string& name) {
  if (name == "yolox_onnx") return DetectorBackend::kYoloxOnnx;
  if (name == "darknet") return DetectorBackend::kDarknet;
  return Status::InvalidArgument("unknown detector backend '" + name +
                                 "' (expected yolox_onnx or darknet)");
}

const char* PreprocessingName(Preprocessing preprocessing) {
  switch (preprocessing) {
    case Preprocessing::kLetterbox:
      return "letterbox";
    case Preprocessing::kCentreCrop:
      return "centre_crop";
    case Preprocessing::kStretch:
      return "stretch";
  }
  return "unknown";
}

Result<Preprocessing> ParsePreprocessing(const std::string& name) {
  if (name == "letterbox") return Preprocessing::kLetterbox;
  if (name == "centre_crop" || name == "center_crop") return Preprocessing::kCentreCrop;
  if (name == "stretch") return Preprocessing::kStretch;
  return Status::InvalidArgument("unknown preprocessing '" + name +
                                 "' (expected letterbox, centre_crop or stretch)");
}

const char* BoxSourceName(BoxSource source) {
  switch (source) {
    case BoxSource::kAgent:
      return "agent";
    case BoxSource::kServer:
      return "server";
    case BoxSource::kBoth:
      return "both";
  }
  return "unknown";
}

Result<BoxSource> ParseBoxSource(const std::string& name) {
  if (name == "agent") return BoxSource::kAgent;
  if (name == "server") return BoxSource::kServer;
  if (name == "both") return BoxSource::kBoth;
  return Status::InvalidArgument("unknown box source '" + name +
                                 "' (expected agent, server or both)");
}

// ---- Configuration -------------------------------------------------------------------------

Status ValidateDetectorConfig(const DetectorConfig& config) {
  if (config.backend != DetectorBackend::kYoloxOnnx && config.backend != DetectorBackend::kDarknet)
    return Status::InvalidArgument("backend is not a known DetectorBackend");
  if (config.model_path.empty()) return Status::InvalidArgument("model_path is empty");
  if (config.backend == DetectorBackend::kDarknet && config.config_path.empty()) {
    return Status::InvalidArgument("config_path (the darknet .cfg) is empty");
  }
  if (config.input_size < 64 || config.input_size > 1280 || config.input_size % 32 != 0) {
    return Status::InvalidArgument("input_size = " + std::to_string(config.input_size) +
                                   " must be a multiple of 32 in [64, 1280]");
  }
  if (config.preprocessing != Preprocessing::kLetterbox &&
      config.preprocessing != Preprocessing::kCentreCrop &&
      config.preprocessing != Preprocessing::kStretch) {
    return Status::InvalidArgument("preprocessing is not a known Preprocessing");
  }
  // Written so that NaN fails too.
  if (!(config.confidence_threshold > 0 && config.confidence_threshold <= 1)) {
    return Status::InvalidArgument(
        "confidence_threshold = " + std::to_string(config.confidence_threshold) +
        " must be in (0, 1]");
  }
  if (!(config.nms_iou_threshold > 0 && config.nms_iou_threshold <= 1)) {
    return Status::InvalidArgument(
        "nms_iou_threshold = " + std::to_string(config.nms_iou_threshold) + " must be in (0, 1]");
  }
  if (config.opencv_threads < 0 || config.opencv_threads > 1024) {
    return Status::InvalidArgument("opencv_threads = " + std::to_string(config.opencv_threads) +
                                   " must be in [0, 1024]");
  }
  if (config.max_concurrent_calls < 0 || config.max_concurrent_calls > 1024) {
    return Status::InvalidArgument(
        "max_concurrent_calls = " + std::to_string(config.max_concurrent_calls) +
        " must be in [0, 1024]");
  }
  Result<std::vector<int>> ids = ResolveDynamicClasses(config.dynamic_classes);
  if (!ids.ok()) return ids.status();
  for (const auto& [name, value] : config.class_confidence) {
    const std::string field = "class_confidence." + name;
    Result<int> id = CocoClassId(name);
    if (!id.ok()) return id.status().WithContext(field);
    if (std::find(ids->begin(), ids->end(), *id) == ids->end()) {
      return Status::InvalidArgument(field + ": '" + name + "' is not one of dynamic_classes");
    }
    if (!(value > 0 && value <= 1)) {
      return Status::InvalidArgument(field + " = " + std::to_string(value) + " must be in (0, 1]");
    }
  }
  const std::pair<const char*, float> shares[] = {
      {"min_box_area", config.min_box_area},
      {"large_box_area", config.large_box_area},
      {"large_box_confidence", config.large_box_confidence}};
  for (const auto& [field, value] : shares) {
    if (!(value >= 0 && value <= 1)) {
      return Status::InvalidArgument(std::string(field) + " = " + std::to_string(value) +
                                     " must be in [0, 1]");
    }
  }
  if (config.min_box_area >= config.large_box_area && config.large_box_confidence > 0) {
    return Status::InvalidArgument(
        "min_box_area = " + std::to_string(config.min_box_area) +
        " must be below large_box_area = " + std::to_string(config.large_box_area));
  }
  return Status::Ok();
}

std::vector<DynamicBox> ApplyBoxRules(std::vector<DynamicBox> boxes, const DetectorConfig& config,
                                      cv::Size image_size) {
  std::array<float, kCocoClassCount> needed;
  needed.fill(config.confidence_threshold);
  for (const auto& [name, value] : config.class_confidence) {
    if (Result<int> id = CocoClassId(name); id.ok()) needed[size_t(*id)] = value;
  }
  const double frame_area = double(image_size.width) * image_size.height;
  std::vector<DynamicBox> kept;
  kept.reserve(boxes.size());
  for (DynamicBox& box : boxes) {
    const bool known = box.class_id >= 0 && box.class_id < kCocoClassCount;
    if (known && box.confidence < needed[size_t(box.class_id)]) continue;
    const double share = frame_area > 0 ? box.rect.area() / frame_area : 0;
    if (share < config.min_box_area) continue;
    if (share > config.large_box_area && box.confidence < config.large_box_confidence) continue;
    kept.push_back(std::move(box));
  }
  return kept;
}

DetectorConfig YoloxNanoConfig(const std::string& models_dir) {
  DetectorConfig config;
  config.backend = DetectorBackend::kYoloxOnnx;
  config.model_path = models_dir + "/yolox_nano.onnx";
  return config;
}

DetectorConfig YoloFastestConfig(const std::string& models_dir) {
  DetectorConfig config;
  config.backend = DetectorBackend::kDarknet;
  config.model_path = models_dir + "/yolo-fastest-1.1-xl.weights";
  config.config_path = models_dir + "/yolo-fastest-1.1-xl.cfg";
  return config;
}

Result<std::unique_ptr<Detector>> CreateDetector(const DetectorConfig& config) {
  PLACEDB_RETURN_IF_ERROR(ValidateDetectorConfig(config));
  Result<std::vector<int>> ids = ResolveDynamicClasses(config.dynamic_classes);
  if (!ids.ok()) return ids.status();

  Result<std::vector<uchar>> model = ReadModelFile(config.model_path, "model_path");
  if (!model.ok()) return model.status();
  std::vector<uchar> cfg;
  if (config.backend == DetectorBackend::kDarknet) {
    Result<std::vector<uchar>> raw_cfg = ReadModelFile(config.config_path, "config_path");
    if (!raw_cfg.ok()) return raw_cfg.status();
    Result<std::vector<uchar>> prepared = PrepareDarknetCfg(*raw_cfg, config.config_path);
    if (!prepared.ok()) return prepared.status();
    cfg = std::move(*prepared);
  }

  if (config.opencv_threads > 0) cv::setNumThreads(config.opencv_threads);
  int capacity = config.max_concurrent_calls;
  if (capacity == 0) capacity = int(std::max(1u, std::thread::hardware_concurrency()));

  int silu_fused = 0;
  std::optional<FocusStem> stem;
  if (config.backend == DetectorBackend::kYoloxOnnx && config.rewrite_graph) {
    RegisterSiluLayer();
    *model = FuseSiluNodes(*model, &silu_fused);
    FocusStem found;
    bool cut = false;
    *model = CutFocusStem(*model, &found, &cut);
    if (cut) stem = found;
  }
  auto detector = std::make_unique<DnnDetector>(config, std::move(*ids), std::move(*model),
                                                std::move(cfg), capacity, silu_fused, stem);
  try {
    PLACEDB_RETURN_IF_ERROR(detector->Initialise());
  } catch (const std::exception& e) {  // e.g. bad_alloc from a hostile file: never escapes
    return Status::FailedPrecondition("loading model '" + config.model_path + "': " + e.what());
  }
  return std::unique_ptr<Detector>(std::move(detector));
}

// ---- Box utilities -------------------------------------------------------------------------

float BoxIoU(const cv::Rect2f& a, const cv::Rect2f& b) {
  if (a.width <= 0 || a.height <= 0 || b.width <= 0 || b.height <= 0) return 0;
  const float ix = std::min(a.x + a.width, b.x + b.width) - std::max(a.x, b.x);
  const float iy = std::min(a.y + a.height, b.y + b.height) - std::max(a.y, b.y);
  if (ix <= 0 || iy <= 0) return 0;
  const float intersection = ix * iy;
  return intersection / (a.area() + b.area() - intersection);
}

std::vector<DynamicBox> SuppressNonMaxima(std::vector<DynamicBox> boxes, float iou_threshold) {
  std::vector<size_t> order(boxes.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return boxes[a].confidence > boxes[b].confidence; });
  std::vector<DynamicBox> kept;
  for (size_t index : order) {
    const DynamicBox& box = boxes[index];
    const bool suppressed = std::any_of(kept.begin(), kept.end(), [&](const DynamicBox& k) {
      return k.class_id == box.class_id && BoxIoU(k.rect, box.rect) > iou_threshold;
    });
    if (!suppressed) kept.push_back(box);
  }
  return kept;
}

std::vector<DynamicBox> MergeBoxes(const std::vector<DynamicBox>& agent_boxes,
                                   const std::vector<DynamicBox>& server_boxes,
                                   float iou_threshold) {
  std::vector<DynamicBox> merged = agent_boxes;
  for (const DynamicBox& server : server_boxes) {
    int best = -1;
    float best_iou = iou_threshold;
    for (size_t i = 0; i < agent_boxes.size(); ++i) {
      if (agent_boxes[i].class_id != server.class_id) continue;
      const float iou = BoxIoU(agent_boxes[i].rect, server.rect);
      if (iou > best_iou) {
        best_iou = iou;
        best = int(i);
      }
    }
    if (best < 0) {
      merged.push_back(server);
    } else if (server.confidence > merged[size_t(best)].confidence) {
      merged[size_t(best)] = server;
    }
  }
  return merged;
}

}  // namespace placedb
