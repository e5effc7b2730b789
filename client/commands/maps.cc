#include "client/commands/maps.h"

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <utility>
#include <vector>

#include "client/commands/common.h"
#include "client/commands/enum_flags.h"
#include "client/format.h"

namespace placedb::client {

namespace {

using Rows = std::vector<std::pair<std::string, std::string>>;

std::string Join(const std::vector<std::string>& items, const std::string& separator) {
  std::string text;
  for (const std::string& item : items) text += (text.empty() ? "" : separator) + item;
  return text;
}

std::string Metres(double metres) {
  return FormatDouble(metres, 2) + " m";
}

std::string SourceText(const v1::VocabularySource& source) {
  std::string text =
      source.origin() + " " + source.checksum() + " (k=" + std::to_string(source.branching()) +
      " L=" + std::to_string(source.depth()) + ", " + std::to_string(source.words()) + " words)";
  if (source.origin() == "learned") {
    text += ", learned " + FormatUnixMs(source.learned_unix_ms()) + " from " +
            std::to_string(source.descriptors_sampled()) + " descriptors of " +
            std::to_string(source.places_sampled()) + " places (of " +
            std::to_string(source.descriptors_offered()) + " in " +
            std::to_string(source.places_offered()) + ")";
  }
  return text;
}

// The `vocabulary` block: which vocabulary the map uses, where it came from, and the previous.
Rows VocabularyRows(const v1::MapVocabulary& vocabulary) {
  Rows rows;
  rows.push_back({"current", SourceText(vocabulary.current())});
  rows.push_back({"generation", std::to_string(vocabulary.generation()) +
                                    (vocabulary.generation() == 0
                                         ? std::string(" (the map's creation vocabulary)")
                                         : ", stored with the map, since " +
                                               FormatUnixMs(vocabulary.since_unix_ms()))});
  if (vocabulary.generation() > 0) {
    rows.push_back({"switch", std::to_string(vocabulary.places_reindexed()) +
                                  " places re-indexed in " +
                                  FormatDouble(vocabulary.reindex_ms() / 1000, 1) + " s"});
  }
  if (vocabulary.has_previous()) rows.push_back({"previous", SourceText(vocabulary.previous())});
  if (vocabulary.switching()) rows.push_back({"now", "switching vocabularies"});
  return rows;
}

// The `map NAME` block of `maps show`: one row per settings group.
Rows ConfigRows(const v1::MapDescription& map) {
  const v1::MapConfig& c = map.config();
  Rows config;
  config.push_back({"created", FormatUnixMs(map.created_unix_ms())});
  config.push_back({"vocabulary", (c.vocabulary().empty() ? "default" : c.vocabulary()) +
                                      " (checksum " + map.vocabulary_checksum() + ")"});
  config.push_back({"features", c.feature_type() == v1::FEATURE_TYPE_UNSPECIFIED
                                    ? std::string("(the vocabulary's)")
                                    : wire::EnumName(c.feature_type())});
  if (c.feature_type() != v1::FEATURE_TYPE_SIFT) {
    const v1::OrbSettings& orb = c.orb();
    config.push_back({"orb", "max_features " + std::to_string(orb.max_features()) +
                                 ", scale_factor " + FormatDouble(orb.scale_factor(), 2) +
                                 ", levels " + std::to_string(orb.levels()) + ", edge_threshold " +
                                 std::to_string(orb.edge_threshold()) + ", patch_size " +
                                 std::to_string(orb.patch_size()) + ", fast_threshold " +
                                 std::to_string(orb.fast_threshold())});
  }
  if (c.feature_type() == v1::FEATURE_TYPE_SIFT) {
    const v1::SiftSettings& sift = c.sift();
    config.push_back({"sift", "max_features " +
                                  (sift.max_features() == 0 && sift.has_max_features()
                                       ? std::string("all")
                                       : std::to_string(sift.max_features())) +
                                  ", octave_layers " + std::to_string(sift.octave_layers()) +
                                  ", contrast_threshold " +
                                  FormatDouble(sift.contrast_threshold(), 3) + ", edge_threshold " +
                                  FormatDouble(sift.edge_threshold(), 1) + ", sigma " +
                                  FormatDouble(sift.sigma(), 2)});
  }
  const v1::DetectionSettings& d = c.detection();
  std::vector<std::string> classes(d.classes().begin(), d.classes().end());
  config.push_back({"detection", std::string(d.enabled() ? "on" : "off") + ", box_source " +
                                     wire::EnumName(d.box_source()) + ", min_confidence " +
                                     FormatDouble(d.min_confidence(), 2) + ", classes " +
                                     (classes.empty() ? "(default)" : Join(classes, ","))});
  const v1::FilterSettings& f = c.filter();
  config.push_back({"filter", wire::EnumName(f.method()) + ", sensitivity " +
                                  FormatDouble(f.sensitivity_threshold(), 2) +
                                  ", place_threshold " + std::to_string(f.place_threshold())});
  const std::string refinement = wire::EnumName(f.box_refinement());
  config.push_back({"refine_boxes",
                    refinement + ", static_budget " + (f.static_feature_budget() ? "on" : "off")});
  const v1::ShortTermSettings& st = f.short_term();
  config.push_back({"short_term", st.enabled()
                                      ? "on, horizon " + FormatDouble(st.horizon_s(), 0) +
                                            " s, max_places " + std::to_string(st.max_places()) +
                                            ", weight " + FormatDouble(st.weight(), 2)
                                      : std::string("off")});
  config.push_back({"scoring", wire::EnumName(c.scoring())});
  const v1::VerificationSettings& v = c.verification();
  config.push_back(
      {"verification",
       wire::EnumName(v.mode()) + ", level " + std::to_string(v.levels_up()) + ", min_inliers " +
           std::to_string(v.min_inliers()) + ", candidates " +
           (v.candidates() == 0 ? std::string("all") : std::to_string(v.candidates())) +
           ", rerank " + (v.rerank() ? "on" : "off")});
  config.push_back({"store_invalid", c.store_invalid() ? "yes" : "no"});
  const v1::VocabularyPolicy& policy = c.vocabulary_policy();
  config.push_back(
      {"vocab_policy", policy.adapt_after_descriptors() == 0 && policy.regrow_factor() == 0
                           ? std::string("off")
                           : "adapt after " + std::to_string(policy.adapt_after_descriptors()) +
                                 " descriptors, regrow factor " +
                                 FormatDouble(policy.regrow_factor(), 1)});
  config.push_back({"thumbnails", c.thumbnails().enabled()
                                      ? "on, " + std::to_string(c.thumbnails().max_side()) +
                                            " px, quality " +
                                            std::to_string(c.thumbnails().jpeg_quality())
                                      : std::string("off")});
  const v1::DepthSettings& depth = c.depth();
  auto on_off = [](bool has, bool value) { return has ? (value ? "on" : "off") : "-"; };
  config.push_back({"depth", std::string("refine_boxes ") +
                                 on_off(depth.has_refine_boxes(), depth.refine_boxes()) +
                                 ", scale " + FormatDouble(depth.scale(), 4) + " m/unit, range " +
                                 FormatDouble(depth.min_depth_m(), 2) + "-" +
                                 FormatDouble(depth.max_depth_m(), 2) + " m, use_range " +
                                 on_off(depth.has_use_range(), depth.use_range()) +
                                 ", features without depth " +
                                 (depth.remove_features_without_depth() ? "removed" : "kept")});
  config.push_back(
      {"depth filter",
       std::string(on_off(depth.has_stream_filter(), depth.stream_filter())) + ", mean over " +
           (depth.mean_all_pixels() ? "all pixels" : "valid pixels") + ", threshold " +
           Metres(depth.threshold_m()) + ", persistence " + std::to_string(depth.persistence()) +
           ", static_window " + std::to_string(depth.static_window()) + ", band " +
           wire::EnumName(depth.band_policy()) + " (rise " +
           FormatDouble(depth.rise_band().near_m(), 2) + "-" +
           FormatDouble(depth.rise_band().far_m(), 2) + " m, fall " +
           FormatDouble(depth.fall_band().near_m(), 2) + "-" +
           FormatDouble(depth.fall_band().far_m(), 2) + " m), rebaseline " +
           (depth.rebaseline_after() == 0 ? std::string("never")
                                          : "after " + std::to_string(depth.rebaseline_after()))});
  const v1::LoopClosureSettings& loop = c.loop_closure();
  config.push_back(
      {"loop closure",
       "loop_threshold " + FormatDouble(loop.loop_threshold(), 3) + ", rehearsal_threshold " +
           FormatDouble(loop.rehearsal_threshold(), 3) + ", stm " +
           std::to_string(loop.short_term_memory()) + ", max_wm " +
           (loop.max_working_memory() == 0 ? std::string("unbounded")
                                           : std::to_string(loop.max_working_memory())) +
           ", time_budget " +
           (loop.time_budget_ms() == 0 ? std::string("none")
                                       : FormatDouble(loop.time_budget_ms(), 1) + " ms") +
           ", min_candidates " + std::to_string(loop.min_candidates()) + ", verify " +
           (loop.verify() ? "on" : "off")});
  return config;
}

Rows StatsRows(const v1::MapStats& s) {
  Rows stats;
  stats.push_back({"places", std::to_string(s.places())});
  stats.push_back({"descriptors kept", std::to_string(s.descriptors_kept())});
  stats.push_back({"descriptors dropped", std::to_string(s.descriptors_dropped())});
  stats.push_back({"invalid rejected", std::to_string(s.invalid_rejected())});
  stats.push_back({"invalid stored", std::to_string(s.invalid_stored())});
  stats.push_back({"bytes on disk", FormatBytes(s.bytes_on_disk())});
  stats.push_back({"bytes in memory", FormatBytes(s.bytes_in_memory())});
  stats.push_back({"streams", std::to_string(s.streams())});
  stats.push_back({"loop working memory", std::to_string(s.loop_working_memory())});
  stats.push_back({"loop long-term", std::to_string(s.loop_long_term())});
  stats.push_back({"loops accepted", std::to_string(s.loops_accepted())});
  stats.push_back(
      {"loops rejected", std::to_string(s.loops_rejected()) + "  (failed verification)"});
  return stats;
}

std::string DamageText(const v1::MapDamage& damage) {
  std::string text = std::to_string(damage.places_lost()) + " places lost";
  if (damage.places_lost() > 0) {
    text += " (ids " + std::to_string(damage.first_lost_place()) + ".." +
            std::to_string(damage.last_lost_place()) + ")";
  }
  text += ", " + std::to_string(damage.writes_lost()) + " writes";
  if (damage.features_lost() > 0) {
    text += ", " + std::to_string(damage.features_lost()) + " places without features";
  }
  if (damage.bow_lost() + damage.records_lost() > 0) {
    text += ", " + std::to_string(damage.bow_lost() + damage.records_lost()) +
            " places dropped (BoW vector or record lost)";
  }
  if (!damage.quarantine().empty()) text += ", files as they were in " + damage.quarantine();
  return text + ": " + damage.reason();
}

// "available", "recovered (N places lost)", "damaged: reason", "unavailable: reason".
std::string StateText(v1::MapState state, uint64_t places_lost, const std::string& reason) {
  switch (state) {
    case v1::MAP_STATE_RECOVERED:
      return "recovered (" + std::to_string(places_lost) + " places lost)";
    case v1::MAP_STATE_DAMAGED:
      return "DAMAGED: " + reason;
    case v1::MAP_STATE_UNAVAILABLE:
      return "unavailable: " + reason;
    default:
      return "available";
  }
}

void PrintMap(const v1::MapDescription& map, CliIo& io) {
  if (map.state() == v1::MAP_STATE_DAMAGED || map.state() == v1::MAP_STATE_UNAVAILABLE) {
    Rows rows = {{"state", StateText(map.state(), map.places_lost(), map.unavailable_reason())}};
    if (map.state() == v1::MAP_STATE_DAMAGED) {
      rows.push_back({"places lost", map.damage().writes_lost() == 0 && map.places_lost() == 0
                                         ? std::string("unknown until recovered")
                                         : std::to_string(map.places_lost())});
      rows.push_back({"recover", "placedb maps recover " + map.name() + " --accept-data-loss"});
    }
    PrintKeyValues(io.out, "map " + map.name(), rows);
    return;
  }
  Rows config = ConfigRows(map);
  config.insert(config.begin(),
                {"state", StateText(map.state(), map.places_lost(), map.unavailable_reason())});
  PrintKeyValues(io.out, "map " + map.name(), config);
  PrintKeyValues(io.out, "statistics", StatsRows(map.stats()));
  if (map.has_vocabulary()) PrintKeyValues(io.out, "vocabulary", VocabularyRows(map.vocabulary()));
  if (map.damage_history_size() > 0) {
    Rows history;
    for (const v1::MapDamage& damage : map.damage_history()) {
      history.push_back({FormatUnixMs(damage.recovered_unix_ms()), DamageText(damage)});
    }
    PrintKeyValues(io.out, "damage history (losses accepted)", history);
  }
  if (map.agents_size() > 0) {
    // What each agent ingested since the server started (GetMap's in-memory activity).
    io.out << "agents (since the server started)\n";
    Table agents({"AGENT", ">FRAMES", ">PLACES", ">FRAMES/S", ">LAST PLACE", "LAST FRAME"});
    for (const v1::AgentActivity& agent : map.agents()) {
      agents.Add({agent.agent_id().empty() ? "(none)" : agent.agent_id(),
                  std::to_string(agent.frames()), std::to_string(agent.places()),
                  FormatDouble(agent.frames_per_second(), 1),
                  agent.last_place_id() == 0 ? "-" : std::to_string(agent.last_place_id()),
                  FormatUnixMs(agent.last_frame_unix_ms())});
    }
    agents.Print(io.out, "  ");
  }
}

// Only the options given are set; the server fills in the rest.
v1::CreateMapRequest CreateRequest(const CreateFlags& flags) {
  v1::CreateMapRequest request;
  request.set_name(flags.name);
  v1::MapConfig* config = request.mutable_config();
  config->set_vocabulary(flags.vocabulary);
  if (!flags.feature_type.empty()) {
    config->set_feature_type(EnumFlagValue<v1::FeatureType>(flags.feature_type));
  }
  if (flags.features_option->count()) config->mutable_orb()->set_max_features(flags.features);
  if (flags.sift_features_option->count()) {
    config->mutable_sift()->set_max_features(flags.sift_features);
  }
  v1::DepthSettings* depth = config->mutable_depth();
  if (flags.no_refine_boxes) depth->set_refine_boxes(false);
  if (flags.no_depth_filter) depth->set_stream_filter(false);
  if (flags.depth_scale_option->count()) depth->set_scale(flags.depth_scale);
  if (flags.depth_threshold_option->count()) depth->set_threshold_m(flags.depth_threshold);
  if (!flags.band_policy.empty())
    depth->set_band_policy(EnumFlagValue<v1::BandPolicy>(flags.band_policy));
  if (flags.paper_literal) {  // Algorithm 1 as written: the mean over all pixels, fixed bands
    depth->set_mean_all_pixels(true);
    depth->set_band_policy(v1::BAND_POLICY_FIXED);
  }
  v1::LoopClosureSettings* loop = config->mutable_loop_closure();
  if (flags.loop_threshold_option->count()) loop->set_loop_threshold(flags.loop_threshold);
  if (flags.rehearsal_threshold_option->count()) {
    loop->set_rehearsal_threshold(flags.rehearsal_threshold);
  }
  if (flags.stm_option->count()) loop->set_short_term_memory(flags.stm);
  if (flags.max_wm_option->count()) loop->set_max_working_memory(flags.max_wm);
  if (flags.wm_time_budget_option->count()) loop->set_time_budget_ms(flags.wm_time_budget_ms);
  if (flags.no_verify_loops) loop->set_verify(false);
  v1::DetectionSettings* detection = config->mutable_detection();
  if (!flags.detection.empty()) detection->set_enabled(flags.detection == "on");
  size_t start = 0;
  while (start < flags.classes.size()) {
    size_t comma = flags.classes.find(',', start);
    if (comma == std::string::npos) comma = flags.classes.size();
    const std::string name = flags.classes.substr(start, comma - start);
    if (!name.empty()) detection->add_classes(name);
    start = comma + 1;
  }
  if (flags.confidence_option->count()) detection->set_min_confidence(flags.confidence);
  if (!flags.box_source.empty()) {
    detection->set_box_source(EnumFlagValue<v1::BoxSource>(flags.box_source));
  }
  v1::FilterSettings* filter = config->mutable_filter();
  if (!flags.filter.empty()) filter->set_method(EnumFlagValue<v1::FilterMethod>(flags.filter));
  if (flags.sensitivity_option->count()) filter->set_sensitivity_threshold(flags.sensitivity);
  if (flags.place_threshold_option->count()) filter->set_place_threshold(flags.place_threshold);
  if (!flags.box_refinement.empty()) {
    filter->set_box_refinement(EnumFlagValue<v1::BoxRefinement>(flags.box_refinement));
  }
  if (!flags.short_term.empty()) {
    filter->mutable_short_term()->set_enabled(flags.short_term == "on");
  }
  if (!flags.static_budget.empty()) {
    filter->set_static_feature_budget(flags.static_budget == "on");
  }
  if (flags.short_term_horizon_option->count()) {
    filter->mutable_short_term()->set_horizon_s(flags.short_term_horizon_s);
  }
  if (!flags.scoring.empty()) config->set_scoring(EnumFlagValue<v1::Scoring>(flags.scoring));
  v1::VerificationSettings* verification = config->mutable_verification();
  if (!flags.verify.empty())
    verification->set_mode(EnumFlagValue<v1::VerificationMode>(flags.verify));
  if (flags.level_option->count()) verification->set_levels_up(flags.level);
  if (flags.min_inliers_option->count()) verification->set_min_inliers(flags.min_inliers);
  if (flags.candidates_option->count()) verification->set_candidates(flags.candidates);
  if (!flags.rerank.empty()) verification->set_rerank(flags.rerank == "on");
  config->set_store_invalid(flags.store_invalid);
  config->mutable_thumbnails()->set_enabled(flags.thumbnails);
  config->mutable_thumbnails()->set_max_side(flags.thumbnail_size);
  config->mutable_vocabulary_policy()->set_adapt_after_descriptors(flags.adapt_vocabulary_after);
  config->mutable_vocabulary_policy()->set_regrow_factor(flags.regrow_factor);
  return request;
}

CLI::App* RegisterCreate(CLI::App* maps, CreateFlags* flags) {
  CLI::App* create = maps->add_subcommand("create", "create a durable map");
  create->add_option("NAME", flags->name, "map name")->required();
  create->add_option("--vocabulary", flags->vocabulary,
                     "vocabulary name from the server's config (default: default)");
  flags->features_option =
      create->add_option("--features", flags->features, "ORB features per frame (default 1000)");
  create
      ->add_option("--detection", flags->detection,
                   "whether boxes mark dynamic objects (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create->add_option("--classes", flags->classes,
                     "dynamic COCO classes, comma-separated (default person,bicycle,car,"
                     "motorcycle,bus,truck)");
  flags->confidence_option =
      create->add_option("--confidence", flags->confidence, "minimum box confidence (default 0.2)");
  create
      ->add_option("--box-source", flags->box_source,
                   "where boxes come from (default: server when the server has a detector and "
                   "detection is on, else agent)")
      ->check(EnumFlag<v1::BoxSource>());
  create
      ->add_option("--filter", flags->filter, "dynamic-descriptor filter (default keypoint_in_box)")
      ->check(EnumFlag<v1::FilterMethod>());
  flags->sensitivity_option = create->add_option(
      "--sensitivity", flags->sensitivity, "exact_coverage threshold in [0, 1) (default 0.25)");
  flags->place_threshold_option =
      create->add_option("--place-threshold", flags->place_threshold,
                         "a frame is a place iff static descriptors > N (default 20)");
  create
      ->add_option("--refine-boxes", flags->box_refinement,
                   "narrow boxes to their objects without depth (default shape)")
      ->check(EnumFlag<v1::BoxRefinement>());
  create
      ->add_option("--short-term", flags->short_term,
                   "keep recent places' dynamic words in memory (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  flags->short_term_horizon_option =
      create->add_option("--short-term-horizon", flags->short_term_horizon_s,
                         "short-term horizon in seconds (default 60)");
  create
      ->add_option("--static-budget", flags->static_budget,
                   "spend the ORB budget on static pixels when objects are known (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create
      ->add_option("--rerank", flags->rerank, "re-rank verified candidates by inliers (default on)")
      ->check(CLI::IsMember({"on", "off"}));
  create->add_option("--scoring", flags->scoring, "score (default l1)")
      ->check(EnumFlag<v1::Scoring>());
  create->add_option("--verify", flags->verify, "geometric verification (default disabled)")
      ->check(EnumFlag<v1::VerificationMode>());
  flags->level_option =
      create->add_option("--level", flags->level, "direct-index level above the words (default 2)");
  flags->min_inliers_option = create->add_option("--min-inliers", flags->min_inliers,
                                                 "inliers to call a match verified (default 15)");
  flags->candidates_option = create->add_option("--candidates", flags->candidates,
                                                "candidates to verify (default 0 = all)");
  create->add_flag("--store-invalid", flags->store_invalid,
                   "keep invalid observations as metadata");
  create->add_flag("--thumbnails", flags->thumbnails,
                   "keep a small JPEG per place, dynamic objects blurred (for the console)");
  create->add_option("--adapt-vocabulary-after", flags->adapt_vocabulary_after,
                     "learn the map's own vocabulary by itself once it holds this many static "
                     "descriptors (at least 5000; default off)");
  create->add_option("--regrow-factor", flags->regrow_factor,
                     "learn again once the map holds this many times the descriptors its "
                     "vocabulary was learned from (> 1, e.g. 2; default off)");
  create
      ->add_option("--thumbnail-size", flags->thumbnail_size,
                   "longest side of the thumbnails in pixels, 16-1024 (default 320)")
      ->needs("--thumbnails");
  create
      ->add_option("--feature-type", flags->feature_type,
                   "orb or sift; must agree with the vocabulary (default: the vocabulary's kind)")
      ->check(EnumFlag<v1::FeatureType>());
  flags->sift_features_option = create
                                    ->add_option("--sift-features", flags->sift_features,
                                                 "SIFT features per frame (default 1000, 0 = all)")
                                    ->check(CLI::Range(0, 100000));
  create->add_flag("--no-refine-boxes", flags->no_refine_boxes,
                   "with depth, a box stays dynamic as a whole (default: only the object's own "
                   "depth layer)");
  create->add_flag("--no-depth-filter", flags->no_depth_filter,
                   "no Algorithm 1 on ingest streams with depth");
  flags->depth_scale_option = create
                                  ->add_option("--depth-scale", flags->depth_scale,
                                               "metres per png16 depth unit (default 0.001)")
                                  ->check(CLI::Range(1e-6, 100.0));
  flags->depth_threshold_option =
      create
          ->add_option("--depth-threshold", flags->depth_threshold,
                       "Algorithm 1: |V_current - V_static| that deviates, metres (default 0.15)")
          ->check(CLI::Range(0.001, 100.0));
  CLI::Option* band_policy =
      create
          ->add_option("--band-policy", flags->band_policy,
                       "depth band removed while deviating (default appeared_layer)")
          ->check(EnumFlag<v1::BandPolicy>());
  create
      ->add_flag("--paper-literal", flags->paper_literal,
                 "Algorithm 1 as written: mean over all pixels, fixed bands")
      ->excludes(band_policy);
  flags->loop_threshold_option =
      create
          ->add_option("--loop-threshold", flags->loop_threshold,
                       "loop closure: posterior to accept a loop, T_loop (default 0.12)")
          ->check(CLI::Range(0.0, 1.0));
  flags->rehearsal_threshold_option =
      create
          ->add_option(
              "--rehearsal-threshold", flags->rehearsal_threshold,
              "loop closure: similarity merging a frame into the previous place (default 0.20; > 1 "
              "disables rehearsal)")
          ->check(CLI::Range(0.0, 10.0));
  flags->stm_option = create
                          ->add_option("--stm", flags->stm,
                                       "loop closure: short-term memory, places (default "
                                       "30)")
                          ->check(CLI::Range(0, 100000));
  flags->max_wm_option =
      create->add_option("--max-wm", flags->max_wm,
                         "loop closure: working-memory bound, places (default 0 = unbounded)");
  flags->wm_time_budget_option =
      create
          ->add_option("--wm-time-budget-ms", flags->wm_time_budget_ms,
                       "loop closure: time budget per update, ms (default 0 = none)")
          ->check(CLI::Range(0.0, 3600000.0));
  create->add_flag("--no-verify-loops", flags->no_verify_loops,
                   "loop closure: keep loops the filter accepts without geometric verification");
  return create;
}

}  // namespace

MapsCommands RegisterMaps(CLI::App& app, MapsFlags* flags) {
  MapsCommands commands;
  CLI::App* maps = app.add_subcommand("maps", "create, list, show and delete maps");
  maps->require_subcommand(1);
  commands.create = RegisterCreate(maps, &flags->create);
  commands.list = maps->add_subcommand("list", "list the maps");
  commands.show = maps->add_subcommand(
      "show", "a map's configuration, statistics and agents' activity (alias: get)");
  commands.show->alias("get");
  commands.show->add_option("NAME", flags->show_name, "map name")->required();
  commands.remove = maps->add_subcommand("delete", "delete a map and all its places");
  commands.remove->add_option("NAME", flags->delete_name, "map name")->required();
  commands.remove->add_flag("--yes,-y", flags->delete_yes, "do not ask for confirmation");
  commands.recover = maps->add_subcommand(
      "recover", "accept a damaged map's losses: reopen it with what can be read");
  commands.recover->add_option("NAME", flags->recover_name, "map name")->required();
  commands.recover->add_flag("--accept-data-loss", flags->accept_data_loss,
                             "required: what cannot be read is dropped for good");
  commands.scrub = maps->add_subcommand(
      "scrub", "read every place of a map and verify its files (exit 3 when damaged)");
  commands.scrub->add_option("NAME", flags->scrub_name, "map name")->required();
  commands.adapt_vocabulary = maps->add_subcommand(
      "adapt-vocabulary",
      "learn a vocabulary from the map's own stored places and switch to it (online)");
  commands.adapt_vocabulary->add_option("NAME", flags->adapt_name, "map name")->required();
  commands.adapt_vocabulary->add_option("--seed", flags->adapt_seed,
                                        "sampling seed (default 1; the same places and seed "
                                        "learn the same vocabulary)");
  commands.adapt_vocabulary->add_option(
      "--max-sample", flags->adapt_max_sample,
      "descriptors sampled at most (default 1000000 ORB, 200000 SIFT)");
  commands.adapt_vocabulary->add_option("--branching", flags->adapt_branching,
                                        "k, children per node (default 10)");
  commands.adapt_vocabulary->add_option("--depth", flags->adapt_depth,
                                        "L, levels (default: 5 below 10^4 sampled descriptors, "
                                        "else 6)");
  commands.revert_vocabulary = maps->add_subcommand(
      "revert-vocabulary", "switch the map back to its previous vocabulary (online)");
  commands.revert_vocabulary->add_option("NAME", flags->revert_name, "map name")->required();
  return commands;
}

int MapsCreate(const Connection& connection, const CreateFlags& flags, bool json, CliIo& io) {
  const v1::CreateMapRequest request = CreateRequest(flags);
  auto context = connection.NewContext();
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->CreateMap(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(map) << '\n';
  } else {
    io.out << "created map '" << map.name() << "'\n";
    PrintMap(map, io);
  }
  return kExitOk;
}

int MapsList(const Connection& connection, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ListMapsResponse response;
  const grpc::Status status = connection.stub()->ListMaps(context.get(), {}, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  if (response.maps_size() == 0) {
    io.out << "no maps\n";
    return kExitOk;
  }
  Table table({"NAME", ">PLACES", "VOCABULARY", "FEATURES", "STATUS"});
  for (const v1::MapSummary& map : response.maps()) {
    // A server without map states (older) says only available or not.
    const v1::MapState state =
        map.state() != v1::MAP_STATE_UNSPECIFIED
            ? map.state()
            : (map.available() ? v1::MAP_STATE_AVAILABLE : v1::MAP_STATE_UNAVAILABLE);
    table.Add({map.name(), map.available() ? std::to_string(map.places()) : "-",
               map.vocabulary().empty() ? "-" : map.vocabulary(),
               map.available() ? wire::EnumName(map.feature_type()) : "-",
               StateText(state, map.places_lost(), map.unavailable_reason())});
  }
  table.Print(io.out);
  return kExitOk;
}

int MapsShow(const Connection& connection, const std::string& name, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::GetMapRequest request;
  request.set_name(name);
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->GetMap(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(map) << '\n';
  } else {
    PrintMap(map, io);
  }
  return kExitOk;
}

int MapsDelete(const Connection& connection, const std::string& name, bool yes, bool json,
               CliIo& io) {
  if (!yes) {
    if (!io.in_is_tty) {
      return UsageError(io, "refusing to delete map '" + name +
                                "' without --yes (standard input is not a terminal to ask on)");
    }
    io.err << "delete map '" << name << "' and all its places? [y/N] " << std::flush;
    std::string answer;
    std::getline(io.in, answer);
    if (answer != "y" && answer != "Y" && answer != "yes") {
      return UsageError(io, "not confirmed: map '" + name + "' was not deleted");
    }
  }
  auto context = connection.NewContext();
  v1::DeleteMapRequest request;
  request.set_name(name);
  v1::DeleteMapResponse response;
  const grpc::Status status = connection.stub()->DeleteMap(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << nlohmann::json({{"deleted", name}}).dump(2) << '\n';
  } else {
    io.out << "deleted map '" << name << "'\n";
  }
  return kExitOk;
}

int MapsRecover(const Connection& connection, const std::string& name, bool accept_data_loss,
                bool json, CliIo& io) {
  if (!accept_data_loss) {
    return UsageError(io, "recovering map '" + name +
                              "' drops for good whatever cannot be read; say so with "
                              "--accept-data-loss (see `placedb maps show " +
                              name + "` for the damage)");
  }
  auto context = connection.NewContext();
  v1::RecoverMapRequest request;
  request.set_name(name);
  request.set_accept_data_loss(true);
  v1::RecoverMapResponse response;
  const grpc::Status status = connection.stub()->RecoverMap(context.get(), request, &response);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(response) << '\n';
    return kExitOk;
  }
  if (response.accepted().reason().empty()) {
    io.out << "map '" << name << "' was not damaged: opened, nothing lost\n";
  } else {
    io.out << "recovered map '" << name << "': " << DamageText(response.accepted()) << '\n';
  }
  if (response.replicas_size() > 0) {  // cluster mode: each replica's part
    Table replicas({"REPLICA", "DAMAGE", "REBUILT FROM"});
    for (const auto& replica : response.replicas()) {
      const std::string found = !replica.error().empty()
                                    ? "error: " + replica.error()
                                    : (replica.damaged() ? replica.found() : std::string("none"));
      const std::string from = !replica.rebuilt()                ? std::string("-")
                               : replica.restored_from().empty() ? std::string("the map's stream")
                                                                 : replica.restored_from();
      replicas.Add({replica.shard(), found, from});
    }
    replicas.Print(io.out);
  }
  PrintMap(response.map(), io);
  return kExitOk;
}

int MapsScrub(const Connection& connection, const std::string& name, bool json, CliIo& io) {
  auto context = connection.NewContext();
  v1::ScrubMapRequest request;
  request.set_name(name);
  v1::ScrubReport report;
  const grpc::Status status = connection.stub()->ScrubMap(context.get(), request, &report);
  if (!status.ok()) return RpcFailed(io, status);
  if (json) {
    io.out << ProtoJson(report) << '\n';
  } else {
    io.out << "scrubbed map '" << name << "': " << report.places_checked() << " places, "
           << report.files_checked() << " files: "
           << (report.clean() ? "no damage"
                              : std::to_string(report.damaged_places_size()) + " places and " +
                                    std::to_string(report.damaged_files_size()) + " files damaged")
           << '\n';
    if (report.damaged_files_size() > 0) {
      Table files({"FILE", "DAMAGE"});
      for (const auto& file : report.damaged_files()) files.Add({file.file(), file.reason()});
      files.Print(io.out);
    }
    if (report.damaged_places_size() > 0) {
      Table places({">PLACE", "DAMAGE"});
      for (const auto& place : report.damaged_places()) {
        places.Add({std::to_string(place.place_id()), place.reason()});
      }
      places.Print(io.out);
    }
    if (report.replicas_size() > 0) {  // cluster mode: each replica's own scrub
      Table replicas({"REPLICA", ">PLACES", ">FILES", "RESULT"});
      for (const auto& replica : report.replicas()) {
        const v1::ScrubReport& own = replica.report();
        replicas.Add({replica.shard(), std::to_string(own.places_checked()),
                      std::to_string(own.files_checked()),
                      !replica.error().empty() ? replica.error()
                      : own.clean()
                          ? std::string("no damage")
                          : std::to_string(own.damaged_places_size()) + " places and " +
                                std::to_string(own.damaged_files_size()) + " files damaged"});
      }
      replicas.Print(io.out);
    }
  }
  return report.clean() ? kExitOk : kExitDamage;
}

namespace {

int PrintSwitched(const v1::MapVocabulary& vocabulary, const char* what, bool json, CliIo& io) {
  if (json) {
    io.out << ProtoJson(vocabulary) << '\n';
    return kExitOk;
  }
  io.out << "map '" << vocabulary.map() << "' " << what << " " << vocabulary.current().origin()
         << " vocabulary " << vocabulary.current().checksum() << '\n';
  PrintKeyValues(io.out, "vocabulary", VocabularyRows(vocabulary));
  return kExitOk;
}

}  // namespace

int MapsAdaptVocabulary(const Connection& connection, const MapsFlags& flags, bool json,
                        CliIo& io) {
  // No deadline: learning and re-indexing a large map takes minutes (the switch goes on on the
  // server even when the client gives up).
  auto context = connection.NewContext(/*unary=*/false);
  v1::AdaptVocabularyRequest request;
  request.set_name(flags.adapt_name);
  request.set_seed(flags.adapt_seed);
  request.set_max_sample_descriptors(flags.adapt_max_sample);
  request.set_branching(flags.adapt_branching);
  request.set_depth(flags.adapt_depth);
  v1::MapVocabulary vocabulary;
  const grpc::Status status =
      connection.stub()->AdaptVocabulary(context.get(), request, &vocabulary);
  if (!status.ok()) return RpcFailed(io, status);
  return PrintSwitched(vocabulary, "switched to the", json, io);
}

int MapsRevertVocabulary(const Connection& connection, const std::string& name, bool json,
                         CliIo& io) {
  auto context = connection.NewContext(/*unary=*/false);  // as for adapt-vocabulary
  v1::RevertVocabularyRequest request;
  request.set_name(name);
  v1::MapVocabulary vocabulary;
  const grpc::Status status =
      connection.stub()->RevertVocabulary(context.get(), request, &vocabulary);
  if (!status.ok()) return RpcFailed(io, status);
  return PrintSwitched(vocabulary, "reverted to the", json, io);
}

}  // namespace placedb::client
