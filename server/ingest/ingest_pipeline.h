// The machinery of one ingest stream, without the wire: frames are read by one thread, processed
// in parallel on a WorkerPool, finished one at a time in the order they were read, and delivered
// in that order by the pipeline's own delivery thread.
//
// A frame's work comes in two halves (IngestPipeline::Frame). Prepare() is independent of the
// other frames (decode, extract, filter), so frames of one stream prepare in parallel, in any
// order. Complete() depends on every earlier frame (a place is stored before the next frame
// searches), so it runs in stream order, one frame at a time: whichever worker finishes preparing
// the frame at the front completes it and every prepared frame behind it (a strand; no thread
// waits for another). Completed frames go to an outbox that the delivery thread drains in order.
//
// Threads and calls:
// - The reader (the one thread that owns the stream, e.g. an RPC handler) calls, in a loop,
//   AwaitRoom() before reading the next request, then Submit() with its frame; when reading ends
//   (end of input, error, refusal) it calls Close(), which returns once every submitted frame is
//   answered. Only the reader calls AwaitRoom(), Submit() and Close().
// - Pool workers run Prepare() and Complete(); the reader runs Refused() and, for a refused frame,
//   may run Complete() too (inside Submit()).
// - The delivery thread runs `deliver`, one frame at a time, in submission order.
// - Drain() and draining() may be called from any thread.
//
// Limits: at most `max_inflight` frames are unanswered (submitted, not yet delivered or skipped);
// AwaitRoom() blocks the reader until there is room, so a slow consumer stops the reading, and
// nothing read is dropped. Submit() waits for room in the pool's queue (global backpressure).
// With a memory budget (Memory), AwaitRoom() also waits until the budget grants the bytes one
// read may bring in (`read_bytes`, the largest message), so nothing is read that the budget has
// not granted; the reader takes that reservation over for the frame it read
// (TakeReadReservation()) and sizes it to the frame, or refuses the frame (Reject()).
//
// Errors and ending:
// - A frame's own failure is its business: Prepare() and Complete() record it in the frame (the
//   stream goes on). They must not throw: a frame whose stage throws is never answered, and the
//   stream never ends.
// - When `deliver` returns false (the consumer is gone), every later frame is still completed but
//   skipped instead of delivered, and AwaitRoom() says kClosed.
// - When `expired` says so (cancelled, past the deadline), AwaitRoom() says kClosed and a Submit()
//   still waiting for the pool gives up (the frame is refused, then completed and answered).
// - Drain() (server shutdown): AwaitRoom() and Submit() refuse from then on, frames already
//   submitted are still completed and delivered, and `interrupt` is called once nothing is left
//   to answer, to unblock a reader waiting for input.
// Close() (or the destructor) is the only safe end: it waits for the workers and the delivery
// thread to be done with the pipeline and with every frame.
#pragma once

#include <cstddef>
#include <deque>
#include <functional>
#include <memory>
#include <thread>

#include "core/base/thread_annotations.h"
#include "server/ingest/memory_budget.h"
#include "server/ingest/worker_pool.h"

namespace placedb::server {

class IngestPipeline {
 public:
  // What AwaitRoom() found.
  enum class Room {
    kReady,     // read and submit the next request
    kDraining,  // Drain() was called: stop reading
    kClosed,    // the consumer is gone, or `expired` said so: stop reading
  };
  // What Submit() did with a frame.
  enum class Admission {
    kQueued,       // on the pool; it will be prepared, completed and delivered
    kDraining,     // Drain() was called: dropped unanswered (never counted as in flight)
    kPoolStopped,  // the pool is stopping: Refused(), then completed and delivered
    kGaveUp,       // `expired` said so while waiting for the pool: as kPoolStopped
  };

  // One request's work, written by the caller. The pipeline owns it from Submit() until it has
  // been delivered (or skipped), and destroys it on the delivery thread (or in Submit(), when it
  // drops it).
  class Frame {
   public:
    virtual ~Frame() = default;
    // The first half, on a pool worker, concurrently with other frames' Prepare() and with the
    // Complete() of earlier frames.
    virtual void Prepare() = 0;
    // Instead of Prepare(), on the reader thread, when the pool did not take the frame
    // (kPoolStopped or kGaveUp). Complete() still follows, in order.
    virtual void Refused(Admission why) = 0;
    // The second half, after this frame's Prepare() (or Refused()) and after every earlier
    // frame's Complete(), before any later frame's: the Complete() calls of one pipeline never
    // overlap, and each sees everything the earlier ones did. Usually on a worker.
    virtual void Complete() = 0;
  };

  struct Callbacks {
    // Sends a completed frame, on the delivery thread, in submission order. False: the consumer
    // is gone (later frames are skipped). Required.
    std::function<bool(Frame&)> deliver;
    // Whether the stream is over (cancelled, past its deadline); polled on the reader thread
    // while it waits, in AwaitRoom() and Submit(). Optional.
    std::function<bool()> expired = {};
    // Unblocks the reader when draining and nothing is left to answer. It runs under the
    // pipeline's lock, possibly more than once: cheap, idempotent, never calls the pipeline.
    // Optional.
    std::function<void()> interrupt = {};
  };

  // Optional: reads are charged to a memory budget (see the file comment).
  struct Memory {
    MemoryBudget* budget = nullptr;  // none: reads are not charged
    uint64_t read_bytes = 0;         // what one read may bring in (limits.max_message_bytes)
    uint64_t keep_free = 0;          // a read leaves this much free (for frames already read)
  };

  // Starts the delivery thread. `pool` (and `memory.budget`) must outlive the pipeline;
  // `max_inflight` >= 1.
  IngestPipeline(WorkerPool* pool, size_t max_inflight, Callbacks callbacks, Memory memory);
  IngestPipeline(WorkerPool* pool, size_t max_inflight, Callbacks callbacks);  // no budget
  ~IngestPipeline();                                                           // Close()
  IngestPipeline(const IngestPipeline&) = delete;
  IngestPipeline& operator=(const IngestPipeline&) = delete;

  // Reader: waits until fewer than `max_inflight` frames are unanswered and (with a budget) the
  // budget has granted `read_bytes` for the next read, or until the stream is draining or closed
  // (checked in that order; `expired` is polled every 50 ms).
  Room AwaitRoom() EXCLUDES(mutex_);
  // Reader, after a read: the reservation AwaitRoom() made for it (empty without a budget), for
  // the frame to hold until its answer is written. The next AwaitRoom() reserves anew.
  MemoryBudget::Reservation TakeReadReservation() { return std::move(read_reservation_); }
  // Reader: admits `frame` at the back of the stream and queues its Prepare() on the pool,
  // waiting for room there (until `expired`). Not kQueued: see Admission.
  Admission Submit(std::unique_ptr<Frame> frame) EXCLUDES(mutex_);
  // Reader: admits `frame` at the back of the stream without preparing it: the reader already
  // decided its answer (e.g. over the memory budget). Only its Complete() runs, in order (at most
  // its own, on this thread), then it is delivered. kQueued, or kDraining (dropped unanswered).
  Admission Reject(std::unique_ptr<Frame> frame) EXCLUDES(mutex_);
  // Reader: no more frames. Returns once every submitted frame is completed and delivered (or
  // skipped) and the delivery thread has ended. Idempotent.
  void Close() EXCLUDES(mutex_);

  // Any thread: refuse new frames, finish the submitted ones (see the file comment).
  void Drain() EXCLUDES(mutex_);
  bool draining() const EXCLUDES(mutex_);

 private:
  struct Slot {
    std::unique_ptr<Frame> frame;
    bool ready = false;  // Prepare() or Refused() done; read and written under mutex_
  };

  // Marks `slot` ready and, unless another thread already is, completes every ready slot at the
  // front of the stream, in order.
  void ReadyAndAdvance(Slot* slot) EXCLUDES(mutex_);
  void Deliver() EXCLUDES(mutex_);  // the delivery thread
  bool delivery_failed() const EXCLUDES(mutex_);

  WorkerPool* const pool_;
  const size_t max_inflight_;
  const Callbacks callbacks_;
  const Memory memory_;
  MemoryBudget::Reservation read_reservation_;  // the reader's only

  mutable Mutex mutex_;
  CondVar changed_;
  // Submitted, not yet completed, in order.
  std::deque<std::unique_ptr<Slot>> pending_ GUARDED_BY(mutex_);
  bool completing_ GUARDED_BY(mutex_) = false;  // a thread is in ReadyAndAdvance()'s loop
  // Completed, not yet delivered, in order.
  std::deque<std::unique_ptr<Frame>> outbox_ GUARDED_BY(mutex_);
  size_t unanswered_ GUARDED_BY(mutex_) = 0;  // submitted, not yet delivered or skipped
  bool reading_done_ GUARDED_BY(mutex_) = false;
  bool deliver_failed_ GUARDED_BY(mutex_) = false;
  bool draining_ GUARDED_BY(mutex_) = false;

  std::thread delivery_;  // last: starts once the state above exists
};

}  // namespace placedb::server
