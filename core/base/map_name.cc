#include "core/base/map_name.h"

#include <cstdio>

#include "core/base/text.h"

namespace placedb {
namespace {

bool IsAsciiAlnum(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9');
}

bool IsNameChar(char c) {
  return IsAsciiAlnum(c) || c == '_' || c == '.' || c == '-';
}

// One byte as the rule's explanation shows it: 'x' when printable, else \xNN.
std::string ByteForMessage(char c) {
  const auto byte = static_cast<unsigned char>(c);
  if (byte >= 0x20 && byte < 0x7f && c != '\'') return std::string("'") + c + "'";
  char hex[8];
  std::snprintf(hex, sizeof hex, "\\x%02x", byte);
  return hex;
}

}  // namespace

std::string QuoteForMessage(std::string_view text, size_t max_bytes) {
  const std::string_view shown = text.substr(0, max_bytes);
  std::string out = "\"";
  AppendEscaped(&out, shown, EscapeMode::kAscii);
  out += '"';
  if (shown.size() < text.size()) out += "... (" + std::to_string(text.size()) + " bytes)";
  return out;
}

Status ValidateMapName(std::string_view name) {
  std::string problem;
  if (name.empty()) {
    problem = "it is empty";
  } else if (name.size() > kMaxMapNameLength) {
    problem = "it is " + std::to_string(name.size()) + " bytes long";
  } else if (!IsAsciiAlnum(name[0])) {
    problem = "it starts with " + ByteForMessage(name[0]);
  } else {
    for (size_t i = 1; i < name.size(); ++i) {
      if (!IsNameChar(name[i])) {
        problem = "byte " + std::to_string(i + 1) + " is " + ByteForMessage(name[i]);
        break;
      }
    }
  }
  if (problem.empty()) return Status::Ok();
  return Status::InvalidArgument("map name " + QuoteForMessage(name) + " is invalid (" + problem +
                                 "): a map name is 1-" + std::to_string(kMaxMapNameLength) +
                                 " characters of A-Z a-z 0-9 _ . - starting with a letter or "
                                 "digit");
}

}  // namespace placedb
