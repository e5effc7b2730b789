// `placedb-server tokens ...`: manages a tokens file (server/auth/tokens.h) without editing YAML.
//
//   placedb-server tokens add NAME --tokens-file F [--role admin] [--role metrics]
//       [--read PATTERN]... [--write PATTERN]... [--certificate-name N]... [--no-token]
//   placedb-server tokens list   --tokens-file F
//   placedb-server tokens revoke NAME --tokens-file F
//   placedb-server tokens rotate NAME --tokens-file F
//
// add and rotate print the new token, once, as the only line on stdout (the file keeps only its
// SHA-256); every hint and error goes to stderr. The file is created if missing (add), written
// atomically with mode 0600; a running server picks the change up within ~2 s or on SIGHUP.
// --tokens-file defaults to $PLACEDB_TOKENS_FILE. Two commands run at once on the same file may
// lose one's change (the last rename wins): run them one at a time.
#pragma once

#include <functional>
#include <iosfwd>

namespace placedb::server::auth {

// Runs the command; argv[0] is "tokens". `getenv` reads PLACEDB_TOKENS_FILE. Returns the exit
// status: 0 done, 1 failed (why on `err`), 2 bad usage.
int RunTokensCommand(int argc, char** argv, std::ostream& out, std::ostream& err,
                     const std::function<const char*(const char*)>& getenv);

}  // namespace placedb::server::auth
