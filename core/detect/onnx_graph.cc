#include "core/detect/onnx_graph.h"

#include <algorithm>
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
constexpr uint32_t kGraphInitializer = 5;
constexpr uint32_t kGraphInput = 11;
constexpr uint32_t kGraphOutput = 12;
constexpr uint32_t kValueInfoName = 1;
constexpr uint32_t kNodeInput = 1;
constexpr uint32_t kNodeOutput = 2;
constexpr uint32_t kNodeName = 3;
constexpr uint32_t kNodeOpType = 4;
constexpr uint32_t kNodeAttribute = 5;
constexpr uint32_t kAttributeName = 1;
constexpr uint32_t kAttributeInt = 3;
constexpr uint32_t kAttributeTensor = 5;
constexpr uint32_t kTensorDataType = 2;
constexpr uint32_t kTensorInt64Data = 7;
constexpr uint32_t kTensorName = 8;
constexpr uint32_t kTensorRawData = 9;
constexpr uint64_t kTensorInt64 = 7;  // TensorProto.DataType.INT64
constexpr int kWireLengthDelimited = 2;

struct Field {
  uint32_t number = 0;
  int wire = 0;
  const unsigned char* begin = nullptr;  // the tag's first byte
  const unsigned char* end = nullptr;    // one past the value
  std::string_view payload;              // length-delimited fields: the bytes
  uint64_t varint = 0;                   // varint fields: the value
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
        f.varint = value;
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
  std::vector<std::string_view> attributes;  // AttributeProto bytes
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
    if (f.number == kNodeAttribute) node->attributes.push_back(f.payload);
  }
  return true;
}

// The first value of an INT64 TensorProto (raw_data or int64_data); false when it has none.
bool TensorFirstInt64(std::string_view tensor, int64_t* value) {
  std::vector<Field> fields;
  if (!ParseFields(tensor, &fields)) return false;
  bool is_int64 = false;
  for (const Field& f : fields) {
    if (f.number == kTensorDataType && f.wire == 0) is_int64 = f.varint == kTensorInt64;
  }
  if (!is_int64) return false;
  for (const Field& f : fields) {
    if (f.number == kTensorRawData && f.wire == kWireLengthDelimited && f.payload.size() >= 8) {
      uint64_t bits = 0;
      for (int i = 7; i >= 0; --i) bits = (bits << 8) | static_cast<unsigned char>(f.payload[i]);
      *value = static_cast<int64_t>(bits);
      return true;
    }
    if (f.number == kTensorInt64Data && f.wire == 0) {
      *value = static_cast<int64_t>(f.varint);
      return true;
    }
    if (f.number == kTensorInt64Data && f.wire == kWireLengthDelimited) {  // packed varints
      const auto* q = reinterpret_cast<const unsigned char*>(f.payload.data());
      uint64_t bits = 0;
      if (!ReadVarint(q, q + f.payload.size(), &bits)) return false;
      *value = static_cast<int64_t>(bits);
      return true;
    }
  }
  return false;
}

// An integer attribute of a node; false when it has no such attribute.
bool IntAttribute(const Node& node, std::string_view name, int64_t* value) {
  for (std::string_view attribute : node.attributes) {
    std::vector<Field> fields;
    if (!ParseFields(attribute, &fields)) return false;
    bool named = false;
    for (const Field& f : fields) {
      if (f.number == kAttributeName && f.wire == kWireLengthDelimited) named = f.payload == name;
    }
    if (!named) continue;
    for (const Field& f : fields) {
      if (f.number == kAttributeInt && f.wire == 0) {
        *value = static_cast<int64_t>(f.varint);
        return true;
      }
    }
  }
  return false;
}

// The `value` tensor of a Constant node.
std::string_view ConstantTensor(const Node& node) {
  for (std::string_view attribute : node.attributes) {
    std::vector<Field> fields;
    if (!ParseFields(attribute, &fields)) return {};
    bool named = false;
    std::string_view tensor;
    for (const Field& f : fields) {
      if (f.number == kAttributeName && f.wire == kWireLengthDelimited)
        named = f.payload == "value";
      if (f.number == kAttributeTensor && f.wire == kWireLengthDelimited) tensor = f.payload;
    }
    if (named) return tensor;
  }
  return {};
}

// The graph's bytes with the pairs fused; false (and *fused untouched) when it does not parse.
// A graph output (ValueInfoProto) counts as one more consumer of the tensor it names, so that
// no rewrite removes a tensor the caller reads. False when the bytes do not parse.
bool CountGraphOutputUse(std::string_view value_info, std::map<std::string_view, int>* uses) {
  std::vector<Field> info;
  if (!ParseFields(value_info, &info)) return false;
  for (const Field& i : info) {
    if (i.number == kValueInfoName && i.wire == kWireLengthDelimited) ++(*uses)[i.payload];
  }
  return true;
}

bool FuseGraph(std::string_view graph, std::vector<unsigned char>* out, int* fused) {
  std::vector<Field> fields;
  if (!ParseFields(graph, &fields)) return false;
  std::vector<Node> nodes;
  std::map<std::string_view, int> uses;      // tensor -> consumers (graph outputs count too)
  std::map<std::string_view, int> producer;  // tensor -> index in `nodes`
  for (const Field& f : fields) {
    if (f.wire != kWireLengthDelimited) continue;
    if (f.number == kGraphOutput) {
      if (!CountGraphOutputUse(f.payload, &uses)) return false;
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
// vector arithmetic, inlined into each kernel below, so it compiles to that target's instructions.
__attribute__((always_inline)) inline void SiluLoop(const float* src, float* dst, size_t count) {
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

// The ValueInfoProto of a 4-D float tensor `name` of shape `dims`: name = 1, type = 2
// (TypeProto.tensor_type = 1: elem_type = 1, shape = 2: TensorShapeProto.dim = 1: dim_value = 1).
std::vector<unsigned char> TensorValueInfo(std::string_view name,
                                           const std::vector<int64_t>& dims) {
  std::vector<unsigned char> shape;
  for (int64_t d : dims) {
    std::vector<unsigned char> dim;
    PutVarint(&dim, (uint64_t(1) << 3) | 0);
    PutVarint(&dim, uint64_t(d));
    PutBytes(&shape, 1, std::string_view(reinterpret_cast<const char*>(dim.data()), dim.size()));
  }
  std::vector<unsigned char> tensor;
  PutVarint(&tensor, (uint64_t(1) << 3) | 0);
  PutVarint(&tensor, 1);  // FLOAT
  PutBytes(&tensor, 2, std::string_view(reinterpret_cast<const char*>(shape.data()), shape.size()));
  std::vector<unsigned char> type;
  PutBytes(&type, 1, std::string_view(reinterpret_cast<const char*>(tensor.data()), tensor.size()));
  std::vector<unsigned char> info;
  PutBytes(&info, kValueInfoName, name);
  PutBytes(&info, 2, std::string_view(reinterpret_cast<const char*>(type.data()), type.size()));
  return info;
}

// The dims (dim_value) of a ValueInfoProto's tensor shape; empty when one is symbolic or absent.
std::vector<int64_t> ValueInfoDims(std::string_view info) {
  std::vector<int64_t> dims;
  std::vector<Field> fields, type, tensor, shape;
  if (!ParseFields(info, &fields)) return {};
  for (const Field& f : fields) {
    if (f.number == 2 && f.wire == kWireLengthDelimited) ParseFields(f.payload, &type);
  }
  for (const Field& f : type) {
    if (f.number == 1 && f.wire == kWireLengthDelimited) ParseFields(f.payload, &tensor);
  }
  for (const Field& f : tensor) {
    if (f.number == 2 && f.wire == kWireLengthDelimited) ParseFields(f.payload, &shape);
  }
  for (const Field& f : shape) {
    if (f.number != 1 || f.wire != kWireLengthDelimited) continue;
    std::vector<Field> dim;
    if (!ParseFields(f.payload, &dim)) return {};
    bool has_value = false;
    for (const Field& d : dim) {
      if (d.number == 1 && d.wire == 0) dims.push_back(int64_t(d.varint)), has_value = true;
    }
    if (!has_value) return {};
  }
  return dims;
}

// The graph's bytes with YOLOX's Focus stem cut (see CutFocusStem); false when the graph does
// not parse or holds no such stem.
bool CutFocusGraph(std::string_view graph, std::vector<unsigned char>* out, FocusStem* stem) {
  std::vector<Field> fields;
  if (!ParseFields(graph, &fields)) return false;
  std::string_view input;
  std::vector<int64_t> input_dims;  // N, C, H, W as declared
  const Field* input_field = nullptr;
  std::map<std::string_view, int64_t> constants;
  std::vector<Node> nodes;
  std::map<std::string_view, int> uses, producer;
  for (const Field& f : fields) {
    if (f.wire != kWireLengthDelimited) continue;
    if (f.number == kGraphInput && input.empty()) {
      std::vector<Field> info;
      if (!ParseFields(f.payload, &info)) return false;
      for (const Field& i : info) {
        if (i.number == kValueInfoName && i.wire == kWireLengthDelimited) input = i.payload;
      }
      input_dims = ValueInfoDims(f.payload);
      input_field = &f;
    } else if (f.number == kGraphInitializer) {
      std::vector<Field> tensor;
      int64_t value = 0;
      if (!ParseFields(f.payload, &tensor) || !TensorFirstInt64(f.payload, &value)) continue;
      for (const Field& t : tensor) {
        if (t.number == kTensorName && t.wire == kWireLengthDelimited) constants[t.payload] = value;
      }
    } else if (f.number == kGraphOutput) {
      if (!CountGraphOutputUse(f.payload, &uses)) return false;
    } else if (f.number == kGraphNode) {
      Node node;
      if (!ParseNode(f.payload, &node)) return false;
      int64_t value = 0;
      if (node.op_type == "Constant" && node.outputs.size() == 1 &&
          TensorFirstInt64(ConstantTensor(node), &value)) {
        constants[node.outputs[0]] = value;
      }
      for (std::string_view name : node.inputs) ++uses[name];
      for (std::string_view name : node.outputs) producer[name] = int(nodes.size());
      nodes.push_back(std::move(node));
    }
  }
  // OpenCV infers shapes at import from the declared input: it must become N x 12 x H/2 x W/2.
  if (input.empty() || input_dims.size() != 4 || input_dims[1] != 3 || input_dims[2] % 2 != 0 ||
      input_dims[3] % 2 != 0) {
    return false;
  }
  auto constant = [&](std::string_view name, int64_t* value) {
    const auto it = constants.find(name);
    if (it == constants.end()) return false;
    *value = it->second;
    return true;
  };
  // A Slice of `data` along `axis` with step 2 from start 0 or 1 to the end: its start, or -1.
  auto phase = [&](const Node& node, std::string_view data, int64_t axis) -> int {
    int64_t start = 0, end = 0, slice_axis = 0, step = 0;
    if (node.op_type != "Slice" || node.inputs.size() != 5 || node.outputs.size() != 1 ||
        node.inputs[0] != data || !constant(node.inputs[1], &start) ||
        !constant(node.inputs[2], &end) || !constant(node.inputs[3], &slice_axis) ||
        !constant(node.inputs[4], &step)) {
      return -1;
    }
    const bool ok =
        slice_axis == axis && step == 2 && (start == 0 || start == 1) && end >= (int64_t(1) << 30);
    return ok ? int(start) : -1;
  };

  for (size_t c = 0; c < nodes.size(); ++c) {
    const Node& concat = nodes[c];
    int64_t axis = 0;
    if (concat.op_type != "Concat" || concat.inputs.size() != 4 || concat.outputs.size() != 1 ||
        !IntAttribute(concat, "axis", &axis) || axis != 1) {
      continue;
    }
    std::vector<size_t> dropped;
    FocusStem found;
    bool ok = uses[input] == 2;
    int seen = 0;  // bit 2r + c for each phase
    for (size_t g = 0; g < 4 && ok; ++g) {
      const auto b = producer.find(concat.inputs[g]);
      ok = b != producer.end() && uses[concat.inputs[g]] == 1;
      if (!ok) break;
      const Node& column_slice = nodes[size_t(b->second)];
      const auto a =
          column_slice.inputs.empty() ? producer.end() : producer.find(column_slice.inputs[0]);
      ok = a != producer.end() && uses[column_slice.inputs[0]] == 2;
      if (!ok) break;
      const Node& row_slice = nodes[size_t(a->second)];
      const int row = phase(row_slice, input, 2);
      const int col = phase(column_slice, row_slice.outputs.empty() ? "" : row_slice.outputs[0], 3);
      ok = row >= 0 && col >= 0 && !(seen & (1 << (2 * row + col)));
      if (!ok) break;
      seen |= 1 << (2 * row + col);
      found.row[g] = row;
      found.col[g] = col;
      dropped.push_back(size_t(b->second));
      if (std::find(dropped.begin(), dropped.end(), size_t(a->second)) == dropped.end()) {
        dropped.push_back(size_t(a->second));
      }
    }
    if (!ok || seen != 15 || dropped.size() != 6) continue;

    size_t index = 0;
    for (const Field& f : fields) {
      if (&f == input_field) {
        const std::vector<unsigned char> info =
            TensorValueInfo(input, {input_dims[0], 12, input_dims[2] / 2, input_dims[3] / 2});
        PutBytes(out, kGraphInput,
                 std::string_view(reinterpret_cast<const char*>(info.data()), info.size()));
        continue;
      }
      if (f.number != kGraphNode || f.wire != kWireLengthDelimited) {
        PutField(out, f);
        continue;
      }
      const size_t i = index++;
      if (std::find(dropped.begin(), dropped.end(), i) != dropped.end()) continue;
      if (i != c) {
        PutField(out, f);
        continue;
      }
      std::vector<unsigned char> node;
      PutBytes(&node, kNodeInput, input);
      PutBytes(&node, kNodeOutput, concat.outputs[0]);
      PutBytes(&node, kNodeName, concat.name);
      PutBytes(&node, kNodeOpType, "Identity");
      PutBytes(out, kGraphNode,
               std::string_view(reinterpret_cast<const char*>(node.data()), node.size()));
    }
    *stem = found;
    return true;
  }
  return false;
}

}  // namespace

std::vector<unsigned char> CutFocusStem(const std::vector<unsigned char>& model, FocusStem* stem,
                                        bool* cut) {
  *cut = false;
  std::vector<Field> fields;
  const std::string_view bytes(reinterpret_cast<const char*>(model.data()), model.size());
  if (!ParseFields(bytes, &fields)) return model;
  std::vector<unsigned char> out;
  out.reserve(model.size());
  bool done = false;
  for (const Field& f : fields) {
    if (f.number != kModelGraph || f.wire != kWireLengthDelimited || done) {
      PutField(&out, f);
      continue;
    }
    std::vector<unsigned char> graph;
    if (!CutFocusGraph(f.payload, &graph, stem)) return model;
    PutBytes(&out, kModelGraph,
             std::string_view(reinterpret_cast<const char*>(graph.data()), graph.size()));
    done = true;
  }
  if (!done) return model;
  *cut = true;
  return out;
}

cv::Mat SpaceToDepthBlob(const cv::Mat& image, const FocusStem& stem) {
  CV_Assert(image.type() == CV_8UC3 && image.rows % 2 == 0 && image.cols % 2 == 0);
  const int rows = image.rows / 2, cols = image.cols / 2;
  const int shape[] = {1, 12, rows, cols};
  cv::Mat blob(4, shape, CV_32F);
  for (int g = 0; g < 4; ++g) {
    float* planes[3];
    for (int c = 0; c < 3; ++c) planes[c] = blob.ptr<float>(0, 3 * g + c);
    for (int y = 0; y < rows; ++y) {
      const unsigned char* src =
          image.ptr<unsigned char>(2 * y + stem.row[size_t(g)]) + 3 * stem.col[size_t(g)];
      const size_t offset = size_t(y) * size_t(cols);
      for (int x = 0; x < cols; ++x, src += 6) {
        planes[0][offset + size_t(x)] = src[0];
        planes[1][offset + size_t(x)] = src[1];
        planes[2][offset + size_t(x)] = src[2];
      }
    }
  }
  return blob;
}

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

// Chosen at run time by Silu(), not by target_clones: an ifunc resolver runs before the
// sanitizers' runtimes are initialised, and crashes ThreadSanitizer builds at load time.
static __attribute__((target("avx2"))) void SiluAvx2(const float* src, float* dst, size_t count) {
  SiluLoop(src, dst, count);
}

static void SiluBaseline(const float* src, float* dst, size_t count) {
  SiluLoop(src, dst, count);
}

void Silu(const float* src, float* dst, size_t count) {
  static const bool avx2 = __builtin_cpu_supports("avx2");
  (avx2 ? SiluAvx2 : SiluBaseline)(src, dst, count);
}

}  // namespace placedb
