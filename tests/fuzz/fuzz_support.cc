#include "tests/fuzz/fuzz_support.h"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <utility>

#include "core/base/files.h"

namespace placedb::fuzz {

namespace fs = std::filesystem;

namespace {

std::string MakeScratchDir() {
  std::string base;
  if (const char* dir = std::getenv("PLACEDB_FUZZ_SCRATCH"); dir && *dir) {
    base = dir;
  } else if (fs::is_directory("/dev/shm")) {
    base = "/dev/shm";  // tmpfs: a file per execution costs microseconds, not a disk write
  } else if (const char* tmp = std::getenv("TMPDIR"); tmp && *tmp) {
    base = tmp;
  } else {
    base = "/tmp";
  }
  std::string pattern = base + "/placedb-fuzz-XXXXXX";
  if (::mkdtemp(pattern.data()) == nullptr) {
    std::perror(("placedb fuzz: cannot create a scratch directory in " + base).c_str());
    std::abort();
  }
  return pattern;
}

void RemoveScratchDir() {
  std::error_code ec;
  fs::remove_all(ScratchDir(), ec);
}

}  // namespace

const std::string& ScratchDir() {
  static const std::string* dir = [] {
    auto* made = new std::string(MakeScratchDir());
    std::atexit(RemoveScratchDir);
    return made;
  }();
  return *dir;
}

std::string WriteScratchFile(const std::string& name, std::string_view bytes) {
  const std::string path = ScratchDir() + "/" + name;
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), std::streamsize(bytes.size()));
  out.close();
  if (!out) {
    std::fprintf(stderr, "placedb fuzz: cannot write %s\n", path.c_str());
    std::abort();
  }
  return path;
}

std::string ReadWholeFileOrDie(const std::string& path) {
  auto text = ReadWholeFile(path);
  if (!text.ok()) Fail("cannot read back " + path, text.status());
  return std::move(text).value();
}

void RemoveScratch(const std::string& name) {
  std::error_code ec;
  fs::remove_all(ScratchDir() + "/" + name, ec);
}

std::vector<std::string_view> SplitParts(std::string_view input) {
  std::vector<std::string_view> parts;
  size_t begin = 0;
  while (true) {
    const size_t at = input.find(kPartSeparator, begin);
    if (at == std::string_view::npos) {
      parts.push_back(input.substr(begin));
      return parts;
    }
    parts.push_back(input.substr(begin, at - begin));
    begin = at + kPartSeparator.size();
  }
}

void Fail(const std::string& what, const Status& status) {
  std::fprintf(stderr, "\nplacedb fuzz: invariant violated: %s%s%s\n", what.c_str(),
               status.ok() ? "" : ": ", status.ok() ? "" : status.ToString().c_str());
  std::fflush(stderr);
  std::abort();
}

}  // namespace placedb::fuzz
