#include "client/cli.h"

#include <unistd.h>

#include <CLI/CLI.hpp>
#include <iostream>
#include <optional>

#include "client/commands/common.h"
#include "client/commands/dynamics.h"
#include "client/commands/ingest.h"
#include "client/commands/load.h"
#include "client/commands/loops.h"
#include "client/commands/maps.h"
#include "client/commands/places.h"
#include "client/commands/query.h"
#include "client/commands/server.h"
#include "client/commands/snapshots.h"
#include "client/connection.h"

namespace placedb::client {

int RunCli(int argc, const char* const* argv, CliIo& io) {
  CLI::App app{"placedb: the command line of the placedb place-recognition database (docs/cli.md)",
               "placedb"};
  app.fallthrough();  // global options anywhere, also after the subcommand
  app.require_subcommand(1);
  app.set_version_flag("--version", PLACEDB_VERSION);

  ConnectionOptions connection_options;
  bool json = false;
  app.add_option("--address", connection_options.address,
                 "server address (HOST:PORT; a bare PORT means localhost)")
      ->envname("PLACEDB_ADDRESS")
      ->capture_default_str();
  app.add_option("--timeout", connection_options.timeout_s,
                 "deadline of each unary RPC, seconds (0 = none)")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_flag("--json", json, "machine-readable output (JSON on stdout)");
  app.add_flag("--tls", connection_options.tls, "connect with TLS (TLS 1.2+)")
      ->envname("PLACEDB_TLS");
  app.add_option("--ca-cert", connection_options.ca_cert,
                 "PEM root certificates for --tls (default: the system's)")
      ->envname("PLACEDB_CA_CERT")
      ->check(CLI::ExistingFile);
  app.add_option("--cert", connection_options.cert,
                 "PEM client certificate for mutual TLS (with --tls and --key)")
      ->envname("PLACEDB_CERT")
      ->check(CLI::ExistingFile);
  app.add_option("--key", connection_options.key,
                 "the client certificate's PEM private key (unencrypted)")
      ->envname("PLACEDB_KEY")
      ->check(CLI::ExistingFile);
  app.add_option("--token", connection_options.token,
                 "sent as 'authorization: Bearer TOKEN' (servers with a tokens file need one; "
                 "prefer the environment variable)")
      ->envname("PLACEDB_TOKEN");

  // The commands, in the order --help lists them.
  MapsFlags maps_flags;
  const MapsCommands maps = RegisterMaps(app, &maps_flags);
  IngestOptions ingest_options;
  CLI::App* ingest = RegisterIngest(app, &ingest_options);
  QueryFlags query_flags;
  CLI::App* query = RegisterQuery(app, &query_flags);
  PlaceFlags place_flags;
  const PlaceCommands place = RegisterPlace(app, &place_flags);
  LoopsFlags loops_flags;
  const LoopsCommands loops = RegisterLoops(app, &loops_flags);
  SnapshotsFlags snapshots_flags;
  const SnapshotsCommands snapshots = RegisterSnapshots(app, &snapshots_flags);
  DynamicsFlags dynamics_flags;
  CLI::App* dynamics = RegisterDynamics(app, &dynamics_flags);
  HealthFlags health_flags;
  const ServerCommands server = RegisterServer(app, &health_flags);
  LoadOptions load_options;
  CLI::App* load = RegisterLoad(app, &load_options);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e, io.out, io.err);
    return code == 0 ? kExitOk : kExitUsage;
  }

  connection_options.address = ServerTarget(connection_options.address);
  io.server_address = connection_options.address;
  if (load->parsed()) return RunLoad(connection_options, load_options, json, io);

  std::string error;
  std::optional<Connection> connection = Connection::Open(connection_options, &error);
  if (!connection) return UsageError(io, error);

  const Connection& c = *connection;
  if (maps.create->parsed()) return MapsCreate(c, maps_flags.create, json, io);
  if (maps.list->parsed()) return MapsList(c, json, io);
  if (maps.show->parsed()) return MapsShow(c, maps_flags.show_name, json, io);
  if (maps.remove->parsed()) {
    return MapsDelete(c, maps_flags.delete_name, maps_flags.delete_yes, json, io);
  }
  if (maps.recover->parsed()) {
    return MapsRecover(c, maps_flags.recover_name, maps_flags.accept_data_loss, json, io);
  }
  if (maps.scrub->parsed()) return MapsScrub(c, maps_flags.scrub_name, json, io);
  if (maps.adapt_vocabulary->parsed()) return MapsAdaptVocabulary(c, maps_flags, json, io);
  if (maps.revert_vocabulary->parsed()) {
    return MapsRevertVocabulary(c, maps_flags.revert_name, json, io);
  }
  if (ingest->parsed()) return RunIngest(c, ingest_options, json, io);
  if (query->parsed()) return RunQuery(c, query_flags, json, io);
  if (place.get->parsed()) {
    return PlaceGet(c, place_flags.map, place_flags.id, place_flags.features, json, io,
                    place_flags.thumbnail);
  }
  if (place.list->parsed()) return PlaceList(c, place_flags, json, io);
  if (place.remove->parsed()) return PlaceDelete(c, place_flags.map, place_flags.id, json, io);
  if (loops.watch->parsed()) return LoopsWatch(c, loops_flags, json, io);
  if (loops.export_->parsed()) return LoopsExport(c, loops_flags, io);
  if (snapshots.create->parsed()) return SnapshotsCreate(c, snapshots_flags.map, json, io);
  if (snapshots.list->parsed()) return SnapshotsList(c, json, io);
  if (snapshots.download->parsed()) return SnapshotsDownload(c, snapshots_flags, json, io);
  if (snapshots.upload->parsed()) return SnapshotsUpload(c, snapshots_flags, json, io);
  if (snapshots.restore->parsed()) {
    return SnapshotsRestore(c, snapshots_flags.id, snapshots_flags.new_map, json, io);
  }
  if (snapshots.remove->parsed()) return SnapshotsDelete(c, snapshots_flags.id, json, io);
  if (dynamics->parsed()) return RunDynamics(c, dynamics_flags, json, io);
  if (server.info->parsed()) return RunInfo(c, json, io);
  if (server.console->parsed()) return RunConsole(c, json, io);
  if (server.health->parsed()) return RunHealth(c, health_flags.service, json, io);
  return UsageError(io, "no command given (see --help)");
}

int CliMain(int argc, const char* const* argv) {
  CliIo io{std::cout, std::cerr, std::cin, isatty(STDERR_FILENO) != 0, isatty(STDIN_FILENO) != 0};
  const int code = RunCli(argc, argv, io);
  std::cout.flush();
  return code;
}

}  // namespace placedb::client
