// client/rosbag_reader and client/recording on bags this test writes byte by byte (the ROS 1 bag
// 2.0 layout, chunks uncompressed, bz2 and lz4): topics, receive-time order, the three message
// types, unindexed bags, and the errors (truncated, unknown compression, not a bag, an unknown
// topic, an unsupported encoding, a damaged message); then the TUM helpers (exact timestamps,
// pose interpolation). tests/recordings/ingest_recordings_test.py ingests bags written by
// python3-rosbag through the real CLI and server.
#include "client/rosbag_reader.h"

#include <bzlib.h>
#include <gtest/gtest.h>
#include <lz4frame.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>

#include "client/recording.h"

namespace placedb::client {
namespace {

namespace fs = std::filesystem;

std::string Le32(uint32_t value) {
  std::string out(4, '\0');
  for (int i = 0; i < 4; ++i) out[size_t(i)] = char((value >> (8 * i)) & 0xFF);
  return out;
}
std::string Le64(uint64_t value) {
  return Le32(uint32_t(value)) + Le32(uint32_t(value >> 32));
}
std::string Time(int64_t ns) {
  return Le32(uint32_t(ns / 1'000'000'000)) + Le32(uint32_t(ns % 1'000'000'000));
}
std::string Field(const std::string& name, const std::string& value) {
  return Le32(uint32_t(name.size() + 1 + value.size())) + name + "=" + value;
}
std::string Record(const std::string& header, const std::string& data) {
  return Le32(uint32_t(header.size())) + header + Le32(uint32_t(data.size())) + data;
}
std::string Op(uint8_t op) {
  return Field("op", std::string(1, char(op)));
}
std::string RosString(const std::string& s) {
  return Le32(uint32_t(s.size())) + s;
}
std::string RosHeader(int64_t stamp_ns) {
  return Le32(7) + Time(stamp_ns) + RosString("cam");
}
std::string F64(double value) {
  uint64_t bits = 0;
  std::memcpy(&bits, &value, 8);
  return Le64(bits);
}

std::string ImageMessage(int64_t stamp_ns, uint32_t width, uint32_t height,
                         const std::string& encoding, uint32_t step, const std::string& data) {
  return RosHeader(stamp_ns) + Le32(height) + Le32(width) + RosString(encoding) +
         std::string(1, '\0') + Le32(step) + RosString(data);
}

std::string CameraInfoMessage(int64_t stamp_ns, const std::string& model,
                              const std::vector<double>& d) {
  std::string out =
      RosHeader(stamp_ns) + Le32(480) + Le32(640) + RosString(model) + Le32(uint32_t(d.size()));
  for (double v : d) out += F64(v);
  const double k[9] = {518, 0, 325.5, 0, 519, 253.5, 0, 0, 1};
  for (double v : k) out += F64(v);
  for (int i = 0; i < 21; ++i) out += F64(0);    // R, P
  out += Le32(0) + Le32(0);                      // binning
  out += Le32(0) + Le32(0) + Le32(0) + Le32(0);  // roi
  return out + std::string(1, '\0');
}

struct Written {
  std::string topic, type;
  int64_t receive_ns = 0;
  std::string data;
};

std::string Compress(const std::string& records, const std::string& compression) {
  if (compression == "bz2") {
    std::string out(records.size() + records.size() / 100 + 600, '\0');
    unsigned int length = unsigned(out.size());
    EXPECT_EQ(BZ2_bzBuffToBuffCompress(out.data(), &length, const_cast<char*>(records.data()),
                                       unsigned(records.size()), 9, 0, 0),
              BZ_OK);
    out.resize(length);
    return out;
  }
  if (compression == "lz4") {
    std::string out(LZ4F_compressFrameBound(records.size(), nullptr), '\0');
    const size_t length =
        LZ4F_compressFrame(out.data(), out.size(), records.data(), records.size(), nullptr);
    EXPECT_FALSE(LZ4F_isError(length));
    out.resize(length);
    return out;
  }
  return records;
}

// One chunk holding every message (in the given order), then the index section.
std::string WriteBag(const std::vector<Written>& messages, const std::string& compression,
                     bool indexed = true) {
  std::map<std::string, uint32_t> ids;
  std::map<std::string, std::string> types;
  for (const Written& m : messages) {
    ids.emplace(m.topic, uint32_t(ids.size()));
    types[m.topic] = m.type;
  }
  const auto connection = [&](const std::string& topic) {
    return Record(Op(0x07) + Field("conn", Le32(ids[topic])) + Field("topic", topic),
                  Field("topic", topic) + Field("type", types[topic]) + Field("md5sum", "*"));
  };
  std::string records;
  for (const auto& [topic, id] : ids) records += connection(topic);
  std::map<uint32_t, uint32_t> counts;
  for (const Written& m : messages) {
    records += Record(
        Op(0x02) + Field("conn", Le32(ids[m.topic])) + Field("time", Time(m.receive_ns)), m.data);
    ++counts[ids[m.topic]];
  }
  const std::string chunk = Record(
      Op(0x05) + Field("compression", compression) + Field("size", Le32(uint32_t(records.size()))),
      Compress(records, compression));
  const std::string magic = "#ROSBAG V2.0\n";
  const auto header = [&](uint64_t index_pos) {
    const std::string fields = Op(0x03) + Field("index_pos", Le64(index_pos)) +
                               Field("conn_count", Le32(uint32_t(ids.size()))) +
                               Field("chunk_count", Le32(1));
    return Record(fields, std::string(4096 - 8 - fields.size(), ' '));
  };
  const uint64_t chunk_pos = magic.size() + header(0).size();
  std::string index;
  for (const auto& [topic, id] : ids) index += connection(topic);
  std::string per_connection;
  for (const auto& [id, count] : counts) per_connection += Le32(id) + Le32(count);
  index += Record(Op(0x06) + Field("ver", Le32(1)) + Field("chunk_pos", Le64(chunk_pos)) +
                      Field("start_time", Time(0)) + Field("end_time", Time(0)) +
                      Field("count", Le32(uint32_t(counts.size()))),
                  per_connection);
  if (!indexed) return magic + header(0) + chunk;
  return magic + header(chunk_pos + chunk.size()) + chunk + index;
}

class BagFiles : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("placedb-rosbag-" + std::to_string(::getpid()) + "-" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string Write(const std::string& name, const std::string& bytes) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path, std::ios::binary) << bytes;
    return path;
  }
  fs::path dir_;
};

constexpr int64_t kStamp = 1'700'000'000'123'456'789;

// Two 4x2 rgb8 frames (rows padded to 16 bytes), written in reverse receive order, and one
// camera info.
std::vector<Written> TwoFrames() {
  std::string pixels;
  for (int row = 0; row < 2; ++row) {
    for (int i = 0; i < 12; ++i) pixels += char(row * 12 + i);
    pixels += std::string(4, char(0xAB));  // padding
  }
  return {
      {"/camera/image_raw", "sensor_msgs/Image", kStamp + 2'000'000'000,
       ImageMessage(kStamp + 1'000'000'000, 4, 2, "rgb8", 16, pixels)},
      {"/camera/image_raw", "sensor_msgs/Image", kStamp + 1'000'000'000,
       ImageMessage(kStamp, 4, 2, "rgb8", 16, pixels)},
      {"/camera/camera_info", "sensor_msgs/CameraInfo", kStamp,
       CameraInfoMessage(kStamp, "plumb_bob", {0.1, -0.2, 0, 0, 0})},
  };
}

TEST_F(BagFiles, ReadsTopicsAndMessagesInEveryCompression) {
  for (const std::string compression : {"none", "bz2", "lz4"}) {
    SCOPED_TRACE(compression);
    std::string error;
    auto bag =
        BagReader::Open(Write(compression + ".bag", WriteBag(TwoFrames(), compression)), &error);
    ASSERT_TRUE(bag) << error;
    const std::vector<BagTopic> topics = bag->topics();
    ASSERT_EQ(topics.size(), 2u);
    EXPECT_EQ(topics[0].topic, "/camera/camera_info");
    EXPECT_EQ(topics[0].messages, 1u);
    EXPECT_EQ(topics[1].type, "sensor_msgs/Image");
    EXPECT_EQ(topics[1].messages, 2u);

    bag->Select({"/camera/image_raw", "/camera/camera_info"});
    std::vector<BagMessage> read;
    BagMessage message;
    while (bag->Next(&message, &error)) read.push_back(message);
    ASSERT_EQ(error, "");
    ASSERT_EQ(read.size(), 3u);
    // By receive time, not file order.
    EXPECT_EQ(read[0].topic, "/camera/camera_info");
    EXPECT_EQ(read[1].receive_time_ns, kStamp + 1'000'000'000);
    RosImage image;
    ASSERT_TRUE(ParseRosImage(read[1].data, &image, &error)) << error;
    EXPECT_EQ(image.stamp_ns, kStamp);
    EXPECT_EQ(image.width, 4u);
    EXPECT_EQ(image.encoding, "rgb8");
    EXPECT_EQ(image.step, 16u);
    RosCameraInfo info;
    ASSERT_TRUE(ParseRosCameraInfo(read[0].data, &info, &error)) << error;
    EXPECT_EQ(info.k[0], 518);
    EXPECT_EQ(info.k[5], 253.5);
    EXPECT_EQ(info.d, (std::vector<double>{0.1, -0.2, 0, 0, 0}));

    bag->Select({"/camera/camera_info"});
    size_t infos = 0;
    while (bag->Next(&message, &error)) ++infos;
    EXPECT_EQ(infos, 1u);
  }
}

TEST_F(BagFiles, AnUnindexedBagIsScanned) {
  std::string error;
  auto bag = BagReader::Open(Write("cut.bag", WriteBag(TwoFrames(), "bz2", false)), &error);
  ASSERT_TRUE(bag) << error;
  ASSERT_EQ(bag->topics().size(), 2u);
  EXPECT_EQ(bag->topics()[1].messages, 2u);
  EXPECT_EQ(bag->topics()[1].type, "sensor_msgs/Image");
}

TEST_F(BagFiles, ErrorsNameTheFileAndTheProblem) {
  const std::string bytes = WriteBag(TwoFrames(), "none");
  std::string error;
  EXPECT_FALSE(BagReader::Open(Write("half.bag", bytes.substr(0, bytes.size() / 2)), &error));
  EXPECT_NE(error.find("half.bag: truncated"), std::string::npos) << error;

  EXPECT_FALSE(BagReader::Open(Write("short.bag", bytes.substr(0, 100)), &error));
  EXPECT_NE(error.find("short.bag: truncated"), std::string::npos) << error;

  EXPECT_FALSE(BagReader::Open(Write("zstd.bag", WriteBag(TwoFrames(), "zstd")), &error));
  EXPECT_NE(error.find("compressed with 'zstd'"), std::string::npos) << error;

  // A chunk declaring 2 GiB uncompressed is refused before anything is allocated.
  std::string huge = WriteBag(TwoFrames(), "bz2");
  const size_t size_field = huge.find("size=");
  ASSERT_NE(size_field, std::string::npos);
  huge.replace(size_field + 5, 4, Le32(0x7FFFFFFF));
  EXPECT_FALSE(BagReader::Open(Write("huge.bag", huge), &error));
  EXPECT_NE(error.find("declares 2147483647 bytes uncompressed"), std::string::npos) << error;

  EXPECT_FALSE(BagReader::Open(Write("text.bag", "hello\n"), &error));
  EXPECT_NE(error.find("not a ROS 1 bag"), std::string::npos) << error;

  EXPECT_FALSE(BagReader::Open((dir_ / "absent.bag").string(), &error));
  EXPECT_NE(error.find("absent.bag: cannot read"), std::string::npos) << error;

  RosImage image;
  const std::string message = TwoFrames()[0].data;
  EXPECT_FALSE(
      ParseRosImage(std::string_view(message).substr(0, message.size() - 3), &image, &error));
  EXPECT_NE(error.find("sensor_msgs/Image"), std::string::npos) << error;
}

TEST_F(BagFiles, AnUnknownTopicListsTheImageTopics) {
  const std::string path = Write("run.bag", WriteBag(TwoFrames(), "none"));
  RecordingOptions options;
  options.topic = "/camera/rgb";
  std::string error;
  EXPECT_FALSE(Recording::Open(path, options, &error));
  EXPECT_NE(error.find("--topic /camera/rgb: not in " + path), std::string::npos) << error;
  EXPECT_NE(error.find("/camera/image_raw (sensor_msgs/Image, 2 messages)"), std::string::npos)
      << error;
  options.topic = "/camera/camera_info";
  EXPECT_FALSE(Recording::Open(path, options, &error));
  EXPECT_NE(error.find("sensor_msgs/CameraInfo, expected sensor_msgs/Image or "
                       "sensor_msgs/CompressedImage"),
            std::string::npos)
      << error;
  options.topic = "";
  EXPECT_FALSE(Recording::Open(path, options, &error));
  EXPECT_NE(error.find("--topic"), std::string::npos) << error;
}

TEST_F(BagFiles, FramesCarryTheirStampCameraAndDepth) {
  std::vector<Written> messages = TwoFrames();
  // 16UC1 depth 3 ms after the first frame (little-endian millimetres 1000..1007).
  std::string mm;
  for (uint16_t v = 1000; v < 1008; ++v) mm += std::string{char(v & 0xFF), char(v >> 8)};
  messages.push_back({"/depth", "sensor_msgs/Image", kStamp + 1'000'000'001,
                      ImageMessage(kStamp + 3'000'000, 4, 2, "16UC1", 8, mm)});
  // A frame whose size its data cannot hold (the row arithmetic must not overflow).
  messages.push_back(
      {"/camera/image_raw", "sensor_msgs/Image", kStamp + 2'500'000'000,
       ImageMessage(kStamp + 1'500'000'000, 0xFFFFFFFF, 0xFFFFFFFF, "bgr8", 0xFFFFFFFF, "abc")});
  // A frame of an encoding placedb does not read.
  messages.push_back({"/camera/image_raw", "sensor_msgs/Image", kStamp + 3'000'000'000,
                      ImageMessage(kStamp + 2'000'000'000, 2, 2, "yuv422", 4, "abcdefgh")});
  RecordingOptions options;
  options.topic = "/camera/image_raw";
  options.depth_topic = "/depth";
  options.camera_info_topic = "/camera/camera_info";
  std::string error;
  auto recording = Recording::Open(Write("run.bag", WriteBag(messages, "lz4")), options, &error);
  ASSERT_TRUE(recording) << error;
  EXPECT_EQ(recording->expected_frames(), 4u);

  RecordedFrame frame;
  ASSERT_TRUE(recording->Next(&frame, &error));
  ASSERT_EQ(error, "");
  const v1::Observation& first = frame.observation;
  EXPECT_EQ(first.timestamp_ns(), kStamp);
  ASSERT_TRUE(first.has_raw_image());
  EXPECT_EQ(first.raw_image().format(), v1::PIXEL_FORMAT_RGB8);
  EXPECT_EQ(first.raw_image().data().size(), 24u);  // the padding dropped
  EXPECT_EQ(first.raw_image().data()[12], char(12));
  EXPECT_EQ(first.camera().fx(), 518);
  EXPECT_EQ(first.camera().distortion_model(), "plumb_bob");
  EXPECT_EQ(first.camera().distortion_size(), 5);
  ASSERT_TRUE(first.has_depth());
  EXPECT_FALSE(first.depth().png16().empty());
  EXPECT_FLOAT_EQ(first.depth().scale(), 0.001f);
  EXPECT_EQ(first.depth().intrinsics().cy(), 253.5);

  ASSERT_TRUE(recording->Next(&frame, &error));
  EXPECT_EQ(frame.observation.timestamp_ns(), kStamp + 1'000'000'000);
  EXPECT_FALSE(frame.observation.has_depth());  // 1 s from the only depth image

  ASSERT_TRUE(recording->Next(&frame, &error));
  EXPECT_NE(error.find("/camera/image_raw message 2: 3 bytes with step 4294967295"),
            std::string::npos)
      << error;
  ASSERT_TRUE(recording->Next(&frame, &error));
  EXPECT_NE(error.find("encoding 'yuv422'"), std::string::npos) << error;
  EXPECT_NE(error.find("/camera/image_raw message 3"), std::string::npos) << error;
  EXPECT_FALSE(recording->Next(&frame, &error));
  EXPECT_EQ(error, "");
  EXPECT_EQ(recording->stats().depth_paired, 1u);
  EXPECT_EQ(recording->stats().depth_missing, 1u);
  EXPECT_EQ(recording->stats().cameras, 2u);
}

TEST(TumHelpers, TimestampsAreExactAndPosesInterpolated) {
  int64_t ns = 0;
  ASSERT_TRUE(ParseSecondsToNs("1305031102.175304", &ns));
  EXPECT_EQ(ns, 1'305'031'102'175'304'000);
  ASSERT_TRUE(ParseSecondsToNs("1700000000.123456789", &ns));
  EXPECT_EQ(ns, 1'700'000'000'123'456'789);
  EXPECT_FALSE(ParseSecondsToNs("1.2.3", &ns));
  EXPECT_FALSE(ParseSecondsToNs("12e3", &ns));
  EXPECT_FALSE(ParseSecondsToNs("", &ns));
  EXPECT_FALSE(ParseSecondsToNs("9999999999.5", &ns));  // beyond int64 nanoseconds

  v1::Pose a, b;
  a.set_qw(1);
  b.set_x(2);
  b.set_qz(std::sin(M_PI / 4));  // 90 degrees about z
  b.set_qw(std::cos(M_PI / 4));
  const std::vector<int64_t> times = {1000, 2000};
  const std::vector<v1::Pose> poses = {a, b};
  const auto half = InterpolatePose(times, poses, 1500, 100, 5000);
  ASSERT_TRUE(half);
  EXPECT_DOUBLE_EQ(half->x(), 1.0);
  EXPECT_NEAR(half->qz(), std::sin(M_PI / 8), 1e-12);  // 45 degrees
  EXPECT_NEAR(half->qw(), std::cos(M_PI / 8), 1e-12);
  // Samples too far apart: the nearest within the offset, else none.
  EXPECT_EQ(InterpolatePose(times, poses, 1050, 100, 500)->x(), 0);
  EXPECT_FALSE(InterpolatePose(times, poses, 1500, 100, 500));
  EXPECT_FALSE(InterpolatePose(times, poses, 2500, 100, 5000));
}

}  // namespace
}  // namespace placedb::client
