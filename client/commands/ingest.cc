#include "client/commands/ingest.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>

#include "client/commands/common.h"
#include "client/format.h"
#include "client/frame_source.h"
#include "client/ingest_stream.h"
#include "client/progress.h"
#include "client/queue.h"
#include "client/recording.h"
#include "core/base/thread_annotations.h"
#include "proto/status.h"

namespace placedb::client {

namespace {

// "invalid place representation: 12 static descriptors ..." -> "invalid place representation".
std::string ReasonKey(const std::string& rejection) {
  const auto colon = rejection.find(':');
  return colon == std::string::npos ? rejection : rejection.substr(0, colon);
}

struct FrameRecord {
  std::string name;
  std::string agent;
  uint64_t sequence = 0;
  bool sent = false;
  bool answered = false;
  double latency_ms = 0;
  v1::IngestResponse response;  // frame images are not kept, only the answer
  std::string local_error;      // unreadable, or not sent because its stream ended
};

nlohmann::json MatchJson(const v1::Match& match) {
  return {{"place_id", match.place_id()},
          {"score", match.score()},
          {"agent_id", match.metadata().agent_id()},
          {"sequence", match.metadata().sequence()},
          {"timestamp_ns", match.metadata().timestamp_ns()},
          {"inliers", match.inliers()},
          {"verified", match.verified()}};
}

// --depth: every image frame needs its depth image (paired by file stem) before anything is sent.
struct DepthPlan {
  bool enabled = false;
  std::vector<std::string> paths;  // by frame index (no videos with --depth)
  v1::Intrinsics intrinsics;
};

// False and *error on a depth option without --depth, a video, or a missing depth image.
bool PlanDepth(const IngestOptions& options, const FrameSource& source, DepthPlan* plan,
               std::string* error) {
  plan->enabled = !options.depth_dir.empty();
  if (!plan->enabled && (options.depth_scale != 0 || !options.intrinsics.empty())) {
    *error = "--depth-scale and --intrinsics describe depth images: they need --depth DIR";
    return false;
  }
  if (!plan->enabled) return true;
  std::error_code ec;
  if (!std::filesystem::is_directory(options.depth_dir, ec)) {
    *error = "--depth: " + options.depth_dir + " is not a folder";
    return false;
  }
  const std::vector<std::string> videos = source.video_paths();
  if (!videos.empty()) {
    *error =
        "--depth pairs depth images with image files by name; " + videos.front() + " is a video";
    return false;
  }
  for (const std::string& path : source.image_paths()) {
    plan->paths.push_back(FindDepthImage(options.depth_dir, path, error));
    if (plan->paths.back().empty()) return false;
  }
  return options.intrinsics.empty() ||
         ParseIntrinsics(options.intrinsics, &plan->intrinsics, error);
}

// An unknown map fails here, once, rather than once per stream.
int CheckMap(const Connection& connection, const std::string& name, CliIo& io) {
  auto context = connection.NewContext();
  v1::GetMapRequest request;
  request.set_name(name);
  v1::MapDescription map;
  const grpc::Status status = connection.stub()->GetMap(context.get(), request, &map);
  if (!status.ok()) return RpcFailed(io, status);
  if (const grpc::Status served = MapServingStatus(map); !served.ok()) {
    return RpcFailed(io, served);
  }
  return kExitOk;
}

std::vector<std::string> AgentIds(const IngestOptions& options) {
  const size_t agents = size_t(std::max(1, options.agents));
  std::vector<std::string> agent_ids;
  for (size_t i = 0; i < agents; ++i) {
    agent_ids.push_back(agents == 1 ? options.agent_id
                                    : options.agent_id + "-" + std::to_string(i + 1));
  }
  return agent_ids;
}

// One ingest run: its agents' streams and queues, and what their answers add up to.
struct IngestRun {
  IngestRun(const Connection& connection, const IngestOptions& options, bool json, CliIo& io,
            std::optional<size_t> total)
      : connection(connection),
        options(options),
        json(json),
        out(io.out),
        agent_ids(AgentIds(options)),
        progress(io.err, io.err_is_tty, total) {
    records.reserve(total.value_or(0));
    for (size_t i = 0; i < agent_ids.size(); ++i) {
      queues.push_back(std::make_unique<BoundedQueue<Outgoing>>(options.window * 2));
    }
    header.set_map(options.map);
    if (options.matches) header.mutable_matches()->set_top_k(uint32_t(std::max(1, options.top_k)));
    header.set_loop_closure(options.loop_closure);
  }

  const Connection& connection;
  const IngestOptions& options;
  const bool json;
  std::ostream& out;
  const std::vector<std::string> agent_ids;
  v1::IngestHeader header;

  // Everything below, and the writes to `out` while agents run. Mutable: the summary, written
  // after the agents have joined, reads under it too (uncontended).
  mutable Mutex mutex;
  std::vector<FrameRecord> records GUARDED_BY(mutex);
  std::vector<double> latencies GUARDED_BY(mutex);
  size_t stored GUARDED_BY(mutex) = 0;
  size_t rejected GUARDED_BY(mutex) = 0;
  size_t frame_errors GUARDED_BY(mutex) = 0;
  size_t merged GUARDED_BY(mutex) = 0;                 // --loop-closure
  size_t loops_found GUARDED_BY(mutex) = 0;            // --loop-closure
  size_t depth_frames_removing GUARDED_BY(mutex) = 0;  // --depth
  size_t depth_removed GUARDED_BY(mutex) = 0;          // --depth
  std::map<std::string, size_t> rejected_by_reason GUARDED_BY(mutex);
  std::map<std::string, size_t> errors_by_code GUARDED_BY(mutex);
  std::vector<std::pair<std::string, grpc::Status>> stream_errors GUARDED_BY(mutex);

  Progress progress;
  std::vector<std::unique_ptr<BoundedQueue<Outgoing>>> queues;  // one per agent
};

// "frame.jpg -> place 12; best match place 3 score 0.0412 (cli #2) verified": the per-frame line
// printed with --matches, --loop-closure, or when depth removed descriptors.
void PrintFrameLine(const IngestRun& run, const FrameRecord& record,
                    const v1::IngestResponse& response, bool was_merged,
                    const std::string& removal) {
  std::ostream& out = run.out;
  out << record.name << " -> ";
  if (response.has_error()) {
    out << "error: " << wire::GrpcCodeName(response.error().code());
  } else if (was_merged) {
    out << FormatLoopClosure(response.loop_closure());
  } else if (response.stored()) {
    out << "place " << response.place_id();
  } else {
    out << "not stored";
    if (!response.rejection().empty()) {
      out << " (" << ReasonKey(response.rejection()) << ")";
    }
  }
  if (run.options.matches && !response.has_error()) {
    if (response.matches_size() > 0) {
      const v1::Match& best = response.matches(0);
      out << "; best match place " << best.place_id() << " score " << FormatDouble(best.score(), 4)
          << " (" << best.metadata().agent_id() << " #" << best.metadata().sequence() << ")"
          << (best.verified() ? " verified" : "");
    } else {
      out << "; no match";
    }
  }
  if (response.has_loop_closure() && !was_merged) {
    out << "; " << FormatLoopClosure(response.loop_closure());
  }
  if (!removal.empty()) out << "; " << removal;
  out << '\n';
}

// An agent's answer: the frame's record, the tallies, and its line.
void RecordAnswer(IngestRun& run, const Answered& answer) {
  MutexLock lock(run.mutex);
  FrameRecord& record = run.records[answer.tag];
  record.answered = true;
  record.latency_ms = answer.latency_ms;
  record.response = answer.response;
  record.response.clear_boxes_used();
  run.latencies.push_back(answer.latency_ms);
  const v1::IngestResponse& response = answer.response;
  // A frame rehearsal merged into an existing place is neither stored nor rejected.
  const bool was_merged = response.has_loop_closure() && response.loop_closure().merged();
  if (response.has_error()) {
    ++run.frame_errors;
    ++run.errors_by_code[wire::GrpcCodeName(response.error().code())];
    run.progress.Message("frame " + record.name + ": " +
                         wire::GrpcCodeName(response.error().code()) + ": " +
                         response.error().message());
  } else if (was_merged) {
    ++run.merged;
  } else if (response.stored()) {
    ++run.stored;
  } else {
    ++run.rejected;
    ++run.rejected_by_reason[ReasonKey(response.rejection())];
  }
  if (!response.has_error() && response.has_loop_closure() &&
      response.loop_closure().loop_found()) {
    ++run.loops_found;
  }
  if (response.counts().depth_removed() > 0) {
    ++run.depth_frames_removing;
    run.depth_removed += response.counts().depth_removed();
  }
  const std::string removal = FormatDepthRemoval(response.counts(), response.depth());
  if (!run.json && (run.options.matches || run.options.loop_closure || !removal.empty())) {
    PrintFrameLine(run, record, response, was_merged, removal);
  }
  run.progress.Add();
}

// Agent i's stream: frames from its queue (paced by --rate) until the producer finishes it.
void RunAgent(IngestRun& run, size_t i) {
  BoundedQueue<Outgoing>& queue = *run.queues[i];
  size_t sent = 0;
  const auto agent_start = Clock::now();
  auto next = [&](Outgoing* outgoing) {
    std::optional<Outgoing> item = queue.Pop();
    if (!item) return false;
    if (run.options.rate > 0) {
      std::this_thread::sleep_until(
          agent_start + std::chrono::duration_cast<Clock::duration>(
                            std::chrono::duration<double>(double(sent) / run.options.rate)));
    }
    ++sent;
    *outgoing = std::move(*item);
    // A recording's frames carry their capture times; the others are captured now.
    if (outgoing->observation.timestamp_ns() == 0) {
      outgoing->observation.set_timestamp_ns(UnixNowNs());
    }
    MutexLock lock(run.mutex);
    run.records[outgoing->tag].sent = true;
    return true;
  };
  auto answered = [&](const Answered& answer) { RecordAnswer(run, answer); };
  const grpc::Status status = IngestStream::Run(run.connection, run.header, run.options.window,
                                                next, answered, [&] { queue.Abort(); });
  queue.Abort();  // whatever is left will not be sent
  if (!status.ok()) {
    MutexLock lock(run.mutex);
    run.stream_errors.emplace_back(run.agent_ids[i], status);
    ++run.errors_by_code[wire::GrpcCodeName(int(status.error_code()))];
  }
}

// The next frame for the agents: its name, its index in the input and its observation (the image
// and what the source knows of it: depth, capture time, camera, pose). Returns false at the end
// (with *error when the input broke off); true with *error when this frame cannot be read.
using NextFrameFn = std::function<bool(std::string* name, size_t* index,
                                       v1::Observation* observation, std::string* error)>;

// Frames from folders, lists and videos, with their --depth images.
NextFrameFn FilesFrames(FrameSource& source, const DepthPlan& depth_plan,
                        const IngestOptions& options) {
  return [&source, &depth_plan, &options](std::string* name, size_t* index,
                                          v1::Observation* observation, std::string* error) {
    Frame frame;
    if (!source.Next(&frame, error)) return false;
    *name = frame.name;
    *index = frame.index;
    if (!error->empty()) return true;
    if (depth_plan.enabled) {
      v1::DepthImage* depth = observation->mutable_depth();
      if (frame.index >= depth_plan.paths.size()) {
        *error = "no depth image for frame " + frame.name;
        return true;
      }
      if (!ReadDepthImage(depth_plan.paths[frame.index], depth, error)) return true;
      depth->set_scale(options.depth_scale);
      if (!options.intrinsics.empty()) *depth->mutable_intrinsics() = depth_plan.intrinsics;
    }
    observation->mutable_encoded_image()->set_data(std::move(frame.bytes));
    return true;
  };
}

NextFrameFn RecordingFrames(Recording& recording) {
  return [&recording](std::string* name, size_t* index, v1::Observation* observation,
                      std::string* error) {
    RecordedFrame frame;
    const bool more = recording.Next(&frame, error);
    if (!more) {
      *name = recording.description();
      return false;
    }
    *name = frame.name;
    *index = frame.index;
    *observation = std::move(frame.observation);
    return true;
  };
}

// The producer: reads frames in order and deals them to the agents round-robin. Returns the
// frames that could not be read (or had no depth image), and a recording that broke off.
size_t DealFrames(IngestRun& run, const NextFrameFn& next) {
  const IngestOptions& options = run.options;
  size_t local_errors = 0;
  auto skip = [&](FrameRecord record, const std::string& error) {
    record.local_error = error;
    ++local_errors;
    run.progress.Message("warning: " + error + " (skipped)");
    MutexLock lock(run.mutex);
    run.records.push_back(std::move(record));
  };
  std::string error;
  size_t dealt = 0;
  for (;;) {
    FrameRecord record;
    size_t index = 0;
    Outgoing outgoing;
    if (!next(&record.name, &index, &outgoing.observation, &error)) {
      if (!error.empty()) skip(std::move(record), error);
      break;
    }
    if (!error.empty()) {
      skip(std::move(record), error);
      continue;
    }
    const size_t agent = dealt++ % run.agent_ids.size();
    outgoing.observation.set_agent_id(run.agent_ids[agent]);
    outgoing.observation.set_sequence(options.sequence_start + index);
    record.agent = run.agent_ids[agent];
    record.sequence = options.sequence_start + index;
    {
      MutexLock lock(run.mutex);
      outgoing.tag = run.records.size();
      run.records.push_back(std::move(record));
    }
    run.queues[agent]->Push(std::move(outgoing));  // fails only when that agent's stream ended
  }
  for (auto& queue : run.queues) queue->Finish();
  return local_errors;
}

// Frames at the end of the run; marks those left unanswered by a stream that ended.
struct IngestTotals {
  size_t sent = 0, answered = 0, unanswered = 0, local_errors = 0;
  double elapsed = 0;  // seconds
  double rate = 0;     // answered frames/s
  bool failed = false;
};

IngestTotals Totals(IngestRun& run, size_t local_errors, double elapsed) {
  MutexLock lock(run.mutex);
  IngestTotals totals;
  for (FrameRecord& record : run.records) {
    totals.sent += record.sent;
    totals.answered += record.answered;
    if (record.local_error.empty() && !record.answered) {
      ++totals.unanswered;
      record.local_error =
          record.sent ? "no response: the stream ended" : "not sent: the stream ended";
    }
  }
  totals.local_errors = local_errors;
  totals.elapsed = elapsed;
  totals.rate = elapsed > 0 ? double(totals.answered) / elapsed : 0;
  totals.failed = !run.stream_errors.empty() || run.frame_errors > 0 || local_errors > 0 ||
                  totals.unanswered > 0;
  return totals;
}

nlohmann::json FrameJson(const FrameRecord& record, bool matches) {
  const v1::IngestResponse& response = record.response;
  nlohmann::json r = {{"name", record.name},
                      {"agent", record.agent},
                      {"sequence", record.sequence},
                      {"stored", response.stored()},
                      {"latency_ms", record.latency_ms}};
  if (response.stored()) r["place_id"] = response.place_id();
  if (response.has_loop_closure()) {
    r["loop_closure"] = LoopClosureJson(response.loop_closure());
    if (response.loop_closure().merged()) r["merged_into"] = response.loop_closure().place_id();
  }
  if (response.has_depth()) r["depth"] = DepthStateJson(response.depth());
  if (!response.rejection().empty()) r["rejection"] = response.rejection();
  if (response.has_error()) {
    r["error"] = {{"code", wire::GrpcCodeName(response.error().code())},
                  {"message", response.error().message()}};
  } else if (!record.local_error.empty()) {
    r["error"] = {{"code", "LOCAL"}, {"message", record.local_error}};
  }
  if (record.answered && !response.has_error()) {
    r["counts"] = {{"total", response.counts().total()},
                   {"dynamic", response.counts().dynamic()},
                   {"depth_removed", response.counts().depth_removed()},
                   {"kept", response.counts().kept()}};
  }
  if (matches) {
    nlohmann::json list = nlohmann::json::array();
    for (const v1::Match& match : response.matches()) list.push_back(MatchJson(match));
    r["matches"] = list;
  }
  return r;
}

nlohmann::json SummaryJson(const IngestRun& run, const IngestTotals& totals, bool with_depth) {
  MutexLock lock(run.mutex);
  nlohmann::json out;
  out["map"] = run.options.map;
  out["agents"] = run.agent_ids;
  out["frames"] = run.records.size();
  out["sent"] = totals.sent;
  out["answered"] = totals.answered;
  out["stored"] = run.stored;
  out["loop_closure"] = run.options.loop_closure;
  out["merged"] = run.merged;
  out["loops_found"] = run.loops_found;
  if (with_depth) {
    out["depth"] = {{"frames_removing", run.depth_frames_removing},
                    {"descriptors_removed", run.depth_removed}};
  }
  out["rejected"] = {{"total", run.rejected}, {"by_reason", run.rejected_by_reason}};
  out["errors"] = {{"frames", run.frame_errors}, {"by_code", run.errors_by_code}};
  out["local_errors"] = totals.local_errors;
  out["unanswered"] = totals.unanswered;
  out["stream_errors"] = StreamErrorsJson(run.stream_errors);
  out["elapsed_s"] = totals.elapsed;
  out["frames_per_s"] = totals.rate;
  out["latency_ms"] = ToJson(Summarize(run.latencies));
  nlohmann::json results = nlohmann::json::array();
  for (const FrameRecord& record : run.records) {
    results.push_back(FrameJson(record, run.options.matches));
  }
  out["results"] = std::move(results);
  return out;
}

// "a: 2, b: 1".
std::string CountList(const std::map<std::string, size_t>& counts) {
  std::string list;
  for (const auto& [key, count] : counts) {
    list += (list.empty() ? "" : ", ") + key + ": " + std::to_string(count);
  }
  return list;
}

void PrintSummary(const IngestRun& run, const IngestTotals& totals, bool with_depth) {
  MutexLock lock(run.mutex);
  const IngestOptions& options = run.options;
  std::ostream& out = run.out;
  const size_t agents = run.agent_ids.size();
  // Sent and answered, not "ingested": the lines below say how many were stored.
  out << "sent " << totals.sent << " of " << run.records.size() << " frames to '" << options.map
      << "' with " << agents << (agents == 1 ? " agent" : " agents") << " in "
      << FormatDuration(totals.elapsed) << " (" << FormatDouble(totals.rate, 1) << " frames/s), "
      << totals.answered << " answered\n";
  out << "  stored     " << run.stored << '\n';
  if (options.loop_closure) out << "  merged     " << run.merged << "  (rehearsal)\n";
  out << "  rejected   " << run.rejected;
  if (!run.rejected_by_reason.empty()) out << "  (" << CountList(run.rejected_by_reason) << ")";
  out << '\n';
  size_t error_total = run.frame_errors + run.stream_errors.size();
  out << "  errors     " << error_total;
  if (!run.errors_by_code.empty()) out << "  (" << CountList(run.errors_by_code) << ")";
  out << '\n';
  if (totals.local_errors > 0) out << "  unreadable " << totals.local_errors << '\n';
  if (totals.unanswered > 0) out << "  unanswered " << totals.unanswered << '\n';
  if (with_depth) {
    out << "  depth      " << run.depth_removed << " descriptors removed by Algorithm 1 in "
        << run.depth_frames_removing << (run.depth_frames_removing == 1 ? " frame" : " frames")
        << '\n';
  }
  const LatencySummary latency = Summarize(run.latencies);
  if (latency.count > 0) {
    out << "  latency    p50 " << FormatDouble(latency.p50, 1) << " ms, p99 "
        << FormatDouble(latency.p99, 1) << " ms, max " << FormatDouble(latency.max, 1)
        << " ms (write to response)\n";
  }
  if (options.loop_closure) {
    out << "loop closure: " << run.records.size() << " frames, " << run.stored << " stored, "
        << run.merged << " merged, " << run.loops_found
        << (run.loops_found == 1 ? " loop" : " loops") << " found\n";
  }
}

}  // namespace

CLI::App* RegisterIngest(CLI::App& app, IngestOptions* options) {
  CLI::App* ingest = app.add_subcommand("ingest", "stream frames into a map");
  ingest->add_option("MAP", options->map, "map name")->required();
  ingest
      ->add_option("SOURCE", options->sources,
                   "image folders, image lists (.txt), videos or images; or one recording: a ROS "
                   "1 bag (.bag) or a TUM RGB-D folder (rgb.txt)")
      ->required();
  ingest
      ->add_option("--agents", options->agents,
                   "agents (Ingest streams) sharing the frames round-robin")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  ingest
      ->add_option("--agent-id", options->agent_id, "agent id (with several agents: ID-1 ... ID-N)")
      ->capture_default_str();
  ingest->add_option("--video-every", options->video_every, "every K-th video frame")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  ingest->add_option("--glob", options->glob,
                     "only folder entries whose name matches (e.g. '*.jpg')");
  ingest->add_flag("--matches", options->matches,
                   "ask for each frame's matches against the map before it");
  ingest->add_option("--top-k", options->top_k, "matches per frame with --matches")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  ingest->add_option("--rate", options->rate, "frames/s per agent (0 = as fast as accepted)")
      ->check(CLI::Range(0.0, 10000.0))
      ->capture_default_str();
  ingest
      ->add_option("--sequence-start", options->sequence_start,
                   "Observation.sequence of the first frame")
      ->capture_default_str();
  ingest->add_option("--window", options->window, "unanswered frames per stream")
      ->check(CLI::Range(1, 1024))
      ->capture_default_str();
  ingest->add_option("--depth", options->depth_dir,
                     "depth images, paired with the frames by file stem (12.jpg -> DIR/12.png, "
                     ".pgm, .tif): 16-bit (millimetres by default) or float32 metres");
  ingest
      ->add_option(
          "--depth-scale", options->depth_scale,
          "metres per depth unit (default: the map's, 0.001 for 16-bit; TUM folders: 1/5000)")
      ->check(CLI::Range(1e-6, 100.0));
  ingest->add_option("--intrinsics", options->intrinsics,
                     "colour camera intrinsics fx,fy,cx,cy in pixels (sent with the depth)");
  ingest->add_option("--camera", options->camera,
                     "the camera fx,fy,cx,cy in pixels (pinhole, the frames' size), kept with "
                     "every place: verified matches then carry their relative pose");
  ingest->add_flag("--loop-closure", options->loop_closure,
                   "Bayesian loop closure per agent: prints each frame's loop or merge");
  ingest->add_option("--topic", options->topic,
                     "ROS 1 bag: the colour topic (sensor_msgs/Image or CompressedImage); header "
                     "stamps become the capture times");
  ingest->add_option("--depth-topic", options->depth_topic,
                     "ROS 1 bag: registered depth, 16UC1 / mono16 (mm) or 32FC1 (m) images");
  ingest->add_option("--camera-info-topic", options->camera_info_topic,
                     "ROS 1 bag: sensor_msgs/CameraInfo, the frames' camera and depth intrinsics");
  ingest
      ->add_option("--max-offset", options->max_offset,
                   "recordings: seconds between a frame and the depth image (TUM: also the pose "
                   "sample) paired with it")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  ingest
      ->add_option("--max-pose-gap", options->max_pose_gap,
                   "TUM folders: ground-truth samples at most this many seconds apart are "
                   "interpolated")
      ->check(CLI::Range(0.0, 60.0))
      ->capture_default_str();
  return ingest;
}

namespace {

// A recording as the one SOURCE; null with *error empty when the sources are not a recording.
std::unique_ptr<Recording> OpenRecording(const IngestOptions& options, std::string* error) {
  const bool any = std::any_of(options.sources.begin(), options.sources.end(),
                               [](const std::string& s) { return Recording::IsRecording(s); });
  if (!any) {
    if (!options.topic.empty() || !options.depth_topic.empty() ||
        !options.camera_info_topic.empty()) {
      *error =
          "--topic, --depth-topic and --camera-info-topic read a ROS 1 bag: give the .bag "
          "file as the SOURCE";
    }
    return nullptr;
  }
  if (options.sources.size() != 1) {
    *error = "a recording (a ROS bag or a TUM RGB-D folder) is the only SOURCE of an ingest";
    return nullptr;
  }
  if (!options.depth_dir.empty()) {
    *error =
        "--depth pairs image files by name; a recording brings its own depth "
        "(--depth-topic, or a TUM folder's depth.txt)";
    return nullptr;
  }
  if (!options.glob.empty()) {
    *error = "--glob filters a folder's images; it does not apply to a recording";
    return nullptr;
  }
  RecordingOptions recording;
  recording.topic = options.topic;
  recording.depth_topic = options.depth_topic;
  recording.camera_info_topic = options.camera_info_topic;
  recording.max_offset_s = options.max_offset;
  recording.max_pose_gap_s = options.max_pose_gap;
  recording.depth_scale = options.depth_scale;
  if (!options.intrinsics.empty()) {
    v1::Intrinsics intrinsics;
    if (!ParseIntrinsics(options.intrinsics, &intrinsics, error)) return nullptr;
    recording.intrinsics = intrinsics;
  }
  return Recording::Open(options.sources.front(), recording, error);
}

// What the recording gave the frames: capture times, depth, cameras and poses.
nlohmann::json RecordingJson(const Recording& recording) {
  const RecordingStats& stats = recording.stats();
  nlohmann::json out = {{"source", recording.description()},
                        {"frames", stats.frames},
                        {"first_timestamp_ns", stats.first_ns.value_or(0)},
                        {"last_timestamp_ns", stats.last_ns.value_or(0)},
                        {"depth_paired", stats.depth_paired},
                        {"depth_missing", stats.depth_missing},
                        {"cameras", stats.cameras},
                        {"poses", stats.poses},
                        {"poses_missing", stats.poses_missing},
                        {"receive_time_stamps", stats.receive_time_stamps}};
  if (stats.camera_refused > 0) {
    out["camera_refused"] = {{"frames", stats.camera_refused},
                             {"distortion_model", stats.refused_model}};
  }
  return out;
}

void PrintRecording(std::ostream& out, const Recording& recording, double max_offset) {
  const RecordingStats& stats = recording.stats();
  out << "  captured   " << FormatUnixNs(stats.first_ns.value_or(0)) << " .. "
      << FormatUnixNs(stats.last_ns.value_or(0)) << "  (" << recording.description() << ")\n";
  if (stats.depth_paired > 0 || stats.depth_missing > 0) {
    out << "  paired     " << stats.depth_paired << " with depth, " << stats.depth_missing
        << " without (none within " << FormatDouble(max_offset, 3) << " s)\n";
  }
  if (stats.cameras > 0 || stats.camera_refused > 0) {
    out << "  camera     " << stats.cameras << " frames from the camera info";
    if (stats.camera_refused > 0) {
      out << ", " << stats.camera_refused << " without (distortion model '" << stats.refused_model
          << "' is not taken)";
    }
    out << '\n';
  }
  if (stats.poses > 0 || stats.poses_missing > 0) {
    out << "  poses      " << stats.poses << ", " << stats.poses_missing
        << " outside the ground truth\n";
  }
  if (stats.receive_time_stamps > 0) {
    out << "  stamps     " << stats.receive_time_stamps
        << " header stamps of 0: the bag's receive times instead\n";
  }
}

}  // namespace

int RunIngest(const Connection& connection, const IngestOptions& options, bool json, CliIo& io) {
  std::string error;
  std::unique_ptr<Recording> recording = OpenRecording(options, &error);
  if (!error.empty()) return UsageError(io, error);
  std::unique_ptr<FrameSource> source;
  DepthPlan depth;
  if (!recording) {
    source = FrameSource::Open(options.sources, options.video_every, options.glob, &error);
    if (!source) return UsageError(io, error);
    if (!PlanDepth(options, *source, &depth, &error)) return UsageError(io, error);
  }
  v1::Camera camera;
  if (!options.camera.empty() && !ParseCamera(options.camera, &camera, &error)) {
    return UsageError(io, error);
  }
  if (const int code = CheckMap(connection, options.map, io); code != kExitOk) return code;

  const std::optional<size_t> total =
      recording ? std::optional<size_t>(recording->expected_frames()) : source->total();
  IngestRun run(connection, options, json, io, total);
  if (!options.camera.empty()) *run.header.mutable_camera() = camera;
  const auto start = Clock::now();
  std::vector<std::thread> threads;
  for (size_t i = 0; i < run.agent_ids.size(); ++i) {
    threads.emplace_back([&run, i] { RunAgent(run, i); });
  }
  const size_t local_errors = DealFrames(
      run, recording ? RecordingFrames(*recording) : FilesFrames(*source, depth, options));
  for (std::thread& thread : threads) thread.join();
  run.progress.Stop();
  const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();

  const IngestTotals totals = Totals(run, local_errors, elapsed);
  {
    MutexLock lock(run.mutex);
    for (const auto& [agent, status] : run.stream_errors) {
      io.err << "error: agent " << agent << ": " << Describe(status) << '\n';
    }
  }
  const bool with_depth = depth.enabled || (recording && recording->stats().depth_paired > 0);
  if (json) {
    nlohmann::json summary = SummaryJson(run, totals, with_depth);
    if (recording) summary["recording"] = RecordingJson(*recording);
    io.out << summary.dump(2) << '\n';
  } else {
    PrintSummary(run, totals, with_depth);
    if (recording) PrintRecording(io.out, *recording, options.max_offset);
  }
  return totals.failed ? kExitRpcError : kExitOk;
}

}  // namespace placedb::client
