// ROS 1 bags (format 2.0, "#ROSBAG V2.0") read without ROS: the container and the three message
// types placedb ingests, so the CLI needs neither ROS nor Debian's librosbag-storage (and its
// Boost). Written from the public format description (wiki.ros.org/Bags/Format/2.0).
//
// The container: after the magic line, records of [uint32 header length][header][uint32 data
// length][data], all little-endian; a header is a list of [uint32 length]["name=value"] fields,
// "op" saying the record's kind: bag header 0x03 (index_pos: where the index section starts),
// chunk 0x05 (compression "none", "bz2" or "lz4" and the uncompressed size; its data holds
// connection and message-data records), index data 0x04, connection 0x07 (topic, and in its data
// the type, md5sum and definition), message data 0x02 (conn, receive time) and chunk info 0x06
// (a chunk's position and its messages per connection). "lz4" is roslz4's stream, which is an
// LZ4 frame (decoded with liblz4's frame API); "bz2" is a bzip2 stream (libbz2).
//
// Open() reads the index section at the end of the file (connections, chunks and message counts),
// or, for a bag whose recording was cut short and never indexed (index_pos 0), scans the chunks.
// Messages are then read chunk by chunk: in file order, and within a chunk by receive time (what
// rosbag's read_messages gives for a recorded bag, whose chunks follow each other in time).
//
//   std::unique_ptr<BagReader> bag = BagReader::Open("run.bag", &error);
//   bag->Select({"/camera/image_raw"});
//   BagMessage message;
//   while (bag->Next(&message, &error)) { ... ParseRosImage(message.data, &image, &error) ... }
//   if (!error.empty()) ...  // a damaged chunk
//
// The messages (ROS 1 serialization: little-endian, strings and variable arrays prefixed by a
// uint32 length, fixed arrays without): sensor_msgs/Image, sensor_msgs/CompressedImage and
// sensor_msgs/CameraInfo, each with its std_msgs/Header's stamp.
#pragma once

#include <cstdint>
#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <string_view>
#include <vector>

namespace placedb::client {

// A topic of the bag: its message type ("sensor_msgs/Image") and how many messages it has.
struct BagTopic {
  std::string topic;
  std::string type;
  uint64_t messages = 0;
};

struct BagMessage {
  std::string topic;
  std::string type;
  int64_t receive_time_ns = 0;  // when the recorder received it (the record's time)
  std::string data;             // the serialized message
};

class BagReader {
 public:
  // Reads the magic, the bag header and the index (or scans an unindexed bag). Null + *error
  // ("run.bag: truncated: ...", "run.bag: a chunk at byte 4117 is compressed with 'zstd' ...",
  // "run.bag: not a ROS 1 bag ...") when the file is not a readable ROS 1 bag.
  static std::unique_ptr<BagReader> Open(const std::string& path, std::string* error);
  ~BagReader();

  const std::string& path() const { return path_; }
  // Every topic, sorted by name (several connections of one topic are added up).
  std::vector<BagTopic> topics() const;

  // Next() yields the messages of these topics only (all topics when never called); rewinds.
  void Select(const std::set<std::string>& topics);

  // The next selected message; false at the end, or with *error when a chunk cannot be read.
  bool Next(BagMessage* message, std::string* error);

 private:
  struct Connection {
    uint32_t id = 0;
    std::string topic;
    std::string type;
    uint64_t messages = 0;
  };
  struct Record;
  BagReader() = default;

  // The record at `position` (its data too unless !with_data); checks that it lies in the file.
  bool ReadRecordAt(uint64_t position, Record* record, std::string* error, bool with_data = true);
  bool CheckChunkHeader(const Record& chunk, std::string* error) const;
  bool ReadIndex(uint64_t index_position, std::string* error);
  bool ScanUnindexed(uint64_t first_record, std::string* error);
  bool LoadChunk(uint64_t position, std::string* error);
  Connection* FindConnection(uint32_t id);
  void AddConnection(const Record& record, std::string_view data);

  std::string path_;
  std::ifstream file_;
  uint64_t file_size_ = 0;
  std::vector<Connection> connections_;
  std::vector<uint64_t> chunk_positions_;  // in file order
  std::set<uint32_t> selected_;            // connection ids; empty = all
  bool select_all_ = true;
  bool scanning_ = false;  // ScanUnindexed: count messages, queue none
  size_t next_chunk_ = 0;
  std::vector<BagMessage> pending_;  // the current chunk's selected messages, by receive time
  size_t next_pending_ = 0;
};

// std_msgs/Header's stamp in nanoseconds.
struct RosImage {
  int64_t stamp_ns = 0;
  uint32_t height = 0;
  uint32_t width = 0;
  std::string encoding;  // "rgb8", "bgr8", "mono8", "16UC1", "32FC1", ...
  bool big_endian = false;
  uint32_t step = 0;  // bytes per row (>= width * bytes per pixel)
  std::string data;
};

struct RosCompressedImage {
  int64_t stamp_ns = 0;
  std::string format;  // "jpeg", "png", "16UC1; compressedDepth png", ...
  std::string data;
};

struct RosCameraInfo {
  int64_t stamp_ns = 0;
  uint32_t height = 0;
  uint32_t width = 0;
  std::string distortion_model;
  std::vector<double> d;
  double k[9] = {};  // row-major 3x3: fx 0 cx / 0 fy cy / 0 0 1
};

// Each false + *error ("a sensor_msgs/Image of 120 bytes ends inside its data") when the bytes
// are not a whole message of that type.
bool ParseRosImage(std::string_view bytes, RosImage* image, std::string* error);
bool ParseRosCompressedImage(std::string_view bytes, RosCompressedImage* image, std::string* error);
bool ParseRosCameraInfo(std::string_view bytes, RosCameraInfo* info, std::string* error);

}  // namespace placedb::client
