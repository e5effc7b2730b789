// The wire library's own helpers for field-path messages ("config.depth.threshold_m: must be
// positive, got -1"); not part of its interface (its users see only the messages).
#pragma once

#include <cstdio>
#include <string>

#include "core/base/status.h"

namespace placedb::wire::internal {

// INVALID_ARGUMENT "<field>: <what>".
inline Status Invalid(const std::string& field, const std::string& what) {
  return Status::InvalidArgument(field + ": " + what);
}

// 700, 0.25, 1e+20: numbers in messages as a person writes them.
inline std::string Num(double v) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%g", v);
  return buffer;
}

}  // namespace placedb::wire::internal
