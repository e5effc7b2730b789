// server/auth/tokens.h and token_store.h: the tokens file's format and validation, hashing,
// generation, resolution and rights, and the store's reloads (on request, on change, through a
// symlink swap as a Kubernetes Secret does it).
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <set>
#include <thread>
#include <vector>

#include "server/auth/token_store.h"
#include "server/auth/tokens.h"
#include "tests/test_support.h"

namespace placedb::server::auth {
namespace {

namespace fs = std::filesystem;

// SHA-256("test"), the FIPS 180 style check value every implementation gives.
constexpr char kTestSha256[] = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

std::string Hash(char c) {
  return std::string(64, c);
}

void WriteText(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::trunc);
  out << text;
  ASSERT_TRUE(out.good()) << path;
}

// The error of parsing `text`, "" if it parsed.
std::string ParseError(const std::string& text) {
  auto parsed = TokensFile::Parse(text, "tokens.yaml");
  if (parsed.ok()) return "";
  EXPECT_EQ(parsed.status().code(), StatusCode::kInvalidArgument);
  return parsed.status().message();
}

TEST(Tokens, HashIsSha256InLowercaseHex) {
  EXPECT_EQ(HashToken("test"), kTestSha256);
  EXPECT_EQ(HashToken("").substr(0, 8), "e3b0c442");
}

TEST(Tokens, GeneratedTokensAreRandomAndWellFormed) {
  std::set<std::string> seen;
  for (int i = 0; i < 100; ++i) {
    auto token = GenerateToken();
    ASSERT_TRUE(token.ok());
    ASSERT_EQ(token->size(), 4u + 43u) << *token;  // pdb_ + base64url of 32 bytes, no padding
    EXPECT_EQ(token->substr(0, 4), "pdb_");
    for (char c : token->substr(4)) {
      EXPECT_TRUE(std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_') << *token;
    }
    EXPECT_TRUE(seen.insert(*token).second);
  }
}

TEST(Tokens, PatternsMatchRunsOfNameCharacters) {
  EXPECT_TRUE(PatternMatches("campus", "campus"));
  EXPECT_FALSE(PatternMatches("campus", "campus2"));
  EXPECT_FALSE(PatternMatches("campus", "campu"));
  EXPECT_TRUE(PatternMatches("warehouse-*", "warehouse-"));
  EXPECT_TRUE(PatternMatches("warehouse-*", "warehouse-7"));
  EXPECT_FALSE(PatternMatches("warehouse-*", "warehouse"));
  EXPECT_FALSE(PatternMatches("warehouse-*", "xwarehouse-7"));
  EXPECT_TRUE(PatternMatches("*", "anything.at_all-1"));
  EXPECT_TRUE(PatternMatches("a*b*c", "a-b-b-c"));
  EXPECT_FALSE(PatternMatches("a*b*c", "a-b-b-cd"));
  EXPECT_TRUE(PatternMatches("*-north", "site-3-north"));
}

TEST(Tokens, ParsesTheDocumentedFormat) {
  const std::string text =
      "# a comment\nprincipals:\n"
      "  - name: ops\n    token_sha256: " +
      Hash('a') +
      "\n    admin: true\n"
      "  - name: robot-7\n    token_sha256: " +
      Hash('b') +
      "\n    maps:\n      \"warehouse-*\": [read, write]\n"
      "      \"campus\": [read]\n"
      "  - name: prometheus\n    token_sha256: " +
      Hash('c') +
      "\n    metrics: true\n"
      "  - name: robot-8-cert\n"
      "    certificate_names: [robot-8.fleet.internal]\n"
      "    maps: {\"*\": [read]}\n";
  auto file = TokensFile::Parse(text, "tokens.yaml");
  ASSERT_TRUE(file.ok()) << file.status().ToString();
  ASSERT_EQ(file->principals().size(), 4u);
  const Principal* ops = file->Find("ops");
  ASSERT_NE(ops, nullptr);
  EXPECT_TRUE(ops->admin);
  EXPECT_TRUE(ops->MayWrite("anything"));
  EXPECT_TRUE(ops->MayScrapeMetrics());
  const Principal* robot = file->Find("robot-7");
  ASSERT_NE(robot, nullptr);
  EXPECT_FALSE(robot->admin);
  EXPECT_TRUE(robot->MayRead("warehouse-3"));
  EXPECT_TRUE(robot->MayWrite("warehouse-3"));
  EXPECT_TRUE(robot->MayRead("campus"));
  EXPECT_FALSE(robot->MayWrite("campus"));
  EXPECT_FALSE(robot->MayRead("campus-2"));
  EXPECT_FALSE(robot->MayScrapeMetrics());
  EXPECT_EQ(robot->DescribeRights(), "read warehouse-*, write warehouse-*, read campus");
  const Principal* prometheus = file->Find("prometheus");
  ASSERT_NE(prometheus, nullptr);
  EXPECT_TRUE(prometheus->MayScrapeMetrics());
  EXPECT_FALSE(prometheus->MayRead("campus"));
  const Principal* cert = file->Find("robot-8-cert");
  ASSERT_NE(cert, nullptr);
  EXPECT_TRUE(cert->token_sha256.empty());
  EXPECT_TRUE(cert->MayRead("x"));
  EXPECT_FALSE(cert->MayWrite("x"));

  EXPECT_EQ(file->FindByCertificateNames({"other", "robot-8.fleet.internal"}), cert);
  EXPECT_EQ(file->FindByCertificateNames({"robot-9.fleet.internal"}), nullptr);

  // An empty file, or one with no principals, is valid and lets nobody in.
  EXPECT_EQ(ParseError(""), "");
  EXPECT_EQ(ParseError("principals: []\n"), "");
}

TEST(Tokens, ResolvesTokensByTheirHash) {
  TokensFile file;
  for (const char* name : {"a", "b", "c"}) {
    Principal p;
    p.name = name;
    p.token_sha256 = HashToken(std::string("token-") + name);
    ASSERT_TRUE(file.Add(p).ok());
  }
  Principal cert_only;
  cert_only.name = "cert";
  cert_only.certificate_names = {"cn"};
  ASSERT_TRUE(file.Add(cert_only).ok());
  for (const char* name : {"a", "b", "c"}) {
    const Principal* found = file.FindByToken(std::string("token-") + name);
    ASSERT_NE(found, nullptr) << name;
    EXPECT_EQ(found->name, name);
  }
  EXPECT_EQ(file.FindByToken("token-d"), nullptr);
  EXPECT_EQ(file.FindByToken(""), nullptr);  // a certificate-only entry has no token
  // The hash itself is not a token.
  EXPECT_EQ(file.FindByToken(HashToken("token-a")), nullptr);
}

TEST(Tokens, RefusesInvalidFilesNamingTheEntryAndKey) {
  const std::string ok_hash = Hash('a');
  struct Case {
    std::string text;
    std::string expected;  // part of the message
  };
  const std::vector<Case> cases = {
      {"principals: [", "not valid YAML"},
      {"- a\n", "must be a mapping"},
      {"principal: []\n", "unknown key 'principal'"},
      {"? [a]\n: b\n", "unknown key '(not a string)'"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash + "\n    ? [x]\n    : y\n",
       "principals[0] 'a'"},
      {"principals: {a: b}\n", "principals must be a list"},
      {"principals:\n  - name: ops\n    token_sha256: " + ok_hash + "\n    admn: true\n",
       "principals[0] 'ops': unknown key 'admn'"},
      {"principals:\n  - token_sha256: " + ok_hash + "\n", "principals[0]: name is missing"},
      {"principals:\n  - name: 'bad name'\n    token_sha256: " + ok_hash + "\n",
       "principals[0] 'bad name': name may only hold"},
      {"principals:\n  - name: ''\n    token_sha256: " + ok_hash + "\n", "name must be 1-64"},
      {"principals:\n  - name: " + std::string(65, 'x') + "\n    token_sha256: " + ok_hash + "\n",
       "name must be 1-64"},
      {"principals:\n  - name: ops\n    token_sha256: ABC\n",
       "principals[0] 'ops': token_sha256 must be 64 lowercase hex"},
      {"principals:\n  - name: ops\n    token_sha256: " + std::string(64, 'A') + "\n",
       "token_sha256 must be 64 lowercase hex"},
      {"principals:\n  - name: ops\n    token_sha256: " + std::string(63, 'a') + "g\n",
       "token_sha256 must be 64 lowercase hex"},
      {"principals:\n  - name: ops\n",
       "principals[0] 'ops': needs token_sha256 or certificate_names"},
      {"principals:\n  - name: ops\n    token_sha256: " + ok_hash +
           "\n  - name: ops\n"
           "    token_sha256: " +
           Hash('b') + "\n",
       "principals[1] 'ops': name: 'ops' is already a principal"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash +
           "\n  - name: b\n"
           "    token_sha256: " +
           ok_hash + "\n",
       "principals[1] 'b': token_sha256: the same token as principal 'a'"},
      {"principals:\n  - name: a\n    certificate_names: [x]\n  - name: b\n"
       "    certificate_names: [x]\n",
       "principals[1] 'b': certificate_names: 'x' already names principal 'a'"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash +
           "\n    maps: {m: [read, delete]}\n",
       "principals[0] 'a': maps: 'm': unknown right 'delete'"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash + "\n    maps: {m: read}\n",
       "maps: 'm' must list rights"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash + "\n    maps: {'../x': [read]}\n",
       "principals[0] 'a': maps: pattern '../x' may only hold"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash + "\n    maps: [campus]\n",
       "maps must be a mapping"},
      {"principals:\n  - name: a\n    token_sha256: " + ok_hash + "\n    admin: maybe\n",
       "principals[0] 'a'"},
      {"principals:\n  - name: a\n    certificate_names: x\n", "certificate_names must be a list"},
  };
  for (const Case& c : cases) {
    const std::string error = ParseError(c.text);
    EXPECT_NE(error.find(c.expected), std::string::npos)
        << "text:\n"
        << c.text << "\nerror: " << error << "\nexpected: " << c.expected;
    EXPECT_EQ(error.rfind("tokens.yaml: ", 0), 0u) << error;
  }
}

TEST(Tokens, SerializeRoundTripsAndSaveIsPrivate) {
  TokensFile file;
  Principal a;
  a.name = "ops@site";
  a.token_sha256 = Hash('1');
  a.admin = true;
  ASSERT_TRUE(file.Add(a).ok());
  Principal b;
  b.name = "robot-7";
  b.token_sha256 = Hash('2');
  b.metrics = true;
  b.maps = {{"warehouse-*", true, true}, {"campus", true, false}, {"yard", false, true}};
  b.certificate_names = {"robot-7.fleet.internal", "spiffe://fleet/robot-7"};
  ASSERT_TRUE(file.Add(b).ok());

  auto again = TokensFile::Parse(file.Serialize(), "serialized");
  ASSERT_TRUE(again.ok()) << again.status().ToString() << "\n" << file.Serialize();
  EXPECT_EQ(again->Serialize(), file.Serialize());
  const Principal* robot = again->Find("robot-7");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->DescribeRights(), b.DescribeRights());
  EXPECT_EQ(robot->certificate_names, b.certificate_names);
  EXPECT_NE(file.Serialize().find("token_sha256: " + Hash('1')), std::string::npos);

  const std::string dir = testing::MakeTempDir("auth_tokens_save");
  const std::string path = dir + "/tokens.yaml";
  ASSERT_TRUE(file.Save(path).ok());
  struct stat st {};
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  auto loaded = TokensFile::Load(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status().ToString();
  EXPECT_EQ(loaded->principals().size(), 2u);
  // Only the file itself: no temp file left next to it.
  EXPECT_EQ(std::distance(fs::directory_iterator(dir), fs::directory_iterator()), 1);

  EXPECT_EQ(file.Remove("nobody").code(), StatusCode::kNotFound);
  ASSERT_TRUE(file.Remove("ops@site").ok());
  EXPECT_EQ(file.principals().size(), 1u);
  fs::remove_all(dir);
}

// ---- The store ---------------------------------------------------------------------------------

std::string OnePrincipal(const std::string& name, const std::string& token) {
  return "principals:\n  - name: " + name + "\n    token_sha256: " + HashToken(token) + "\n";
}

TEST(TokenStore, ReloadSwapsTheSnapshotAndKeepsItOnError) {
  const std::string dir = testing::MakeTempDir("auth_store_reload");
  const std::string path = dir + "/tokens.yaml";
  WriteText(path, OnePrincipal("a", "token-a"));
  std::vector<bool> reloads;
  auto store = TokenStore::Open(path, [&](bool ok) { reloads.push_back(ok); });
  ASSERT_TRUE(store.ok()) << store.status().ToString();
  auto first = (*store)->snapshot();
  EXPECT_NE(first->FindByToken("token-a"), nullptr);
  EXPECT_EQ((*store)->generation(), 0u);

  WriteText(path, OnePrincipal("b", "token-b"));
  ASSERT_TRUE((*store)->Reload().ok());
  EXPECT_EQ((*store)->generation(), 1u);
  EXPECT_EQ((*store)->snapshot()->FindByToken("token-a"), nullptr);
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);
  // The old snapshot is unchanged for whoever still holds it.
  EXPECT_NE(first->FindByToken("token-a"), nullptr);

  WriteText(path, "principals:\n  - name: b\n    token_sha256: nothex\n");
  const Status failed = (*store)->Reload();
  EXPECT_EQ(failed.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(failed.message().find("token_sha256"), std::string::npos);
  EXPECT_EQ((*store)->generation(), 1u);
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);

  fs::remove(path);
  EXPECT_EQ((*store)->Reload().code(), StatusCode::kNotFound);
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);
  EXPECT_EQ(reloads, (std::vector<bool>{true, false, false}));
  fs::remove_all(dir);
}

TEST(TokenStore, OpenFailsOnABadFile) {
  const std::string dir = testing::MakeTempDir("auth_store_open");
  EXPECT_EQ(TokenStore::Open(dir + "/missing.yaml").status().code(), StatusCode::kNotFound);
  WriteText(dir + "/bad.yaml", "principals: 3\n");
  auto bad = TokenStore::Open(dir + "/bad.yaml");
  EXPECT_EQ(bad.status().code(), StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("bad.yaml"), std::string::npos);
  fs::remove_all(dir);
}

// Waits (bounded, generously) until the store's generation reaches `generation`.
bool AwaitGeneration(const TokenStore& store, uint64_t generation) {
  for (int i = 0; i < 300 && store.generation() < generation; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return store.generation() >= generation;
}

TEST(TokenStore, WatcherReloadsAChangedFile) {
  const std::string dir = testing::MakeTempDir("auth_store_watch");
  const std::string path = dir + "/tokens.yaml";
  WriteText(path, OnePrincipal("a", "token-a"));
  auto store = TokenStore::Open(path);
  ASSERT_TRUE(store.ok());
  (*store)->StartWatching(std::chrono::milliseconds(50));

  // Replaced the way `tokens add` does it: a new file renamed over the old one.
  auto next = TokensFile::Parse(OnePrincipal("b", "token-b"), "b");
  ASSERT_TRUE(next.ok());
  ASSERT_TRUE(next->Save(path).ok());
  ASSERT_TRUE(AwaitGeneration(**store, 1));
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);

  // A broken edit keeps the principals; fixing it loads again.
  WriteText(path, "principals: [");
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  EXPECT_EQ((*store)->generation(), 1u);
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);
  WriteText(path,
            OnePrincipal("c", "token-c-longer"));  // another size: seen even within an mtime tick
  ASSERT_TRUE(AwaitGeneration(**store, 2));
  EXPECT_NE((*store)->snapshot()->FindByToken("token-c-longer"), nullptr);
  (*store)->StopWatching();
  fs::remove_all(dir);
}

// Calls resolve tokens on gRPC's threads while the watcher and SIGHUP reload: every snapshot a
// reader takes is one whole file (ThreadSanitizer runs this: "Concurren").
TEST(TokenStore, ConcurrentLookupsDuringReloadsSeeWholeFiles) {
  const std::string dir = testing::MakeTempDir("auth_store_concurrent");
  const std::string path = dir + "/tokens.yaml";
  auto file_with = [](const std::string& token) {
    return TokensFile::Parse(OnePrincipal("p", token) +
                                 "  - name: q\n    token_sha256: " + HashToken(token + "-q") + "\n",
                             "test");
  };
  ASSERT_TRUE(file_with("token-a")->Save(path).ok());
  auto store = TokenStore::Open(path);
  ASSERT_TRUE(store.ok());
  (*store)->StartWatching(std::chrono::milliseconds(10));

  std::atomic<bool> stop{false};
  std::atomic<int> torn{0}, lookups{0};
  std::vector<std::thread> readers;
  for (int r = 0; r < 3; ++r) {
    readers.emplace_back([&] {
      while (!stop.load()) {
        const auto snapshot = (*store)->snapshot();
        const bool a = snapshot->FindByToken("token-a") && snapshot->FindByToken("token-a-q");
        const bool b = snapshot->FindByToken("token-b") && snapshot->FindByToken("token-b-q");
        if (a == b) torn.fetch_add(1);  // exactly one file's pair, never a mix or neither
        lookups.fetch_add(1);
      }
    });
  }
  for (int round = 0; round < 40; ++round) {
    EXPECT_TRUE(file_with(round % 2 ? "token-a" : "token-b")->Save(path).ok());
    if (round % 3 == 0) {
      EXPECT_TRUE((*store)->Reload().ok());
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(15));
  }
  stop = true;
  for (std::thread& reader : readers) reader.join();
  (*store)->StopWatching();
  EXPECT_EQ(torn.load(), 0);
  EXPECT_GT(lookups.load(), 0);
  EXPECT_GT((*store)->generation(), 0u);
  fs::remove_all(dir);
}

// A Kubernetes Secret volume: tokens.yaml -> ..data/tokens.yaml, ..data -> ..<timestamp>; an
// update writes a new timestamped directory and swaps the ..data symlink.
TEST(TokenStore, WatcherFollowsASecretsSymlinkSwap) {
  const std::string dir = testing::MakeTempDir("auth_store_symlink");
  fs::create_directory(dir + "/..2026_1");
  WriteText(dir + "/..2026_1/tokens.yaml", OnePrincipal("a", "token-a"));
  fs::create_directory_symlink("..2026_1", dir + "/..data");
  fs::create_symlink("..data/tokens.yaml", dir + "/tokens.yaml");
  auto store = TokenStore::Open(dir + "/tokens.yaml");
  ASSERT_TRUE(store.ok()) << store.status().ToString();
  (*store)->StartWatching(std::chrono::milliseconds(50));

  fs::create_directory(dir + "/..2026_2");
  WriteText(dir + "/..2026_2/tokens.yaml", OnePrincipal("b", "token-b"));
  fs::create_directory_symlink("..2026_2", dir + "/..data_tmp");
  fs::rename(dir + "/..data_tmp", dir + "/..data");  // the atomic swap
  fs::remove_all(dir + "/..2026_1");
  ASSERT_TRUE(AwaitGeneration(**store, 1));
  EXPECT_NE((*store)->snapshot()->FindByToken("token-b"), nullptr);
  EXPECT_EQ((*store)->snapshot()->FindByToken("token-a"), nullptr);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace placedb::server::auth
