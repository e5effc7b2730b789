// Small text helpers shared by names, file extensions, labels, messages and log lines.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
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

// 16 lowercase hex digits: how checksums (a vocabulary's) are shown.
std::string Hex64(uint64_t value);
// Hex64's inverse: exactly 16 hex digits (either case); nullopt otherwise.
std::optional<uint64_t> ParseHex64(std::string_view text);

// How AppendEscaped shows what is not printable ASCII.
enum class EscapeMode {
  // Every byte outside printable ASCII (control bytes, DEL, every byte of non-ASCII UTF-8) as
  // \xNN: for messages that quote an identifier, where any such byte is the error.
  kAscii,
  // Readable, for log lines: \n \r \t by name, other control bytes and DEL as \xNN, valid UTF-8
  // kept except the code points that break a line or reorder what follows it (C1 controls,
  // U+2028, U+2029, bidi embeddings/overrides/isolates) as \uNNNN, each byte of invalid UTF-8
  // as \xNN.
  kLog,
};

// Appends `text` to `out` so that it cannot end a line, close a double-quoted field or drive a
// terminal: '"' and '\' escaped with '\', the rest as `mode` says. Printable ASCII is unchanged.
void AppendEscaped(std::string* out, std::string_view text, EscapeMode mode);

inline constexpr size_t kMaxLogTextBytes = 1024;

// A string that came from outside (a client's map name, agent id, snapshot id, method, peer,
// user agent, or a message echoing any of them) as one log line may show it: escaped
// (EscapeMode::kLog), without quotes (the log line has its own), cut after `max_bytes` of `text`
// (at a character boundary) and then followed by "... (N bytes)". Every log line that prints such
// a string goes through here, so a client can neither forge log lines nor write terminal escapes.
std::string ForLog(std::string_view text, size_t max_bytes = kMaxLogTextBytes);

}  // namespace placedb
