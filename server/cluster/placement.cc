#include "server/cluster/placement.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <nlohmann/json.hpp>

namespace placedb::cluster {

ClusterKeys::ClusterKeys(std::string cluster_name)
    : root("/placedb/" + std::move(cluster_name) + "/") {}

std::string HexOf(const std::string& bytes) {
  static const char* kDigits = "0123456789ABCDEF";
  std::string out;
  out.reserve(bytes.size() * 2);
  for (const unsigned char c : bytes) {
    out.push_back(kDigits[c >> 4]);
    out.push_back(kDigits[c & 15]);
  }
  return out;
}

namespace {

std::string Upper(std::string text) {
  for (char& c : text) c = char(std::toupper(static_cast<unsigned char>(c)));
  return text;
}

}  // namespace

std::string StreamName(const std::string& cluster_name, const std::string& map) {
  return "PLACEDB_" + Upper(cluster_name) + "_" + HexOf(map);
}

std::string StreamSubject(const std::string& cluster_name, const std::string& map) {
  return "placedb." + cluster_name + ".map." + HexOf(map);
}

std::string SnapshotStreamName(const std::string& cluster_name) {
  return "PLACEDB_" + Upper(cluster_name) + "_SNAPSHOTS";
}

std::string SnapshotSubject(const std::string& cluster_name, const std::string& id) {
  return "placedb." + cluster_name + ".snapshots." + HexOf(id);
}

std::string EncodePlacement(const Placement& placement) {
  nlohmann::json json;
  json["epoch"] = placement.epoch;
  json["replicas"] = placement.replicas;
  return json.dump();
}

Result<Placement> DecodePlacement(const std::string& text) {
  try {
    const nlohmann::json json = nlohmann::json::parse(text);
    Placement out;
    out.epoch = json.at("epoch").get<int64_t>();
    out.replicas = json.at("replicas").get<std::vector<std::string>>();
    return out;
  } catch (const std::exception& e) {
    return Status::InvalidArgument(std::string("placement is not valid JSON: ") + e.what());
  }
}

std::string EncodeMapInfo(const MapRecordInfo& info) {
  nlohmann::json json;
  json["config"] = nlohmann::json::parse(info.config_json.empty() ? "{}" : info.config_json);
  json["stream"] = info.stream;
  json["created_unix_ms"] = info.created_unix_ms;
  if (!info.snapshot.empty()) {
    json["snapshot"] = info.snapshot;
    json["snapshot_base"] = info.snapshot_base;
  }
  return json.dump();
}

Result<MapRecordInfo> DecodeMapInfo(const std::string& text) {
  try {
    const nlohmann::json json = nlohmann::json::parse(text);
    MapRecordInfo out;
    out.config_json = json.at("config").dump();
    out.stream = json.at("stream").get<std::string>();
    out.created_unix_ms = json.value("created_unix_ms", int64_t(0));
    out.snapshot = json.value("snapshot", std::string());
    out.snapshot_base = json.value("snapshot_base", uint64_t(0));
    return out;
  } catch (const std::exception& e) {
    return Status::InvalidArgument(std::string("map record is not valid JSON: ") + e.what());
  }
}

// ---- ClusterView --------------------------------------------------------------------------------

ClusterView::ClusterView(EtcdClient* etcd, std::string cluster_name)
    : etcd_(etcd), keys_(std::move(cluster_name)) {}

Result<std::unique_ptr<ClusterView>> ClusterView::Start(EtcdClient* etcd,
                                                        std::string cluster_name) {
  std::unique_ptr<ClusterView> view(new ClusterView(etcd, std::move(cluster_name)));
  PLACEDB_RETURN_IF_ERROR(view->Load());
  view->restart_ = std::thread([raw = view.get()] { raw->RestartLoop(); });
  return view;
}

ClusterView::~ClusterView() {
  Stop();
}

void ClusterView::Stop() {
  {
    MutexLock lock(mutex_);
    if (stopping_) return;
    stopping_ = true;
    changed_.NotifyAll();
  }
  if (restart_.joinable()) restart_.join();
  if (watcher_) watcher_->Stop();
}

Status ClusterView::Load() {
  auto read = etcd_->Get(keys_.root, /*prefix=*/true);
  if (!read.ok()) return read.status().WithContext("reading the cluster's keys");
  {
    MutexLock lock(mutex_);
    maps_.clear();
    shards_.clear();
    placements_.clear();
    applied_.clear();
    for (const KeyValue& kv : read->kvs) Apply(kv, false);
    changed_.NotifyAll();
  }
  if (watcher_) watcher_->Stop();
  watcher_ = etcd_->Watch(
      keys_.root, read->revision + 1,
      [this](const std::vector<WatchEvent>& events) {
        MutexLock lock(mutex_);
        for (const WatchEvent& event : events) {
          Apply(event.kv, event.type == WatchEvent::Type::kDelete);
        }
        changed_.NotifyAll();
      },
      [this](const Status& why) { OnEnd(why); });
  return Status::Ok();
}

void ClusterView::OnEnd(const Status& why) {
  spdlog::warn("cluster view: the etcd watch ended ({}); reading the keys again", why.ToString());
  MutexLock lock(mutex_);
  restart_wanted_ = true;
  changed_.NotifyAll();
}

void ClusterView::RestartLoop() {
  MutexLock lock(mutex_);
  while (!stopping_) {
    if (!restart_wanted_) {
      changed_.Wait(mutex_);
      continue;
    }
    restart_wanted_ = false;
    lock.Unlock();
    Status loaded = Load();
    lock.Lock();
    if (!loaded.ok()) {
      spdlog::warn("cluster view: {}; retrying", loaded.ToString());
      restart_wanted_ = true;
      changed_.WaitFor(mutex_, std::chrono::seconds(1));
    }
  }
}

void ClusterView::Apply(const KeyValue& kv, bool deleted) {
  if (kv.key.rfind(keys_.root, 0) != 0) return;
  const std::string rest = kv.key.substr(keys_.root.size());
  auto after = [&](const std::string& prefix) -> std::optional<std::string> {
    if (rest.rfind(prefix, 0) != 0) return std::nullopt;
    return rest.substr(prefix.size());
  };
  if (auto id = after("shards/")) {
    if (deleted) {
      shards_.erase(*id);
      return;
    }
    try {
      shards_[*id] = nlohmann::json::parse(kv.value).at("address").get<std::string>();
    } catch (const std::exception& e) {
      spdlog::warn("cluster view: {} is not {{\"address\": ...}}: {}", kv.key, e.what());
    }
    return;
  }
  if (auto map = after("maps/")) {
    if (deleted) {
      maps_.erase(*map);
      return;
    }
    auto info = DecodeMapInfo(kv.value);
    if (!info.ok()) {
      spdlog::warn("cluster view: {}: {}", kv.key, info.status().ToString());
      return;
    }
    MapView& view = maps_[*map];
    view.info = std::move(info).value();
    view.create_revision = kv.create_revision;
    if (auto it = placements_.find(*map); it != placements_.end()) view.placement = it->second;
    if (auto it = applied_.find(*map); it != applied_.end()) view.applied = it->second;
    return;
  }
  if (auto map = after("placement/")) {
    std::optional<Placement> placement;
    if (!deleted) {
      auto decoded = DecodePlacement(kv.value);
      if (!decoded.ok()) {
        spdlog::warn("cluster view: {}: {}", kv.key, decoded.status().ToString());
        return;
      }
      decoded->mod_revision = kv.mod_revision;
      placement = std::move(decoded).value();
    }
    if (placement) {
      placements_[*map] = *placement;
    } else {
      placements_.erase(*map);
    }
    if (auto it = maps_.find(*map); it != maps_.end()) it->second.placement = placement;
    return;
  }
  if (auto tail = after("applied/")) {
    // applied/<map>/<shard>: the map name may hold '/', the shard id may not.
    const auto slash = tail->rfind('/');
    if (slash == std::string::npos) return;
    const std::string map = tail->substr(0, slash), shard = tail->substr(slash + 1);
    if (deleted) {
      applied_[map].erase(shard);
      if (auto it = maps_.find(map); it != maps_.end()) it->second.applied.erase(shard);
      return;
    }
    uint64_t sequence = 0;
    try {
      sequence = std::stoull(kv.value);
    } catch (const std::exception&) {
      return;
    }
    applied_[map][shard] = sequence;
    if (auto it = maps_.find(map); it != maps_.end()) it->second.applied[shard] = sequence;
  }
}

std::optional<MapView> ClusterView::Map(const std::string& map) const {
  MutexLock lock(mutex_);
  auto it = maps_.find(map);
  if (it == maps_.end()) return std::nullopt;
  return it->second;
}

std::map<std::string, MapView> ClusterView::Maps() const {
  MutexLock lock(mutex_);
  return maps_;
}

std::map<std::string, std::string> ClusterView::Shards() const {
  MutexLock lock(mutex_);
  return shards_;
}

bool ClusterView::WaitFor(const std::string& map,
                          const std::function<bool(const std::optional<MapView>&)>& ready,
                          std::chrono::steady_clock::time_point deadline) {
  MutexLock lock(mutex_);
  while (true) {
    auto it = maps_.find(map);
    const std::optional<MapView> view =
        it == maps_.end() ? std::nullopt : std::optional<MapView>(it->second);
    if (ready(view)) return true;
    if (stopping_ || !changed_.WaitUntil(mutex_, deadline)) {
      it = maps_.find(map);
      return ready(it == maps_.end() ? std::nullopt : std::optional<MapView>(it->second));
    }
  }
}

// ---- Coordinator --------------------------------------------------------------------------------

Coordinator::Coordinator(EtcdClient* etcd, ClusterView* view, CoordinatorOptions options)
    : etcd_(etcd), view_(view), options_(std::move(options)), thread_([this] { Run(); }) {}

Coordinator::~Coordinator() {
  Stop();
}

void Coordinator::Stop() {
  {
    MutexLock lock(mutex_);
    if (stopping_) return;
    stopping_ = true;
    wake_.NotifyAll();
  }
  thread_.join();
  if (keeper_) keeper_->Stop();
  // Another worker takes over at once instead of after the TTL.
  if (lease_ != 0) (void)etcd_->RevokeLease(lease_);
  leading_ = false;
}

void Coordinator::Run() {
  MutexLock lock(mutex_);
  while (!stopping_) {
    lock.Unlock();
    Campaign();
    if (leading_) Place();
    lock.Lock();
    if (!stopping_) wake_.WaitFor(mutex_, options_.period);
  }
}

void Coordinator::Campaign() {
  if (keeper_ && keeper_->lost()) {
    spdlog::warn("coordinator {}: lease lost, campaigning again", options_.self);
    keeper_->Stop();
    keeper_.reset();
    lease_ = 0;
    leading_ = false;
  }
  if (lease_ == 0) {
    auto lease = etcd_->GrantLease(options_.lease_ttl_s);
    if (!lease.ok()) return;  // etcd unreachable: not leading; next round
    lease_ = lease->id;
    keeper_ = etcd_->KeepAlive(*lease, [](const Status&) {});
  }
  const std::string key = view_->keys().Coordinator();
  auto txn = etcd_->Txn({Compare::Absent(key)}, {TxnOp::Put(key, options_.self, lease_)},
                        {TxnOp::Get(key)});
  if (!txn.ok()) return;
  bool held = txn->succeeded;
  if (!held && !txn->gets.empty() && !txn->gets[0].kvs.empty()) {
    held = txn->gets[0].kvs[0].lease == lease_;
  }
  if (held != leading_.load()) {
    spdlog::info("coordinator {}: {}", options_.self, held ? "elected" : "not the coordinator");
    if (held) missing_since_.clear();  // grace timers start with this term
  }
  leading_ = held;
}

bool Coordinator::Write(const std::string& map, const std::optional<Placement>& previous,
                        const Placement& next) {
  const ClusterKeys& keys = view_->keys();
  const std::string key = keys.Placement(map);
  std::vector<Compare> compares = {
      Compare::ValueIs(keys.Coordinator(), options_.self),
      // the map still exists (DeleteMap removes both)
      Compare{keys.Map(map), Compare::Target::kCreateRevision, Compare::Op::kGreater, 0, {}}};
  compares.push_back(previous ? Compare::ModRevisionIs(key, previous->mod_revision)
                              : Compare::Absent(key));
  auto txn = etcd_->Txn(compares, {TxnOp::Put(key, EncodePlacement(next))});
  if (!txn.ok() || !txn->succeeded) return false;
  ++written_;
  std::string replicas;
  for (const std::string& r : next.replicas) replicas += (replicas.empty() ? "" : ",") + r;
  spdlog::info("coordinator {}: map '{}' placed on [{}] epoch {}", options_.self, map, replicas,
               next.epoch);
  return true;
}

void Coordinator::Place() {
  const auto now = std::chrono::steady_clock::now();
  const std::map<std::string, std::string> live = view_->Shards();
  const std::map<std::string, MapView> maps = view_->Maps();
  std::map<std::string, int> load;
  for (const auto& [id, address] : live) load[id] = 0;
  for (const auto& [name, view] : maps) {
    if (!view.placement) continue;
    for (const std::string& shard : view.placement->replicas) {
      if (live.count(shard)) ++load[shard];
      if (!live.count(shard)) missing_since_.emplace(shard, now);  // first seen missing
    }
  }
  for (auto it = missing_since_.begin(); it != missing_since_.end();) {
    it = live.count(it->first) ? missing_since_.erase(it) : std::next(it);
  }
  // The least loaded live shard not in `taken` (ties: by id, so every run agrees).
  auto pick = [&](const std::vector<std::string>& taken) -> std::optional<std::string> {
    std::optional<std::string> best;
    for (const auto& [id, count] : load) {
      if (std::find(taken.begin(), taken.end(), id) != taken.end()) continue;
      if (!best || count < load[*best]) best = id;
    }
    return best;
  };
  for (const auto& [name, view] : maps) {
    Placement next;
    if (!view.placement) {
      while (int(next.replicas.size()) < options_.replicas) {
        auto shard = pick(next.replicas);
        if (!shard) break;
        next.replicas.push_back(*shard);
        ++load[*shard];
      }
      if (next.replicas.empty()) continue;  // no live shard yet
      next.epoch = 1;
      (void)Write(name, std::nullopt, next);
      continue;
    }
    next = *view.placement;
    bool changed = false;
    for (std::string& shard : next.replicas) {
      if (live.count(shard)) continue;
      auto since = missing_since_.find(shard);
      if (since == missing_since_.end() || now - since->second < options_.replace_after) continue;
      auto replacement = pick(next.replicas);
      if (!replacement) continue;
      spdlog::warn("coordinator {}: map '{}': shard '{}' gone for {} s, replaced by '{}'",
                   options_.self, name, shard,
                   std::chrono::duration_cast<std::chrono::seconds>(now - since->second).count(),
                   *replacement);
      ++load[*replacement];
      shard = *replacement;
      changed = true;
    }
    // Too few replicas (fewer live shards when the map was placed): top up.
    while (int(next.replicas.size()) < options_.replicas) {
      auto shard = pick(next.replicas);
      if (!shard) break;
      next.replicas.push_back(*shard);
      ++load[*shard];
      changed = true;
    }
    if (!changed) continue;
    ++next.epoch;
    (void)Write(name, view.placement, next);
  }
}

}  // namespace placedb::cluster
