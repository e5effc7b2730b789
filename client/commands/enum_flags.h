// Flags that take a placedb.v1 enum by name (`maps create --scoring chi2`): the names and the
// older spellings proto/names.h accepts, checked by CLI11, with the canonical names in --help.
#pragma once

#include <CLI/CLI.hpp>
#include <string>

#include "proto/names.h"

namespace placedb::client {

// A CLI11 check that accepts exactly what wire::ParseEnum<E> parses; --help shows the names.
template <wire::ProtoEnum E>
CLI::Validator EnumFlag() {
  std::string choices;
  for (const std::string& name : wire::EnumNames<E>()) {
    choices += (choices.empty() ? "" : ",") + name;
  }
  return CLI::Validator(
      [](std::string& value) -> std::string {
        auto parsed = wire::ParseEnum<E>(value);
        return parsed.ok() ? std::string() : parsed.status().message();
      },
      "{" + choices + "}");
}

// The value of a flag EnumFlag<E>() has checked.
template <wire::ProtoEnum E>
E EnumFlagValue(const std::string& flag) {
  return *wire::ParseEnum<E>(flag);
}

}  // namespace placedb::client
