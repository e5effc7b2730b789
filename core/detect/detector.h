// Dynamic-object detection (Munoz & Dexter, section V-A): a COCO-trained single-shot detector run
// on every frame, keeping only the dynamic classes (by default person, bicycle, car, motorcycle,
// bus, truck) above a confidence threshold. Its boxes feed the DC/SC split of dynamic_filter.h.
//
// Two backends, both through OpenCV DNN on the CPU:
//  - kYoloxOnnx: YOLOX-Nano exported to ONNX. Input BGR 0..255, letterboxed top-left with pad
//    114; output [1, N, 85] raw grid predictions decoded here (strides 8, 16, 32).
//  - kDarknet: Yolo-Fastest 1.1 XL (.cfg + .weights). Input RGB scaled to 0..1; OpenCV's YOLO
//    layers emit rows [cx, cy, w, h, objectness, 80 x (objectness * class probability)]
//    normalised to the network input.
//
// Preprocessing maps the frame onto the square network input and every box back to full-image
// pixels:
//  - kLetterbox: scale to fit, top-left, pad the rest (nothing is lost);
//  - kCentreCrop: the paper's choice, "cropped equal amounts from each side" to a square, then
//    resized: objects outside the central square are simply not seen;
//  - kStretch: resize without keeping the aspect ratio (how darknet models are usually trained).
//
// Threading: a Detector is safe to call from any number of threads. cv::dnn::Net is not, so each
// call borrows a Net from a small pool (grown lazily up to max_concurrent_calls, then callers
// wait); every Net is built from the model bytes read once at creation. See docs/detector.md.
#pragma once

#include <map>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "core/base/status.h"
#include "core/detect/dynamic_objects.h"

namespace placedb {

// ---- COCO-80 class names -------------------------------------------------------------------

inline constexpr int kCocoClassCount = 80;

// The official COCO-2017 name of a contiguous class id in [0, 80) ("person", "motorcycle",
// "traffic light", ...), or "unknown" outside that range.
const char* CocoClassName(int class_id);
// Id of a COCO class name: case-insensitive; also accepts darknet's coco.names spellings
// ("motorbike", "aeroplane", "sofa", "tvmonitor", ...). Unknown -> INVALID_ARGUMENT naming it.
Result<int> CocoClassId(const std::string& name);
// The paper's dynamic classes: person, bicycle, car, motorcycle, bus, truck.
std::vector<std::string> DefaultDynamicClassNames();

// ---- Configuration -------------------------------------------------------------------------

enum class DetectorBackend { kYoloxOnnx, kDarknet };
const char* DetectorBackendName(DetectorBackend backend);
// Parses "yolox_onnx" or "darknet".
Result<DetectorBackend> ParseDetectorBackend(const std::string& name);

enum class Preprocessing { kLetterbox, kCentreCrop, kStretch };
const char* PreprocessingName(Preprocessing preprocessing);
// Parses "letterbox", "centre_crop" (or "center_crop"), "stretch".
Result<Preprocessing> ParsePreprocessing(const std::string& name);

// Where a frame's boxes come from: the agent sends them, the server detects them, or both
// (merged with MergeBoxes).
enum class BoxSource { kAgent, kServer, kBoth };
const char* BoxSourceName(BoxSource source);
// Parses "agent", "server", "both".
Result<BoxSource> ParseBoxSource(const std::string& name);

struct DetectorConfig {
  DetectorBackend backend = DetectorBackend::kYoloxOnnx;
  std::string model_path;   // YOLOX: the .onnx file; darknet: the .weights file
  std::string config_path;  // darknet: the .cfg file; unused by YOLOX
  // Side of the square network input, a multiple of 32 in [64, 1280]. The paper uses 416.
  int input_size = 416;
  Preprocessing preprocessing = Preprocessing::kLetterbox;
  // YOLOX with kLetterbox only: the network input is input_size on the frame's long side and the
  // short side's scaled length rounded up to a multiple of 32 (416x320 for a 4:3 frame at 416),
  // instead of input_size x input_size. The frame's pixels in the input are the same, only padding
  // is left out, and YOLOX-Nano's cost is proportional to the input's area (23 % less for 4:3).
  // false: the square input (the paper's shape). darknet always uses the square.
  bool rectangular_letterbox = true;
  // YOLOX: the ONNX graph rewritten for OpenCV 4.6 (onnx_graph.h): each SiLU (Sigmoid + Mul)
  // one activation fused into its convolution, and the Focus stem's slices done while making the
  // input blob. Same outputs within float rounding, about a third less time per frame.
  // false: the model's graph as exported. Ignored by darknet.
  bool rewrite_graph = true;
  // Scores below this are dropped; the paper evaluates 0.1 to 0.4 and reports 0.2. In (0, 1].
  float confidence_threshold = 0.2f;
  // Class-aware non-maximum suppression: a box is dropped when it overlaps a better box of the
  // same class with IoU above this. In (0, 1].
  float nms_iou_threshold = 0.45f;
  // Per-class score thresholds (ApplyBoxRules): COCO name (one of dynamic_classes) -> the score
  // that class needs instead of confidence_threshold, in (0, 1]. A class the scene makes
  // unlikely (a bus indoors) can need more than a person. Empty = confidence_threshold for all.
  std::map<std::string, float> class_confidence;
  // Box plausibility (ApplyBoxRules), as shares of the frame's area, in [0, 1]. A box smaller
  // than min_box_area is dropped (0 = off). A box larger than large_box_area must score at least
  // large_box_confidence (0 = off): a real object that close is seen whole and scored high, while
  // a low score on a third of the frame (YOLOX-Nano's "bus 0.23" on a corridor's poster wall, 39 %
  // of RTAB-Map loop frame 32) would drop the keypoints of much of a static place. On by default:
  // of the cached YOLOX-Nano boxes at 0.2 and above, it drops that one box of the RTAB-Map loop's
  // 5 and none of CamVid's 5,302 (none covers 30 %), and no recognition figure changes
  // (docs/detector.md, "Box plausibility").
  float min_box_area = 0.0f;
  float large_box_area = 0.3f;
  float large_box_confidence = 0.5f;
  // COCO names (see CocoClassId) of the classes reported; all others are ignored. Not empty.
  std::vector<std::string> dynamic_classes = DefaultDynamicClassNames();
  // > 0: cv::setNumThreads(opencv_threads) when the detector is created. This setting is
  // process-wide. With a frame-level pool of N workers, 1 gives the best throughput; for a
  // single stream, the core count (2 here). 0 leaves OpenCV's setting alone.
  int opencv_threads = 0;
  // Most Detect() calls that run at once (one cv::dnn::Net each, a few MB apiece); further
  // callers wait. 0 = std::thread::hardware_concurrency().
  int max_concurrent_calls = 0;
};

// Checks the values only (not the files): INVALID_ARGUMENT naming the first bad field.
Status ValidateDetectorConfig(const DetectorConfig& config);

// The conventional file names inside a models directory (as tools/install_models.sh installs
// them), with every other field at its default.
DetectorConfig YoloxNanoConfig(const std::string& models_dir);    // yolox_nano.onnx
DetectorConfig YoloFastestConfig(const std::string& models_dir);  // yolo-fastest-1.1-xl.*

// ---- Detector ------------------------------------------------------------------------------

class Detector {
 public:
  virtual ~Detector() = default;

  // Dynamic objects of one frame (8-bit BGR; grayscale and BGRA are converted), in full-image
  // pixels clipped to the image, sorted by decreasing confidence. An empty or non-8-bit image is
  // INVALID_ARGUMENT. Thread-safe.
  virtual Result<std::vector<DynamicBox>> Detect(const cv::Mat& bgr_image) const = 0;

  // "yolox_nano.onnx", "yolo-fastest-1.1-xl.weights": the model file's name.
  virtual std::string model_name() const = 0;
  // One line: backend, model, input size, preprocessing, thresholds, classes.
  virtual std::string Describe() const = 0;
  virtual int input_size() const = 0;
  virtual const DetectorConfig& config() const = 0;
};

// Validates `config`, reads the model file(s), builds the network and runs it once on a blank
// input to check its output layout. Errors: INVALID_ARGUMENT for bad values or an unknown class
// name; NOT_FOUND for a missing file; IO_ERROR for an unreadable one; FAILED_PRECONDITION for a
// file that is not a loadable model of the backend, or whose output is not the expected layout
// (YOLOX [1, sum (input/stride)^2, 85]; darknet YOLO rows of 85).
Result<std::unique_ptr<Detector>> CreateDetector(const DetectorConfig& config);

// ---- Box utilities -------------------------------------------------------------------------

// The per-class thresholds and plausibility rules of `config` (class_confidence, min_box_area,
// large_box_area / large_box_confidence) on the boxes of a frame of `image_size`, order kept.
// Detect() applies them after non-maximum suppression; tools holding boxes detected with the
// rules off (a detection cache) apply them the same way. `config` must be valid.
std::vector<DynamicBox> ApplyBoxRules(std::vector<DynamicBox> boxes, const DetectorConfig& config,
                                      cv::Size image_size);

// Intersection over union of two rectangles; 0 when either is empty.
float BoxIoU(const cv::Rect2f& a, const cv::Rect2f& b);

// Class-aware greedy non-maximum suppression: within each class, boxes in decreasing confidence
// order (ties: input order) are kept unless they overlap a kept box with IoU > iou_threshold.
// Returns the kept boxes sorted by decreasing confidence.
std::vector<DynamicBox> SuppressNonMaxima(std::vector<DynamicBox> boxes, float iou_threshold);

// The "both" policy: the union of the agent's and the server's boxes without duplicates. A server
// box duplicates the agent box of the same class it overlaps most, when that IoU exceeds
// iou_threshold; it is then dropped, and takes the agent box's place if it is more confident (the
// agent's box wins ties). Other server boxes are appended in their order.
std::vector<DynamicBox> MergeBoxes(const std::vector<DynamicBox>& agent_boxes,
                                   const std::vector<DynamicBox>& server_boxes,
                                   float iou_threshold);

}  // namespace placedb
