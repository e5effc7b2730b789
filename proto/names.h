// The names of the placedb.v1 enum values in the CLI, in JSON reports and in stored maps, derived
// from the generated enum descriptors so that a value added to proto/placedb.proto is named
// without code here.
//
// A value's name is its (placedb.v1.name) option, else its value name without the enum's prefix,
// in lowercase: FILTER_METHOD_KEYPOINT_IN_BOX -> "keypoint_in_box", SCORING_CHI_SQUARE -> "chi2"
// (the option: the core's and stored maps' name). These are the names core's own Name/Parse
// functions use, so a name read from a map, a flag or a report means the same everywhere.
//
// Parsing accepts the name, the lowercase suffix ("chi_square", "dot_product", "direct_index")
// and the full value name ("SCORING_L2", the proto3 JSON spelling). UNSPECIFIED (value 0) is
// printed as the value the server takes it for (its option: SCORING_UNSPECIFIED -> "l1"), or
// "unspecified" when that depends on the server (FEATURE_TYPE_UNSPECIFIED); it is never parsed.
//
//   wire::EnumName(v1::SCORING_CHI_SQUARE)            // "chi2"
//   wire::ParseEnum<v1::Scoring>("chi_square")        // v1::SCORING_CHI_SQUARE
//   wire::EnumNames<v1::Scoring>()                    // {"l1", "l2", "chi2", "kl", ...}
//   CLI::IsMember(wire::EnumSpellings<v1::Scoring>())  // every spelling a flag may use
//   wire::DynamicClassName(9)                         // "traffic light" (v1::CocoClass)
#pragma once

#include <google/protobuf/descriptor.h>
#include <google/protobuf/generated_enum_reflection.h>

#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "core/base/status.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

template <typename E>
concept ProtoEnum = google::protobuf::is_proto_enum<E>::value;

// The descriptor-level functions the templates below call; `number` may be outside the enum
// (proto3 enums are open): it is named "<enum>_<number>", e.g. "scoring_17".
std::string EnumValueName(const google::protobuf::EnumDescriptor* type, int number);
// INVALID_ARGUMENT naming the enum and the expected names for anything else.
Result<int> ParseEnumValue(const google::protobuf::EnumDescriptor* type, std::string_view name);
std::vector<std::string> EnumValueNames(const google::protobuf::EnumDescriptor* type);
std::vector<std::string> EnumValueSpellings(const google::protobuf::EnumDescriptor* type);

template <ProtoEnum E>
std::string EnumName(E value) {
  return EnumValueName(google::protobuf::GetEnumDescriptor<E>(), int(value));
}

template <ProtoEnum E>
Result<E> ParseEnum(std::string_view name) {
  auto number = ParseEnumValue(google::protobuf::GetEnumDescriptor<E>(), name);
  if (!number.ok()) return number.status();
  return E(*number);
}

// The names of the specified values, in declaration order (help texts, CLI choices).
template <ProtoEnum E>
std::vector<std::string> EnumNames() {
  return EnumValueNames(google::protobuf::GetEnumDescriptor<E>());
}

// Every lowercase spelling ParseEnum accepts: the names, then the suffixes that differ from them.
template <ProtoEnum E>
std::vector<std::string> EnumSpellings() {
  return EnumValueSpellings(google::protobuf::GetEnumDescriptor<E>());
}

// ---- COCO classes (v1::CocoClass) -----------------------------------------------------------
// Dynamic objects' classes travel as ints (Box.class_id, UsedBox.class_id, DynamicClassCount
// .class_id); v1::CocoClass is their table. Value 0 is a class (person), not UNSPECIFIED, so these
// are not EnumName / ParseEnum.

// "person" for 0, "traffic light" for 9 (the value's name option, COCO-2017's spelling); an id
// outside the table as its number ("80").
std::string DynamicClassName(int class_id);
// A class name as the server reads one: case-insensitive, '_' for ' ', surrounding blanks
// ignored, darknet's spellings ("motorbike": the enum's aliases) too. INVALID_ARGUMENT otherwise.
Result<int> ParseDynamicClass(std::string_view name);

}  // namespace placedb::wire
