#include "core/base/text.h"

#include <algorithm>
#include <cstdint>
#include <cstdio>

namespace placedb {

std::string Hex64(uint64_t value) {
  char buffer[17];
  std::snprintf(buffer, sizeof buffer, "%016llx", static_cast<unsigned long long>(value));
  return buffer;
}

std::optional<uint64_t> ParseHex64(std::string_view text) {
  if (text.size() != 16) return std::nullopt;
  uint64_t value = 0;
  for (const char c : text) {
    int digit = -1;
    if (c >= '0' && c <= '9') digit = c - '0';
    if (c >= 'a' && c <= 'f') digit = c - 'a' + 10;
    if (c >= 'A' && c <= 'F') digit = c - 'A' + 10;
    if (digit < 0) return std::nullopt;
    value = value << 4 | uint64_t(digit);
  }
  return value;
}

namespace {

void AppendHexByte(std::string* out, unsigned char byte) {
  char hex[8];
  std::snprintf(hex, sizeof hex, "\\x%02x", byte);
  *out += hex;
}

// The length (2-4) of the well-formed UTF-8 sequence starting `text` (whose first byte is not
// ASCII) and its code point; 0 when it is not one (overlong forms, surrogates and code points
// past U+10FFFF included).
size_t DecodeUtf8(std::string_view text, uint32_t* code_point) {
  const auto at = [&](size_t i) { return static_cast<unsigned char>(text[i]); };
  const unsigned char lead = at(0);
  size_t length = 0;
  unsigned char low = 0x80, high = 0xbf;  // the second byte's range
  if (lead >= 0xc2 && lead <= 0xdf) {
    length = 2;
  } else if (lead >= 0xe0 && lead <= 0xef) {
    length = 3;
    if (lead == 0xe0) low = 0xa0;
    if (lead == 0xed) high = 0x9f;
  } else if (lead >= 0xf0 && lead <= 0xf4) {
    length = 4;
    if (lead == 0xf0) low = 0x90;
    if (lead == 0xf4) high = 0x8f;
  } else {
    return 0;
  }
  if (text.size() < length || at(1) < low || at(1) > high) return 0;
  uint32_t value = lead & (0xff >> (length + 1));
  for (size_t i = 1; i < length; ++i) {
    if ((at(i) & 0xc0) != 0x80) return 0;
    value = (value << 6) | (at(i) & 0x3f);
  }
  *code_point = value;
  return length;
}

// Code points that a log viewer or terminal may take as a line break or as a reordering of the
// text after them.
bool HiddenControl(uint32_t c) {
  return (c >= 0x80 && c <= 0x9f) || c == 0x2028 || c == 0x2029 || (c >= 0x202a && c <= 0x202e) ||
         (c >= 0x2066 && c <= 0x2069);
}

}  // namespace

void AppendEscaped(std::string* out, std::string_view text, EscapeMode mode) {
  for (size_t i = 0; i < text.size();) {
    const char c = text[i];
    const auto byte = static_cast<unsigned char>(c);
    if (c == '"' || c == '\\') {
      *out += '\\';
      *out += c;
    } else if (byte >= 0x20 && byte < 0x7f) {
      *out += c;
    } else if (mode == EscapeMode::kAscii || byte < 0x80) {
      if (mode == EscapeMode::kLog && c == '\n') {
        *out += "\\n";
      } else if (mode == EscapeMode::kLog && c == '\r') {
        *out += "\\r";
      } else if (mode == EscapeMode::kLog && c == '\t') {
        *out += "\\t";
      } else {
        AppendHexByte(out, byte);
      }
    } else {
      uint32_t code_point = 0;
      const size_t length = DecodeUtf8(text.substr(i), &code_point);
      if (length == 0) {
        AppendHexByte(out, byte);
      } else {
        if (HiddenControl(code_point)) {
          char escaped[12];
          std::snprintf(escaped, sizeof escaped, "\\u%04x", static_cast<unsigned>(code_point));
          *out += escaped;
        } else {
          out->append(text.substr(i, length));
        }
        i += length;
        continue;
      }
    }
    ++i;
  }
}

std::string ForLog(std::string_view text, size_t max_bytes) {
  size_t cut = std::min(max_bytes, text.size());
  // Back to the start of a character when the cut falls inside one (at most 3 continuation bytes).
  for (int back = 0; back < 3 && cut > 0 && cut < text.size() &&
                     (static_cast<unsigned char>(text[cut]) & 0xc0) == 0x80;
       ++back) {
    --cut;
  }
  std::string out;
  out.reserve(cut + 8);
  AppendEscaped(&out, text.substr(0, cut), EscapeMode::kLog);
  if (cut < text.size()) out += "... (" + std::to_string(text.size()) + " bytes)";
  return out;
}

}  // namespace placedb
