#include "client/rosbag_reader.h"

#include <bzlib.h>
#include <lz4frame.h>

#include <algorithm>
#include <cstring>
#include <map>

namespace placedb::client {

namespace {

constexpr std::string_view kMagic = "#ROSBAG V2.0\n";
constexpr uint8_t kOpMessageData = 0x02;
constexpr uint8_t kOpBagHeader = 0x03;
constexpr uint8_t kOpChunk = 0x05;
constexpr uint8_t kOpChunkInfo = 0x06;
constexpr uint8_t kOpConnection = 0x07;
// A record's header or data larger than this is damage, not data; so is a chunk declaring more
// than kMaxChunkSize uncompressed (rosbag's chunks are ~768 KB): refused before it is allocated.
constexpr uint64_t kMaxRecordPart = uint64_t(1) << 31;
constexpr uint64_t kMaxChunkSize = uint64_t(1) << 30;

uint32_t U32(std::string_view bytes, size_t at) {
  uint32_t value = 0;
  for (int i = 3; i >= 0; --i) value = (value << 8) | uint8_t(bytes[at + size_t(i)]);
  return value;
}

uint64_t U64(std::string_view bytes, size_t at) {
  return uint64_t(U32(bytes, at)) | (uint64_t(U32(bytes, at + 4)) << 32);
}

// A ROS time (uint32 seconds, uint32 nanoseconds) in nanoseconds.
int64_t TimeNs(std::string_view bytes, size_t at) {
  return int64_t(U32(bytes, at)) * 1'000'000'000 + int64_t(U32(bytes, at + 4));
}

// "name=value" fields of a record header.
using Fields = std::map<std::string, std::string, std::less<>>;

bool ParseFields(std::string_view header, Fields* fields) {
  size_t at = 0;
  while (at < header.size()) {
    if (header.size() - at < 4) return false;
    const uint32_t length = U32(header, at);
    at += 4;
    if (length > header.size() - at) return false;
    const std::string_view field = header.substr(at, length);
    at += length;
    const size_t equals = field.find('=');
    if (equals == std::string_view::npos) return false;
    (*fields)[std::string(field.substr(0, equals))] = std::string(field.substr(equals + 1));
  }
  return true;
}

std::string Hex(uint8_t value) {
  const char* digits = "0123456789abcdef";
  return std::string("0x") + digits[value >> 4] + digits[value & 15];
}

// Reads fixed-size and length-prefixed values of a ROS 1 serialized message.
class Cursor {
 public:
  explicit Cursor(std::string_view bytes) : bytes_(bytes) {}
  bool U8(uint8_t* value) {
    if (!Need(1)) return false;
    *value = uint8_t(bytes_[at_++]);
    return true;
  }
  bool U32(uint32_t* value) {
    if (!Need(4)) return false;
    *value = client::U32(bytes_, at_);
    at_ += 4;
    return true;
  }
  bool F64(double* value) {
    if (!Need(8)) return false;
    const uint64_t bits = client::U64(bytes_, at_);
    std::memcpy(value, &bits, 8);
    at_ += 8;
    return true;
  }
  bool String(std::string* value) {  // also uint8[]: the same layout
    uint32_t length = 0;
    if (!U32(&length) || !Need(length)) return false;
    value->assign(bytes_.substr(at_, length));
    at_ += length;
    return true;
  }
  // std_msgs/Header: seq, stamp, frame_id.
  bool Header(int64_t* stamp_ns) {
    uint32_t seq = 0, secs = 0, nsecs = 0;
    std::string frame_id;
    if (!U32(&seq) || !U32(&secs) || !U32(&nsecs) || !String(&frame_id)) return false;
    *stamp_ns = int64_t(secs) * 1'000'000'000 + int64_t(nsecs);
    return true;
  }

 private:
  bool Need(size_t n) const { return bytes_.size() - at_ >= n; }
  std::string_view bytes_;
  size_t at_ = 0;
};

bool Truncated(std::string_view type, size_t size, std::string* error) {
  *error = "a " + std::string(type) + " of " + std::to_string(size) +
           " bytes ends inside its fields (not a whole message of that type)";
  return false;
}

bool DecompressBz2(std::string_view in, std::string* out, std::string* error) {
  unsigned int length = unsigned(out->size());
  const int result = BZ2_bzBuffToBuffDecompress(out->data(), &length, const_cast<char*>(in.data()),
                                                unsigned(in.size()), 0, 0);
  if (result != BZ_OK || length != out->size()) {
    *error = "its bz2 data does not decompress to its declared size (bzip2 error " +
             std::to_string(result) + ")";
    return false;
  }
  return true;
}

bool DecompressLz4(std::string_view in, std::string* out, std::string* error) {
  LZ4F_dctx* context = nullptr;
  if (LZ4F_isError(LZ4F_createDecompressionContext(&context, LZ4F_VERSION))) {
    *error = "cannot create an LZ4 decompression context";
    return false;
  }
  size_t read = 0, written = 0;
  size_t hint = 1;
  while (hint != 0 && read < in.size() && written < out->size()) {
    size_t in_size = in.size() - read;
    size_t out_size = out->size() - written;
    hint = LZ4F_decompress(context, out->data() + written, &out_size, in.data() + read, &in_size,
                           nullptr);
    if (LZ4F_isError(hint)) {
      *error = std::string("its lz4 data is damaged (") + LZ4F_getErrorName(hint) + ")";
      LZ4F_freeDecompressionContext(context);
      return false;
    }
    read += in_size;
    written += out_size;
    if (in_size == 0 && out_size == 0) break;
  }
  LZ4F_freeDecompressionContext(context);
  if (written != out->size()) {
    *error = "its lz4 data decompresses to " + std::to_string(written) + " bytes, not the " +
             std::to_string(out->size()) + " it declares";
    return false;
  }
  return true;
}

}  // namespace

struct BagReader::Record {
  uint64_t position = 0;
  uint64_t end = 0;  // the next record's position
  Fields fields;
  std::string data;
  uint8_t op() const {
    auto it = fields.find("op");
    return it == fields.end() || it->second.size() != 1 ? 0 : uint8_t(it->second[0]);
  }
  // A little-endian integer field of `bytes` bytes; false when absent or of another size.
  bool Integer(std::string_view name, size_t bytes, uint64_t* value) const {
    auto it = fields.find(name);
    if (it == fields.end() || it->second.size() != bytes) return false;
    *value = bytes == 8 ? U64(it->second, 0) : U32(it->second, 0);
    return true;
  }
};

BagReader::~BagReader() = default;

std::unique_ptr<BagReader> BagReader::Open(const std::string& path, std::string* error) {
  std::unique_ptr<BagReader> bag(new BagReader());
  bag->path_ = path;
  bag->file_.open(path, std::ios::binary);
  if (!bag->file_) {
    *error = path + ": cannot read";
    return nullptr;
  }
  bag->file_.seekg(0, std::ios::end);
  bag->file_size_ = uint64_t(bag->file_.tellg());
  bag->file_.seekg(0);
  std::string magic(kMagic.size(), '\0');
  bag->file_.read(magic.data(), std::streamsize(magic.size()));
  if (!bag->file_ || magic != kMagic) {
    *error = path + ": not a ROS 1 bag (it does not start with '#ROSBAG V2.0')";
    return nullptr;
  }
  Record header;
  if (!bag->ReadRecordAt(kMagic.size(), &header, error)) return nullptr;
  uint64_t index_position = 0;
  if (header.op() != kOpBagHeader || !header.Integer("index_pos", 8, &index_position)) {
    *error = path + ": its first record is not a bag header (op 0x03 with index_pos)";
    return nullptr;
  }
  const bool indexed = index_position != 0;
  if (indexed && index_position >= bag->file_size_) {
    *error = path + ": truncated: its index starts at byte " + std::to_string(index_position) +
             " but the file has " + std::to_string(bag->file_size_) + " bytes";
    return nullptr;
  }
  if (indexed ? !bag->ReadIndex(index_position, error) : !bag->ScanUnindexed(header.end, error)) {
    return nullptr;
  }
  return bag;
}

bool BagReader::ReadRecordAt(uint64_t position, Record* record, std::string* error,
                             bool with_data) {
  const auto truncated = [&](const std::string& what) {
    *error = path_ + ": truncated: the record at byte " + std::to_string(position) + " " + what +
             " (the file has " + std::to_string(file_size_) + " bytes)";
    return false;
  };
  record->position = position;
  record->fields.clear();
  record->data.clear();
  std::string length(4, '\0');
  if (position + 4 > file_size_) return truncated("has no header length");
  file_.clear();
  file_.seekg(std::streamoff(position));
  file_.read(length.data(), 4);
  const uint64_t header_length = U32(length, 0);
  if (header_length > kMaxRecordPart || position + 4 + header_length + 4 > file_size_) {
    return truncated("declares a header of " + std::to_string(header_length) + " bytes");
  }
  std::string header(header_length, '\0');
  file_.read(header.data(), std::streamsize(header_length));
  file_.read(length.data(), 4);
  const uint64_t data_length = U32(length, 0);
  const uint64_t data_start = position + 4 + header_length + 4;
  if (data_length > kMaxRecordPart || data_start + data_length > file_size_) {
    return truncated("declares " + std::to_string(data_length) + " bytes of data");
  }
  record->end = data_start + data_length;
  if (with_data) {
    record->data.resize(data_length);
    file_.read(record->data.data(), std::streamsize(data_length));
  }
  if (!file_) {
    *error = path_ + ": cannot read the record at byte " + std::to_string(position);
    return false;
  }
  if (!ParseFields(header, &record->fields)) {
    *error = path_ + ": the record at byte " + std::to_string(position) +
             " has a malformed header (fields are [uint32 length]name=value)";
    return false;
  }
  return true;
}

bool BagReader::CheckChunkHeader(const Record& chunk, std::string* error) const {
  const std::string where = path_ + ": the chunk at byte " + std::to_string(chunk.position);
  if (chunk.op() != kOpChunk) {
    *error = where + " is not a chunk record (op " + Hex(chunk.op()) + ")";
    return false;
  }
  uint64_t size = 0;
  const auto compression = chunk.fields.find("compression");
  if (compression == chunk.fields.end() || !chunk.Integer("size", 4, &size)) {
    *error = where + " lacks its compression or size field";
    return false;
  }
  if (size > kMaxChunkSize) {
    *error = where + " declares " + std::to_string(size) + " bytes uncompressed (at most " +
             std::to_string(kMaxChunkSize) + " are read)";
    return false;
  }
  if (compression->second != "none" && compression->second != "bz2" &&
      compression->second != "lz4") {
    *error = where + " is compressed with '" + compression->second +
             "'; placedb reads ROS 1 chunks compressed with none, bz2 or lz4";
    return false;
  }
  return true;
}

BagReader::Connection* BagReader::FindConnection(uint32_t id) {
  for (Connection& connection : connections_) {
    if (connection.id == id) return &connection;
  }
  return nullptr;
}

void BagReader::AddConnection(const Record& record, std::string_view data) {
  uint64_t id = 0;
  if (!record.Integer("conn", 4, &id) || FindConnection(uint32_t(id))) return;
  Connection connection;
  connection.id = uint32_t(id);
  if (auto it = record.fields.find("topic"); it != record.fields.end()) {
    connection.topic = it->second;
  }
  Fields details;  // the connection's data: a header of its own (topic, type, md5sum, ...)
  if (ParseFields(data, &details)) {
    if (auto it = details.find("type"); it != details.end()) connection.type = it->second;
    if (connection.topic.empty()) {
      if (auto it = details.find("topic"); it != details.end()) connection.topic = it->second;
    }
  }
  connections_.push_back(std::move(connection));
}

bool BagReader::ReadIndex(uint64_t index_position, std::string* error) {
  uint64_t position = index_position;
  Record record;
  while (position < file_size_) {
    if (!ReadRecordAt(position, &record, error)) return false;
    position = record.end;
    if (record.op() == kOpConnection) {
      AddConnection(record, record.data);
    } else if (record.op() == kOpChunkInfo) {
      uint64_t chunk_position = 0;
      if (!record.Integer("chunk_pos", 8, &chunk_position) || chunk_position >= file_size_) {
        *error = path_ + ": the chunk info at byte " + std::to_string(record.position) +
                 " points outside the file";
        return false;
      }
      chunk_positions_.push_back(chunk_position);
      // [conn uint32][count uint32] per connection with messages in the chunk.
      for (size_t at = 0; at + 8 <= record.data.size(); at += 8) {
        if (Connection* c = FindConnection(U32(record.data, at)))
          c->messages += U32(record.data, at + 4);
      }
    }
  }
  std::sort(chunk_positions_.begin(), chunk_positions_.end());
  chunk_positions_.erase(std::unique(chunk_positions_.begin(), chunk_positions_.end()),
                         chunk_positions_.end());
  // Every chunk whole and of a known compression before anything is read from it.
  for (const uint64_t chunk_position : chunk_positions_) {
    if (!ReadRecordAt(chunk_position, &record, error, /*with_data=*/false) ||
        !CheckChunkHeader(record, error)) {
      return false;
    }
  }
  return true;
}

bool BagReader::ScanUnindexed(uint64_t first_record, std::string* error) {
  uint64_t position = first_record;
  Record record;
  while (position < file_size_) {
    if (!ReadRecordAt(position, &record, error, /*with_data=*/false)) return false;
    position = record.end;
    if (record.op() == kOpChunk) {
      if (!CheckChunkHeader(record, error)) return false;
      chunk_positions_.push_back(record.position);
    }
    if (record.op() == kOpConnection) {
      if (!ReadRecordAt(record.position, &record, error)) return false;
      AddConnection(record, record.data);
    }
  }
  // Connections live inside the chunks too, and only the messages tell the counts.
  scanning_ = true;
  for (const uint64_t chunk : chunk_positions_) {
    if (!LoadChunk(chunk, error)) return false;
  }
  scanning_ = false;
  pending_.clear();
  next_pending_ = 0;
  return true;
}

// Decompresses the chunk at `position` and queues its selected messages by receive time. While
// scanning an unindexed bag it only learns the connections and counts their messages.
bool BagReader::LoadChunk(uint64_t position, std::string* error) {
  Record chunk;
  if (!ReadRecordAt(position, &chunk, error)) return false;
  if (!CheckChunkHeader(chunk, error)) return false;
  const std::string where = path_ + ": the chunk at byte " + std::to_string(position);
  uint64_t size = 0;
  chunk.Integer("size", 4, &size);
  const std::string& compression = chunk.fields.find("compression")->second;
  std::string records;
  if (compression == "none") {
    records = std::move(chunk.data);
  } else {
    records.resize(size);
    std::string why;
    const bool ok = compression == "bz2" ? DecompressBz2(chunk.data, &records, &why)
                                         : DecompressLz4(chunk.data, &records, &why);
    if (!ok) {
      *error = where + ": " + why;
      return false;
    }
  }
  pending_.clear();
  next_pending_ = 0;
  size_t at = 0;
  while (at < records.size()) {
    const std::string_view view(records);
    if (records.size() - at < 8 || U32(view, at) > records.size() - at - 8) {
      *error = where + ": its records are cut short at byte " + std::to_string(at) + " of its " +
               std::to_string(records.size());
      return false;
    }
    const uint32_t header_length = U32(view, at);
    const std::string_view header = view.substr(at + 4, header_length);
    const uint32_t data_length = U32(view, at + 4 + header_length);
    const size_t data_start = at + 8 + header_length;
    if (data_length > records.size() - data_start) {
      *error = where + ": its record at byte " + std::to_string(at) + " declares " +
               std::to_string(data_length) + " bytes of data beyond the chunk's end";
      return false;
    }
    Record inner;
    inner.position = at;
    if (!ParseFields(header, &inner.fields)) {
      *error = where + ": its record at byte " + std::to_string(at) + " has a malformed header";
      return false;
    }
    const std::string_view data = view.substr(data_start, data_length);
    at = data_start + data_length;
    if (inner.op() == kOpConnection) {
      AddConnection(inner, data);
      continue;
    }
    if (inner.op() != kOpMessageData) continue;
    uint64_t id = 0;
    const auto time = inner.fields.find("time");
    if (!inner.Integer("conn", 4, &id) || time == inner.fields.end() || time->second.size() != 8) {
      *error = where + ": a message record without conn or time";
      return false;
    }
    Connection* connection = FindConnection(uint32_t(id));
    if (connection == nullptr) {
      *error = where + ": a message of connection " + std::to_string(id) +
               ", which the bag never declares";
      return false;
    }
    if (scanning_) ++connection->messages;
    if (!select_all_ && !selected_.count(connection->id)) continue;
    if (scanning_) continue;
    BagMessage message;
    message.topic = connection->topic;
    message.type = connection->type;
    message.receive_time_ns = TimeNs(time->second, 0);
    message.data.assign(data);
    pending_.push_back(std::move(message));
  }
  std::stable_sort(pending_.begin(), pending_.end(), [](const BagMessage& a, const BagMessage& b) {
    return a.receive_time_ns < b.receive_time_ns;
  });
  return true;
}

std::vector<BagTopic> BagReader::topics() const {
  std::map<std::string, BagTopic> by_topic;
  for (const Connection& connection : connections_) {
    BagTopic& topic = by_topic[connection.topic];
    topic.topic = connection.topic;
    if (topic.type.empty()) topic.type = connection.type;
    topic.messages += connection.messages;
  }
  std::vector<BagTopic> topics;
  for (auto& [name, topic] : by_topic) topics.push_back(std::move(topic));
  return topics;
}

void BagReader::Select(const std::set<std::string>& topics) {
  select_all_ = false;
  selected_.clear();
  for (const Connection& connection : connections_) {
    if (topics.count(connection.topic)) selected_.insert(connection.id);
  }
  next_chunk_ = 0;
  pending_.clear();
  next_pending_ = 0;
}

bool BagReader::Next(BagMessage* message, std::string* error) {
  error->clear();
  while (next_pending_ >= pending_.size()) {
    if (next_chunk_ >= chunk_positions_.size()) return false;
    if (!LoadChunk(chunk_positions_[next_chunk_++], error)) {
      next_chunk_ = chunk_positions_.size();  // nothing more can be trusted
      return false;
    }
  }
  *message = std::move(pending_[next_pending_++]);
  return true;
}

bool ParseRosImage(std::string_view bytes, RosImage* image, std::string* error) {
  Cursor cursor(bytes);
  uint8_t big_endian = 0;
  if (!cursor.Header(&image->stamp_ns) || !cursor.U32(&image->height) ||
      !cursor.U32(&image->width) || !cursor.String(&image->encoding) || !cursor.U8(&big_endian) ||
      !cursor.U32(&image->step) || !cursor.String(&image->data)) {
    return Truncated("sensor_msgs/Image", bytes.size(), error);
  }
  image->big_endian = big_endian != 0;
  return true;
}

bool ParseRosCompressedImage(std::string_view bytes, RosCompressedImage* image,
                             std::string* error) {
  Cursor cursor(bytes);
  if (!cursor.Header(&image->stamp_ns) || !cursor.String(&image->format) ||
      !cursor.String(&image->data)) {
    return Truncated("sensor_msgs/CompressedImage", bytes.size(), error);
  }
  return true;
}

bool ParseRosCameraInfo(std::string_view bytes, RosCameraInfo* info, std::string* error) {
  Cursor cursor(bytes);
  uint32_t coefficients = 0;
  if (!cursor.Header(&info->stamp_ns) || !cursor.U32(&info->height) || !cursor.U32(&info->width) ||
      !cursor.String(&info->distortion_model) || !cursor.U32(&coefficients) ||
      coefficients > bytes.size() / 8) {
    return Truncated("sensor_msgs/CameraInfo", bytes.size(), error);
  }
  info->d.assign(coefficients, 0.0);
  for (double& value : info->d) {
    if (!cursor.F64(&value)) return Truncated("sensor_msgs/CameraInfo", bytes.size(), error);
  }
  for (double& value : info->k) {
    if (!cursor.F64(&value)) return Truncated("sensor_msgs/CameraInfo", bytes.size(), error);
  }
  // R (9), P (12), binning and roi follow; placedb needs none of them, but they must be there.
  double unused = 0;
  for (int i = 0; i < 21; ++i) {
    if (!cursor.F64(&unused)) return Truncated("sensor_msgs/CameraInfo", bytes.size(), error);
  }
  return true;
}

}  // namespace placedb::client
