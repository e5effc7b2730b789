#include "core/base/status.h"

#include <gtest/gtest.h>

#include <memory>
#include <string>

namespace placedb {
namespace {

TEST(Status, DefaultIsOk) {
  Status status;
  EXPECT_TRUE(status.ok());
  EXPECT_EQ(status.ToString(), "OK");
}

TEST(Status, CarriesCodeAndMessage) {
  Status status = Status::InvalidArgument("keypoints[3].x is outside the image");
  EXPECT_FALSE(status.ok());
  EXPECT_EQ(status.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(status.ToString(), "INVALID_ARGUMENT: keypoints[3].x is outside the image");
}

TEST(Status, WithContextKeepsCode) {
  Status status = Status::Corruption("bad magic").WithContext("loading vocab.pdbv");
  EXPECT_EQ(status.code(), StatusCode::kCorruption);
  EXPECT_EQ(status.message(), "loading vocab.pdbv: bad magic");
  EXPECT_TRUE(Status::Ok().WithContext("ignored").ok());
}

TEST(Status, EveryCodeHasAName) {
  for (StatusCode code : {StatusCode::kOk, StatusCode::kInvalidArgument, StatusCode::kNotFound,
                          StatusCode::kAlreadyExists, StatusCode::kFailedPrecondition,
                          StatusCode::kResourceExhausted, StatusCode::kCorruption,
                          StatusCode::kIoError, StatusCode::kInternal, StatusCode::kCancelled}) {
    EXPECT_STRNE(StatusCodeName(code), "UNKNOWN");
  }
}

Result<int> Half(int value) {
  if (value % 2 != 0) return Status::InvalidArgument("value must be even");
  return value / 2;
}

Status Chain(int value, int* out) {
  auto half = Half(value);
  PLACEDB_RETURN_IF_ERROR(half.status());
  *out = *half;
  return Status::Ok();
}

TEST(Result, HoldsValueOrStatus) {
  auto ok = Half(8);
  ASSERT_TRUE(ok.ok());
  EXPECT_EQ(*ok, 4);
  EXPECT_TRUE(ok.status().ok());
  auto bad = Half(3);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), StatusCode::kInvalidArgument);
}

TEST(Result, MoveOnlyValues) {
  Result<std::unique_ptr<int>> result(std::make_unique<int>(7));
  ASSERT_TRUE(result.ok());
  std::unique_ptr<int> taken = std::move(result).value();
  EXPECT_EQ(*taken, 7);
}

TEST(Status, ReturnIfErrorPropagates) {
  int out = 0;
  EXPECT_TRUE(Chain(10, &out).ok());
  EXPECT_EQ(out, 5);
  Status failed = Chain(7, &out);
  EXPECT_EQ(failed.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(out, 5);
}

}  // namespace
}  // namespace placedb
