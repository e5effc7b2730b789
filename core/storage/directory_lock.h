// An exclusive, advisory lock on a data directory, so that two processes never serve (and
// write) the same maps.
//
// The lock is flock(2) on the directory's LOCK file, which also records the holder's pid for
// the message a second process gets. The kernel releases it when the holder exits, however it
// exits (SIGKILL included), so a crash never leaves a stale lock behind. Locks belong to open
// file descriptions: a second Acquire() on the same directory fails even in the same process.
#pragma once

#include <string>

#include "core/base/status.h"

namespace placedb {

class DirectoryLock {
 public:
  static constexpr char kFileName[] = "LOCK";

  // Takes the lock on `directory` (which must exist) without waiting. FAILED_PRECONDITION
  // naming the holder's pid when another process (or another DirectoryLock) holds it; IO_ERROR
  // when the lock file cannot be opened. Nothing is changed on failure.
  static Result<DirectoryLock> Acquire(const std::string& directory);

  DirectoryLock(DirectoryLock&& other) noexcept : fd_(other.fd_) { other.fd_ = -1; }
  DirectoryLock& operator=(DirectoryLock&& other) noexcept;
  DirectoryLock(const DirectoryLock&) = delete;
  DirectoryLock& operator=(const DirectoryLock&) = delete;
  ~DirectoryLock();  // releases the lock

 private:
  explicit DirectoryLock(int fd) : fd_(fd) {}
  int fd_ = -1;
};

}  // namespace placedb
