#include "core/storage/loop_log.h"

#include <rocksdb/db.h>
#include <rocksdb/write_batch.h>

#include <algorithm>
#include <nlohmann/json.hpp>

#include "core/storage/map_storage.h"

namespace placedb {

namespace {

using Json = nlohmann::json;

std::string SequenceKey(uint64_t sequence) {
  std::string key(8, '\0');
  for (int i = 7; i >= 0; --i, sequence >>= 8) key[size_t(i)] = char(sequence & 0xff);
  return key;
}

std::optional<uint64_t> SequenceOfKey(const rocksdb::Slice& key) {
  if (key.size() != 8) return std::nullopt;
  uint64_t sequence = 0;
  for (size_t i = 0; i < 8; ++i) sequence = (sequence << 8) | uint8_t(key[i]);
  return sequence;
}

int64_t NowUnixNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// The last sequence `family` holds (0: none); CORRUPTION for a key that is not a sequence.
Result<uint64_t> LastSequenceIn(rocksdb::DB* db, rocksdb::ColumnFamilyHandle* family) {
  std::unique_ptr<rocksdb::Iterator> it(db->NewIterator(rocksdb::ReadOptions(), family));
  it->SeekToLast();
  uint64_t last = 0;
  if (it->Valid()) {
    auto sequence = SequenceOfKey(it->key());
    if (!sequence) {
      return Status::Corruption("the loop log holds a key that is not a sequence (" +
                                std::to_string(it->key().size()) + " bytes)");
    }
    last = *sequence;
  }
  PLACEDB_RETURN_IF_ERROR(detail::FromRocks(it->status(), "reading the loop log"));
  return last;
}

Json MetadataJson(const PlaceMetadata& metadata) {
  Json j = {{"agent", metadata.agent_id},
            {"sequence", metadata.sequence},
            {"t_ns", metadata.timestamp_ns}};
  if (metadata.pose) {
    j["position"] = metadata.pose->position;
    j["orientation"] = metadata.pose->orientation;
  }
  return j;
}

PlaceMetadata MetadataOf(const Json& j) {
  PlaceMetadata metadata;
  metadata.agent_id = j.at("agent").get<std::string>();
  metadata.sequence = j.at("sequence").get<uint64_t>();
  metadata.timestamp_ns = j.at("t_ns").get<int64_t>();
  if (j.contains("position")) {
    Pose pose;
    pose.position = j.at("position").get<std::array<double, 3>>();
    pose.orientation = j.at("orientation").get<std::array<double, 4>>();
    metadata.pose = pose;
  }
  return metadata;
}

}  // namespace

const char* LoopSourceName(LoopSource source) {
  return source == LoopSource::kLoopClosure ? "loop_closure" : "match";
}

bool LoopFilter::Accepts(const LoopConstraint& constraint) const {
  const bool inter = constraint.inter_agent();
  if (inter_agent_only && !inter) return false;
  if (!inter && min_sequence_gap > 0) {
    const uint64_t a = constraint.query.sequence, b = constraint.place_metadata.sequence;
    if ((a > b ? a - b : b - a) < min_sequence_gap) return false;
  }
  if (agents.empty()) return true;
  auto listed = [&](const std::string& agent) {
    return std::find(agents.begin(), agents.end(), agent) != agents.end();
  };
  return listed(constraint.query.agent_id) || listed(constraint.place_metadata.agent_id);
}

std::vector<LoopConstraint> LoopConstraintsOf(const PlaceMetadata& frame,
                                              const std::vector<Match>& matches) {
  const int64_t now = NowUnixNs();
  std::vector<LoopConstraint> found;
  for (const Match& match : matches) {
    if (!match.verified) continue;
    LoopConstraint& c = found.emplace_back();
    c.source = LoopSource::kMatch;
    c.query = frame;
    c.place = match.place;
    c.place_metadata = match.metadata;
    c.score = match.score;
    c.inliers = match.inliers;
    c.pose = match.relative_pose;
    if (c.pose) c.pose->inlier_indices.clear();
    c.pose_unavailable = match.pose_unavailable;
    c.found_unix_ns = now;
  }
  return found;
}

void AddDetectorLoop(const LoopClosureOutcome& outcome, const PlaceMetadata& frame,
                     std::vector<LoopConstraint>* found) {
  if (outcome.loop) {
    std::erase_if(*found, [&](const LoopConstraint& c) { return c.place == *outcome.loop; });
    LoopConstraint& loop = found->emplace_back();
    loop.source = LoopSource::kLoopClosure;
    loop.query = frame;
    loop.place = *outcome.loop;
    loop.score = outcome.loop_posterior;
    loop.inliers = outcome.loop_inliers;
    loop.pose = outcome.loop_pose;
    if (loop.pose) loop.pose->inlier_indices.clear();
    loop.pose_unavailable = outcome.loop_pose_unavailable;
    loop.found_unix_ns = NowUnixNs();
  }
  for (LoopConstraint& constraint : *found) constraint.merged = outcome.merged;
}

std::string EncodeLoopConstraint(const LoopConstraint& c) {
  Json j = {{"source", int(c.source)},    {"query_place", c.query_place},
            {"merged", c.merged},         {"query", MetadataJson(c.query)},
            {"place", c.place},           {"place_metadata", MetadataJson(c.place_metadata)},
            {"score", c.score},           {"inliers", c.inliers},
            {"found_ns", c.found_unix_ns}};
  if (c.pose) {
    const RelativePose& p = *c.pose;
    j["pose"] = {{"transform", p.transform},    {"metric", p.metric},
                 {"solver", int(p.solver)},     {"correspondences", p.correspondences},
                 {"inliers", p.inliers},        {"rms_px", p.rms_error_px},
                 {"information", p.information}};
  } else {
    j["pose_unavailable"] = c.pose_unavailable;
  }
  return j.dump();
}

Result<LoopConstraint> DecodeLoopConstraint(uint64_t sequence, const std::string& value) {
  try {
    const Json j = Json::parse(value);
    LoopConstraint c;
    c.sequence = sequence;
    const int source = j.at("source").get<int>();
    if (source != int(LoopSource::kMatch) && source != int(LoopSource::kLoopClosure)) {
      throw std::runtime_error("unknown source " + std::to_string(source));
    }
    c.source = LoopSource(source);
    c.query_place = j.at("query_place").get<PlaceId>();
    c.merged = j.at("merged").get<bool>();
    c.query = MetadataOf(j.at("query"));
    c.place = j.at("place").get<PlaceId>();
    c.place_metadata = MetadataOf(j.at("place_metadata"));
    c.score = j.at("score").get<double>();
    c.inliers = j.at("inliers").get<int>();
    c.found_unix_ns = j.at("found_ns").get<int64_t>();
    if (j.contains("pose")) {
      const Json& p = j.at("pose");
      RelativePose pose;
      pose.transform = p.at("transform").get<std::array<double, 16>>();
      pose.metric = p.at("metric").get<bool>();
      const int solver = p.at("solver").get<int>();
      if (solver < int(PoseSolver::kPnpPlaceDepth) || solver > int(PoseSolver::kEssential)) {
        throw std::runtime_error("unknown pose solver " + std::to_string(solver));
      }
      pose.solver = PoseSolver(solver);
      pose.correspondences = p.at("correspondences").get<int>();
      pose.inliers = p.at("inliers").get<int>();
      pose.rms_error_px = p.at("rms_px").get<double>();
      pose.information = p.at("information").get<std::array<double, 36>>();
      c.pose = pose;
    } else {
      c.pose_unavailable = j.at("pose_unavailable").get<std::string>();
    }
    return c;
  } catch (const std::exception& e) {
    return Status::Corruption("loop constraint " + std::to_string(sequence) +
                              " is damaged: " + e.what());
  }
}

Result<std::unique_ptr<LoopLog>> LoopLog::Open(rocksdb::DB* db,
                                               rocksdb::ColumnFamilyHandle* family) {
  uint64_t last = 0;
  if (family) {
    auto stored = LastSequenceIn(db, family);
    if (!stored.ok()) return stored.status();
    last = *stored;
  }
  return std::unique_ptr<LoopLog>(new LoopLog(db, family, last));
}

LoopLog::LoopLog(rocksdb::DB* db, rocksdb::ColumnFamilyHandle* family, uint64_t last)
    : db_(db), family_(family), next_(last + 1), published_(last) {}

Status LoopLog::Write(std::vector<LoopConstraint>* constraints, rocksdb::WriteBatch* batch,
                      const std::function<Status()>& write) {
  if (constraints->empty()) return write();
  if (!family_) return Status::FailedPrecondition("the map's loop log is not open for writing");
  MutexLock lock(mutex_);
  for (LoopConstraint& constraint : *constraints) {
    constraint.sequence = next_++;
    batch->Put(family_, SequenceKey(constraint.sequence), EncodeLoopConstraint(constraint));
  }
  Status written = write();
  if (written.ok()) {
    published_ = constraints->back().sequence;
    published_cv_.NotifyAll();
    return written;
  }
  for (LoopConstraint& constraint : *constraints) constraint.sequence = 0;
  // Numbering goes on after what the database holds: the failed batch's sequences are reused
  // unless it reached the database. Cluster replicas number alike only so.
  if (auto last = LastSequenceIn(db_, family_); last.ok()) next_ = *last + 1;
  return written;
}

Result<std::vector<LoopConstraint>> LoopLog::Read(uint64_t from, size_t max,
                                                  const LoopFilter& filter,
                                                  uint64_t* scanned) const {
  const uint64_t until = last_sequence();
  from = std::max<uint64_t>(from, 1);
  *scanned = from - 1;
  std::vector<LoopConstraint> out;
  if (!family_ || from > until || max == 0) return out;
  std::unique_ptr<rocksdb::Iterator> it(db_->NewIterator(rocksdb::ReadOptions(), family_));
  for (it->Seek(SequenceKey(from)); it->Valid(); it->Next()) {
    auto sequence = SequenceOfKey(it->key());
    if (!sequence) return Status::Corruption("the loop log holds a key that is not a sequence");
    if (*sequence > until) break;
    auto constraint = DecodeLoopConstraint(*sequence, it->value().ToString());
    if (!constraint.ok()) return constraint.status();
    *scanned = *sequence;
    if (!filter.Accepts(*constraint)) continue;
    out.push_back(std::move(constraint).value());
    if (out.size() >= max) break;
  }
  PLACEDB_RETURN_IF_ERROR(detail::FromRocks(it->status(), "reading the loop log"));
  if (out.size() < max) *scanned = std::max(*scanned, until);
  return out;
}

uint64_t LoopLog::last_sequence() const {
  MutexLock lock(mutex_);
  return published_;
}

uint64_t LoopLog::WaitBeyond(uint64_t sequence,
                             std::chrono::steady_clock::time_point deadline) const {
  MutexLock lock(mutex_);
  while (published_ <= sequence && !closed_) {
    if (!published_cv_.WaitUntil(mutex_, deadline)) break;
  }
  return published_;
}

void LoopLog::Close() {
  {
    MutexLock lock(mutex_);
    closed_ = true;
  }
  published_cv_.NotifyAll();
}

bool LoopLog::closed() const {
  MutexLock lock(mutex_);
  return closed_;
}

}  // namespace placedb
