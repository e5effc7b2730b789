// Ingest: one stream per call, its frames prepared on the pool (Prepare, query.cc) and completed
// in stream order (Complete: the agent's stream state, then search and store through the
// stream's IngestSession); each answer assembled once (Settle) on the delivery thread.
#include <algorithm>
#include <set>

#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/convert_result.h"
#include "proto/status.h"
#include "server/ingest/ingest_pipeline.h"
#include "server/rpc/call_support.h"
#include "server/rpc/frame_memory.h"

namespace placedb::server {

using wire::GrpcCodeLabel;
using wire::GrpcCodeName;
using wire::HidePaths;
using wire::LoopClosureToProto;
using wire::TimingsToProto;
using wire::ToGrpc;

// One open Ingest call: the handler thread reads, the pipeline does the rest.
struct PlaceDbService::Stream {
  grpc::ServerContext* context = nullptr;
  Watch* watch = nullptr;
  std::shared_ptr<const MapEntry> map;
  std::optional<v1::MatchOptions> header_matches;
  std::optional<v1::Camera> camera;    // IngestHeader.camera: for observations without their own
  bool loop_closure = false;           // IngestHeader.loop_closure
  IngestPipeline* pipeline = nullptr;  // set before the stream is listed in streams_
  grpc::Status refusal;                // why the pool refused the last frame (handler thread)
  // Search and store through the backend (Complete() only: stream order, one frame at a time).
  std::unique_ptr<IngestSession> session;
  std::optional<StreamExpiry> expiry_check;  // set with `context`
  bool expiry() const { return (*expiry_check)(); }

  // For the close log line, read after the pipeline is closed. `frames` and `agents`: the handler
  // thread; the outcomes: Settle(), on the pipeline's delivery thread, one frame at a time.
  uint64_t frames = 0, stored = 0, merged = 0, rejected = 0, errors = 0;
  std::vector<std::string> agents;  // first few distinct agent ids
};

// One observation of a stream, from its arrival to its response.
struct PlaceDbService::Slot final : IngestPipeline::Frame {
  // Made when the observation has been read; destroyed once answered (or dropped): while it
  // exists, its stream is never idle.
  Slot(PlaceDbService* service, Stream* stream) : service(service), stream(stream) {
    stream->watch->FrameRead();
  }
  ~Slot() override {
    service->Settle(stream, this);  // a skipped frame's place is still waited for and counted
    stream->watch->FrameDone();
  }
  Slot(const Slot&) = delete;
  Slot& operator=(const Slot&) = delete;

  void Prepare() override {
    queue_ms = MsSince(arrived);
    work.expiry = &*stream->expiry_check;
    status = Guarded("processing the observation", [&] {
      return service->Prepare(stream->context, *stream->map, request->observation(), "observation",
                              FrameRole::kStream, &work);
    });
    request.reset();  // the decoded frame is all that is needed now
    memory.TryResize(std::min(memory.bytes(), kPreparedFrameBytes));  // shrinking never fails
  }
  void Refused(IngestPipeline::Admission why) override {
    status = why == IngestPipeline::Admission::kPoolStopped
                 ? service->Unavailable()
                 : Cancelled(stream->context, "while waiting for a worker");
    request.reset();
    stream->refusal = status;
  }
  void Complete() override { service->Complete(stream, this); }

  PlaceDbService* const service;
  Stream* const stream;
  uint64_t index = 0;
  uint64_t sequence = 0;
  std::string agent_id;  // the observation's, for the agent's activity
  Clock::time_point arrived;
  double queue_ms = 0;
  std::unique_ptr<v1::IngestRequest> request;  // freed once decoded
  grpc::Status status;                         // the outcome so far
  std::optional<v1::MatchOptions> matches;
  Work work;                    // freed once settled
  v1::IngestResponse response;  // Complete()'s and Settle()'s, for the writer
  // Set by Complete() once the frame was handed to the backend to store; Settle() waits for it.
  std::shared_ptr<PendingCommit> commit;
  std::optional<LoopClosureOutcome> loop;  // loop-closure mode: the detector's outcome
  bool completed = false;                  // Complete() ran (a dropped frame never completes)
  bool settled = false;                    // Settle() ran (delivery thread)
  // The frame's share of the memory budget, from its read until its answer is written (the
  // pipeline destroys the slot after delivering it).
  MemoryBudget::Reservation memory;
};

void PlaceDbService::Complete(Stream* stream, Slot* slot) {
  v1::IngestResponse& response = slot->response;
  response.set_sequence(slot->sequence);
  response.set_index(slot->index);
  if (slot->status.ok() && stream->expiry()) {
    slot->status = Cancelled(stream->context, "before storing");
  }
  if (slot->status.ok()) {
    Work& work = slot->work;
    const MapEntry& map = *stream->map;
    ProcessedFrame& frame = work.frame;
    IngestSession& session = *stream->session;
    const auto deadline = DeadlineOf(stream->context);
    // De-duplication across reconnects (cluster mode): the agent's id and frame number.
    std::string message_id = slot->agent_id + "/" + std::to_string(slot->sequence);
    if (slot->agent_id.empty() && slot->sequence == 0) message_id.clear();  // none: no de-dup
    slot->status = Guarded("searching and storing", [&] {
      // The agent's stream state, in its order: Algorithm 1 on depth, then validity and the
      // BoW vector (a no-op for frames without depth).
      if (Status advanced = map.map->AdvanceStream(&frame, work.metadata.agent_id);
          !advanced.ok()) {
        return ToGrpc(advanced, "observation");
      }
      work.timings.depth_ms = frame.timings.depth_ms;
      work.timings.transform_ms = frame.timings.transform_ms;
      if (slot->matches && frame.valid) {
        const grpc::Status searched = session.Search(frame, work.metadata, *slot->matches, deadline,
                                                     response.mutable_matches(), &work.timings);
        if (!searched.ok()) return searched;
      }
      wire::FrameAnswerToProto(frame, &response);
      metrics_->CountDescriptors(map.name, frame.counts.dynamic, frame.counts.depth_removed,
                                 frame.counts.static_);
      if (stream->loop_closure && frame.valid) {
        AddResult stored;
        auto outcome = session.CloseLoop(frame, work.metadata, message_id, deadline, &stored);
        if (!outcome.ok()) return ToGrpc(outcome.status(), "loop closure");
        work.timings.loop_closure_ms = outcome->update_ms;
        slot->loop = std::move(outcome).value();
        slot->commit = std::make_shared<PendingCommit>();
        slot->commit->Complete(std::move(stored));
      } else {
        // Group commit where the backend has it: the worker goes on; the answer waits for
        // durability (Settle()).
        slot->commit = session.Store(std::move(frame), work.metadata, message_id, deadline);
      }
      return grpc::Status::OK;
    });
    if (!slot->status.ok()) slot->commit.reset();
  }
  slot->completed = true;
  if (!slot->commit) slot->work = Work();  // the frame's data need not wait for the writer
}

void PlaceDbService::Settle(Stream* stream, Slot* slot) {
  if (!slot->completed || slot->settled) return;
  slot->settled = true;
  v1::IngestResponse& response = slot->response;
  const std::string& map_name = stream->map->name;
  if (slot->commit) {
    const Result<AddResult>& added = slot->commit->Wait();
    if (!added.ok()) {
      metrics_->StorageError(map_name, added.status());
      slot->status = ToGrpc(added.status(), "storing");
    } else {
      Work& work = slot->work;
      work.timings.store_ms = added->timings.store_ms;
      const std::optional<LoopClosureOutcome>& loop = slot->loop;
      if (loop) {
        LoopClosureToProto(*loop, response.mutable_loop_closure());
        if (loop->loop) metrics_->LoopClosed(map_name);
        if (loop->loop_rejected) metrics_->LoopRejected(map_name);
      }
      if (loop && loop->merged) {
        // Rehearsal: the frame is the place it was merged into; nothing new is stored.
        response.set_stored(false);
        response.set_place_id(loop->place);
        metrics_->FrameMerged(map_name);
      } else if (added->stored) {
        response.set_stored(true);
        response.set_place_id(added->id);
        metrics_->FrameIngested(map_name);
      } else {
        response.set_stored(false);
        response.set_rejection(added->rejection);
        metrics_->FrameRejected(map_name, "invalid_place");
      }
      work.timings.total_ms = MsSince(slot->arrived);
      TimingsToProto(work.timings, slot->queue_ms, response.mutable_timings());
      ObserveStages(work.timings);
    }
    slot->commit.reset();
  }
  if (!slot->status.ok()) {
    // The frame's answer is its error alone.
    response.clear_counts();
    response.clear_boxes_used();
    response.clear_depth();
    response.clear_matches();
    response.clear_loop_closure();
    response.mutable_error()->set_code(int(slot->status.error_code()));
    response.mutable_error()->set_message(
        HidePaths(slot->status.error_message(), config_.data_dir));
    metrics_->FrameRejected(map_name, GrpcCodeLabel(slot->status.error_code()));
    if (slot->status.error_code() != grpc::StatusCode::CANCELLED &&
        slot->status.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED) {
      spdlog::warn("ingest frame error map={} index={} sequence={} code={} message=\"{}\"",
                   ForLog(map_name), slot->index, slot->sequence,
                   GrpcCodeName(slot->status.error_code()), ForLog(slot->status.error_message()));
    }
  }
  slot->work = Work();  // the response may wait for a slow reader; the frame's data need not
  FrameOutcome outcome = FrameOutcome::kInvalid;
  if (!slot->status.ok()) {
    ++stream->errors;
    outcome = FrameOutcome::kRefused;
  } else if (response.stored()) {
    ++stream->stored;
    outcome = FrameOutcome::kStored;
  } else if (response.loop_closure().merged()) {
    ++stream->merged;
    outcome = FrameOutcome::kMerged;
  } else {
    ++stream->rejected;
  }
  activity_.Record(stream->map->name, slot->agent_id, outcome,
                   slot->status.ok() ? response.place_id() : 0, Clock::now(),
                   std::chrono::duration_cast<std::chrono::milliseconds>(
                       std::chrono::system_clock::now().time_since_epoch())
                       .count());
}

grpc::Status PlaceDbService::IngestStream(grpc::ServerContext* context, IngestStreamIo* io) {
  CallScope scope(this);
  const Clock::time_point opened = Clock::now();
  const Limits& limits = config_.limits;

  // Admission first: a stream holds a handler thread from now on, header or not, so it counts
  // against the limit from now on; over it, the thread is freed at once.
  Watch watch(context, "Ingest");
  const WatchScope listed(this, &watch);
  if (!listed.status().ok()) return Finish("Ingest", context, listed.status());

  // The header names the map. The watchdog cancels the call if it does not come in time.
  v1::IngestRequest first;
  const bool read_header = io->Read(&first);
  if (read_header) watch.HeaderArrived();
  if (!read_header && !io->ReadError().ok()) return Finish("Ingest", context, io->ReadError());
  if (!read_header) {
    if (auto closed = watch.Closed()) return Finish("Ingest", context, *closed);
    return Finish("Ingest", context,
                  Expired(context) ? Cancelled(context, "before the header")
                                   : Invalid("the stream ended before its IngestHeader"));
  }
  if (!first.has_header()) {
    return Finish("Ingest", context,
                  Invalid("header: the first message of an Ingest stream must be an IngestHeader"));
  }
  auto entry = backend_->Map(first.header().map(), "header.map");
  if (!entry.ok()) return Finish("Ingest", context, ToGrpc(entry.status()));
  if (first.header().has_camera()) {
    // Checked once here; each frame checks it again against its own size.
    auto camera = wire::CameraFromProto(first.header().camera(), 0, 0, "header.camera");
    if (!camera.ok()) return Finish("Ingest", context, ToGrpc(camera.status()));
  }

  Stream stream;
  stream.context = context;
  stream.expiry_check.emplace(context);
  stream.watch = &watch;
  stream.map = *entry;
  stream.session = backend_->OpenIngest(stream.map);
  if (first.header().has_matches()) stream.header_matches = first.header().matches();
  stream.loop_closure = first.header().loop_closure();
  if (first.header().has_camera()) stream.camera = first.header().camera();
  // Declared after `stream`, so closed before it: its frames point to the stream. Made under the
  // lock that lists the stream, so a drain never sees a listed stream without its pipeline.
  std::optional<IngestPipeline> admitted;
  {
    MutexLock lock(streams_mutex_);
    if (draining_) return Finish("Ingest", context, Unavailable());
    admitted.emplace(
        pool_, limits.max_inflight_per_stream,
        IngestPipeline::Callbacks{.deliver =
                                      [this, io, &watch](IngestPipeline::Frame& frame) {
                                        auto& slot = static_cast<Slot&>(frame);
                                        Settle(slot.stream, &slot);
                                        // Timed: a client that takes no answers blocks here.
                                        watch.Writing();
                                        const bool written =
                                            io->Write(static_cast<Slot&>(frame).response);
                                        watch.Written();
                                        return written;
                                      },
                                  .expired = [&stream] { return stream.expiry(); },
                                  // Unblocks a handler waiting in Read().
                                  .interrupt = [context] { context->TryCancel(); }},
        // Reads never take the last quarter of the budget: streams waiting for their next
        // message would otherwise hold it all, and the frames read could not grow into it.
        IngestPipeline::Memory{.budget = budget_,
                               .read_bytes = limits.max_message_bytes,
                               .keep_free = (budget_->limit() - budget_->fixed()) / 4});
    stream.pipeline = &*admitted;
    streams_.insert(&stream);
  }
  IngestPipeline& pipeline = *admitted;
  spdlog::info("ingest stream opened peer={} map={} loop_closure={}", Peer(context),
               ForLog(stream.map->name), stream.loop_closure);

  grpc::Status status = grpc::Status::OK;
  uint64_t index = 0;
  while (true) {
    // Backpressure, per stream: no more than max_inflight_per_stream unanswered frames.
    watch.HeldBack();
    const auto room = pipeline.AwaitRoom();
    watch.Released();
    if (room != IngestPipeline::Room::kReady) {
      status = room == IngestPipeline::Room::kDraining ? Unavailable()
                                                       : Cancelled(context, "(stream closed)");
      break;
    }
    auto request = std::make_unique<v1::IngestRequest>();
    if (!io->Read(request.get())) {
      if (!io->ReadError().ok()) {
        status = io->ReadError();  // the frames before it are still answered
      } else if (Expired(context)) {
        status = pipeline.draining() ? Unavailable() : Cancelled(context, "(stream cancelled)");
      }
      break;
    }
    if (!request->has_observation()) {
      status = Invalid("message " + std::to_string(index + 1) +
                       ": after the header, every message must be an observation");
      break;
    }
    auto slot = std::make_unique<Slot>(this, &stream);
    slot->index = index++;
    slot->arrived = Clock::now();
    slot->sequence = request->observation().sequence();
    slot->agent_id = request->observation().agent_id();
    if (request->observation().has_matches()) {
      slot->matches = request->observation().matches();
    } else {
      slot->matches = stream.header_matches;
    }
    if (stream.camera && !request->observation().has_camera()) {
      *request->mutable_observation()->mutable_camera() = *stream.camera;
    }
    std::string agent = request->observation().agent_id();
    // The read's reservation, sized to the frame; a frame that does not fit is answered with
    // RESOURCE_EXHAUSTED and the stream goes on.
    slot->memory = pipeline.TakeReadReservation();
    slot->status =
        ChargeFrame(context, *stream.map, request->observation(), "this frame", &slot->memory);
    const bool charged = slot->status.ok();
    if (charged) {
      slot->request = std::move(request);
    } else {
      request.reset();
      slot->memory.Release();
    }
    // Global backpressure is inside: Submit() waits for room in the pool's queue.
    const IngestPipeline::Admission admission =
        charged ? pipeline.Submit(std::move(slot)) : pipeline.Reject(std::move(slot));
    if (admission == IngestPipeline::Admission::kDraining) {
      status = Unavailable();  // refused unread: the client sees it was never answered
      break;
    }
    ++stream.frames;
    if (stream.agents.size() < 4 &&
        std::find(stream.agents.begin(), stream.agents.end(), agent) == stream.agents.end()) {
      stream.agents.push_back(std::move(agent));
    }
    if (admission != IngestPipeline::Admission::kQueued) {
      status = stream.refusal;  // the frame itself was answered with the same error
      break;
    }
  }

  // Every frame read is completed and answered (or dropped if the client is gone) before the
  // call returns: the workers reference this stream.
  pipeline.Close();
  {
    MutexLock lock(streams_mutex_);
    streams_.erase(&stream);
  }
  if (auto closed = watch.Closed()) status = *closed;
  std::string agents;
  for (const std::string& agent : stream.agents) agents += (agents.empty() ? "" : ",") + agent;
  spdlog::info(
      "ingest stream closed peer={} map={} agent={} frames={} stored={} merged={} rejected={} "
      "errors={} duration={:.3f}s status={}",
      Peer(context), ForLog(stream.map->name), ForLog(agents), stream.frames, stream.stored,
      stream.merged, stream.rejected, stream.errors, MsSince(opened) / 1000.0,
      GrpcCodeName(status.error_code()));
  return Finish("Ingest", context, status);
}

void PlaceDbService::BeginDrain() {
  MutexLock lock(streams_mutex_);
  draining_ = true;
  draining_flag_ = true;
  for (Watch* watch : watches_) {
    MutexLock watch_lock(watch->mutex);
    if (!watch->header) watch->context->TryCancel();  // blocked reading its header
    // An upload still reading (not importing): the client sends it again to another server.
    if (std::string_view(watch->method) == "UploadSnapshot" && watch->in_flight == 0) {
      watch->context->TryCancel();
    }
  }
  // An idle stream's handler is blocked in Read() and is cancelled now; a busy one once its last
  // frame is answered (IngestPipeline::Drain).
  for (Stream* stream : streams_) stream->pipeline->Drain();
}

}  // namespace placedb::server
