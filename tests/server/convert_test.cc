// proto/convert_frame (the server's observation decoding): image headers read without decoding
// the image.
#include <gtest/gtest.h>

#include <cstdint>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "proto/convert_frame.h"
#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

TEST(ServerConvertTest, ImageHeadersAreReadWithoutDecoding) {
  auto png = wire::ReadImageHeader(EncodePng(cv::Mat::zeros(30, 40, CV_8U)));
  ASSERT_TRUE(png.ok());
  EXPECT_EQ(png->width, 40);
  EXPECT_EQ(png->height, 30);
  std::vector<uint8_t> jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", cv::Mat::zeros(70, 90, CV_8UC3), jpeg));
  auto header = wire::ReadImageHeader(std::string(jpeg.begin(), jpeg.end()));
  ASSERT_TRUE(header.ok()) << header.status().ToString();
  EXPECT_EQ(header->width, 90);
  EXPECT_EQ(header->height, 70);
  EXPECT_FALSE(wire::ReadImageHeader("GIF89a").ok());
  EXPECT_FALSE(wire::ReadImageHeader(std::string(jpeg.begin(), jpeg.begin() + 20)).ok());
}

}  // namespace
}  // namespace placedb::server_testing
