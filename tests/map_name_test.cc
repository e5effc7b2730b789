// core/base/map_name: the one map-name rule, and how a refused name is shown in its message.
#include "core/base/map_name.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

namespace placedb {
namespace {

using namespace std::string_literals;

// Every byte of `text` is printable ASCII: a message that can be logged and shown as it is.
bool AllPrintable(const std::string& text) {
  for (char c : text) {
    const auto byte = static_cast<unsigned char>(c);
    if (byte < 0x20 || byte >= 0x7f) return false;
  }
  return true;
}

TEST(MapName, AcceptsTheRule) {
  for (const std::string& name : {"a"s, "Z"s, "7"s, "loop"s, "warehouse-7"s, "campus_2024.v2"s,
                                  "a..b"s, "0-_.x"s, std::string(kMaxMapNameLength, 'm')}) {
    EXPECT_TRUE(ValidateMapName(name).ok()) << name << ": " << ValidateMapName(name).ToString();
  }
}

TEST(MapName, RefusesNamesThatAreNotOnePlainPathComponent) {
  const std::vector<std::string> refused = {
      ""s,
      "."s,
      ".."s,
      "../evil"s,
      "a/b"s,
      "/etc/passwd"s,
      "a\\b"s,
      "a\0b"s,  // an embedded NUL: a C API would see "a"
      "\0"s,
      "\x7f"s,
      "a\x7f"s,
      "a\nb"s,
      "a\tb"s,
      "caf\xc3\xa9"s,               // café
      "\xe5\x9c\xb0\xe5\x9b\xbe"s,  // 地图
      "\xf0\x9f\x97\xba"s,          // an emoji
      "\xff\xfe"s,                  // not UTF-8 at all
      "-leading-dash"s,
      ".hidden"s,
      "_under"s,
      " space"s,
      "two words"s,
      "trailing "s,
      "a:b"s,
      "a*"s,
      "a\"b"s,
      std::string(kMaxMapNameLength + 1, 'm'),
      std::string(100000, 'x'),
  };
  for (const std::string& name : refused) {
    const Status status = ValidateMapName(name);
    const std::string shown = QuoteForMessage(name);
    EXPECT_EQ(status.code(), StatusCode::kInvalidArgument) << shown;
    // The message states the rule, quotes the name safely and stays short.
    EXPECT_NE(status.message().find("1-64 characters of A-Z a-z 0-9 _ . - starting with a letter "
                                    "or digit"),
              std::string::npos)
        << status.message();
    EXPECT_NE(status.message().find(shown), std::string::npos) << status.message();
    EXPECT_TRUE(AllPrintable(status.message())) << shown;
    EXPECT_LT(status.message().size(), 500u) << shown;
  }
}

TEST(MapName, SixtyFourIsTheLongest) {
  EXPECT_TRUE(ValidateMapName(std::string(64, 'a')).ok());
  const Status too_long = ValidateMapName(std::string(65, 'a'));
  EXPECT_EQ(too_long.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(too_long.message().find("it is 65 bytes long"), std::string::npos)
      << too_long.message();
}

TEST(MapName, MessageSaysWhatIsWrong) {
  EXPECT_NE(ValidateMapName("").message().find("(it is empty)"), std::string::npos);
  EXPECT_NE(ValidateMapName("../evil").message().find("(it starts with '.')"), std::string::npos);
  EXPECT_NE(ValidateMapName("-x").message().find("(it starts with '-')"), std::string::npos);
  EXPECT_NE(ValidateMapName("a/b").message().find("(byte 2 is '/')"), std::string::npos);
  EXPECT_NE(ValidateMapName("a\0b"s).message().find("(byte 2 is \\x00)"), std::string::npos)
      << ValidateMapName("a\0b"s).message();
  EXPECT_NE(ValidateMapName("caf\xc3\xa9").message().find("(byte 4 is \\xc3)"), std::string::npos);
  EXPECT_EQ(ValidateMapName("../evil").message(),
            "map name \"../evil\" is invalid (it starts with '.'): a map name is 1-64 characters "
            "of A-Z a-z 0-9 _ . - starting with a letter or digit");
}

TEST(MapName, QuoteEscapesAndTruncates) {
  EXPECT_EQ(QuoteForMessage("loop"), "\"loop\"");
  EXPECT_EQ(QuoteForMessage(""), "\"\"");
  EXPECT_EQ(QuoteForMessage("a\0b"s), "\"a\\x00b\"");
  EXPECT_EQ(QuoteForMessage("\x7f"), "\"\\x7f\"");
  EXPECT_EQ(QuoteForMessage("caf\xc3\xa9"), "\"caf\\xc3\\xa9\"");
  EXPECT_EQ(QuoteForMessage("a\"b\\c"), "\"a\\\"b\\\\c\"");
  EXPECT_EQ(QuoteForMessage("line\nbreak"), "\"line\\x0abreak\"");
  EXPECT_EQ(QuoteForMessage(std::string(64, 'x')), "\"" + std::string(64, 'x') + "\"");
  EXPECT_EQ(QuoteForMessage(std::string(100000, 'x')),
            "\"" + std::string(64, 'x') + "\"... (100000 bytes)");
  EXPECT_EQ(QuoteForMessage("abcdef", 3), "\"abc\"... (6 bytes)");
}

}  // namespace
}  // namespace placedb
