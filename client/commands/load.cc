#include "client/commands/load.h"

#include <unistd.h>

#include <CLI/CLI.hpp>
#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>

#include "client/commands/common.h"
#include "client/format.h"
#include "client/frame_source.h"
#include "client/image_io.h"
#include "client/ingest_stream.h"
#include "client/loopback.h"
#include "client/progress.h"
#include "client/queue.h"
#include "core/base/thread_annotations.h"
#include "proto/status.h"

namespace placedb::client {

namespace {

double MsBetween(Clock::time_point from, Clock::time_point to) {
  return std::chrono::duration<double, std::milli>(to - from).count();
}

Clock::duration Seconds(double seconds) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
}

// Slot g (global, 0-based) is a query when the running count of queries steps up there: exactly
// round(g * ratio) of the first g slots are queries, spread evenly.
bool IsQuerySlot(uint64_t g, double ratio) {
  if (ratio <= 0) return false;
  if (ratio >= 1) return true;
  return std::floor(double(g + 1) * ratio) > std::floor(double(g) * ratio);
}

// --mode features' extractor: none until a linked placedb_load_orb installs one (load.h).
constinit LoadFeatureExtractor load_feature_extractor = nullptr;

// What one RPC kind (ingest or query) measured.
struct KindStats {
  size_t count = 0;     // answered (a response or a final status)
  size_t ok = 0;        // processed without error
  size_t stored = 0;    // ingest: stored as places
  size_t rejected = 0;  // ingest: invalid places
  size_t errors = 0;
  std::vector<double> latency_ms;
  std::map<std::string, std::vector<double>> stage_ms;  // by StageTimings field
  std::map<std::string, size_t> errors_by_code;

  void AddTimings(const v1::StageTimings& timings) {
    for (const StageField& field : StageFields()) {
      stage_ms[field.name].push_back((timings.*field.get)());
    }
  }
};

struct QueryJob {
  uint64_t slot = 0;
  std::optional<Clock::time_point> due;
};

// False (error printed) unless the target is loopback and the mode known.
bool CheckTarget(const ConnectionOptions& connection_options, const LoadOptions& options,
                 CliIo& io) {
  std::string why;
  if (!IsLoopbackTarget(connection_options.address, &why)) {
    io.err << "error: refusing to load " << connection_options.address
           << ": the load tester only targets this machine (loopback: 127.0.0.0/8, ::1, "
              "localhost); "
           << why << '\n';
    return false;
  }
  if (options.mode != "encoded" && options.mode != "features") {
    io.err << "error: --mode must be encoded or features\n";
    return false;
  }
  if (options.mode == "features" && load_feature_extractor == nullptr) {
    io.err << "error: --mode features extracts ORB here, and this program has no feature "
              "extractor linked: use placedb-load, or --mode encoded\n";
    return false;
  }
  return true;
}

// Frames, preloaded so the client costs the server nothing during the run. False (error
// printed) when the sources cannot be opened or hold no readable frame.
bool PreloadFrames(const LoadOptions& options, std::vector<std::string>* encoded, CliIo& io) {
  std::string error;
  std::unique_ptr<FrameSource> source =
      FrameSource::Open(options.sources, options.video_every, options.glob, &error);
  if (!source) {
    UsageError(io, error);
    return false;
  }
  Frame frame;
  while (encoded->size() < options.max_source_frames && source->Next(&frame, &error)) {
    if (!error.empty()) {
      io.err << "warning: " << error << " (skipped)\n";
      continue;
    }
    encoded->push_back(std::move(frame.bytes));
  }
  if (encoded->empty()) {
    UsageError(io, "no readable frames in the sources");
    return false;
  }
  return true;
}

// The map under load: the given one (created when missing), or a temporary one.
struct LoadMap {
  std::string name;
  bool temporary = false;
  v1::MapDescription description;
};

// False (error printed) when the map can be neither read nor created.
bool OpenMap(const Connection& connection, const LoadOptions& options, LoadMap* map, CliIo& io) {
  map->temporary = options.map.empty();
  map->name = map->temporary
                  ? "load-" + std::to_string(getpid()) + "-" + std::to_string(UnixNowNs() / 1000000)
                  : options.map;
  auto context = connection.NewContext();
  v1::GetMapRequest request;
  request.set_name(map->name);
  grpc::Status status = map->temporary
                            ? grpc::Status(grpc::StatusCode::NOT_FOUND, "")
                            : connection.stub()->GetMap(context.get(), request, &map->description);
  if (status.error_code() == grpc::StatusCode::NOT_FOUND) {
    auto create_context = connection.NewContext();
    v1::CreateMapRequest create;
    create.set_name(map->name);
    status = connection.stub()->CreateMap(create_context.get(), create, &map->description);
  }
  if (status.ok()) status = MapServingStatus(map->description);
  if (!status.ok()) {
    io.err << "error: map '" << map->name << "': " << Describe(status) << '\n';
    return false;
  }
  return true;
}

void DeleteTemporaryMap(const Connection& connection, const LoadOptions& options,
                        const LoadMap& map, CliIo& io) {
  if (!map.temporary || options.keep_map) return;
  auto context = connection.NewContext();
  v1::DeleteMapRequest request;
  request.set_name(map.name);
  v1::DeleteMapResponse response;
  const grpc::Status status = connection.stub()->DeleteMap(context.get(), request, &response);
  if (!status.ok()) {
    io.err << "warning: could not delete the temporary map '" << map.name
           << "': " << Describe(status) << '\n';
  }
}

// Observation templates: the frame, or its features with the map's ORB settings. Consumes
// *encoded. False (error printed) for a SIFT map in features mode or a frame ORB cannot read.
bool MakeTemplates(const LoadOptions& options, const LoadMap& map,
                   std::vector<std::string>* encoded, std::vector<v1::Observation>* templates,
                   CliIo& io) {
  const v1::MapConfig& config = map.description.config();
  if (options.mode == "features" && config.feature_type() == v1::FEATURE_TYPE_SIFT) {
    io.err << "error: --mode features extracts ORB here, and map '" << map.name
           << "' is a SIFT map: use --mode encoded\n";
    return false;
  }
  templates->resize(encoded->size());
  for (size_t i = 0; i < encoded->size(); ++i) {
    if (options.mode == "encoded") {
      (*templates)[i].mutable_encoded_image()->set_data(std::move((*encoded)[i]));
      continue;
    }
    const std::string& bytes = (*encoded)[i];
    cv::Mat gray;
    std::string decode_error;
    const Status extracted =
        !DecodeImageBytes(bytes, ImageRead::kGray, &gray, &decode_error)
            ? Status::InvalidArgument("undecodable: " + decode_error)
            : load_feature_extractor(gray, config.orb(), (*templates)[i].mutable_features());
    if (!extracted.ok()) {
      io.err << "error: extracting features of source frame " << i << ": " << extracted.ToString()
             << '\n';
      return false;
    }
  }
  encoded->clear();
  return true;
}

// The run's parameters, read by every agent.
struct LoadPlan {
  const Connection& connection;
  const LoadOptions& options;
  std::string map_name;
  std::vector<v1::Observation> templates{};
  size_t agents = 1;
  double per_agent_rate = 0;  // frames/s
  uint64_t frame_bound = 0;   // 0 = none
  double query_ratio = 0;
  Clock::time_point t0{};
  std::optional<Clock::time_point> end{};

  v1::Observation MakeObservation(uint64_t slot, size_t agent) const {
    v1::Observation observation = templates[slot % templates.size()];
    observation.set_agent_id(options.agent_prefix + "-" + std::to_string(agent + 1));
    observation.set_sequence(slot);
    observation.set_timestamp_ns(UnixNowNs());
    return observation;
  }
};

// What the agents measured.
struct LoadCounts {
  KindStats ingest, query;
  std::vector<std::pair<std::string, grpc::Status>> stream_errors;
  Clock::time_point last_answer;
};

// The agents' shared tally; read once, locked, after they have joined.
struct LoadTally {
  Mutex mutex;
  LoadCounts counts GUARDED_BY(mutex);
};

// Agent i's queries, one at a time beside its Ingest stream.
void RunQuerier(const LoadPlan& plan, size_t i, BoundedQueue<QueryJob>& queries, LoadTally& tally,
                Progress& progress) {
  while (std::optional<QueryJob> job = queries.Pop()) {
    v1::QueryRequest request;
    request.set_map(plan.map_name);
    *request.mutable_observation() = plan.MakeObservation(job->slot, i);
    request.mutable_options()->set_top_k(uint32_t(std::max(1, plan.options.top_k)));
    v1::QueryResponse response;
    auto context = plan.connection.NewContext();
    const Clock::time_point sent = Clock::now();
    const grpc::Status status = plan.connection.stub()->Query(context.get(), request, &response);
    const Clock::time_point now = Clock::now();
    MutexLock lock(tally.mutex);
    KindStats& query = tally.counts.query;
    ++query.count;
    query.latency_ms.push_back(MsBetween(job->due.value_or(sent), now));
    if (status.ok()) {
      ++query.ok;
      query.AddTimings(response.timings());
    } else {
      ++query.errors;
      ++query.errors_by_code[wire::GrpcCodeName(int(status.error_code()))];
    }
    tally.counts.last_answer = std::max(tally.counts.last_answer, now);
    progress.Add();
  }
}

// Agent i: its slots (i, i + agents, ...) paced by the rate until a bound, the query slots
// handed to its querier, the others sent on its Ingest stream.
void RunAgent(const LoadPlan& plan, size_t i, LoadTally& tally, Progress& progress) {
  BoundedQueue<QueryJob> queries(2);
  std::thread querier;
  if (plan.query_ratio > 0) {
    querier = std::thread([&] { RunQuerier(plan, i, queries, tally, progress); });
  }

  uint64_t local = 0;  // this agent's slot counter
  auto next = [&](Outgoing* outgoing) {
    while (true) {
      const uint64_t slot = uint64_t(i) + local * plan.agents;
      if (plan.frame_bound > 0 && slot >= plan.frame_bound) return false;
      std::optional<Clock::time_point> due;
      if (plan.per_agent_rate > 0) {
        // Agents are staggered evenly inside each period.
        due = plan.t0 +
              Seconds((double(local) + double(i) / double(plan.agents)) / plan.per_agent_rate);
        if (plan.end && *due >= *plan.end) return false;
        std::this_thread::sleep_until(*due);
      } else if (plan.end && Clock::now() >= *plan.end) {
        return false;
      }
      ++local;
      if (IsQuerySlot(slot, plan.query_ratio)) {
        queries.Push({slot, due});
        continue;
      }
      outgoing->observation = plan.MakeObservation(slot, i);
      outgoing->tag = slot;
      outgoing->due = due;
      return true;
    }
  };
  auto answered = [&](const Answered& answer) {
    const Clock::time_point now = Clock::now();
    const v1::IngestResponse& response = answer.response;
    MutexLock lock(tally.mutex);
    KindStats& ingest = tally.counts.ingest;
    ++ingest.count;
    ingest.latency_ms.push_back(answer.latency_ms);
    if (response.has_error()) {
      ++ingest.errors;
      ++ingest.errors_by_code[wire::GrpcCodeName(response.error().code())];
    } else {
      ++ingest.ok;
      (response.stored() ? ingest.stored : ingest.rejected)++;
      ingest.AddTimings(response.timings());
    }
    tally.counts.last_answer = std::max(tally.counts.last_answer, now);
    progress.Add();
  };
  v1::IngestHeader header;
  header.set_map(plan.map_name);
  if (plan.options.matches) {
    header.mutable_matches()->set_top_k(uint32_t(std::max(1, plan.options.top_k)));
  }
  const grpc::Status status =
      IngestStream::Run(plan.connection, header, plan.options.window, next, answered);
  queries.Finish();
  if (querier.joinable()) querier.join();
  if (!status.ok()) {
    MutexLock lock(tally.mutex);
    tally.counts.stream_errors.emplace_back(plan.options.agent_prefix + "-" + std::to_string(i + 1),
                                            status);
    ++tally.counts.ingest.errors_by_code[wire::GrpcCodeName(int(status.error_code()))];
  }
}

// Errors of both kinds by code name.
nlohmann::json ErrorsTotal(const LoadCounts& tally) {
  nlohmann::json errors_total = nlohmann::json::object();
  for (const auto* kind : {&tally.ingest, &tally.query}) {
    for (const auto& [code, n] : kind->errors_by_code) {
      errors_total[code] = errors_total.value(code, size_t(0)) + n;
    }
  }
  return errors_total;
}

nlohmann::json KindJson(const KindStats& kind, bool is_ingest, double elapsed) {
  nlohmann::json j = {{"count", kind.count},
                      {"ok", kind.ok},
                      {"errors", kind.errors},
                      {"per_s", double(kind.count) / elapsed},
                      {"latency_ms", ToJson(Summarize(kind.latency_ms))},
                      {"errors_by_code", kind.errors_by_code}};
  if (is_ingest) {
    j["stored"] = kind.stored;
    j["rejected"] = kind.rejected;
  }
  nlohmann::json stages = nlohmann::json::object();
  for (const StageField& field : StageFields()) {
    auto it = kind.stage_ms.find(field.name);
    if (it != kind.stage_ms.end()) stages[field.name] = ToJson(Summarize(it->second));
  }
  j["stages_ms"] = stages;
  return j;
}

// What a finished run reports, as JSON (--json, --json-out) and as text.
struct LoadReport {
  const std::string& target;
  const LoadPlan& plan;
  const LoadMap& map;
  const LoadCounts& tally;
  double elapsed = 0;  // seconds, from the start to the last answer
  size_t answered = 0;
  nlohmann::json errors_total;
};

nlohmann::json ReportJson(const LoadReport& r) {
  const LoadOptions& options = r.plan.options;
  nlohmann::json report;
  report["target"] = r.target;
  report["map"] = r.map.name;
  report["temporary_map"] = r.map.temporary;
  report["mode"] = options.mode;
  report["agents"] = r.plan.agents;
  report["window"] = options.window;
  report["source_frames"] = r.plan.templates.size();
  report["rate"] = {{"per_agent_fps", r.plan.per_agent_rate},
                    {"total_fps", r.plan.per_agent_rate * double(r.plan.agents)}};
  report["bound"] = {{"frames", r.plan.frame_bound}, {"duration_s", options.duration_s}};
  report["query_ratio"] = r.plan.query_ratio;
  report["matches"] = options.matches;
  report["elapsed_s"] = r.elapsed;
  report["frames"] = r.answered;
  report["throughput_fps"] = double(r.answered) / r.elapsed;
  report["rpc"] = {{"ingest", KindJson(r.tally.ingest, true, r.elapsed)},
                   {"query", KindJson(r.tally.query, false, r.elapsed)}};
  report["errors"] = r.errors_total;
  report["stream_errors"] = StreamErrorsJson(r.tally.stream_errors);
  return report;
}

// The target, the bound and the throughput.
void PrintRunLines(const LoadReport& r, std::ostream& out) {
  const LoadOptions& options = r.plan.options;
  const double per_agent_rate = r.plan.per_agent_rate;
  const uint64_t frame_bound = r.plan.frame_bound;
  out << "placedb load: " << r.target << ", map '" << r.map.name << "'"
      << (r.map.temporary ? (options.keep_map ? " (temporary, kept)" : " (temporary, deleted)")
                          : "")
      << ", " << r.plan.agents << " agents, " << options.mode << " frames ("
      << r.plan.templates.size() << " distinct), window " << options.window << '\n';
  out << "  target   "
      << (per_agent_rate > 0
              ? FormatDouble(per_agent_rate, 1) + " frames/s per agent (" +
                    FormatDouble(per_agent_rate * double(r.plan.agents), 1) + " total)"
              : std::string("as fast as the server takes them"))
      << "; bound " << (frame_bound > 0 ? std::to_string(frame_bound) + " frames" : std::string(""))
      << (frame_bound > 0 && options.duration_s > 0 ? " or " : "")
      << (options.duration_s > 0 ? FormatDuration(options.duration_s) : std::string(""))
      << (r.plan.query_ratio > 0 ? "; queries " + FormatDouble(r.plan.query_ratio * 100, 0) + "%"
                                 : std::string(""))
      << '\n';
  out << "  result   " << r.answered << " frames in " << FormatDuration(r.elapsed) << ": "
      << FormatDouble(double(r.answered) / r.elapsed, 1) << " frames/s\n\n";
}

// Count, outcome and latency percentiles per RPC kind.
void PrintRpcTable(const LoadReport& r, std::ostream& out) {
  const KindStats& ingest = r.tally.ingest;
  Table rpcs({"RPC", ">COUNT", ">OK", ">STORED", ">REJECTED", ">ERRORS", ">PER S", ">P50 MS",
              ">P90 MS", ">P99 MS", ">MAX MS"});
  for (const auto& [name, kind] :
       {std::pair<const char*, const KindStats*>{"ingest", &ingest}, {"query", &r.tally.query}}) {
    const LatencySummary s = Summarize(kind->latency_ms);
    const bool is_ingest = kind == &ingest;
    rpcs.Add({name, std::to_string(kind->count), std::to_string(kind->ok),
              is_ingest ? std::to_string(kind->stored) : "-",
              is_ingest ? std::to_string(kind->rejected) : "-", std::to_string(kind->errors),
              FormatDouble(double(kind->count) / r.elapsed, 1), FormatDouble(s.p50, 1),
              FormatDouble(s.p90, 1), FormatDouble(s.p99, 1), FormatDouble(s.max, 1)});
  }
  rpcs.Print(out, "  ");
  out << "  (latency: "
      << (r.plan.per_agent_rate > 0 ? "from the frame's scheduled time" : "from the write")
      << " to its response; ingest keeps at most " << r.plan.options.window
      << " frames unanswered per agent)\n\n";
}

// Percentiles of the server's stage timings, ingest beside query.
void PrintStageTable(const LoadReport& r, std::ostream& out) {
  out << "  server stages (ms, from the responses' timings)\n";
  Table stages(
      {"STAGE", ">INGEST P50", ">P90", ">P99", ">MAX", ">QUERY P50", ">P90", ">P99", ">MAX"});
  for (const StageField& field : StageFields()) {
    std::vector<std::string> row = {field.name};
    for (const KindStats* kind : {&r.tally.ingest, &r.tally.query}) {
      auto it = kind->stage_ms.find(field.name);
      if (it == kind->stage_ms.end()) {
        row.insert(row.end(), {"-", "-", "-", "-"});
        continue;
      }
      const LatencySummary s = Summarize(it->second);
      row.insert(row.end(), {FormatDouble(s.p50, 2), FormatDouble(s.p90, 2), FormatDouble(s.p99, 2),
                             FormatDouble(s.max, 2)});
    }
    stages.Add(row);
  }
  stages.Print(out, "  ");
  out << '\n';
}

void PrintReport(const LoadReport& r, std::ostream& out) {
  PrintRunLines(r, out);
  PrintRpcTable(r, out);
  PrintStageTable(r, out);
  if (r.errors_total.empty()) {
    out << "  errors   none\n";
  } else {
    out << "  errors  ";
    for (const auto& [code, n] : r.errors_total.items()) out << " " << code << ": " << n;
    out << '\n';
  }
  for (const auto& [agent, status] : r.tally.stream_errors) {
    out << "  agent " << agent << ": stream ended with " << Describe(status) << '\n';
  }
  if (!r.plan.options.json_out.empty()) out << "  report   " << r.plan.options.json_out << '\n';
}

}  // namespace

CLI::App* RegisterLoad(CLI::App& app, LoadOptions* options) {
  CLI::App* load =
      app.add_subcommand("load", "load-test a server on this machine (loopback targets only)");
  load->add_option("SOURCE", options->sources,
                   "image folders, image lists (.txt), videos or images (preloaded, cycled)")
      ->required();
  load->add_option("--agents", options->agents, "concurrent agents (Ingest streams)")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  load->add_option("--map", options->map,
                   "map to load (created when missing); default: a temporary map, deleted after");
  load->add_flag("--keep-map", options->keep_map, "keep the temporary map");
  load->add_option("--mode", options->mode,
                   "encoded: send the images; features: ORB extracted once here, loads the index "
                   "alone")
      ->check(CLI::IsMember({"encoded", "features"}))
      ->capture_default_str();
  CLI::Option* rate = load->add_option("--rate", options->rate,
                                       "target frames/s per agent (0 = as fast as accepted)")
                          ->check(CLI::Range(0.0, 10000.0));
  load->add_option("--total-rate", options->total_rate, "target frames/s of all agents")
      ->check(CLI::Range(0.0, 100000.0))
      ->excludes(rate);
  load->add_option("--frames", options->frames,
                   "stop after N frames in total (default: one pass over the sources)");
  load->add_option("--duration", options->duration_s, "stop after S seconds")
      ->check(CLI::Range(0.0, 604800.0));
  load->add_option("--query-ratio", options->query_ratio,
                   "fraction of the frames sent as Query instead of ingested")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  load->add_option("--top-k", options->top_k, "matches per query")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  load->add_flag("--matches", options->matches, "ingest with matches (search, then store)");
  load->add_option("--window", options->window, "unanswered frames per agent")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  load->add_option("--json-out", options->json_out, "write the report as JSON");
  load->add_option("--video-every", options->video_every, "every K-th video frame")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  load->add_option("--glob", options->glob,
                   "only folder entries whose name matches (e.g. '*.jpg')");
  load->add_option("--max-source-frames", options->max_source_frames, "distinct frames to preload")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  return load;
}

int RunLoad(const ConnectionOptions& connection_options, const LoadOptions& options, bool json,
            CliIo& io) {
  if (!CheckTarget(connection_options, options, io)) return kExitUsage;
  std::string error;
  auto connection = Connection::Open(connection_options, &error);
  if (!connection) return UsageError(io, error);
  std::vector<std::string> encoded;
  if (!PreloadFrames(options, &encoded, io)) return kExitUsage;
  LoadMap map;
  if (!OpenMap(*connection, options, &map, io)) return kExitRpcError;
  LoadPlan plan{.connection = *connection, .options = options, .map_name = map.name};
  if (!MakeTemplates(options, map, &encoded, &plan.templates, io)) {
    DeleteTemporaryMap(*connection, options, map, io);
    return kExitUsage;
  }

  plan.agents = size_t(std::max(1, options.agents));
  plan.per_agent_rate =
      options.total_rate > 0 ? options.total_rate / double(plan.agents) : options.rate;
  plan.frame_bound = options.frames > 0
                         ? options.frames
                         : (options.duration_s > 0 ? 0 : uint64_t(plan.templates.size()));
  plan.query_ratio = std::clamp(options.query_ratio, 0.0, 1.0);
  LoadTally tally;
  std::optional<size_t> total;
  if (plan.frame_bound > 0) total = size_t(plan.frame_bound);
  Progress progress(io.err, io.err_is_tty, total, 5.0);
  plan.t0 = Clock::now();
  if (options.duration_s > 0) plan.end = plan.t0 + Seconds(options.duration_s);
  {
    MutexLock lock(tally.mutex);
    tally.counts.last_answer = plan.t0;
  }

  std::vector<std::thread> threads;
  for (size_t i = 0; i < plan.agents; ++i) {
    threads.emplace_back([&, i] { RunAgent(plan, i, tally, progress); });
  }
  for (std::thread& thread : threads) thread.join();
  progress.Stop();
  const LoadCounts counts = [&] {
    MutexLock lock(tally.mutex);  // the agents have joined: uncontended
    return tally.counts;
  }();
  DeleteTemporaryMap(*connection, options, map, io);

  const double elapsed =
      std::max(1e-9, std::chrono::duration<double>(counts.last_answer - plan.t0).count());
  const LoadReport report{.target = connection_options.address,
                          .plan = plan,
                          .map = map,
                          .tally = counts,
                          .elapsed = elapsed,
                          .answered = counts.ingest.count + counts.query.count,
                          .errors_total = ErrorsTotal(counts)};
  const nlohmann::json report_json = ReportJson(report);
  if (!options.json_out.empty()) {
    std::ofstream out(options.json_out);
    out << report_json.dump(2) << '\n';
    if (!out) {
      io.err << "error: cannot write " << options.json_out << '\n';
      return kExitUsage;
    }
  }
  if (json) {
    io.out << report_json.dump(2) << '\n';
  } else {
    PrintReport(report, io.out);
  }
  return counts.stream_errors.empty() && report.errors_total.empty() ? kExitOk : kExitRpcError;
}

void SetLoadFeatureExtractor(LoadFeatureExtractor extractor) {
  load_feature_extractor = extractor;
}

}  // namespace placedb::client
