#include "core/base/files.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <new>
#include <stdexcept>
#include <utility>

#include "core/base/text.h"

namespace placedb {

namespace {

namespace fs = std::filesystem;

std::string Errno(const std::string& what, const std::string& path) {
  return what + " " + path + ": " + std::strerror(errno);
}

bool IsDigit(char c) {
  return std::isdigit(static_cast<unsigned char>(c)) != 0;
}

// Closes a file descriptor on scope exit.
struct FdCloser {
  int fd;
  ~FdCloser() { ::close(fd); }
};

}  // namespace

Result<std::string> ReadWholeFile(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return Status::NotFound("no such file: " + path);
    return Status::IoError(Errno("cannot open", path));
  }
  const FdCloser closer{fd};
  struct stat info;
  if (::fstat(fd, &info) != 0) return Status::IoError(Errno("cannot stat", path));
  std::string contents;
  size_t size = 0;
  try {
    // st_size is a hint only (0 for /proc files, stale if the file grows): read to the end.
    contents.resize(std::max<size_t>(size_t(info.st_size) + 1, 4096));
    for (;;) {
      if (size == contents.size()) contents.resize(contents.size() * 2);
      // Linux transfers at most ~2 GiB per call.
      const size_t chunk = std::min<size_t>(contents.size() - size, size_t{1} << 30);
      const ssize_t got = ::read(fd, contents.data() + size, chunk);
      if (got < 0) {
        if (errno == EINTR) continue;
        return Status::IoError(Errno("cannot read", path));
      }
      if (got == 0) break;
      size += size_t(got);
    }
  } catch (const std::bad_alloc&) {
    return Status::ResourceExhausted("out of memory reading " + path);
  } catch (const std::length_error&) {
    return Status::ResourceExhausted("file too large: " + path);
  }
  contents.resize(size);
  return contents;
}

bool IsImageFile(const fs::path& path) {
  const std::string ext = AsciiLower(path.extension().string());
  static const char* const kImages[] = {".jpg", ".jpeg", ".png", ".bmp",  ".pgm",
                                        ".ppm", ".pnm",  ".tif", ".tiff", ".webp"};
  return std::find(std::begin(kImages), std::end(kImages), ext) != std::end(kImages);
}

bool NaturalLess(std::string_view a, std::string_view b) {
  size_t i = 0, j = 0;
  while (i < a.size() && j < b.size()) {
    if (!IsDigit(a[i]) || !IsDigit(b[j])) {
      if (a[i] != b[j]) return a[i] < b[j];
      ++i;
      ++j;
      continue;
    }
    size_t end_a = i, end_b = j;
    while (end_a < a.size() && IsDigit(a[end_a])) ++end_a;
    while (end_b < b.size() && IsDigit(b[end_b])) ++end_b;
    // By value: without leading zeros (keeping one digit), a longer run is larger.
    size_t start_a = i, start_b = j;
    while (start_a + 1 < end_a && a[start_a] == '0') ++start_a;
    while (start_b + 1 < end_b && b[start_b] == '0') ++start_b;
    const std::string_view value_a = a.substr(start_a, end_a - start_a);
    const std::string_view value_b = b.substr(start_b, end_b - start_b);
    if (value_a.size() != value_b.size()) return value_a.size() < value_b.size();
    if (value_a != value_b) return value_a < value_b;
    // Same value: fewer leading zeros first, so that only equal names are equivalent.
    if (end_a - i != end_b - j) return end_a - i < end_b - j;
    i = end_a;
    j = end_b;
  }
  return a.size() - i < b.size() - j;
}

Result<std::vector<std::string>> ListImageFiles(const std::string& directory) {
  std::error_code ec;
  if (!fs::is_directory(directory, ec)) return Status::NotFound(directory + ": not a directory");
  std::vector<fs::path> images;
  for (fs::directory_iterator it(directory, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code type_ec;
    if (it->is_regular_file(type_ec) && IsImageFile(it->path())) images.push_back(it->path());
  }
  if (ec) return Status::IoError("cannot list " + directory + ": " + ec.message());
  std::sort(images.begin(), images.end(), [](const fs::path& x, const fs::path& y) {
    return NaturalLess(x.filename().string(), y.filename().string());
  });
  std::vector<std::string> paths;
  paths.reserve(images.size());
  for (const fs::path& image : images) paths.push_back(image.string());
  return paths;
}

}  // namespace placedb
