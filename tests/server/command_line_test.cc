// placedb-server's command line (issue 33): usage errors exit 2 as placedb's and placedb-load's
// do (not CLI11's own 104-109), and --help lists the `tokens` command group main() parses first.
#include <gtest/gtest.h>

#include <string>

#include "server/config.h"

namespace placedb::server {
namespace {

const char* NoEnvironment(const char*) {
  return nullptr;
}

TEST(ServerCommandLine, UsageErrorsExit2) {
  const std::vector<std::vector<const char*>> lines = {
      {"placedb-server", "--bogus"},            // CLI11: ExtrasError (109)
      {"placedb-server", "--max-boxes", "-1"},  // ConversionError (104)
      {"placedb-server", "--threads", "x"},     // ConversionError
      {"placedb-server", "--listen"}};          // ArgumentMismatch
  for (const auto& argv : lines) {
    testing::internal::CaptureStderr();
    testing::internal::CaptureStdout();
    auto parsed = ParseCommandLine(int(argv.size()), argv.data(), NoEnvironment);
    const std::string err = testing::internal::GetCapturedStderr();
    testing::internal::GetCapturedStdout();
    ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
    ASSERT_TRUE(parsed->exit_code.has_value()) << argv[1];
    EXPECT_EQ(*parsed->exit_code, 2) << argv[1] << ": " << err;
  }
}

TEST(ServerCommandLine, HelpListsTokensAndExitCodes) {
  const char* argv[] = {"placedb-server", "--help"};
  testing::internal::CaptureStdout();
  auto parsed = ParseCommandLine(2, argv, NoEnvironment);
  const std::string out = testing::internal::GetCapturedStdout();
  ASSERT_TRUE(parsed.ok());
  ASSERT_TRUE(parsed->exit_code.has_value());
  EXPECT_EQ(*parsed->exit_code, 0);
  EXPECT_NE(out.find("  tokens "), std::string::npos) << out;
  EXPECT_NE(out.find("placedb-server tokens --help"), std::string::npos) << out;
  EXPECT_NE(out.find("Exit codes"), std::string::npos) << out;
}

}  // namespace
}  // namespace placedb::server
