#include "server/ingest/ingest_pipeline.h"

#include <algorithm>
#include <chrono>
#include <utility>

namespace placedb::server {

IngestPipeline::IngestPipeline(WorkerPool* pool, size_t max_inflight, Callbacks callbacks,
                               Memory memory)
    : pool_(pool),
      max_inflight_(std::max<size_t>(max_inflight, 1)),
      callbacks_(std::move(callbacks)),
      memory_(memory),
      delivery_([this] { Deliver(); }) {}

IngestPipeline::IngestPipeline(WorkerPool* pool, size_t max_inflight, Callbacks callbacks)
    : IngestPipeline(pool, max_inflight, std::move(callbacks), Memory{}) {}

IngestPipeline::~IngestPipeline() {
  Close();
}

IngestPipeline::Room IngestPipeline::AwaitRoom() {
  // `expired` has no wake-up hook (a cancelled call does not signal us): poll it.
  constexpr auto kPoll = std::chrono::milliseconds(50);
  const auto expired = [this] { return callbacks_.expired && callbacks_.expired(); };
  {
    MutexLock lock(mutex_);
    while (unanswered_ >= max_inflight_ && !draining_ && !deliver_failed_ && !expired()) {
      changed_.WaitFor(mutex_, kPoll);
    }
    if (draining_) return Room::kDraining;
    if (deliver_failed_ || expired()) return Room::kClosed;
  }
  if (!memory_.budget || read_reservation_) return Room::kReady;
  // Backpressure on memory: nothing is read until the budget grants what a read may bring in.
  // The window cannot fill meanwhile (only this thread submits), so it need not be re-checked.
  auto reserved = memory_.budget->Reserve(
      memory_.read_bytes, "reading the next frame", MemoryBudget::Clock::time_point::max(),
      [&] { return draining() || delivery_failed() || expired(); }, memory_.keep_free);
  if (reserved.ok()) {
    read_reservation_ = std::move(reserved).value();
    return Room::kReady;
  }
  if (draining()) return Room::kDraining;
  // The consumer is gone or the call expired; or `read_bytes` exceeds what the budget can ever
  // grant (the server refuses such a configuration at startup).
  return Room::kClosed;
}

IngestPipeline::Admission IngestPipeline::Submit(std::unique_ptr<Frame> frame) {
  auto owned = std::make_unique<Slot>();
  owned->frame = std::move(frame);
  Slot* const slot = owned.get();
  {
    MutexLock lock(mutex_);
    if (draining_) return Admission::kDraining;  // the caller sees it was never answered
    pending_.push_back(std::move(owned));
    ++unanswered_;
  }
  // Captures plain pointers: once ReadyAndAdvance() returns, the task never touches either again
  // (the slot may be delivered and destroyed by then, and the pipeline closed).
  auto task = [this, slot] {
    slot->frame->Prepare();
    ReadyAndAdvance(slot);
  };
  // Global backpressure: the reader waits here for room in the pool's queue before reading on.
  const auto submitted = pool_->Submit(task, WorkerPool::Clock::time_point::max(), [this] {
    return callbacks_.expired && callbacks_.expired();
  });
  if (submitted == WorkerPool::SubmitResult::kQueued) return Admission::kQueued;
  const Admission why = submitted == WorkerPool::SubmitResult::kStopped ? Admission::kPoolStopped
                                                                        : Admission::kGaveUp;
  slot->frame->Refused(why);
  // Only this frame can be ready and not yet completed here, so at most its own (cheap)
  // Complete() runs on the reader thread.
  ReadyAndAdvance(slot);
  return why;
}

IngestPipeline::Admission IngestPipeline::Reject(std::unique_ptr<Frame> frame) {
  auto owned = std::make_unique<Slot>();
  owned->frame = std::move(frame);
  Slot* const slot = owned.get();
  {
    MutexLock lock(mutex_);
    if (draining_) return Admission::kDraining;
    pending_.push_back(std::move(owned));
    ++unanswered_;
  }
  ReadyAndAdvance(slot);
  return Admission::kQueued;
}

// Marking and checking happen under one lock hold, so exactly one thread completes each frame,
// and a thread that returns from here never touches the pipeline again.
void IngestPipeline::ReadyAndAdvance(Slot* slot) {
  MutexLock lock(mutex_);
  slot->ready = true;
  if (completing_) return;  // the completing thread will reach this slot
  completing_ = true;
  while (!pending_.empty() && pending_.front()->ready) {
    std::unique_ptr<Frame> front = std::move(pending_.front()->frame);
    pending_.pop_front();
    lock.Unlock();
    front->Complete();
    lock.Lock();
    outbox_.push_back(std::move(front));
    changed_.NotifyAll();
  }
  completing_ = false;
}

void IngestPipeline::Deliver() {
  MutexLock lock(mutex_);
  while (true) {
    while (outbox_.empty() && !(reading_done_ && unanswered_ == 0)) changed_.Wait(mutex_);
    if (outbox_.empty()) return;
    std::unique_ptr<Frame> frame = std::move(outbox_.front());
    outbox_.pop_front();
    const bool skip = deliver_failed_;
    lock.Unlock();
    const bool delivered = !skip && callbacks_.deliver(*frame);
    frame.reset();  // outside the lock: a frame may hold a lot
    lock.Lock();
    if (!delivered) deliver_failed_ = true;
    --unanswered_;
    changed_.NotifyAll();
    if (draining_ && unanswered_ == 0 && !reading_done_ && callbacks_.interrupt) {
      callbacks_.interrupt();  // the reader may be blocked on input; nothing is left to answer
    }
  }
}

void IngestPipeline::Close() {
  read_reservation_.Release();  // no more reads
  {
    MutexLock lock(mutex_);
    reading_done_ = true;
    changed_.NotifyAll();
  }
  // Every submitted frame is answered before this returns: workers reference the pipeline.
  if (delivery_.joinable()) delivery_.join();
}

void IngestPipeline::Drain() {
  MutexLock lock(mutex_);
  draining_ = true;
  changed_.NotifyAll();
  // An idle reader is blocked on input: interrupt it now. A busy one is interrupted by the
  // delivery thread once its last frame is answered.
  if (unanswered_ == 0 && callbacks_.interrupt) callbacks_.interrupt();
}

bool IngestPipeline::draining() const {
  MutexLock lock(mutex_);
  return draining_;
}

bool IngestPipeline::delivery_failed() const {
  MutexLock lock(mutex_);
  return deliver_failed_;
}

}  // namespace placedb::server
