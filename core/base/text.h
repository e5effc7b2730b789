// Small text helpers shared by names, file extensions and labels.
#pragma once

#include <string>
#include <string_view>

namespace placedb {

// `text` with ASCII letters in lowercase; other bytes (UTF-8 included) unchanged.
inline std::string AsciiLower(std::string_view text) {
  std::string out(text);
  for (char& c : out) {
    if (c >= 'A' && c <= 'Z') c = char(c - 'A' + 'a');
  }
  return out;
}

}  // namespace placedb
