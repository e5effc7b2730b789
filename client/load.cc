#include "client/load.h"

#include <unistd.h>

#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "client/format.h"
#include "client/frame_source.h"
#include "client/ingest_stream.h"
#include "client/loopback.h"
#include "client/progress.h"
#include "client/queue.h"
#include "core/base/thread_annotations.h"
#include "core/features/orb_features.h"

namespace placedb::client {

namespace {

int64_t UnixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

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

OrbConfig OrbFromMap(const v1::MapConfig& config) {
  OrbConfig orb;
  const v1::OrbSettings& s = config.orb();
  if (s.has_max_features()) orb.max_features = s.max_features();
  if (s.has_scale_factor()) orb.scale_factor = s.scale_factor();
  if (s.has_levels()) orb.levels = s.levels();
  if (s.has_edge_threshold()) orb.edge_threshold = s.edge_threshold();
  if (s.has_patch_size()) orb.patch_size = s.patch_size();
  if (s.has_fast_threshold()) orb.fast_threshold = s.fast_threshold();
  return orb;
}

void ToProto(const FeatureSet& features, v1::Features* out) {
  out->set_image_width(uint32_t(features.image_width));
  out->set_image_height(uint32_t(features.image_height));
  for (const Keypoint& k : features.keypoints) {
    v1::Keypoint* keypoint = out->add_keypoints();
    keypoint->set_x(k.x);
    keypoint->set_y(k.y);
    keypoint->set_size(k.size);
    keypoint->set_angle(k.angle);
    keypoint->set_response(k.response);
    keypoint->set_octave(k.octave);
  }
  std::string* bytes = out->mutable_descriptors();
  bytes->resize(features.descriptors.size() * size_t(Descriptor256::kBytes));
  for (size_t i = 0; i < features.descriptors.size(); ++i) {
    features.descriptors[i].ToBytes(reinterpret_cast<uint8_t*>(bytes->data()) +
                                    i * size_t(Descriptor256::kBytes));
  }
}

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

}  // namespace

int RunLoad(const ConnectionOptions& connection_options, const LoadOptions& options, bool json,
            CliIo& io) {
  std::string why;
  if (!IsLoopbackTarget(connection_options.address, &why)) {
    io.err << "error: refusing to load " << connection_options.address
           << ": the load tester only targets this machine (loopback: 127.0.0.0/8, ::1, "
              "localhost); "
           << why << '\n';
    return kExitUsage;
  }
  if (options.mode != "encoded" && options.mode != "features") {
    io.err << "error: --mode must be encoded or features\n";
    return kExitUsage;
  }
  std::string error;
  auto connection = Connection::Open(connection_options, &error);
  if (!connection) {
    io.err << "error: " << error << '\n';
    return kExitUsage;
  }

  // ---- Frames, preloaded so the client costs the server nothing during the run.
  std::unique_ptr<FrameSource> source =
      FrameSource::Open(options.sources, options.video_every, options.glob, &error);
  if (!source) {
    io.err << "error: " << error << '\n';
    return kExitUsage;
  }
  std::vector<std::string> encoded;
  {
    Frame frame;
    while (encoded.size() < options.max_source_frames && source->Next(&frame, &error)) {
      if (!error.empty()) {
        io.err << "warning: " << error << " (skipped)\n";
        continue;
      }
      encoded.push_back(std::move(frame.bytes));
    }
  }
  if (encoded.empty()) {
    io.err << "error: no readable frames in the sources\n";
    return kExitUsage;
  }

  // ---- The map: the given one (created when missing), or a temporary one.
  const bool temporary = options.map.empty();
  const std::string map_name =
      temporary ? "load-" + std::to_string(getpid()) + "-" + std::to_string(UnixNowNs() / 1000000)
                : options.map;
  v1::MapDescription description;
  {
    auto context = connection->NewContext();
    v1::GetMapRequest request;
    request.set_name(map_name);
    grpc::Status status = temporary
                              ? grpc::Status(grpc::StatusCode::NOT_FOUND, "")
                              : connection->stub()->GetMap(context.get(), request, &description);
    if (status.error_code() == grpc::StatusCode::NOT_FOUND) {
      auto create_context = connection->NewContext();
      v1::CreateMapRequest create;
      create.set_name(map_name);
      status = connection->stub()->CreateMap(create_context.get(), create, &description);
    }
    if (!status.ok()) {
      io.err << "error: map '" << map_name << "': " << Describe(status) << '\n';
      return kExitRpcError;
    }
  }
  auto delete_temporary = [&] {
    if (!temporary || options.keep_map) return;
    auto context = connection->NewContext();
    v1::DeleteMapRequest request;
    request.set_name(map_name);
    v1::DeleteMapResponse response;
    const grpc::Status status = connection->stub()->DeleteMap(context.get(), request, &response);
    if (!status.ok()) {
      io.err << "warning: could not delete the temporary map '" << map_name
             << "': " << Describe(status) << '\n';
    }
  };

  if (options.mode == "features" && description.config().feature_type() == v1::FEATURE_TYPE_SIFT) {
    io.err << "error: --mode features extracts ORB here, and map '" << map_name
           << "' is a SIFT map: use --mode encoded\n";
    delete_temporary();
    return kExitUsage;
  }

  // Observation templates: the frame, or its features with the map's ORB settings.
  std::vector<v1::Observation> templates(encoded.size());
  for (size_t i = 0; i < encoded.size(); ++i) {
    if (options.mode == "encoded") {
      templates[i].mutable_encoded_image()->set_data(std::move(encoded[i]));
      continue;
    }
    const std::string& bytes = encoded[i];
    cv::Mat gray =
        cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())),
                     cv::IMREAD_GRAYSCALE);
    auto features = gray.empty() ? Result<FeatureSet>(Status::InvalidArgument("undecodable"))
                                 : ExtractOrb(gray, OrbFromMap(description.config()));
    if (!features.ok()) {
      io.err << "error: extracting features of source frame " << i << ": "
             << features.status().ToString() << '\n';
      delete_temporary();
      return kExitUsage;
    }
    ToProto(*features, templates[i].mutable_features());
  }
  encoded.clear();

  // ---- The run.
  const size_t agents = size_t(std::max(1, options.agents));
  const double per_agent_rate =
      options.total_rate > 0 ? options.total_rate / double(agents) : options.rate;
  const uint64_t frame_bound = options.frames > 0
                                   ? options.frames
                                   : (options.duration_s > 0 ? 0 : uint64_t(templates.size()));
  const double query_ratio = std::clamp(options.query_ratio, 0.0, 1.0);

  // Stats below. Locals cannot be GUARDED_BY (only members can).
  Mutex mutex;
  KindStats ingest, query;
  std::vector<std::pair<std::string, grpc::Status>> stream_errors;
  Clock::time_point last_answer;

  std::optional<size_t> total;
  if (frame_bound > 0) total = size_t(frame_bound);
  Progress progress(io.err, io.err_is_tty, total, 5.0);

  const Clock::time_point t0 = Clock::now();
  const std::optional<Clock::time_point> end =
      options.duration_s > 0 ? std::optional(t0 + Seconds(options.duration_s)) : std::nullopt;
  last_answer = t0;

  auto make_observation = [&](uint64_t slot, size_t agent) {
    v1::Observation observation = templates[slot % templates.size()];
    observation.set_agent_id(options.agent_prefix + "-" + std::to_string(agent + 1));
    observation.set_sequence(slot);
    observation.set_timestamp_ns(UnixNowNs());
    return observation;
  };

  std::vector<std::thread> threads;
  for (size_t i = 0; i < agents; ++i) {
    threads.emplace_back([&, i] {
      BoundedQueue<QueryJob> queries(2);
      std::thread querier;
      if (query_ratio > 0) {
        querier = std::thread([&] {
          while (std::optional<QueryJob> job = queries.Pop()) {
            v1::QueryRequest request;
            request.set_map(map_name);
            *request.mutable_observation() = make_observation(job->slot, i);
            request.mutable_options()->set_top_k(uint32_t(std::max(1, options.top_k)));
            v1::QueryResponse response;
            auto context = connection->NewContext();
            const Clock::time_point sent = Clock::now();
            const grpc::Status status =
                connection->stub()->Query(context.get(), request, &response);
            const Clock::time_point now = Clock::now();
            MutexLock lock(mutex);
            ++query.count;
            query.latency_ms.push_back(MsBetween(job->due.value_or(sent), now));
            if (status.ok()) {
              ++query.ok;
              query.AddTimings(response.timings());
            } else {
              ++query.errors;
              ++query.errors_by_code[CodeName(int(status.error_code()))];
            }
            last_answer = std::max(last_answer, now);
            progress.Add();
          }
        });
      }

      uint64_t local = 0;  // this agent's slot counter
      auto next = [&](Outgoing* outgoing) {
        while (true) {
          const uint64_t slot = uint64_t(i) + local * agents;
          if (frame_bound > 0 && slot >= frame_bound) return false;
          std::optional<Clock::time_point> due;
          if (per_agent_rate > 0) {
            // Agents are staggered evenly inside each period.
            due = t0 + Seconds((double(local) + double(i) / double(agents)) / per_agent_rate);
            if (end && *due >= *end) return false;
            std::this_thread::sleep_until(*due);
          } else if (end && Clock::now() >= *end) {
            return false;
          }
          ++local;
          if (IsQuerySlot(slot, query_ratio)) {
            queries.Push({slot, due});
            continue;
          }
          outgoing->observation = make_observation(slot, i);
          outgoing->tag = slot;
          outgoing->due = due;
          return true;
        }
      };
      auto answered = [&](const Answered& answer) {
        const Clock::time_point now = Clock::now();
        const v1::IngestResponse& response = answer.response;
        MutexLock lock(mutex);
        ++ingest.count;
        ingest.latency_ms.push_back(answer.latency_ms);
        if (response.has_error()) {
          ++ingest.errors;
          ++ingest.errors_by_code[CodeName(response.error().code())];
        } else {
          ++ingest.ok;
          (response.stored() ? ingest.stored : ingest.rejected)++;
          ingest.AddTimings(response.timings());
        }
        last_answer = std::max(last_answer, now);
        progress.Add();
      };
      v1::IngestHeader header;
      header.set_map(map_name);
      if (options.matches) {
        header.mutable_matches()->set_top_k(uint32_t(std::max(1, options.top_k)));
      }
      const grpc::Status status =
          IngestStream::Run(*connection, header, options.window, next, answered);
      queries.Finish();
      if (querier.joinable()) querier.join();
      if (!status.ok()) {
        MutexLock lock(mutex);
        stream_errors.emplace_back(options.agent_prefix + "-" + std::to_string(i + 1), status);
        ++ingest.errors_by_code[CodeName(int(status.error_code()))];
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  progress.Stop();
  delete_temporary();

  // ---- Report.
  const double elapsed = std::max(1e-9, std::chrono::duration<double>(last_answer - t0).count());
  const size_t answered = ingest.count + query.count;
  nlohmann::json report;
  report["target"] = connection_options.address;
  report["map"] = map_name;
  report["temporary_map"] = temporary;
  report["mode"] = options.mode;
  report["agents"] = agents;
  report["window"] = options.window;
  report["source_frames"] = templates.size();
  report["rate"] = {{"per_agent_fps", per_agent_rate},
                    {"total_fps", per_agent_rate * double(agents)}};
  report["bound"] = {{"frames", frame_bound}, {"duration_s", options.duration_s}};
  report["query_ratio"] = query_ratio;
  report["matches"] = options.matches;
  report["elapsed_s"] = elapsed;
  report["frames"] = answered;
  report["throughput_fps"] = double(answered) / elapsed;
  nlohmann::json errors_total = nlohmann::json::object();
  for (const auto* kind : {&ingest, &query}) {
    for (const auto& [code, n] : kind->errors_by_code) {
      errors_total[code] = errors_total.value(code, size_t(0)) + n;
    }
  }
  auto kind_json = [&](const KindStats& kind, bool is_ingest) {
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
  };
  report["rpc"] = {{"ingest", kind_json(ingest, true)}, {"query", kind_json(query, false)}};
  report["errors"] = errors_total;
  nlohmann::json streams = nlohmann::json::array();
  for (const auto& [agent, status] : stream_errors) {
    streams.push_back({{"agent", agent},
                       {"code", CodeName(int(status.error_code()))},
                       {"message", status.error_message()}});
  }
  report["stream_errors"] = streams;

  if (!options.json_out.empty()) {
    std::ofstream out(options.json_out);
    out << report.dump(2) << '\n';
    if (!out) {
      io.err << "error: cannot write " << options.json_out << '\n';
      return kExitUsage;
    }
  }

  if (json) {
    io.out << report.dump(2) << '\n';
  } else {
    io.out << "placedb load: " << connection_options.address << ", map '" << map_name << "'"
           << (temporary ? (options.keep_map ? " (temporary, kept)" : " (temporary, deleted)") : "")
           << ", " << agents << " agents, " << options.mode << " frames (" << templates.size()
           << " distinct), window " << options.window << '\n';
    io.out << "  target   "
           << (per_agent_rate > 0 ? FormatDouble(per_agent_rate, 1) + " frames/s per agent (" +
                                        FormatDouble(per_agent_rate * double(agents), 1) + " total)"
                                  : std::string("as fast as the server takes them"))
           << "; bound "
           << (frame_bound > 0 ? std::to_string(frame_bound) + " frames" : std::string(""))
           << (frame_bound > 0 && options.duration_s > 0 ? " or " : "")
           << (options.duration_s > 0 ? FormatDuration(options.duration_s) : std::string(""))
           << (query_ratio > 0 ? "; queries " + FormatDouble(query_ratio * 100, 0) + "%"
                               : std::string(""))
           << '\n';
    io.out << "  result   " << answered << " frames in " << FormatDuration(elapsed) << ": "
           << FormatDouble(double(answered) / elapsed, 1) << " frames/s\n\n";

    Table rpcs({"RPC", ">COUNT", ">OK", ">STORED", ">REJECTED", ">ERRORS", ">PER S", ">P50 MS",
                ">P90 MS", ">P99 MS", ">MAX MS"});
    for (const auto& [name, kind] :
         {std::pair<const char*, const KindStats*>{"ingest", &ingest}, {"query", &query}}) {
      const LatencySummary s = Summarize(kind->latency_ms);
      const bool is_ingest = kind == &ingest;
      rpcs.Add({name, std::to_string(kind->count), std::to_string(kind->ok),
                is_ingest ? std::to_string(kind->stored) : "-",
                is_ingest ? std::to_string(kind->rejected) : "-", std::to_string(kind->errors),
                FormatDouble(double(kind->count) / elapsed, 1), FormatDouble(s.p50, 1),
                FormatDouble(s.p90, 1), FormatDouble(s.p99, 1), FormatDouble(s.max, 1)});
    }
    rpcs.Print(io.out, "  ");
    io.out << "  (latency: "
           << (per_agent_rate > 0 ? "from the frame's scheduled time" : "from the write")
           << " to its response; ingest keeps at most " << options.window
           << " frames unanswered per agent)\n\n";

    io.out << "  server stages (ms, from the responses' timings)\n";
    Table stages(
        {"STAGE", ">INGEST P50", ">P90", ">P99", ">MAX", ">QUERY P50", ">P90", ">P99", ">MAX"});
    for (const StageField& field : StageFields()) {
      std::vector<std::string> row = {field.name};
      for (const KindStats* kind : {&ingest, &query}) {
        auto it = kind->stage_ms.find(field.name);
        if (it == kind->stage_ms.end()) {
          row.insert(row.end(), {"-", "-", "-", "-"});
          continue;
        }
        const LatencySummary s = Summarize(it->second);
        row.insert(row.end(), {FormatDouble(s.p50, 2), FormatDouble(s.p90, 2),
                               FormatDouble(s.p99, 2), FormatDouble(s.max, 2)});
      }
      stages.Add(row);
    }
    stages.Print(io.out, "  ");
    io.out << '\n';
    if (errors_total.empty()) {
      io.out << "  errors   none\n";
    } else {
      io.out << "  errors  ";
      for (const auto& [code, n] : errors_total.items()) io.out << " " << code << ": " << n;
      io.out << '\n';
    }
    for (const auto& [agent, status] : stream_errors) {
      io.out << "  agent " << agent << ": stream ended with " << Describe(status) << '\n';
    }
    if (!options.json_out.empty()) io.out << "  report   " << options.json_out << '\n';
  }
  return stream_errors.empty() && errors_total.empty() ? kExitOk : kExitRpcError;
}

}  // namespace placedb::client
