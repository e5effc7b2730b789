#include "server/auth/token_store.h"

#include <spdlog/spdlog.h>
#include <sys/stat.h>

namespace placedb::server::auth {

TokenStore::TokenStore(std::string path, ReloadCallback on_reload)
    : path_(std::move(path)), on_reload_(std::move(on_reload)) {}

TokenStore::~TokenStore() {
  StopWatching();
}

Result<std::unique_ptr<TokenStore>> TokenStore::Open(const std::string& path,
                                                     ReloadCallback on_reload) {
  std::unique_ptr<TokenStore> store(new TokenStore(path, std::move(on_reload)));
  MutexLock reload(store->reload_mutex_);
  // Stamped before reading: a change during the read is seen by the next check.
  store->loaded_stamp_ = store->Stamp();
  auto file = TokensFile::Load(path);
  if (!file.ok()) return file.status().WithContext("tokens file");
  MutexLock lock(store->mutex_);
  store->current_ = std::make_shared<const TokensFile>(std::move(file).value());
  return store;
}

std::shared_ptr<const TokensFile> TokenStore::snapshot() const {
  MutexLock lock(mutex_);
  return current_;
}

TokenStore::FileStamp TokenStore::Stamp() const {
  struct stat st {};
  FileStamp stamp;
  if (::stat(path_.c_str(), &st) != 0) return stamp;  // stat follows symlinks (k8s Secrets)
  stamp.exists = true;
  stamp.inode = st.st_ino;
  stamp.size = st.st_size;
  stamp.mtime = st.st_mtim;
  return stamp;
}

Status TokenStore::Reload() {
  MutexLock reload(reload_mutex_);
  loaded_stamp_ = Stamp();
  auto file = TokensFile::Load(path_);
  if (!file.ok()) {
    spdlog::error("tokens file {}: reload failed, keeping the previous principals: {}", path_,
                  file.status().ToString());
    if (on_reload_) on_reload_(false);
    return file.status();
  }
  const size_t principals = file->principals().size();
  uint64_t generation = 0;
  {
    MutexLock lock(mutex_);
    current_ = std::make_shared<const TokensFile>(std::move(file).value());
    generation = generation_.fetch_add(1, std::memory_order_acq_rel) + 1;
  }
  spdlog::info("tokens file {}: reloaded, {} principals (generation {})", path_, principals,
               generation);
  if (on_reload_) on_reload_(true);
  return Status::Ok();
}

void TokenStore::StartWatching(std::chrono::milliseconds interval) {
  MutexLock lock(watch_mutex_);
  if (watching_) return;
  watching_ = true;
  stop_ = false;
  watcher_ = std::thread([this, interval] { Watch(interval); });
}

void TokenStore::StopWatching() {
  {
    MutexLock lock(watch_mutex_);
    if (!watching_) return;
    stop_ = true;
    watch_wake_.NotifyAll();
  }
  watcher_.join();
  MutexLock lock(watch_mutex_);
  watching_ = false;
}

void TokenStore::Watch(std::chrono::milliseconds interval) {
  // A change is loaded once the file looked the same on two checks in a row: an editor writing
  // in place is not caught half-way (an empty file is a valid one: nobody may call).
  FileStamp pending;  // exists == false: none
  while (true) {
    {
      MutexLock lock(watch_mutex_);
      const auto until = std::chrono::steady_clock::now() + interval;
      while (!stop_ && watch_wake_.WaitUntil(watch_mutex_, until)) {
      }
      if (stop_) return;
    }
    const FileStamp now = Stamp();
    bool changed = false;
    {
      MutexLock reload(reload_mutex_);
      changed = !(now == loaded_stamp_);
    }
    // A file that vanished (mid-swap, or deleted) is not loaded: the next stamp decides.
    if (!changed || !now.exists) {
      pending = FileStamp();
    } else if (pending == now) {
      pending = FileStamp();
      (void)Reload();
    } else {
      pending = now;
    }
  }
}

}  // namespace placedb::server::auth
