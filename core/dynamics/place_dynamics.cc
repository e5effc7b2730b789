#include "core/dynamics/place_dynamics.h"

#include <algorithm>
#include <cmath>

namespace placedb {

namespace {

constexpr uint8_t kVersion = 1;
constexpr int64_t kNsPerSecond = 1'000'000'000;

uint32_t ToPpm(double coverage) {
  if (!std::isfinite(coverage)) return 0;
  coverage = std::clamp(coverage, 0.0, 1.0);
  return uint32_t(std::lround(coverage * kCoverageScale));
}

void PutVarint(std::string* out, uint64_t v) {
  while (v >= 0x80) {
    out->push_back(char(uint8_t(v) | 0x80));
    v >>= 7;
  }
  out->push_back(char(v));
}

uint64_t ZigZag(int64_t v) {
  return (uint64_t(v) << 1) ^ uint64_t(v >> 63);
}
int64_t UnZigZag(uint64_t v) {
  return int64_t(v >> 1) ^ -int64_t(v & 1);
}

class Reader {
 public:
  explicit Reader(std::string_view bytes) : bytes_(bytes) {}
  bool Varint(uint64_t* v) {
    *v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      if (at_ >= bytes_.size()) return false;
      const uint8_t byte = uint8_t(bytes_[at_++]);
      if (shift == 63 && byte > 1) return false;  // more than 64 bits
      *v |= uint64_t(byte & 0x7f) << shift;
      if (!(byte & 0x80)) return true;
    }
    return false;
  }
  bool Byte(uint8_t* v) {
    if (at_ >= bytes_.size()) return false;
    *v = uint8_t(bytes_[at_++]);
    return true;
  }
  bool done() const { return at_ == bytes_.size(); }

 private:
  std::string_view bytes_;
  size_t at_ = 0;
};

// (timestamp, coverage) ordering of `last`: the newer observation wins, ties the larger coverage,
// so the choice does not depend on the order of merging.
bool Newer(int64_t t1, uint32_t c1, int64_t t2, uint32_t c2) {
  return t1 != t2 ? t1 > t2 : c1 > c2;
}

}  // namespace

double PlaceDynamics::mean_coverage() const {
  if (observations == 0) return 0;
  return double(coverage_ppm_sum) / double(observations) / double(kCoverageScale);
}

int HourBinOf(int64_t timestamp_ns) {
  const int64_t seconds = timestamp_ns / kNsPerSecond;
  const int64_t days = seconds / 86400;
  const int hour = int((seconds % 86400) / 3600);
  // 1970-01-01 was a Thursday (weekday 3 with Monday = 0).
  const int weekday = int((days + 3) % 7);
  return weekday * kHours + hour;
}

PlaceDynamics MakeObservation(double dynamic_coverage, const std::vector<DynamicBox>& boxes,
                              int64_t timestamp_ns, int64_t now_unix_ns) {
  PlaceDynamics d;
  d.observations = 1;
  const uint32_t ppm = ToPpm(dynamic_coverage);
  d.coverage_ppm_sum = ppm;
  d.coverage_ppm_max = ppm;
  if (timestamp_ns <= 0) {
    d.untimed = 1;
  } else if (timestamp_ns > now_unix_ns && timestamp_ns - now_unix_ns > kFutureToleranceNs) {
    d.future = 1;
  } else {
    d.last_timestamp_ns = timestamp_ns;
    d.last_coverage_ppm = ppm;
    HourBin& bin = d.hours[size_t(HourBinOf(timestamp_ns))];
    bin.observations = 1;
    bin.coverage_ppm_sum = ppm;
  }
  for (const DynamicBox& box : boxes) {
    if (box.class_id < 0 || box.class_id > kMaxClassId) {
      ++d.unknown_class_boxes;
      continue;
    }
    ClassCount& count = d.classes[box.class_id];
    count.frames = 1;
    ++count.boxes;
  }
  return d;
}

void Merge(PlaceDynamics* into, const PlaceDynamics& other) {
  if (Newer(other.last_timestamp_ns, other.last_coverage_ppm, into->last_timestamp_ns,
            into->last_coverage_ppm)) {
    into->last_timestamp_ns = other.last_timestamp_ns;
    into->last_coverage_ppm = other.last_coverage_ppm;
  }
  into->observations += other.observations;
  into->coverage_ppm_sum += other.coverage_ppm_sum;
  into->coverage_ppm_max = std::max(into->coverage_ppm_max, other.coverage_ppm_max);
  into->untimed += other.untimed;
  into->future += other.future;
  into->unknown_class_boxes += other.unknown_class_boxes;
  for (const auto& [id, count] : other.classes) {
    ClassCount& mine = into->classes[id];
    mine.frames += count.frames;
    mine.boxes += count.boxes;
  }
  for (size_t i = 0; i < into->hours.size(); ++i) {
    into->hours[i].observations += other.hours[i].observations;
    into->hours[i].coverage_ppm_sum += other.hours[i].coverage_ppm_sum;
  }
}

std::string EncodeDynamics(const PlaceDynamics& d) {
  std::string out;
  out.push_back(char(kVersion));
  PutVarint(&out, d.observations);
  PutVarint(&out, d.coverage_ppm_sum);
  PutVarint(&out, d.coverage_ppm_max);
  PutVarint(&out, ZigZag(d.last_timestamp_ns));
  PutVarint(&out, d.last_coverage_ppm);
  PutVarint(&out, d.untimed);
  PutVarint(&out, d.future);
  PutVarint(&out, d.unknown_class_boxes);
  PutVarint(&out, d.classes.size());
  for (const auto& [id, count] : d.classes) {
    PutVarint(&out, uint64_t(id));
    PutVarint(&out, count.frames);
    PutVarint(&out, count.boxes);
  }
  size_t bins = 0;
  for (const HourBin& bin : d.hours) bins += bin.observations ? 1 : 0;
  PutVarint(&out, bins);
  for (size_t i = 0; i < d.hours.size(); ++i) {
    if (!d.hours[i].observations) continue;
    PutVarint(&out, i);
    PutVarint(&out, d.hours[i].observations);
    PutVarint(&out, d.hours[i].coverage_ppm_sum);
  }
  return out;
}

Result<PlaceDynamics> DecodeDynamics(std::string_view bytes) {
  auto bad = [](const std::string& what) { return Status::Corruption("dynamics record: " + what); };
  Reader in(bytes);
  uint8_t version = 0;
  if (!in.Byte(&version)) return bad("empty");
  if (version != kVersion) return bad("unknown version " + std::to_string(version));
  PlaceDynamics d;
  uint64_t max = 0, last_ts = 0, last_cov = 0, classes = 0, bins = 0;
  if (!in.Varint(&d.observations) || !in.Varint(&d.coverage_ppm_sum) || !in.Varint(&max) ||
      !in.Varint(&last_ts) || !in.Varint(&last_cov) || !in.Varint(&d.untimed) ||
      !in.Varint(&d.future) || !in.Varint(&d.unknown_class_boxes) || !in.Varint(&classes)) {
    return bad("truncated");
  }
  if (max > kCoverageScale || last_cov > kCoverageScale) return bad("coverage above 1");
  d.coverage_ppm_max = uint32_t(max);
  d.last_timestamp_ns = UnZigZag(last_ts);
  d.last_coverage_ppm = uint32_t(last_cov);
  int64_t previous = -1;
  for (uint64_t i = 0; i < classes; ++i) {
    uint64_t id = 0;
    ClassCount count;
    if (!in.Varint(&id) || !in.Varint(&count.frames) || !in.Varint(&count.boxes)) {
      return bad("truncated class counts");
    }
    if (id > uint64_t(kMaxClassId) || int64_t(id) <= previous) {
      return bad("class id " + std::to_string(id) + " out of range or order");
    }
    previous = int64_t(id);
    d.classes.emplace(int(id), count);
  }
  if (!in.Varint(&bins)) return bad("truncated");
  previous = -1;
  for (uint64_t i = 0; i < bins; ++i) {
    uint64_t index = 0;
    HourBin bin;
    if (!in.Varint(&index) || !in.Varint(&bin.observations) || !in.Varint(&bin.coverage_ppm_sum)) {
      return bad("truncated histogram");
    }
    if (index >= uint64_t(kHourBins) || int64_t(index) <= previous || bin.observations == 0) {
      return bad("histogram bin " + std::to_string(index) + " out of range or order");
    }
    previous = int64_t(index);
    d.hours[index] = bin;
  }
  if (!in.done()) return bad("trailing bytes");
  return d;
}

}  // namespace placedb
