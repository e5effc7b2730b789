#include "core/base/files.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "tests/test_support.h"

namespace placedb {
namespace {

namespace fs = std::filesystem;

void WriteFile(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out << bytes;
  ASSERT_TRUE(out.good()) << path;
}

std::vector<std::string> Sorted(std::vector<std::string> names) {
  std::sort(names.begin(), names.end(), NaturalLess);
  return names;
}

TEST(NaturalLess, DigitRunsCompareByValue) {
  EXPECT_EQ(Sorted({"10.jpg", "2.jpg", "1.jpg", "frame_011.png", "frame_9.png", "b.jpg", "a10.jpg",
                    "a9.jpg"}),
            (std::vector<std::string>{"1.jpg", "2.jpg", "10.jpg", "a9.jpg", "a10.jpg", "b.jpg",
                                      "frame_9.png", "frame_011.png"}));
  // placedb-recognize once put frame_10 first: a run with leading zeros is not a larger number.
  EXPECT_TRUE(NaturalLess("frame_007", "frame_10"));
  EXPECT_FALSE(NaturalLess("frame_10", "frame_007"));
  EXPECT_TRUE(NaturalLess("frame_9", "frame_0010"));
  EXPECT_TRUE(NaturalLess("x2y10", "x2y11"));
  EXPECT_TRUE(NaturalLess("x2y11", "x10y1"));
}

TEST(NaturalLess, IsATotalOrder) {
  // Equal values with different leading zeros: fewer zeros first, and never equivalent.
  EXPECT_TRUE(NaturalLess("7", "07"));
  EXPECT_TRUE(NaturalLess("07", "007"));
  EXPECT_FALSE(NaturalLess("07", "7"));
  EXPECT_TRUE(NaturalLess("a0", "a00"));
  EXPECT_FALSE(NaturalLess("same1", "same1"));
  // A prefix comes first; non-digits compare byte by byte.
  EXPECT_TRUE(NaturalLess("frame", "frame1"));
  EXPECT_TRUE(NaturalLess("", "a"));
  EXPECT_FALSE(NaturalLess("", ""));
  EXPECT_TRUE(NaturalLess("B1", "a1"));
  // Every pair of distinct names is ordered one way exactly, and the order is transitive.
  const std::vector<std::string> names = {
      "",    "0",    "00",  "1",   "01",   "10", "a",      "a0",  "a00",    "a1", "a01",
      "a1b", "a01b", "a1c", "a10", "a010", "b",  "b2.jpg", "b02", "b2.png", "9z", "10a"};
  for (const auto& x : names) {
    for (const auto& y : names) {
      if (x == y) continue;
      EXPECT_NE(NaturalLess(x, y), NaturalLess(y, x)) << x << " vs " << y;
      for (const auto& z : names) {
        if (NaturalLess(x, y) && NaturalLess(y, z)) {
          EXPECT_TRUE(NaturalLess(x, z)) << x << " < " << y << " < " << z;
        }
      }
    }
  }
}

TEST(IsImageFile, KnownExtensionsInAnyCase) {
  for (const char* name : {"a.jpg", "a.JPG", "a.jpeg", "a.Jpeg", "a.png", "a.PNG", "a.bmp", "a.pgm",
                           "a.ppm", "a.pnm", "a.tif", "a.TIFF", "a.webp", "/x/y.z.png"}) {
    EXPECT_TRUE(IsImageFile(name)) << name;
  }
  for (const char* name : {"a", "a.txt", "a.jpgx", "jpg", "a.png.bak", "a.avi", ".png.d/x"}) {
    EXPECT_FALSE(IsImageFile(name)) << name;
  }
}

TEST(ListImageFiles, ImagesOnlyInNaturalOrder) {
  const std::string dir = testing::MakeTempDir("placedb-files");
  for (const char* name : {"frame_10.jpg", "frame_007.PNG", "frame_9.jpeg", "notes.txt", "b.bmp"}) {
    WriteFile(dir + "/" + name, "x");
  }
  fs::create_directory(dir + "/folder.png");  // a directory is not an image file
  auto listed = ListImageFiles(dir);
  ASSERT_TRUE(listed.ok()) << listed.status().ToString();
  EXPECT_EQ(*listed, (std::vector<std::string>{dir + "/b.bmp", dir + "/frame_007.PNG",
                                               dir + "/frame_9.jpeg", dir + "/frame_10.jpg"}));

  const std::string empty = testing::MakeTempDir("placedb-files-empty");
  auto none = ListImageFiles(empty);
  ASSERT_TRUE(none.ok());
  EXPECT_TRUE(none->empty());

  EXPECT_EQ(ListImageFiles(dir + "/missing").status().code(), StatusCode::kNotFound);
  EXPECT_EQ(ListImageFiles(dir + "/notes.txt").status().code(), StatusCode::kNotFound);
}

TEST(ReadWholeFile, ReadsEveryByte) {
  const std::string dir = testing::MakeTempDir("placedb-read");
  std::string bytes;
  for (int i = 0; i < 100000; ++i) bytes.push_back(char(i * 7919 % 256));  // with NULs
  WriteFile(dir + "/data.bin", bytes);
  auto read = ReadWholeFile(dir + "/data.bin");
  ASSERT_TRUE(read.ok()) << read.status().ToString();
  EXPECT_EQ(*read, bytes);

  WriteFile(dir + "/empty", "");
  auto empty = ReadWholeFile(dir + "/empty");
  ASSERT_TRUE(empty.ok());
  EXPECT_TRUE(empty->empty());

  // st_size is 0 for /proc files: the reader goes by end of file, not by the size.
  auto proc = ReadWholeFile("/proc/self/status");
  ASSERT_TRUE(proc.ok()) << proc.status().ToString();
  EXPECT_NE(proc->find("Name:"), std::string::npos);
}

TEST(ReadWholeFile, ErrorsNameThePath) {
  const std::string dir = testing::MakeTempDir("placedb-read-errors");
  const auto missing = ReadWholeFile(dir + "/missing.bin");
  EXPECT_EQ(missing.status().code(), StatusCode::kNotFound);
  EXPECT_EQ(missing.status().message(), "no such file: " + dir + "/missing.bin");

  const auto directory = ReadWholeFile(dir);
  EXPECT_EQ(directory.status().code(), StatusCode::kIoError);
  EXPECT_NE(directory.status().message().find(dir), std::string::npos);
  EXPECT_NE(directory.status().message().find("Is a directory"), std::string::npos)
      << directory.status().message();
}

}  // namespace
}  // namespace placedb
