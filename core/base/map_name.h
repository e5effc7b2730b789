// Map names: the one rule every layer applies (storage, every RPC, authorization, the CLI).
//
// A valid name is 1-64 bytes of [A-Za-z0-9_.-] whose first byte is a letter or digit. Such a
// name is always one plain path component: never empty, "." or "..", never holding '/', '\',
// NUL or any other control byte, so a map's directory can never leave the data directory and a
// name is safe to print in logs and messages. The check is byte-wise and locale-independent:
// non-ASCII UTF-8 letters are refused (a map name is an identifier, not a title).
#pragma once

#include <cstddef>
#include <string>
#include <string_view>

#include "core/base/status.h"

namespace placedb {

inline constexpr size_t kMaxMapNameLength = 64;

// OK for a valid name. Otherwise INVALID_ARGUMENT whose message quotes the name
// (QuoteForMessage), says what is wrong with it and states the rule, e.g.
//   map name "../evil" is invalid (it starts with '.'): a map name is 1-64 characters of
//   A-Z a-z 0-9 _ . - starting with a letter or digit
// Callers prefix the request field ("name: ...") with Status::WithContext.
Status ValidateMapName(std::string_view name);

// `text` between double quotes, safe to print (AppendEscaped, EscapeMode::kAscii:
// core/base/text.h): bytes outside printable ASCII (control bytes, DEL, every byte of non-ASCII
// UTF-8) as \xNN, '"' and '\' escaped with '\'; text longer than `max_bytes` is cut there and
// followed by "... (N bytes)" after the closing quote.
std::string QuoteForMessage(std::string_view text, size_t max_bytes = kMaxMapNameLength);

}  // namespace placedb
