#include "core/detect/onnx_silu.h"

#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <mutex>
#include <opencv2/dnn.hpp>
#include <opencv2/dnn/all_layers.hpp>
#include <string>
#include <string_view>

namespace placedb {

namespace {

// ---- Protobuf wire format, just enough to edit an ONNX graph's nodes ------------------------
//
// ModelProto.graph = 7; GraphProto.node = 1, GraphProto.output = 12 (ValueInfoProto.name = 1);
// NodeProto.input = 1, .output = 2, .name = 3, .op_type = 4 (onnx.proto). Every other field is
// copied through byte for byte.

constexpr uint32_t kModelGraph = 7;
constexpr uint32_t kGraphNode = 1;
constexpr uint32_t kGraphOutput = 12;
constexpr uint32_t kValueInfoName = 1;
constexpr uint32_t kNodeInput = 1;
constexpr uint32_t kNodeOutput = 2;
constexpr uint32_t kNodeName = 3;
constexpr uint32_t kNodeOpType = 4;
constexpr int kWireLengthDelimited = 2;

struct Field {
  uint32_t number = 0;
  int wire = 0;
  const unsigned char* begin = nullptr;  // the tag's first byte
  const unsigned char* end = nullptr;    // one past the value
  std::string_view payload;              // length-delimited fields: the bytes
};

bool ReadVarint(const unsigned char*& p, const unsigned char* end, uint64_t* value) {
  *value = 0;
  for (int shift = 0; shift < 64 && p < end; shift += 7) {
    const unsigned char byte = *p++;
    *value |= uint64_t(byte & 0x7f) << shift;
    if (!(byte & 0x80)) return true;
  }
  return false;
}

// The fields of one message, in order; false when the bytes are not the wire format.
bool ParseFields(std::string_view bytes, std::vector<Field>* fields) {
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data());
  const auto* end = p + bytes.size();
  while (p < end) {
    Field f;
    f.begin = p;
    uint64_t tag = 0, value = 0;
    if (!ReadVarint(p, end, &tag) || (tag >> 3) == 0 || (tag >> 3) > UINT32_MAX) return false;
    f.number = uint32_t(tag >> 3);
    f.wire = int(tag & 7);
    switch (f.wire) {
      case 0:
        if (!ReadVarint(p, end, &value)) return false;
        break;
      case 1:
        if (end - p < 8) return false;
        p += 8;
        break;
      case 5:
        if (end - p < 4) return false;
        p += 4;
        break;
      case kWireLengthDelimited:
        if (!ReadVarint(p, end, &value) || value > uint64_t(end - p)) return false;
        f.payload = std::string_view(reinterpret_cast<const char*>(p), size_t(value));
        p += value;
        break;
      default:  // groups (3, 4) do not occur in ONNX
        return false;
    }
    f.end = p;
    fields->push_back(f);
  }
  return true;
}

void PutVarint(std::vector<unsigned char>* out, uint64_t value) {
  while (value >= 0x80) {
    out->push_back(static_cast<unsigned char>(value | 0x80));
    value >>= 7;
  }
  out->push_back(static_cast<unsigned char>(value));
}

void PutBytes(std::vector<unsigned char>* out, uint32_t number, std::string_view bytes) {
  PutVarint(out, (uint64_t(number) << 3) | kWireLengthDelimited);
  PutVarint(out, bytes.size());
  out->insert(out->end(), bytes.begin(), bytes.end());
}

void PutField(std::vector<unsigned char>* out, const Field& field) {
  out->insert(out->end(), field.begin, field.end);
}

struct Node {
  std::vector<std::string_view> inputs, outputs;
  std::string_view name, op_type;
};

bool ParseNode(std::string_view bytes, Node* node) {
  std::vector<Field> fields;
  if (!ParseFields(bytes, &fields)) return false;
  for (const Field& f : fields) {
    if (f.wire != kWireLengthDelimited) continue;
    if (f.number == kNodeInput) node->inputs.push_back(f.payload);
    if (f.number == kNodeOutput) node->outputs.push_back(f.payload);
    if (f.number == kNodeName) node->name = f.payload;
    if (f.number == kNodeOpType) node->op_type = f.payload;
  }
  return true;
}

// The graph's bytes with the pairs fused; false (and *fused untouched) when it does not parse.
bool FuseGraph(std::string_view graph, std::vector<unsigned char>* out, int* fused) {
  std::vector<Field> fields;
  if (!ParseFields(graph, &fields)) return false;
  std::vector<Node> nodes;
  std::map<std::string_view, int> uses;      // tensor -> consumers (graph outputs count too)
  std::map<std::string_view, int> producer;  // tensor -> index in `nodes`
  for (const Field& f : fields) {
    if (f.wire != kWireLengthDelimited) continue;
    if (f.number == kGraphOutput) {
      std::vector<Field> info;
      if (!ParseFields(f.payload, &info)) return false;
      for (const Field& i : info) {
        if (i.number == kValueInfoName && i.wire == kWireLengthDelimited) ++uses[i.payload];
      }
    } else if (f.number == kGraphNode) {
      Node node;
      if (!ParseNode(f.payload, &node)) return false;
      for (std::string_view input : node.inputs) ++uses[input];
      for (std::string_view output : node.outputs) producer[output] = int(nodes.size());
      nodes.push_back(node);
    }
  }

  enum class Action { kKeep, kDrop, kSilu };
  std::vector<Action> actions(nodes.size(), Action::kKeep);
  std::vector<std::string_view> silu_input(nodes.size());
  for (size_t m = 0; m < nodes.size(); ++m) {
    const Node& mul = nodes[m];
    if (mul.op_type != "Mul" || mul.inputs.size() != 2 || mul.outputs.size() != 1) continue;
    for (int k = 0; k < 2; ++k) {
      const auto it = producer.find(mul.inputs[size_t(k)]);
      if (it == producer.end() || size_t(it->second) >= m) continue;
      const Node& sigmoid = nodes[size_t(it->second)];
      if (sigmoid.op_type == "Sigmoid" && sigmoid.inputs.size() == 1 &&
          sigmoid.outputs.size() == 1 && sigmoid.inputs[0] == mul.inputs[size_t(1 - k)] &&
          uses[sigmoid.outputs[0]] == 1 && actions[size_t(it->second)] == Action::kKeep) {
        actions[size_t(it->second)] = Action::kDrop;
        actions[m] = Action::kSilu;
        silu_input[m] = sigmoid.inputs[0];
        break;
      }
    }
  }

  size_t index = 0;
  int count = 0;
  for (const Field& f : fields) {
    if (f.number != kGraphNode || f.wire != kWireLengthDelimited) {
      PutField(out, f);
      continue;
    }
    const size_t i = index++;
    if (actions[i] == Action::kKeep) {
      PutField(out, f);
    } else if (actions[i] == Action::kSilu) {
      std::vector<unsigned char> node;
      PutBytes(&node, kNodeInput, silu_input[i]);
      PutBytes(&node, kNodeOutput, nodes[i].outputs[0]);
      PutBytes(&node, kNodeName, nodes[i].name);
      PutBytes(&node, kNodeOpType, kSiluLayerType);
      PutBytes(out, kGraphNode,
               std::string_view(reinterpret_cast<const char*>(node.data()), node.size()));
      ++count;
    }
  }
  *fused = count;
  return true;
}

// ---- The layer ------------------------------------------------------------------------------

// An ActivationLayer, so that OpenCV fuses it into the convolution before it (which then calls
// forwardSlice on each block of output channels it has just computed).
class SiluLayer final : public cv::dnn::ActivationLayer {
 public:
  explicit SiluLayer(const cv::dnn::LayerParams& params) { setParamsFrom(params); }

  static cv::Ptr<cv::dnn::Layer> Create(cv::dnn::LayerParams& params) {
    return cv::makePtr<SiluLayer>(params);
  }

  bool getMemoryShapes(const std::vector<cv::dnn::MatShape>& inputs, int /*required_outputs*/,
                       std::vector<cv::dnn::MatShape>& outputs,
                       std::vector<cv::dnn::MatShape>& /*internals*/) const override {
    outputs = inputs;
    return true;  // may run in place
  }

  void forward(cv::InputArrayOfArrays inputs_array, cv::OutputArrayOfArrays outputs_array,
               cv::OutputArrayOfArrays /*internals*/) override {
    std::vector<cv::Mat> inputs, outputs;
    inputs_array.getMatVector(inputs);
    outputs_array.getMatVector(outputs);
    for (size_t i = 0; i < inputs.size() && i < outputs.size(); ++i) {
      CV_Assert(inputs[i].type() == CV_32F && inputs[i].isContinuous() &&
                outputs[i].isContinuous() && inputs[i].total() == outputs[i].total());
      Silu(inputs[i].ptr<float>(), outputs[i].ptr<float>(), inputs[i].total());
    }
  }

  void forwardSlice(const float* src, float* dst, int len, size_t plane_size, int first_channel,
                    int end_channel) const override {
    for (int c = first_channel; c < end_channel; ++c, src += plane_size, dst += plane_size) {
      Silu(src, dst, size_t(len));
    }
  }
};

// ---- The kernel -----------------------------------------------------------------------------

using Float8 = float __attribute__((vector_size(32)));
using Int8 = int32_t __attribute__((vector_size(32)));

// exp(-x) by Cephes' expf: -x = k ln 2 + r with |r| <= ln 2 / 2, e^r by a degree-6 polynomial,
// 2^k by building the float's exponent; -x is clamped to +-87 so 2^k stays a normal float. Plain
// vector arithmetic, so each clone below compiles to that target's instructions.
__attribute__((target_clones("avx2", "default"))) void SiluKernel(const float* src, float* dst,
                                                                  size_t count) {
  size_t i = 0;
  for (; i + 8 <= count; i += 8) {
    Float8 x;
    std::memcpy(&x, src + i, sizeof x);
    Float8 t = -x;
    t = t < -87.0f ? Float8{} - 87.0f : t;
    t = t > 87.0f ? Float8{} + 87.0f : t;
    const Float8 fx = t * 1.44269504088896341f + 0.5f;
    Int8 k = __builtin_convertvector(fx, Int8);  // truncates: floor below
    k = __builtin_convertvector(k, Float8) > fx ? k - 1 : k;
    const Float8 kf = __builtin_convertvector(k, Float8);
    const Float8 r = t - kf * 0.693359375f + kf * 2.12194440e-4f;
    Float8 y = 1.9875691500e-4f * r + 1.3981999507e-3f;
    y = y * r + 8.3334519073e-3f;
    y = y * r + 4.1665795894e-2f;
    y = y * r + 1.6666665459e-1f;
    y = y * r + 5.0000001201e-1f;
    y = y * (r * r) + r + 1.0f;
    const Int8 exponent = (k + 127) << 23;
    Float8 two_k;
    std::memcpy(&two_k, &exponent, sizeof two_k);
    const Float8 result = x / (1.0f + y * two_k);
    std::memcpy(dst + i, &result, sizeof result);
  }
  for (; i < count; ++i) dst[i] = src[i] / (1.0f + std::exp(-src[i]));
}

}  // namespace

std::vector<unsigned char> FuseSiluNodes(const std::vector<unsigned char>& model, int* fused) {
  *fused = 0;
  std::vector<Field> fields;
  const std::string_view bytes(reinterpret_cast<const char*>(model.data()), model.size());
  if (!ParseFields(bytes, &fields)) return model;
  std::vector<unsigned char> out;
  out.reserve(model.size());
  int count = 0;
  for (const Field& f : fields) {
    if (f.number != kModelGraph || f.wire != kWireLengthDelimited) {
      PutField(&out, f);
      continue;
    }
    std::vector<unsigned char> graph;
    int graph_fused = 0;
    if (!FuseGraph(f.payload, &graph, &graph_fused)) return model;
    PutBytes(&out, kModelGraph,
             std::string_view(reinterpret_cast<const char*>(graph.data()), graph.size()));
    count += graph_fused;
  }
  if (count == 0) return model;
  *fused = count;
  return out;
}

void RegisterSiluLayer() {
  static std::once_flag once;
  std::call_once(once,
                 [] { cv::dnn::LayerFactory::registerLayer(kSiluLayerType, SiluLayer::Create); });
}

void Silu(const float* src, float* dst, size_t count) {
  SiluKernel(src, dst, count);
}

}  // namespace placedb
