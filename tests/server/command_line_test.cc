// placedb-server's command line (issue 33): usage errors exit 2 as placedb's and placedb-load's
// do (not CLI11's own 104-109), --help lists the `tokens` command group main() parses first, and
// the embedded defaults' files are found from the executable or PLACEDB_HOME, not the working
// directory.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <string>

#include "server/config.h"
#include "tests/test_support.h"

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
    ::testing::internal::CaptureStderr();
    ::testing::internal::CaptureStdout();
    auto parsed = ParseCommandLine(int(argv.size()), argv.data(), NoEnvironment);
    const std::string err = ::testing::internal::GetCapturedStderr();
    ::testing::internal::GetCapturedStdout();
    ASSERT_TRUE(parsed.ok()) << parsed.status().ToString();
    ASSERT_TRUE(parsed->exit_code.has_value()) << argv[1];
    EXPECT_EQ(*parsed->exit_code, 2) << argv[1] << ": " << err;
  }
}

TEST(ServerCommandLine, HelpListsTokensAndExitCodes) {
  const char* argv[] = {"placedb-server", "--help"};
  ::testing::internal::CaptureStdout();
  auto parsed = ParseCommandLine(2, argv, NoEnvironment);
  const std::string out = ::testing::internal::GetCapturedStdout();
  ASSERT_TRUE(parsed.ok());
  ASSERT_TRUE(parsed->exit_code.has_value());
  EXPECT_EQ(*parsed->exit_code, 0);
  EXPECT_NE(out.find("  tokens "), std::string::npos) << out;
  EXPECT_NE(out.find("placedb-server tokens --help"), std::string::npos) << out;
  EXPECT_NE(out.find("Exit codes"), std::string::npos) << out;
}

// A directory laid out as a checkout: server/placedb.yaml, and var/vocabulary/default.pdbv
// unless `with_vocabulary` is false.
std::string FakeCheckout(const std::string& name, bool with_vocabulary) {
  namespace fs = std::filesystem;
  const fs::path root = fs::path(::placedb::testing::MakeTempDir(name));
  fs::create_directories(root / "server");
  fs::create_directories(root / "build" / "server");
  std::ofstream(root / "server" / "placedb.yaml") << "# the example\n";
  if (with_vocabulary) {
    fs::create_directories(root / "var" / "vocabulary");
    std::ofstream(root / "var" / "vocabulary" / "default.pdbv") << "words";
  }
  return root.string();
}

TEST(ServerDefaultPaths, RootsArePlacedbHomeAloneOrTheExecutablesCheckoutThenTheWorkingDirectory) {
  const std::string checkout = FakeCheckout("placedb-roots", true);
  const std::string exe = checkout + "/build/server/placedb-server";
  const auto roots = DefaultPathRoots(NoEnvironment, exe);
  ASSERT_EQ(roots.size(), 2u);
  EXPECT_EQ(roots[0].dir, checkout);
  EXPECT_EQ(roots[0].why, "the checkout of " + exe);
  EXPECT_EQ(roots[1].dir, std::filesystem::current_path().string());
  EXPECT_EQ(roots[1].why, "the working directory");

  const std::map<std::string, std::string> env = {{"PLACEDB_HOME", "/opt/placedb"}};
  const auto home = DefaultPathRoots(
      [&](const char* name) -> const char* {
        auto it = env.find(name);
        return it == env.end() ? nullptr : it->second.c_str();
      },
      exe);
  ASSERT_EQ(home.size(), 1u);
  EXPECT_EQ(home[0].dir, "/opt/placedb");
  EXPECT_EQ(home[0].why, "PLACEDB_HOME");

  // An executable outside any checkout (an install): the working directory only.
  const auto installed = DefaultPathRoots(NoEnvironment, "/nonexistent/bin/placedb-server");
  ASSERT_EQ(installed.size(), 1u);
  EXPECT_EQ(installed[0].why, "the working directory");
}

TEST(ServerDefaultPaths, EmbeddedDefaultsResolveUnderTheFirstRootHoldingTheVocabulary) {
  const std::string without = FakeCheckout("placedb-no-vocabulary", false);
  const std::string with = FakeCheckout("placedb-vocabulary", true);
  ServerConfig config;
  ASSERT_TRUE(ResolveDefaultPaths({{without, "first"}, {with, "second"}}, &config).ok());
  EXPECT_EQ(config.vocabularies.at("default"), with + "/var/vocabulary/default.pdbv");
  EXPECT_EQ(config.vocabularies.at("sift"), with + "/var/vocabulary/sift-debian.pdbfv");
  EXPECT_TRUE(config.optional_vocabularies.count("sift"));  // still optional: the embedded one
  EXPECT_EQ(config.data_dir, with + "/var/data");

  // The operator's own paths keep their meaning (relative to the working directory).
  ServerConfig own;
  own.vocabularies = {{"default", "mine.pdbv"}, {"sift", "var/vocabulary/sift-debian.pdbfv"}};
  own.data_dir = "maps";
  ASSERT_TRUE(ResolveDefaultPaths({{without, "first"}, {with, "second"}}, &own).ok());
  EXPECT_EQ(own.vocabularies.at("default"), "mine.pdbv");
  EXPECT_EQ(own.data_dir, "maps");
  // Embedded entries left beside it resolve under the first root.
  EXPECT_EQ(own.vocabularies.at("sift"), without + "/var/vocabulary/sift-debian.pdbfv");

  ServerConfig missing;
  const Status none =
      ResolveDefaultPaths({{without, "first"}, {without + "/x", "second"}}, &missing);
  EXPECT_EQ(none.code(), StatusCode::kNotFound);
  EXPECT_NE(none.message().find(without + "/var/vocabulary/default.pdbv (first), " + without +
                                "/x/var/vocabulary/default.pdbv (second)"),
            std::string::npos)
      << none.ToString();
  EXPECT_NE(none.message().find("PLACEDB_HOME"), std::string::npos) << none.ToString();
}

}  // namespace
}  // namespace placedb::server
