// SiLU (x * sigmoid(x)) as one OpenCV DNN activation layer, for ONNX models that spell it as two
// nodes (YOLOX: y = Sigmoid(x); z = Mul(x, y) after every convolution).
//
// Why: OpenCV 4.6 imports that pair as a Sigmoid layer (scalar exp) and an element-wise Mul, and
// since the convolution's output then feeds two layers it cannot fuse either into the
// convolution. On YOLOX-Nano at 416 the pair costs 14.5 of 36 ms per frame (Net::getPerfProfile,
// docs/detector.md "Profile"). FuseSiluNodes rewrites the model's bytes so that each pair becomes
// one node of type kSiluLayerType; RegisterSiluLayer gives OpenCV a layer for that type, which
// OpenCV fuses into the preceding convolution (applied to each output slice while it is still in
// cache), computed with a vectorised exp (AVX2 when the CPU has it).
//
// Threading: FuseSiluNodes and SiluInPlace are pure; RegisterSiluLayer may be called from any
// thread, any number of times (it registers once).
#pragma once

#include <cstddef>
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

}  // namespace placedb
