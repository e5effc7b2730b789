// `placedb maps create|list|show|delete|recover|scrub|adapt-vocabulary|revert-vocabulary`
// (docs/cli.md, "maps"). Options of `maps
// create` left unset keep the server's defaults: the request sets only what was given.
#pragma once

#include <cstdint>
#include <string>

#include "client/cli.h"
#include "client/connection.h"

namespace CLI {
class App;
class Option;
}  // namespace CLI

namespace placedb::client {

struct CreateFlags {
  std::string name;
  std::string vocabulary;
  int features = 0;
  std::string detection;
  std::string classes;  // comma-separated
  float confidence = 0;
  std::string box_source;
  std::string filter;
  float sensitivity = 0;
  int place_threshold = 0;
  std::string scoring;
  std::string verify;
  int level = 0;
  int min_inliers = 0;
  int candidates = 0;
  bool store_invalid = false;
  bool thumbnails = false;      // keep a thumbnail per place
  uint32_t thumbnail_size = 0;  // their longest side; 0 = the server's default
  // The vocabulary policy (issue 29): 0 = off.
  uint64_t adapt_vocabulary_after = 0;
  double regrow_factor = 0;
  // Feature type (SIFT maps need a float vocabulary) and SIFT.
  std::string feature_type;
  int sift_features = 0;
  // Depth (docs/rgbd.md).
  bool no_refine_boxes = false;
  bool no_depth_filter = false;
  // Monocular box refinement, the short-term tier and re-ranking.
  std::string box_refinement;
  std::string short_term;  // on | off
  double short_term_horizon_s = 0;
  CLI::Option* short_term_horizon_option = nullptr;
  std::string rerank;         // on | off
  std::string static_budget;  // on | off
  float depth_scale = 0;
  float depth_threshold = 0;
  std::string band_policy;
  bool paper_literal = false;  // mean over all pixels + fixed bands
  // Loop closure (ingest streams with --loop-closure).
  double loop_threshold = 0;
  double rehearsal_threshold = 0;
  int stm = 0;
  uint32_t max_wm = 0;
  double wm_time_budget_ms = 0;
  bool no_verify_loops = false;
  // Which were given (unset fields take the server's defaults).
  CLI::Option* features_option = nullptr;
  CLI::Option* sift_features_option = nullptr;
  CLI::Option* depth_scale_option = nullptr;
  CLI::Option* depth_threshold_option = nullptr;
  CLI::Option* loop_threshold_option = nullptr;
  CLI::Option* rehearsal_threshold_option = nullptr;
  CLI::Option* stm_option = nullptr;
  CLI::Option* max_wm_option = nullptr;
  CLI::Option* wm_time_budget_option = nullptr;
  CLI::Option* confidence_option = nullptr;
  CLI::Option* sensitivity_option = nullptr;
  CLI::Option* place_threshold_option = nullptr;
  CLI::Option* level_option = nullptr;
  CLI::Option* min_inliers_option = nullptr;
  CLI::Option* candidates_option = nullptr;
};

struct MapsFlags {
  CreateFlags create;
  std::string show_name;
  std::string delete_name;
  bool delete_yes = false;
  std::string recover_name;
  bool accept_data_loss = false;
  std::string scrub_name;
  // adapt-vocabulary / revert-vocabulary (issue 29).
  std::string adapt_name;
  uint64_t adapt_seed = 0;
  uint64_t adapt_max_sample = 0;
  uint32_t adapt_branching = 0;
  uint32_t adapt_depth = 0;
  std::string revert_name;
};

// The `maps` subcommands; the one parsed says which Maps* function runs.
struct MapsCommands {
  CLI::App* create = nullptr;
  CLI::App* list = nullptr;
  CLI::App* show = nullptr;
  CLI::App* remove = nullptr;
  CLI::App* recover = nullptr;
  CLI::App* scrub = nullptr;
  CLI::App* adapt_vocabulary = nullptr;
  CLI::App* revert_vocabulary = nullptr;
};

// Adds `maps` and its subcommands to `app`, their options bound to *flags.
MapsCommands RegisterMaps(CLI::App& app, MapsFlags* flags);

int MapsCreate(const Connection& connection, const CreateFlags& flags, bool json, CliIo& io);
int MapsList(const Connection& connection, bool json, CliIo& io);
int MapsShow(const Connection& connection, const std::string& name, bool json, CliIo& io);
// Asks on io.in unless `yes`; refuses when io.in is not a terminal.
int MapsDelete(const Connection& connection, const std::string& name, bool yes, bool json,
               CliIo& io);
// RecoverMap: refused locally without --accept-data-loss (the server refuses it too).
int MapsRecover(const Connection& connection, const std::string& name, bool accept_data_loss,
                bool json, CliIo& io);
// ScrubMap: prints the report; kExitDamage when anything is damaged.
int MapsScrub(const Connection& connection, const std::string& name, bool json, CliIo& io);
// AdaptVocabulary / RevertVocabulary: print the map's vocabulary once switched.
int MapsAdaptVocabulary(const Connection& connection, const MapsFlags& flags, bool json, CliIo& io);
int MapsRevertVocabulary(const Connection& connection, const std::string& name, bool json,
                         CliIo& io);

}  // namespace placedb::client
