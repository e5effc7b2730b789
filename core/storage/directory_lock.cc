#include "core/storage/directory_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>

namespace placedb {

Result<DirectoryLock> DirectoryLock::Acquire(const std::string& directory) {
  const std::string path = (std::filesystem::path(directory) / kFileName).string();
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) {
    return Status::IoError("cannot open the lock file " + path + ": " + std::strerror(errno));
  }
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int error = errno;
    std::string holder;
    char text[32] = {};
    if (::pread(fd, text, sizeof(text) - 1, 0) > 0) holder = text;
    while (!holder.empty() && (holder.back() == '\n' || holder.back() == ' ')) holder.pop_back();
    ::close(fd);
    if (error == EWOULDBLOCK) {
      // The caller names the directory (DataDirectory::Open's callers add it as context).
      return Status::FailedPrecondition("in use by another placedb process" +
                                        (holder.empty() ? std::string() : " (pid " + holder + ")") +
                                        "; stop it, or give this one its own data directory");
    }
    return Status::IoError("cannot lock " + path + ": " + std::strerror(error));
  }
  // The pid is only for the message above: the lock itself is the flock.
  const std::string pid = std::to_string(::getpid()) + "\n";
  if (::ftruncate(fd, 0) != 0 ||
      ::pwrite(fd, pid.data(), pid.size(), 0) != static_cast<ssize_t>(pid.size())) {
    const int error = errno;
    ::close(fd);
    return Status::IoError("cannot write the lock file " + path + ": " + std::strerror(error));
  }
  return DirectoryLock(fd);
}

DirectoryLock& DirectoryLock::operator=(DirectoryLock&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = other.fd_;
    other.fd_ = -1;
  }
  return *this;
}

DirectoryLock::~DirectoryLock() {
  if (fd_ >= 0) ::close(fd_);  // closing the last descriptor releases the flock
}

}  // namespace placedb
