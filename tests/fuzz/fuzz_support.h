// What the libFuzzer targets of tests/fuzz share: a per-process scratch directory on tmpfs for
// loaders that take paths, the input's split into named parts, and a check that reports a broken
// invariant as a crash (so libFuzzer keeps the input). docs/fuzzing.md.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"

namespace placedb::fuzz {

// A directory private to this process (under $PLACEDB_FUZZ_SCRATCH, else /dev/shm when it exists,
// else $TMPDIR or /tmp), removed at exit. Paths-only loaders read their input from here.
const std::string& ScratchDir();

// Writes `bytes` to ScratchDir()/`name` (replacing it) and returns the path; aborts when the
// write fails, which is the machine's fault, not the input's.
std::string WriteScratchFile(const std::string& name, std::string_view bytes);

// The contents of a file this process wrote; aborts when it cannot be read.
std::string ReadWholeFileOrDie(const std::string& path);

// Removes ScratchDir()/`name` (file or directory tree) if present.
void RemoveScratch(const std::string& name);

// The input's parts, split at kPartSeparator: lets one input carry several files or messages
// while staying easy to write by hand and to mutate (tools/fuzz.sh seeds use the same split).
inline constexpr std::string_view kPartSeparator = "\n--8<--\n";
std::vector<std::string_view> SplitParts(std::string_view input);

// Reports a violated invariant with `what` and the status, then aborts (libFuzzer saves the
// input as a crash artefact).
[[noreturn]] void Fail(const std::string& what, const Status& status = Status::Ok());

}  // namespace placedb::fuzz

// Fails the run when `condition` is false.
#define PLACEDB_FUZZ_CHECK(condition, what)        \
  do {                                             \
    if (!(condition)) ::placedb::fuzz::Fail(what); \
  } while (false)
