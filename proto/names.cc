#include "proto/names.h"

#include <cctype>

#include "core/base/text.h"

namespace placedb::wire {

namespace {

using google::protobuf::EnumDescriptor;
using google::protobuf::EnumValueDescriptor;

// "FilterMethod" -> "filter_method": the enum's value prefix in lowercase, without its '_'.
std::string SnakeName(const EnumDescriptor* type) {
  std::string out;
  for (char c : type->name()) {
    if (std::isupper(static_cast<unsigned char>(c)) && !out.empty()) out += '_';
    out += char(std::tolower(static_cast<unsigned char>(c)));
  }
  return out;
}

// FILTER_METHOD_KEYPOINT_IN_BOX -> "keypoint_in_box" (proto style prefixes every value with the
// enum's name; a value that is not prefixed keeps its whole name).
std::string Suffix(const EnumValueDescriptor* value) {
  const std::string prefix = SnakeName(value->type()) + "_";
  std::string name = AsciiLower(value->name());
  if (name.size() > prefix.size() && name.compare(0, prefix.size(), prefix) == 0) {
    name.erase(0, prefix.size());
  }
  return name;
}

std::string Name(const EnumValueDescriptor* value) {
  const std::string& option = value->options().GetExtension(v1::name);
  return option.empty() ? Suffix(value) : option;
}

}  // namespace

std::string EnumValueName(const EnumDescriptor* type, int number) {
  const EnumValueDescriptor* value = type->FindValueByNumber(number);
  if (value == nullptr) return SnakeName(type) + "_" + std::to_string(number);
  return Name(value);
}

Result<int> ParseEnumValue(const EnumDescriptor* type, std::string_view name) {
  for (int i = 0; i < type->value_count(); ++i) {
    const EnumValueDescriptor* value = type->value(i);
    if (value->number() == 0) continue;  // UNSPECIFIED is what an unset field says, not a choice
    if (name == Name(value) || name == Suffix(value) || name == value->name()) {
      return value->number();
    }
  }
  std::string expected;
  const std::vector<std::string> names = EnumValueNames(type);
  for (size_t i = 0; i < names.size(); ++i) {
    if (i > 0) expected += i + 1 == names.size() ? " or " : ", ";
    expected += names[i];
  }
  std::string label = SnakeName(type);
  for (char& c : label) c = c == '_' ? ' ' : c;
  return Status::InvalidArgument("unknown " + label + " '" + std::string(name) + "' (expected " +
                                 expected + ")");
}

std::vector<std::string> EnumValueNames(const EnumDescriptor* type) {
  std::vector<std::string> names;
  for (int i = 0; i < type->value_count(); ++i) {
    if (type->value(i)->number() != 0) names.push_back(Name(type->value(i)));
  }
  return names;
}

std::vector<std::string> EnumValueSpellings(const EnumDescriptor* type) {
  std::vector<std::string> spellings = EnumValueNames(type);
  for (int i = 0; i < type->value_count(); ++i) {
    const EnumValueDescriptor* value = type->value(i);
    if (value->number() != 0 && Suffix(value) != Name(value)) spellings.push_back(Suffix(value));
  }
  return spellings;
}

namespace {

// Lower case, '_' as ' ', surrounding blanks dropped: "Traffic_Light " -> "traffic light".
std::string ClassKey(std::string_view name) {
  std::string key;
  for (char c : name) key += c == '_' ? ' ' : char(std::tolower(static_cast<unsigned char>(c)));
  const size_t first = key.find_first_not_of(' ');
  if (first == std::string::npos) return "";
  return key.substr(first, key.find_last_not_of(' ') - first + 1);
}

}  // namespace

std::string DynamicClassName(int class_id) {
  const EnumValueDescriptor* value = v1::CocoClass_descriptor()->FindValueByNumber(class_id);
  return value == nullptr ? std::to_string(class_id) : Name(value);
}

Result<int> ParseDynamicClass(std::string_view name) {
  const std::string key = ClassKey(name);
  const EnumDescriptor* type = v1::CocoClass_descriptor();
  for (int i = 0; i < type->value_count(); ++i) {  // the aliases after the classes
    if (key == ClassKey(Name(type->value(i)))) return type->value(i)->number();
  }
  return Status::InvalidArgument("unknown COCO class name '" + std::string(name) +
                                 "' (expected a COCO-80 name such as person, car, truck)");
}

}  // namespace placedb::wire
