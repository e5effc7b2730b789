#include "client/ingest.h"

#include <chrono>
#include <filesystem>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <thread>

#include "client/format.h"
#include "client/frame_source.h"
#include "client/ingest_stream.h"
#include "client/progress.h"
#include "client/queue.h"
#include "core/base/thread_annotations.h"

namespace placedb::client {

namespace {

int64_t UnixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

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

}  // namespace

int RunIngest(const Connection& connection, const IngestOptions& options, bool json, CliIo& io) {
  std::string error;
  std::unique_ptr<FrameSource> source =
      FrameSource::Open(options.sources, options.video_every, options.glob, &error);
  if (!source) {
    io.err << "error: " << error << '\n';
    return kExitUsage;
  }
  auto usage = [&](const std::string& message) {
    io.err << "error: " << message << '\n';
    return kExitUsage;
  };
  // Depth: every image frame needs its depth image (paired by file stem) before anything is sent.
  const bool with_depth = !options.depth_dir.empty();
  std::vector<std::string> depth_paths;  // by frame index (no videos with --depth)
  v1::Intrinsics intrinsics;
  if (!with_depth && (options.depth_scale != 0 || !options.intrinsics.empty())) {
    return usage("--depth-scale and --intrinsics describe depth images: they need --depth DIR");
  }
  if (with_depth) {
    std::error_code ec;
    if (!std::filesystem::is_directory(options.depth_dir, ec)) {
      return usage("--depth: " + options.depth_dir + " is not a folder");
    }
    const std::vector<std::string> videos = source->video_paths();
    if (!videos.empty()) {
      return usage("--depth pairs depth images with image files by name; " + videos.front() +
                   " is a video");
    }
    for (const std::string& path : source->image_paths()) {
      depth_paths.push_back(FindDepthImage(options.depth_dir, path, &error));
      if (depth_paths.back().empty()) return usage(error);
    }
    if (!options.intrinsics.empty() && !ParseIntrinsics(options.intrinsics, &intrinsics, &error)) {
      return usage(error);
    }
  }
  {
    // An unknown map fails here, once, rather than once per stream.
    auto context = connection.NewContext();
    v1::GetMapRequest request;
    request.set_name(options.map);
    v1::MapDescription map;
    const grpc::Status status = connection.stub()->GetMap(context.get(), request, &map);
    if (!status.ok()) {
      io.err << "error: " << Describe(status) << '\n';
      return kExitRpcError;
    }
  }
  const size_t agents = size_t(std::max(1, options.agents));
  std::vector<std::string> agent_ids;
  for (size_t i = 0; i < agents; ++i) {
    agent_ids.push_back(agents == 1 ? options.agent_id
                                    : options.agent_id + "-" + std::to_string(i + 1));
  }

  // Everything below, and io.out. Locals cannot be GUARDED_BY (only members can).
  Mutex mutex;
  std::vector<FrameRecord> records;
  records.reserve(source->total().value_or(0));
  std::vector<double> latencies;
  size_t stored = 0, rejected = 0, frame_errors = 0;
  size_t merged = 0, loops_found = 0;                   // --loop-closure
  size_t depth_frames_removing = 0, depth_removed = 0;  // --depth
  std::map<std::string, size_t> rejected_by_reason, errors_by_code;
  std::vector<std::pair<std::string, grpc::Status>> stream_errors;

  Progress progress(io.err, io.err_is_tty, source->total());
  std::vector<std::unique_ptr<BoundedQueue<Outgoing>>> queues;
  for (size_t i = 0; i < agents; ++i) {
    queues.push_back(std::make_unique<BoundedQueue<Outgoing>>(options.window * 2));
  }

  const auto start = Clock::now();
  v1::IngestHeader header;
  header.set_map(options.map);
  if (options.matches) header.mutable_matches()->set_top_k(uint32_t(std::max(1, options.top_k)));
  header.set_loop_closure(options.loop_closure);

  std::vector<std::thread> threads;
  for (size_t i = 0; i < agents; ++i) {
    threads.emplace_back([&, i] {
      size_t sent = 0;
      const auto agent_start = Clock::now();
      auto next = [&](Outgoing* outgoing) {
        std::optional<Outgoing> item = queues[i]->Pop();
        if (!item) return false;
        if (options.rate > 0) {
          std::this_thread::sleep_until(
              agent_start + std::chrono::duration_cast<Clock::duration>(
                                std::chrono::duration<double>(double(sent) / options.rate)));
        }
        ++sent;
        *outgoing = std::move(*item);
        outgoing->observation.set_timestamp_ns(UnixNowNs());
        MutexLock lock(mutex);
        records[outgoing->tag].sent = true;
        return true;
      };
      auto answered = [&](const Answered& answer) {
        MutexLock lock(mutex);
        FrameRecord& record = records[answer.tag];
        record.answered = true;
        record.latency_ms = answer.latency_ms;
        record.response = answer.response;
        record.response.clear_boxes_used();
        latencies.push_back(answer.latency_ms);
        const v1::IngestResponse& response = answer.response;
        // A frame rehearsal merged into an existing place is neither stored nor rejected.
        const bool was_merged = response.has_loop_closure() && response.loop_closure().merged();
        if (response.has_error()) {
          ++frame_errors;
          ++errors_by_code[CodeName(response.error().code())];
          progress.Message("frame " + record.name + ": " + CodeName(response.error().code()) +
                           ": " + response.error().message());
        } else if (was_merged) {
          ++merged;
        } else if (response.stored()) {
          ++stored;
        } else {
          ++rejected;
          ++rejected_by_reason[ReasonKey(response.rejection())];
        }
        if (!response.has_error() && response.has_loop_closure() &&
            response.loop_closure().loop_found()) {
          ++loops_found;
        }
        if (response.counts().depth_removed() > 0) {
          ++depth_frames_removing;
          depth_removed += response.counts().depth_removed();
        }
        const std::string removal = FormatDepthRemoval(response.counts(), response.depth());
        if (!json && (options.matches || options.loop_closure || !removal.empty())) {
          io.out << record.name << " -> ";
          if (response.has_error()) {
            io.out << "error: " << CodeName(response.error().code());
          } else if (was_merged) {
            io.out << FormatLoopClosure(response.loop_closure());
          } else if (response.stored()) {
            io.out << "place " << response.place_id();
          } else {
            io.out << "not stored";
            if (!response.rejection().empty()) {
              io.out << " (" << ReasonKey(response.rejection()) << ")";
            }
          }
          if (options.matches && !response.has_error()) {
            if (response.matches_size() > 0) {
              const v1::Match& best = response.matches(0);
              io.out << "; best match place " << best.place_id() << " score "
                     << FormatDouble(best.score(), 4) << " (" << best.metadata().agent_id() << " #"
                     << best.metadata().sequence() << ")" << (best.verified() ? " verified" : "");
            } else {
              io.out << "; no match";
            }
          }
          if (response.has_loop_closure() && !was_merged) {
            io.out << "; " << FormatLoopClosure(response.loop_closure());
          }
          if (!removal.empty()) io.out << "; " << removal;
          io.out << '\n';
        }
        progress.Add();
      };
      const grpc::Status status = IngestStream::Run(connection, header, options.window, next,
                                                    answered, [&] { queues[i]->Abort(); });
      queues[i]->Abort();  // whatever is left will not be sent
      if (!status.ok()) {
        MutexLock lock(mutex);
        stream_errors.emplace_back(agent_ids[i], status);
        ++errors_by_code[CodeName(int(status.error_code()))];
      }
    });
  }

  // The producer: reads frames in order and deals them to the agents round-robin.
  size_t local_errors = 0;
  {
    Frame frame;
    size_t dealt = 0;
    while (source->Next(&frame, &error)) {
      FrameRecord record;
      record.name = frame.name;
      if (!error.empty()) {
        record.local_error = error;
        ++local_errors;
        progress.Message("warning: " + error + " (skipped)");
        MutexLock lock(mutex);
        records.push_back(std::move(record));
        continue;
      }
      Outgoing outgoing;
      if (with_depth) {
        v1::DepthImage* depth = outgoing.observation.mutable_depth();
        if (frame.index >= depth_paths.size() ||
            !ReadDepthImage(depth_paths[frame.index], depth, &error)) {
          if (frame.index >= depth_paths.size()) error = "no depth image for frame " + frame.name;
          record.local_error = error;
          ++local_errors;
          progress.Message("warning: " + error + " (skipped)");
          MutexLock lock(mutex);
          records.push_back(std::move(record));
          continue;
        }
        depth->set_scale(options.depth_scale);
        if (!options.intrinsics.empty()) *depth->mutable_intrinsics() = intrinsics;
      }
      const size_t agent = dealt++ % agents;
      outgoing.observation.set_agent_id(agent_ids[agent]);
      outgoing.observation.set_sequence(options.sequence_start + frame.index);
      outgoing.observation.mutable_encoded_image()->set_data(std::move(frame.bytes));
      record.agent = agent_ids[agent];
      record.sequence = options.sequence_start + frame.index;
      {
        MutexLock lock(mutex);
        outgoing.tag = records.size();
        records.push_back(std::move(record));
      }
      queues[agent]->Push(std::move(outgoing));  // fails only when that agent's stream ended
    }
    for (auto& queue : queues) queue->Finish();
  }
  for (std::thread& thread : threads) thread.join();
  progress.Stop();
  const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();

  size_t sent = 0, answered = 0, unanswered = 0;
  for (FrameRecord& record : records) {
    sent += record.sent;
    answered += record.answered;
    if (record.local_error.empty() && !record.answered) {
      ++unanswered;
      record.local_error =
          record.sent ? "no response: the stream ended" : "not sent: the stream ended";
    }
  }
  const LatencySummary latency = Summarize(latencies);
  const double rate = elapsed > 0 ? double(answered) / elapsed : 0;
  const bool failed =
      !stream_errors.empty() || frame_errors > 0 || local_errors > 0 || unanswered > 0;

  for (const auto& [agent, status] : stream_errors) {
    io.err << "error: agent " << agent << ": " << Describe(status) << '\n';
  }
  if (json) {
    nlohmann::json out;
    out["map"] = options.map;
    out["agents"] = agent_ids;
    out["frames"] = records.size();
    out["sent"] = sent;
    out["answered"] = answered;
    out["stored"] = stored;
    out["loop_closure"] = options.loop_closure;
    out["merged"] = merged;
    out["loops_found"] = loops_found;
    if (with_depth) {
      out["depth"] = {{"frames_removing", depth_frames_removing},
                      {"descriptors_removed", depth_removed}};
    }
    out["rejected"] = {{"total", rejected}, {"by_reason", rejected_by_reason}};
    out["errors"] = {{"frames", frame_errors}, {"by_code", errors_by_code}};
    out["local_errors"] = local_errors;
    out["unanswered"] = unanswered;
    nlohmann::json streams = nlohmann::json::array();
    for (const auto& [agent, status] : stream_errors) {
      streams.push_back({{"agent", agent},
                         {"code", CodeName(int(status.error_code()))},
                         {"message", status.error_message()}});
    }
    out["stream_errors"] = streams;
    out["elapsed_s"] = elapsed;
    out["frames_per_s"] = rate;
    out["latency_ms"] = ToJson(latency);
    nlohmann::json results = nlohmann::json::array();
    for (const FrameRecord& record : records) {
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
        r["error"] = {{"code", CodeName(response.error().code())},
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
      if (options.matches) {
        nlohmann::json matches = nlohmann::json::array();
        for (const v1::Match& match : response.matches()) matches.push_back(MatchJson(match));
        r["matches"] = matches;
      }
      results.push_back(std::move(r));
    }
    out["results"] = std::move(results);
    io.out << out.dump(2) << '\n';
    return failed ? kExitRpcError : kExitOk;
  }

  io.out << "ingested " << answered << " of " << records.size() << " frames into '" << options.map
         << "' with " << agents << (agents == 1 ? " agent" : " agents") << " in "
         << FormatDuration(elapsed) << " (" << FormatDouble(rate, 1) << " frames/s)\n";
  io.out << "  stored     " << stored << '\n';
  if (options.loop_closure) io.out << "  merged     " << merged << "  (rehearsal)\n";
  io.out << "  rejected   " << rejected;
  if (!rejected_by_reason.empty()) {
    std::string list;
    for (const auto& [reason, count] : rejected_by_reason) {
      list += (list.empty() ? "" : ", ") + reason + ": " + std::to_string(count);
    }
    io.out << "  (" << list << ")";
  }
  io.out << '\n';
  size_t error_total = frame_errors + stream_errors.size();
  io.out << "  errors     " << error_total;
  if (!errors_by_code.empty()) {
    std::string list;
    for (const auto& [code, count] : errors_by_code) {
      list += (list.empty() ? "" : ", ") + code + ": " + std::to_string(count);
    }
    io.out << "  (" << list << ")";
  }
  io.out << '\n';
  if (local_errors > 0) io.out << "  unreadable " << local_errors << '\n';
  if (unanswered > 0) io.out << "  unanswered " << unanswered << '\n';
  if (with_depth) {
    io.out << "  depth      " << depth_removed << " descriptors removed by Algorithm 1 in "
           << depth_frames_removing << (depth_frames_removing == 1 ? " frame" : " frames") << '\n';
  }
  if (latency.count > 0) {
    io.out << "  latency    p50 " << FormatDouble(latency.p50, 1) << " ms, p99 "
           << FormatDouble(latency.p99, 1) << " ms, max " << FormatDouble(latency.max, 1)
           << " ms (write to response)\n";
  }
  if (options.loop_closure) {
    io.out << "loop closure: " << records.size() << " frames, " << stored << " stored, " << merged
           << " merged, " << loops_found << (loops_found == 1 ? " loop" : " loops") << " found\n";
  }
  return failed ? kExitRpcError : kExitOk;
}

}  // namespace placedb::client
