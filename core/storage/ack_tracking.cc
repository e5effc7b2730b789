// Acknowledging a map's writes (ack_tracking.h): the WAL group sync (GroupCommitter) and the
// ACKED file (its two checksummed slots, reading it, creating it, AckTracker).
#include "core/storage/ack_tracking.h"

#include <fcntl.h>
#include <rocksdb/db.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <optional>

namespace fs = std::filesystem;

namespace placedb::detail {

GroupCommitter::GroupCommitter(rocksdb::DB* db, std::chrono::milliseconds delay)
    : db_(db), delay_(delay), thread_([this] { Run(); }) {}

GroupCommitter::~GroupCommitter() {
  {
    MutexLock lock(mutex_);
    stopping_ = true;
  }
  wake_syncer_.NotifyAll();
  thread_.join();
}

rocksdb::Status GroupCommitter::WaitDurable() {
  MutexLock lock(mutex_);
  const uint64_t ticket = ++requested_;
  wake_syncer_.NotifyOne();
  while (synced_ < ticket) synced_cv_.Wait(mutex_);
  return last_status_;
}

void GroupCommitter::Run() {
  MutexLock lock(mutex_);
  while (true) {
    while (!stopping_ && requested_ <= synced_) wake_syncer_.Wait(mutex_);
    if (requested_ == synced_ && stopping_) return;
    if (!stopping_) {
      // Let more writers join this sync, bounded by the configured delay.
      const auto deadline = std::chrono::steady_clock::now() + delay_;
      while (!stopping_ && wake_syncer_.WaitUntil(mutex_, deadline)) {
      }
    }
    const uint64_t target = requested_;
    lock.Unlock();
    const rocksdb::Status synced = db_->SyncWAL();
    lock.Lock();
    last_status_ = synced;
    synced_ = target;
    synced_cv_.NotifyAll();
  }
}

namespace {

// The layout of ACKED (AckState, ack_tracking.h).
constexpr char kAckMagic[8] = {'P', 'D', 'B', 'A', 'C', 'K', '0', '1'};
constexpr size_t kAckSlotBytes = 40;
constexpr off_t kAckSlotOffset[2] = {0, 512};
constexpr size_t kAckFileBytes = 1024;

uint64_t Fnv1a(const unsigned char* data, size_t size) {
  uint64_t hash = 0xcbf29ce484222325ull;
  for (size_t i = 0; i < size; ++i) hash = (hash ^ data[i]) * 0x100000001b3ull;
  return hash;
}

void PutLe64(unsigned char* out, uint64_t v) {
  for (int i = 0; i < 8; ++i) out[i] = static_cast<unsigned char>(v >> (8 * i));
}

uint64_t GetLe64(const unsigned char* in) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | in[i];
  return v;
}

std::string Errno(const std::string& what) {
  return what + ": " + std::strerror(errno);
}

Status WriteAckSlot(int fd, const AckState& state) {
  unsigned char slot[kAckSlotBytes];
  std::memcpy(slot, kAckMagic, 8);
  PutLe64(slot + 8, state.generation);
  PutLe64(slot + 16, state.writes);
  PutLe64(slot + 24, state.max_place);
  PutLe64(slot + 32, Fnv1a(slot, 32));
  const off_t offset = kAckSlotOffset[state.generation % 2];
  // A full disk is RESOURCE_EXHAUSTED, as for RocksDB's own writes (FromRocks).
  auto failed = [](const std::string& what) {
    const std::string message = Errno(what);
    return errno == ENOSPC || errno == EDQUOT ? Status::ResourceExhausted(message)
                                              : Status::IoError(message);
  };
  if (pwrite(fd, slot, sizeof slot, offset) != ssize_t(sizeof slot)) {
    return failed("writing ACKED");
  }
  if (fdatasync(fd) != 0) return failed("syncing ACKED");
  return Status::Ok();
}

}  // namespace

Result<AckState> ReadAcked(const std::string& file) {
  const int fd = open(file.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return Status::NotFound("ACKED is missing");
    return Status::IoError(Errno("opening ACKED"));
  }
  unsigned char bytes[kAckFileBytes] = {};
  const ssize_t n = pread(fd, bytes, sizeof bytes, 0);
  close(fd);
  if (n < 0) return Status::IoError(Errno("reading ACKED"));
  std::optional<AckState> best;
  for (off_t offset : kAckSlotOffset) {
    if (n < offset + ssize_t(kAckSlotBytes)) continue;
    const unsigned char* slot = bytes + offset;
    if (std::memcmp(slot, kAckMagic, 8) != 0 || GetLe64(slot + 32) != Fnv1a(slot, 32)) continue;
    AckState state{GetLe64(slot + 8), GetLe64(slot + 16), GetLe64(slot + 24)};
    if (!best || state.generation > best->generation) best = state;
  }
  if (!best) {
    return Status::Corruption("ACKED is damaged: " + std::to_string(n) +
                              " bytes, no record passes its checksum");
  }
  return *best;
}

namespace {

Status SyncDirectory(const std::string& directory) {
  const int fd = open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) return Status::IoError(Errno("opening " + directory));
  const int synced = fsync(fd);
  close(fd);
  if (synced != 0) return Status::IoError(Errno("syncing " + directory));
  return Status::Ok();
}

}  // namespace

Status CreateAcked(const std::string& map_path, AckState state) {
  const std::string file = (fs::path(map_path) / kAckedFile).string();
  const std::string staging = file + ".tmp";
  const int fd = open(staging.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return Status::IoError(Errno("creating ACKED"));
  Status written;
  // Full size up front: later slot writes never change the size, so fdatasync stays cheap.
  if (ftruncate(fd, off_t(kAckFileBytes)) != 0) written = Status::IoError(Errno("sizing ACKED"));
  for (int i = 0; i < 2 && written.ok(); ++i, ++state.generation) {
    written = WriteAckSlot(fd, state);
  }
  close(fd);
  if (written.ok() && rename(staging.c_str(), file.c_str()) != 0) {
    written = Status::IoError(Errno("installing ACKED"));
  }
  if (written.ok()) written = SyncDirectory(map_path);
  return written;
}

Result<std::unique_ptr<AckTracker>> AckTracker::Open(const std::string& map_path, AckState state) {
  const std::string file = (fs::path(map_path) / kAckedFile).string();
  const int fd = open(file.c_str(), O_WRONLY | O_CLOEXEC);
  if (fd < 0) return Status::IoError(Errno("opening ACKED for writing"));
  return std::unique_ptr<AckTracker>(new AckTracker(fd, state));
}

AckTracker::~AckTracker() {
  close(fd_);
}

Status AckTracker::Raise(const AckState& state) {
  MutexLock lock(mutex_);
  while (syncing_) synced_cv_.Wait(mutex_);
  pending_.writes = std::max(pending_.writes, state.writes);
  pending_.max_place = std::max(pending_.max_place, state.max_place);
  AckState next = pending_;
  next.generation = ++generation_;
  return WriteAckSlot(fd_, next);
}

Status AckTracker::Acknowledge(PlaceId place, uint64_t writes) {
  MutexLock lock(mutex_);
  pending_.writes += writes;
  pending_.max_place = std::max<uint64_t>(pending_.max_place, place);
  const uint64_t ticket = ++requested_;
  while (durable_ < ticket) {
    if (syncing_) {
      synced_cv_.Wait(mutex_);
      continue;
    }
    syncing_ = true;
    const uint64_t target = requested_;
    AckState next = pending_;
    next.generation = ++generation_;
    lock.Unlock();
    const Status written = WriteAckSlot(fd_, next);
    lock.Lock();
    syncing_ = false;
    last_status_ = written;
    durable_ = target;
    synced_cv_.NotifyAll();
  }
  return last_status_;
}

}  // namespace placedb::detail
