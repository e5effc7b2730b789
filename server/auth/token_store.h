// The server's current tokens file, reloaded on request (SIGHUP, Server::ReloadTokens) and when
// the file changes (docs/security.md, "Reload").
//
//   auto store = TokenStore::Open(path, on_reload);   // the first load must succeed
//   store->StartWatching(std::chrono::seconds(1));
//   std::shared_ptr<const TokensFile> tokens = store->snapshot();   // any thread, any time
//
// A snapshot is immutable; a reload swaps in a new one and advances generation(), so a holder of
// an old snapshot (an open Ingest stream) knows to resolve its caller again. A file that fails
// to load keeps the previous snapshot (and generation) and is logged as an error.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <chrono>
#include <ctime>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "core/base/status.h"
#include "core/base/thread_annotations.h"
#include "server/auth/tokens.h"

namespace placedb::server::auth {

class TokenStore {
 public:
  // Called after every reload attempt (not the first load): true = loaded, false = kept the
  // previous snapshot. The server counts placedb_tokens_reloads_total{result} with it.
  using ReloadCallback = std::function<void(bool ok)>;

  // Loads `path`; its errors (TokensFile::Load) are returned as they are.
  static Result<std::unique_ptr<TokenStore>> Open(const std::string& path,
                                                  ReloadCallback on_reload = {});
  ~TokenStore();  // stops the watcher

  const std::string& path() const { return path_; }
  std::shared_ptr<const TokensFile> snapshot() const EXCLUDES(mutex_);
  // Advances by one on each successful reload (after the new snapshot is in place). Lock-free:
  // an open Ingest stream asks at every message.
  uint64_t generation() const { return generation_.load(std::memory_order_acquire); }

  // Loads the file again. On success the new snapshot is current; on failure the previous one
  // stays and the error is returned (and logged).
  Status Reload() EXCLUDES(mutex_);

  // Starts a thread that checks the file (stat, following symlinks: mtime, size, inode) every
  // `interval` and reloads it when one of them changed and then stayed the same for one more
  // check (so within about two intervals). Idempotent.
  void StartWatching(std::chrono::milliseconds interval) EXCLUDES(watch_mutex_);
  void StopWatching() EXCLUDES(watch_mutex_);

 private:
  struct FileStamp {
    bool exists = false;
    ino_t inode = 0;
    off_t size = 0;
    timespec mtime{};
    bool operator==(const FileStamp& o) const {
      return exists == o.exists && inode == o.inode && size == o.size &&
             mtime.tv_sec == o.mtime.tv_sec && mtime.tv_nsec == o.mtime.tv_nsec;
    }
  };
  TokenStore(std::string path, ReloadCallback on_reload);
  FileStamp Stamp() const;
  void Watch(std::chrono::milliseconds interval) EXCLUDES(watch_mutex_);

  const std::string path_;
  const ReloadCallback on_reload_;

  mutable Mutex mutex_;
  std::shared_ptr<const TokensFile> current_ GUARDED_BY(mutex_);
  std::atomic<uint64_t> generation_{0};  // written under mutex_

  Mutex reload_mutex_;  // one reload at a time (SIGHUP and the watcher may race)
  FileStamp loaded_stamp_ GUARDED_BY(reload_mutex_);  // what the last attempt read

  Mutex watch_mutex_;
  CondVar watch_wake_;
  bool watching_ GUARDED_BY(watch_mutex_) = false;
  bool stop_ GUARDED_BY(watch_mutex_) = false;
  std::thread watcher_;
};

}  // namespace placedb::server::auth
