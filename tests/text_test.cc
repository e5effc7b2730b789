// Text helpers (core/base/text.h): the escaping every log line applies to client-supplied strings
// and that QuoteForMessage shares.
#include "core/base/text.h"

#include <gtest/gtest.h>

#include <string>

#include "core/base/map_name.h"

namespace placedb {
namespace {

using namespace std::string_literals;

TEST(TextTest, ParseHex64IsHex64sInverse) {
  for (const uint64_t value :
       {uint64_t(0), uint64_t(1), uint64_t(0xfedcba9876543210), ~uint64_t(0)}) {
    EXPECT_EQ(ParseHex64(Hex64(value)), value);
  }
  EXPECT_EQ(ParseHex64("FEDCBA9876543210"), uint64_t(0xfedcba9876543210));
  EXPECT_EQ(ParseHex64(""), std::nullopt);
  EXPECT_EQ(ParseHex64("123"), std::nullopt);                // too short
  EXPECT_EQ(ParseHex64("00000000000000000"), std::nullopt);  // too long
  EXPECT_EQ(ParseHex64("000000000000000g"), std::nullopt);   // not a digit
  EXPECT_EQ(ParseHex64("-00000000000000f"), std::nullopt);
}

TEST(TextTest, ForLogEscapesWhatCouldBreakALineOrDriveATerminal) {
  EXPECT_EQ(ForLog("robot-7"), "robot-7");
  EXPECT_EQ(ForLog(""), "");
  EXPECT_EQ(ForLog("a\nb"), "a\\nb");
  EXPECT_EQ(ForLog("a\r\nINFO forged"), "a\\r\\nINFO forged");
  EXPECT_EQ(ForLog("tab\there"), "tab\\there");
  EXPECT_EQ(ForLog("\x1b[31mred\x1b[0m"), "\\x1b[31mred\\x1b[0m");
  EXPECT_EQ(ForLog("nul\0byte"s), "nul\\x00byte");
  EXPECT_EQ(ForLog("del\x7f"), "del\\x7f");
  EXPECT_EQ(ForLog("say \"hi\" \\ bye"), "say \\\"hi\\\" \\\\ bye");
  // Valid UTF-8 stays readable; invalid bytes (a lone continuation byte, a truncated sequence,
  // an overlong '/', a surrogate, 0xff) are escaped one by one.
  EXPECT_EQ(ForLog("caf\xc3\xa9 \xe6\x9d\xb1\xe4\xba\xac \xf0\x9f\xa4\x96"),
            "caf\xc3\xa9 \xe6\x9d\xb1\xe4\xba\xac \xf0\x9f\xa4\x96");
  EXPECT_EQ(ForLog("a\x80z"), "a\\x80z");
  EXPECT_EQ(ForLog("a\xc3"), "a\\xc3");
  EXPECT_EQ(ForLog("\xc0\xaf"), "\\xc0\\xaf");
  EXPECT_EQ(ForLog("\xed\xa0\x80"), "\\xed\\xa0\\x80");
  EXPECT_EQ(ForLog("\xff\xfe"), "\\xff\\xfe");
  // Code points that end a line or reorder the text after them: NEL, LINE SEPARATOR, PARAGRAPH
  // SEPARATOR, RIGHT-TO-LEFT OVERRIDE, FIRST STRONG ISOLATE.
  EXPECT_EQ(ForLog("a\xc2\x85"
                   "b"),
            "a\\u0085b");
  EXPECT_EQ(ForLog("a\xe2\x80\xa8"
                   "b\xe2\x80\xa9"),
            "a\\u2028b\\u2029");
  EXPECT_EQ(ForLog("\xe2\x80\xae"
                   "evil"),
            "\\u202eevil");
  EXPECT_EQ(ForLog("\xe2\x81\xa8"), "\\u2068");
}

TEST(TextTest, ForLogCutsLongTextAtACharacterBoundary) {
  EXPECT_EQ(ForLog("abcdef", 3), "abc... (6 bytes)");
  EXPECT_EQ(ForLog("abc", 3), "abc");
  // The cut would fall inside "é" (2 bytes): it moves back before it.
  EXPECT_EQ(ForLog("ab\xc3\xa9z", 3), "ab... (5 bytes)");
  const std::string flood(100'000, '\n');
  const std::string shown = ForLog(flood);
  EXPECT_EQ(shown.find('\n'), std::string::npos);
  EXPECT_EQ(shown.size(), 2 * kMaxLogTextBytes + std::string("... (100000 bytes)").size());
}

TEST(TextTest, QuoteForMessageSharesTheEscapingInItsAsciiForm) {
  // Every byte outside printable ASCII as \xNN, newline included: the form error messages use.
  EXPECT_EQ(QuoteForMessage("line\nbreak"), "\"line\\x0abreak\"");
  EXPECT_EQ(QuoteForMessage("caf\xc3\xa9"), "\"caf\\xc3\\xa9\"");
  std::string escaped;
  AppendEscaped(&escaped, "a\n\"\xc3\xa9", EscapeMode::kAscii);
  EXPECT_EQ(escaped, "a\\x0a\\\"\\xc3\\xa9");
}

}  // namespace
}  // namespace placedb
