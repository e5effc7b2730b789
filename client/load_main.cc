// placedb-load: the load tester on its own; the same as `placedb load ...` (docs/cli.md).
#include <csignal>
#include <vector>

#include "client/cli.h"

int main(int argc, char** argv) {
  std::signal(SIGPIPE, SIG_IGN);
  std::vector<const char*> args = {argc > 0 ? argv[0] : "placedb-load", "load"};
  for (int i = 1; i < argc; ++i) args.push_back(argv[i]);
  return placedb::client::CliMain(int(args.size()), args.data());
}
