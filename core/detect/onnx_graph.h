// Rewrites of an ONNX model's graph (its bytes, protobuf wire format, no ONNX library) that make
// OpenCV 4.6's DNN module run YOLOX faster while computing the same function.
//
// 1. SiLU (x * sigmoid(x)) as one OpenCV DNN activation layer, for ONNX models that spell it as
// two nodes (YOLOX: y = Sigmoid(x); z = Mul(x, y) after every convolution).
//
// Why: OpenCV 4.6 imports that pair as a Sigmoid layer (scalar exp) and an element-wise Mul, and
// since the convolution's output then feeds two layers it cannot fuse either into the
// convolution. On YOLOX-Nano at 416 the pair costs 14.5 of 36 ms per frame (Net::getPerfProfile,
// docs/detector.md "Profile"). FuseSiluNodes rewrites the model's bytes so that each pair becomes
// one node of type kSiluLayerType; RegisterSiluLayer gives OpenCV a layer for that type, which
// OpenCV fuses into the preceding convolution (applied to each output slice while it is still in
// cache), computed with a vectorised exp (AVX2 when the CPU has it).
//
// 2. YOLOX's Focus stem: the input image is split into its four pixel phases (even/odd rows x
// even/odd columns) by six strided Slice nodes and a Concat, 12 channels at half resolution, which
// OpenCV does slowly (2.7 of 23 ms at 416x320). CutFocusStem removes them so that the network
// takes that 12-channel tensor as its input, and SpaceToDepthBlob builds it straight from the
// 8-bit letterboxed image in one pass (instead of cv::dnn::blobFromImage, then the slices).
//
// Threading: every function here is pure, except RegisterSiluLayer, which may be called from any
// thread, any number of times (it registers once).
#pragma once

#include <array>
#include <cstddef>
#include <opencv2/core.hpp>
#include <vector>

namespace placedb {

// The layer type the fused nodes get (unique to placedb, so no OpenCV layer is replaced).
inline constexpr const char* kSiluLayerType = "PlacedbSiLU";

// `model`: the bytes of an ONNX ModelProto. Returns them with every pair `s = Sigmoid(x);
// m = Mul(x, s)` (either input order) whose `s` feeds nothing else and is no graph output
// replaced by one node `m = PlacedbSiLU(x)` (the Mul's name and output kept, at the Mul's place;
// the Sigmoid node removed), and sets *fused to the number of pairs replaced. Bytes that do not
// parse as the protobuf wire format, or a model without such pairs, come back unchanged with
// *fused = 0: loading them then fails or succeeds exactly as before.
std::vector<unsigned char> FuseSiluNodes(const std::vector<unsigned char>& model, int* fused);

// Registers kSiluLayerType with cv::dnn::LayerFactory (process-wide, once). Call before loading
// a model that FuseSiluNodes changed.
void RegisterSiluLayer();

// dst[i] = src[i] / (1 + exp(-src[i])) for i < count; src == dst is allowed. Relative error
// below 1e-6 against the formula in double precision for x >= -87; below, x / (1 + e^87) (about
// x * 1.6e-38: zero in practice). NaN stays NaN.
void Silu(const float* src, float* dst, size_t count);

// The pixel phase of each group of 3 channels of the Focus stem's output, in its channel order:
// group g holds the pixels (2y + row[g], 2x + col[g]) of the input image.
struct FocusStem {
  std::array<int, 4> row{}, col{};
};

// `model`: the bytes of an ONNX ModelProto. When its first graph input X feeds exactly YOLOX's
// Focus stem (two Slices of X along axis 2 with step 2 and starts 0 and 1, each sliced again along
// axis 3 with step 2 and starts 0 and 1, the four results concatenated along axis 1, the
// intermediate tensors used by nothing else), returns the model with those seven nodes replaced
// by `Concat's output = Identity(X)`, so X must then be the 12-channel stem output, and sets
// *stem and *cut = true. Otherwise returns the bytes unchanged and *cut = false.
std::vector<unsigned char> CutFocusStem(const std::vector<unsigned char>& model, FocusStem* stem,
                                        bool* cut);

// The input blob of a stem-cut network for `image` (8-bit, 3 channels, even width and height):
// 1 x 12 x rows/2 x cols/2, CV_32F, channel 3g + c = image channel c at the phase of group g,
// values as they are (0..255). Equal to what the stem computed from blobFromImage(image).
cv::Mat SpaceToDepthBlob(const cv::Mat& image, const FocusStem& stem);

}  // namespace placedb
