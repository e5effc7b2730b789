// placedb: the command line (docs/cli.md).
#include <csignal>

#include "client/cli.h"

int main(int argc, char** argv) {
  std::signal(SIGPIPE, SIG_IGN);  // `placedb ... | head` ends with an error, not a signal
  return placedb::client::CliMain(argc, argv);
}
