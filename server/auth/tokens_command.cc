#include "server/auth/tokens_command.h"

#include <CLI/CLI.hpp>
#include <filesystem>
#include <map>
#include <ostream>

#include "server/auth/tokens.h"

namespace placedb::server::auth {

namespace {

// The file as it is, or empty when it does not exist yet and `create` is set.
Result<TokensFile> LoadForChange(const std::string& path, bool create) {
  std::error_code ec;
  if (create && !std::filesystem::exists(path, ec)) return TokensFile();
  return TokensFile::Load(path);
}

int Fail(std::ostream& err, const Status& status) {
  err << "placedb-server tokens: " << status.ToString() << "\n";
  return 1;
}

}  // namespace

int RunTokensCommand(int argc, char** argv, std::ostream& out, std::ostream& err,
                     const std::function<const char*(const char*)>& getenv) {
  CLI::App app{"placedb-server tokens: manage the tokens file (docs/security.md)",
               "placedb-server tokens"};
  app.require_subcommand(1);
  std::string tokens_file;
  app.add_option("--tokens-file", tokens_file, "the tokens file (default $PLACEDB_TOKENS_FILE)");

  std::string name;
  std::vector<std::string> roles, reads, writes, certificate_names;
  bool no_token = false;
  CLI::App* add = app.add_subcommand("add", "add a principal; prints its new token once");
  add->add_option("NAME", name, "principal name: 1-64 of [A-Za-z0-9_.@-]")->required();
  add->add_option("--role", roles, "admin | metrics (repeatable)")
      ->check(CLI::IsMember({"admin", "metrics"}));
  add->add_option("--read", reads, "read on maps matching PATTERN ('*' = any run; repeatable)");
  add->add_option("--write", writes, "write on maps matching PATTERN (repeatable)");
  add->add_option("--certificate-name", certificate_names,
                  "a client certificate CN or SAN naming this principal (mTLS; repeatable)");
  add->add_flag("--no-token", no_token, "no token: certificate names only");
  CLI::App* list = app.add_subcommand("list", "list principals and their rights (no secrets)");
  CLI::App* revoke = app.add_subcommand("revoke", "remove a principal");
  revoke->add_option("NAME", name, "principal name")->required();
  CLI::App* rotate = app.add_subcommand("rotate", "give a principal a new token (same rights)");
  rotate->add_option("NAME", name, "principal name")->required();
  for (CLI::App* sub : {add, list, revoke, rotate}) {
    sub->add_option("--tokens-file", tokens_file, "the tokens file (default $PLACEDB_TOKENS_FILE)");
  }

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e, out, err) == 0 ? 0 : 2;
  }
  if (tokens_file.empty()) {
    if (const char* env = getenv("PLACEDB_TOKENS_FILE"); env && *env) tokens_file = env;
  }
  if (tokens_file.empty()) {
    err << "placedb-server tokens: no tokens file (--tokens-file F or PLACEDB_TOKENS_FILE)\n";
    return 2;
  }

  if (list->parsed()) {
    auto file = TokensFile::Load(tokens_file);
    if (!file.ok()) return Fail(err, file.status());
    for (const Principal& p : file->principals()) {
      out << p.name << "\t" << p.DescribeRights() << "\t"
          << (p.token_sha256.empty() ? std::string("no token")
                                     : "token sha256 " + p.token_sha256.substr(0, 8) + "...");
      if (!p.certificate_names.empty()) {
        out << "\tcertificates";
        for (const std::string& cert : p.certificate_names) out << " " << cert;
      }
      out << "\n";
    }
    return 0;
  }

  auto file = LoadForChange(tokens_file, add->parsed());
  if (!file.ok()) return Fail(err, file.status());
  std::string token;
  if (add->parsed() || rotate->parsed()) {
    if (!(add->parsed() && no_token)) {
      auto generated = GenerateToken();
      if (!generated.ok()) return Fail(err, generated.status());
      token = std::move(generated).value();
    }
  }

  if (add->parsed()) {
    if (no_token && certificate_names.empty()) {
      err << "placedb-server tokens: --no-token needs --certificate-name\n";
      return 2;
    }
    if (file->Find(name)) {
      return Fail(err, Status::AlreadyExists("principal '" + name + "' exists in " + tokens_file +
                                             " (tokens rotate gives it a new token)"));
    }
    Principal p;
    p.name = name;
    if (!token.empty()) p.token_sha256 = HashToken(token);
    p.certificate_names = certificate_names;
    for (const std::string& role : roles) {
      if (role == "admin") p.admin = true;
      if (role == "metrics") p.metrics = true;
    }
    // One grant per pattern, in the order given.
    auto grant = [&p](const std::string& pattern) -> MapGrant& {
      for (MapGrant& g : p.maps) {
        if (g.pattern == pattern) return g;
      }
      p.maps.push_back(MapGrant{pattern, false, false});
      return p.maps.back();
    };
    for (const std::string& pattern : reads) grant(pattern).read = true;
    for (const std::string& pattern : writes) grant(pattern).write = true;
    const std::string rights = p.DescribeRights();
    if (Status added = file->Add(std::move(p)); !added.ok()) {
      return Fail(err, added.WithContext(tokens_file));
    }
    if (Status saved = file->Save(tokens_file); !saved.ok()) return Fail(err, saved);
    err << "added principal '" << name << "' (" << rights << ") to " << tokens_file << "\n";
  } else if (revoke->parsed()) {
    if (Status removed = file->Remove(name); !removed.ok()) {
      return Fail(err, removed.WithContext(tokens_file));
    }
    if (Status saved = file->Save(tokens_file); !saved.ok()) return Fail(err, saved);
    err << "revoked principal '" << name << "' in " << tokens_file << "\n";
  } else if (rotate->parsed()) {
    if (!file->Find(name)) {
      return Fail(err, Status::NotFound(tokens_file + ": no principal named '" + name + "'"));
    }
    // Rebuilt in the same order (certificate names resolve in file order), through Add, so the
    // new hash is checked against the others like any entry.
    TokensFile rotated;
    for (Principal p : file->principals()) {
      if (p.name == name) p.token_sha256 = HashToken(token);
      if (Status added = rotated.Add(std::move(p)); !added.ok()) return Fail(err, added);
    }
    *file = std::move(rotated);
    if (Status saved = file->Save(tokens_file); !saved.ok()) return Fail(err, saved);
    err << "new token for principal '" << name << "' in " << tokens_file
        << "; the old one stops working when the server reloads\n";
  }
  if (!token.empty()) {
    out << token << "\n";
    err << "the token above is shown once: only its SHA-256 is stored. A running server picks "
           "the change up within ~2 s (or on SIGHUP).\n";
  } else {
    err << "a running server picks the change up within ~2 s (or on SIGHUP).\n";
  }
  return 0;
}

}  // namespace placedb::server::auth
