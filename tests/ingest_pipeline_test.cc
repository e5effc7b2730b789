// IngestPipeline without gRPC: a real WorkerPool and real threads, frames that record what was
// done to them, and gates that hold a frame's work until the test opens them.
#include "server/ingest/ingest_pipeline.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace placedb::server {
namespace {

using namespace std::chrono_literals;
using Admission = IngestPipeline::Admission;
using Room = IngestPipeline::Room;

// Holds whoever waits on it until opened.
class Gate {
 public:
  void Open() {
    {
      std::lock_guard lock(mutex_);
      open_ = true;
    }
    opened_.notify_all();
  }
  void Wait() {
    std::unique_lock lock(mutex_);
    opened_.wait(lock, [&] { return open_; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable opened_;
  bool open_ = false;
};

// What happened to one stream's frames, in the order it happened; the test waits on it.
struct StreamLog {
  std::mutex mutex;
  std::condition_variable changed;
  std::vector<int> prepared;         // Prepare() finished
  std::vector<int> completed;        // Complete() ran
  std::vector<int> offered;          // given to `deliver`
  std::vector<std::string> answers;  // accepted by `deliver`
  int alive = 0;                     // frames not yet destroyed
  int submitted = 0;                 // kept by the tests' readers
  int interrupts = 0;
  size_t answers_at_interrupt = 0;

  // Written by Complete() only, without a lock: the pipeline's strand orders those calls.
  std::vector<int> strand;
  std::atomic<bool> completing{false};

  template <typename Change>
  void Update(Change&& change) {
    {
      std::lock_guard lock(mutex);
      change();
    }
    changed.notify_all();
  }
  // Whether `done` (read under the lock) held within `timeout`.
  template <typename Done>
  bool WaitFor(Done&& done, std::chrono::milliseconds timeout = 60s) {
    std::unique_lock lock(mutex);
    return changed.wait_for(lock, timeout, [&] { return done(); });
  }
};

class TestFrame final : public IngestPipeline::Frame {
 public:
  // `gate` (optional) holds Prepare(); `fail`: the frame's own work fails.
  TestFrame(StreamLog* log, int index, Gate* gate = nullptr, bool fail = false, int spin = 0)
      : log_(log), index_(index), gate_(gate), fail_(fail), spin_(spin) {
    log_->Update([&] { ++log_->alive; });
  }
  ~TestFrame() override {
    log_->Update([&] { --log_->alive; });
  }

  void Prepare() override {
    if (gate_) gate_->Wait();
    for (int i = 0; i < spin_; ++i) std::this_thread::yield();  // uneven work across frames
    outcome_ = fail_ ? "error" : "ok";
    log_->Update([&] { log_->prepared.push_back(index_); });
  }
  void Refused(Admission why) override {
    outcome_ = why == Admission::kPoolStopped ? "pool stopped" : "gave up";
  }
  void Complete() override {
    EXPECT_FALSE(log_->completing.exchange(true)) << "Complete() calls overlap at " << index_;
    // Every earlier frame's Complete() is visible here, and no later one has run.
    EXPECT_EQ(log_->strand.size(), size_t(index_));
    log_->strand.push_back(index_);
    answer_ = std::to_string(index_) + ":" + outcome_;
    completed_on_ = std::this_thread::get_id();
    log_->completing = false;
    log_->Update([&] { log_->completed.push_back(index_); });
  }

  int index() const { return index_; }
  const std::string& answer() const { return answer_; }
  std::thread::id completed_on() const { return completed_on_; }

 private:
  StreamLog* const log_;
  const int index_;
  Gate* const gate_;
  const bool fail_;
  const int spin_;
  std::string outcome_ = "unprepared";
  std::string answer_;
  std::thread::id completed_on_;
};

// A consumer that accepts every frame (after `hold`, when given) and records its answer.
std::function<bool(IngestPipeline::Frame&)> Accept(StreamLog* log, Gate* hold = nullptr) {
  return [log, hold](IngestPipeline::Frame& frame) {
    if (hold) hold->Wait();
    const auto& test_frame = static_cast<TestFrame&>(frame);
    log->Update([&] {
      log->offered.push_back(test_frame.index());
      log->answers.push_back(test_frame.answer());
    });
    return true;
  };
}

std::vector<int> Range(int from, int to, int step = 1) {
  std::vector<int> out;
  for (int i = from; step > 0 ? i < to : i > to; i += step) out.push_back(i);
  return out;
}

std::vector<std::string> OkAnswers(int n) {
  std::vector<std::string> out;
  for (int i = 0; i < n; ++i) out.push_back(std::to_string(i) + ":ok");
  return out;
}

// ---- Ordering, backpressure, ending, several streams (also run under TSan) ---------------------
// Waits that threads still depend on are EXPECTs: a failure reports and goes on to release them
// instead of hanging the test.

TEST(IngestPipelineConcurrency, DeliversInSubmissionOrderWhileWorkFinishesOutOfOrder) {
  constexpr int kFrames = 8;
  WorkerPool pool(kFrames, kFrames);  // every frame on its own worker at once
  StreamLog log;
  std::deque<Gate> gates(kFrames);
  {
    IngestPipeline pipeline(&pool, kFrames, {.deliver = Accept(&log)});
    for (int i = 0; i < kFrames; ++i) {
      ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
      ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i, &gates[size_t(i)])),
                Admission::kQueued);
    }
    // The last frames finish first; none completes while the first is still being prepared.
    for (int i = kFrames - 1; i > 0; --i) {
      gates[size_t(i)].Open();
      EXPECT_TRUE(log.WaitFor([&] { return log.prepared.size() == size_t(kFrames - i); }));
      std::lock_guard lock(log.mutex);
      EXPECT_TRUE(log.completed.empty());
      EXPECT_TRUE(log.offered.empty());
    }
    gates[0].Open();
    pipeline.Close();
  }
  EXPECT_EQ(log.prepared, Range(kFrames - 1, -1, -1));
  EXPECT_EQ(log.completed, Range(0, kFrames));
  EXPECT_EQ(log.strand, Range(0, kFrames));
  EXPECT_EQ(log.answers, OkAnswers(kFrames));
  EXPECT_EQ(log.alive, 0);
}

TEST(IngestPipelineConcurrency, SlowConsumerPausesIntakeAndNothingIsLost) {
  constexpr int kFrames = 20;
  constexpr size_t kInflight = 3;
  WorkerPool pool(2, 4);
  StreamLog log;
  Gate consumer;  // the consumer takes nothing until opened
  IngestPipeline pipeline(&pool, kInflight, {.deliver = Accept(&log, &consumer)});
  std::thread reader([&] {
    for (int i = 0; i < kFrames; ++i) {
      ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
      log.Update([&] {
        // Unanswered = read and not yet taken by the consumer: always under the limit.
        EXPECT_LT(size_t(log.submitted) - log.answers.size(), kInflight);
        ++log.submitted;
      });
      ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i)), Admission::kQueued);
    }
  });
  // The reader stops at the limit, with every frame read completed and waiting for the consumer.
  EXPECT_TRUE(
      log.WaitFor([&] { return log.submitted == kInflight && log.completed.size() == kInflight; }));
  EXPECT_FALSE(log.WaitFor([&] { return log.submitted > int(kInflight); }, 200ms));
  consumer.Open();
  reader.join();
  pipeline.Close();
  EXPECT_EQ(log.answers, OkAnswers(kFrames));
  EXPECT_EQ(log.alive, 0);
}

TEST(IngestPipelineConcurrency, FullPoolQueuePausesIntake) {
  WorkerPool pool(1, 1);  // one worker, one waiting task
  StreamLog log;
  Gate first;
  IngestPipeline pipeline(&pool, 16, {.deliver = Accept(&log)});
  std::thread reader([&] {
    for (int i = 0; i < 4; ++i) {
      ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
      ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i, i == 0 ? &first : nullptr)),
                Admission::kQueued);
      log.Update([&] { ++log.submitted; });
    }
  });
  // Frame 0 holds the worker and frame 1 fills the queue: the third Submit() waits.
  EXPECT_TRUE(log.WaitFor([&] { return log.submitted == 2; }));
  EXPECT_FALSE(log.WaitFor([&] { return log.submitted > 2; }, 200ms));
  first.Open();
  reader.join();
  pipeline.Close();
  EXPECT_EQ(log.answers, OkAnswers(4));
  EXPECT_EQ(log.alive, 0);
}

TEST(IngestPipelineConcurrency, CancelledStreamEndsOnlyOnceEveryFrameReadIsAnswered) {
  constexpr int kFrames = 6;
  WorkerPool pool(3, kFrames);
  StreamLog log;
  std::deque<Gate> gates(kFrames);
  std::atomic<bool> cancelled{false};
  std::thread opener;
  {
    IngestPipeline pipeline(&pool, kFrames + 1,
                            {.deliver = Accept(&log), .expired = [&] { return cancelled.load(); }});
    for (int i = 0; i < kFrames; ++i) {
      ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
      ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i, &gates[size_t(i)])),
                Admission::kQueued);
    }
    cancelled = true;  // the client went away with every frame still in the pool
    EXPECT_EQ(pipeline.AwaitRoom(), Room::kClosed);
    // Close() while the work is still held: it must wait for all of it.
    opener = std::thread([&] {
      for (int i = kFrames - 1; i >= 0; --i) gates[size_t(i)].Open();
    });
    pipeline.Close();
    // Close() returned: every frame is answered and gone, and no worker holds the pipeline.
    EXPECT_EQ(log.answers, OkAnswers(kFrames));
    EXPECT_EQ(log.alive, 0);
  }  // the pipeline is destroyed right away
  opener.join();
  pool.Stop();
  EXPECT_EQ(log.completed, Range(0, kFrames));
}

TEST(IngestPipelineConcurrency, DrainAnswersWhatWasReadThenInterruptsTheReader) {
  WorkerPool pool(2, 4);
  StreamLog log;
  std::deque<Gate> gates(2);
  IngestPipeline pipeline(&pool, 8, {.deliver = Accept(&log), .interrupt = [&] {
                                       // Under the pipeline's lock, not the log's: safe to take it.
                                       log.Update([&] {
                                         ++log.interrupts;
                                         log.answers_at_interrupt = log.answers.size();
                                       });
                                     }});
  for (int i = 0; i < 2; ++i) {
    ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i, &gates[size_t(i)])),
              Admission::kQueued);
  }
  pipeline.Drain();
  EXPECT_TRUE(pipeline.draining());
  EXPECT_EQ(pipeline.AwaitRoom(), Room::kDraining);
  // A frame read after the drain began is dropped unanswered, at once.
  EXPECT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 2)), Admission::kDraining);
  {
    std::lock_guard lock(log.mutex);
    EXPECT_EQ(log.alive, 2);
    EXPECT_EQ(log.interrupts, 0);  // two frames are still unanswered
  }
  gates[1].Open();
  gates[0].Open();
  ASSERT_TRUE(log.WaitFor([&] { return log.interrupts > 0; }));
  pipeline.Close();
  EXPECT_EQ(log.answers, OkAnswers(2));
  EXPECT_EQ(log.answers_at_interrupt, 2u);
  EXPECT_EQ(log.alive, 0);
}

TEST(IngestPipelineConcurrency, DrainInterruptsAnIdleReaderAtOnce) {
  WorkerPool pool(1, 1);
  StreamLog log;
  IngestPipeline pipeline(&pool, 4, {.deliver = Accept(&log), .interrupt = [&] {
                                       log.Update([&] { ++log.interrupts; });
                                     }});
  pipeline.Drain();
  EXPECT_EQ(log.interrupts, 1);
  EXPECT_EQ(pipeline.AwaitRoom(), Room::kDraining);
  pipeline.Close();
  EXPECT_TRUE(log.answers.empty());
}

TEST(IngestPipelineConcurrency, StreamsSharingThePoolEachKeepTheirOrder) {
  constexpr int kStreams = 4;
  constexpr int kFrames = 200;
  WorkerPool pool(3, 2);
  std::deque<StreamLog> logs(kStreams);
  std::vector<std::thread> readers;
  for (int s = 0; s < kStreams; ++s) {
    readers.emplace_back([&, s] {
      StreamLog& log = logs[size_t(s)];
      IngestPipeline pipeline(&pool, size_t(1 + s), {.deliver = Accept(&log)});
      for (int i = 0; i < kFrames; ++i) {
        ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
        const bool fail = (i + s) % 17 == 0;
        ASSERT_EQ(pipeline.Submit(
                      std::make_unique<TestFrame>(&log, i, nullptr, fail, (i * 7 + s * 3) % 50)),
                  Admission::kQueued);
      }
      pipeline.Close();
    });
  }
  for (auto& reader : readers) reader.join();
  for (int s = 0; s < kStreams; ++s) {
    const StreamLog& log = logs[size_t(s)];
    ASSERT_EQ(log.answers.size(), size_t(kFrames)) << "stream " << s;
    for (int i = 0; i < kFrames; ++i) {
      EXPECT_EQ(log.answers[size_t(i)], std::to_string(i) + ((i + s) % 17 == 0 ? ":error" : ":ok"))
          << "stream " << s;
    }
    EXPECT_EQ(log.completed, Range(0, kFrames));
    EXPECT_EQ(log.alive, 0);
  }
}

TEST(IngestPipelineConcurrency, ReadsWaitForTheMemoryBudgetAndEachReadIsGrantedAWholeMessage) {
  constexpr uint64_t kMiB = uint64_t(1) << 20;
  MemoryBudget budget(10 * kMiB);
  WorkerPool pool(2, 4);
  StreamLog log;
  std::vector<MemoryBudget::Reservation> held;  // what the frames read keep (by the test here)
  std::atomic<bool> expired{false};
  IngestPipeline pipeline(&pool, 8,
                          {.deliver = Accept(&log), .expired = [&] { return expired.load(); }},
                          {.budget = &budget, .read_bytes = 4 * kMiB});
  std::thread reader([&] {
    for (int i = 0; i < 3; ++i) {
      ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
      MemoryBudget::Reservation read = pipeline.TakeReadReservation();
      EXPECT_EQ(read.bytes(), 4 * kMiB);
      log.Update([&] {
        held.push_back(std::move(read));
        ++log.submitted;
      });
      ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i)), Admission::kQueued);
    }
    // Blocked on the budget until the stream expires: nothing more is read.
    EXPECT_EQ(pipeline.AwaitRoom(), Room::kClosed);
  });
  // Two reads of 4 MiB fit in 10; the third waits until a frame gives its share back.
  EXPECT_TRUE(log.WaitFor([&] { return log.submitted == 2; }));
  EXPECT_FALSE(log.WaitFor([&] { return log.submitted > 2; }, 200ms));
  EXPECT_EQ(budget.in_use(), 8 * kMiB);
  MemoryBudget::Reservation first;
  log.Update([&] { first = std::move(held.front()); });
  first.Release();
  EXPECT_TRUE(log.WaitFor([&] { return log.submitted == 3; }));
  expired = true;
  reader.join();
  pipeline.Close();
  EXPECT_EQ(log.answers, OkAnswers(3));
  held.clear();
  EXPECT_EQ(budget.in_use(), 0u);  // Close() returned the pending read's reservation
}

// ---- Errors -------------------------------------------------------------------------------------

TEST(IngestPipelineTest, ARejectedFrameIsAnsweredInItsPlaceUnprepared) {
  WorkerPool pool(2, 4);
  StreamLog log;
  Gate first;
  IngestPipeline pipeline(&pool, 4, {.deliver = Accept(&log)});
  ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 0, &first)), Admission::kQueued);
  ASSERT_EQ(pipeline.Reject(std::make_unique<TestFrame>(&log, 1)), Admission::kQueued);
  ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 2)), Admission::kQueued);
  // Frame 2 is prepared on the other worker; frames 1 and 2 wait for frame 0.
  EXPECT_TRUE(log.WaitFor([&] { return log.prepared.size() == 1; }));
  {
    std::lock_guard lock(log.mutex);
    EXPECT_TRUE(log.completed.empty());
  }
  first.Open();
  pipeline.Close();
  EXPECT_EQ(log.answers, (std::vector<std::string>{"0:ok", "1:unprepared", "2:ok"}));
  EXPECT_EQ(log.prepared, (std::vector<int>{2, 0}));
}

TEST(IngestPipelineTest, AFailedFrameIsAnsweredInItsPlaceAndTheStreamGoesOn) {
  WorkerPool pool(2, 4);
  StreamLog log;
  IngestPipeline pipeline(&pool, 4, {.deliver = Accept(&log)});
  for (int i = 0; i < 5; ++i) {
    ASSERT_EQ(pipeline.AwaitRoom(), Room::kReady);
    ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i, nullptr, i == 2)),
              Admission::kQueued);
  }
  EXPECT_EQ(pipeline.AwaitRoom(), Room::kReady);
  pipeline.Close();
  EXPECT_EQ(log.answers, (std::vector<std::string>{"0:ok", "1:ok", "2:error", "3:ok", "4:ok"}));
}

TEST(IngestPipelineTest, WhenTheConsumerIsGoneTheRestIsCompletedButNotDelivered) {
  WorkerPool pool(2, 4);
  StreamLog log;
  IngestPipeline pipeline(&pool, 8, {.deliver = [&](IngestPipeline::Frame& frame) {
    const int index = static_cast<TestFrame&>(frame).index();
    log.Update([&] { log.offered.push_back(index); });
    return index != 1;  // the write of frame 1 fails
  }});
  for (int i = 0; i < 4; ++i) {
    ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, i)), Admission::kQueued);
  }
  ASSERT_TRUE(log.WaitFor([&] { return log.alive == 0; }));
  EXPECT_EQ(pipeline.AwaitRoom(), Room::kClosed);
  pipeline.Close();
  EXPECT_EQ(log.completed, Range(0, 4));
  EXPECT_EQ(log.offered, (std::vector<int>{0, 1}));
}

TEST(IngestPipelineTest, ASubmitThatGivesUpOnThePoolIsAnsweredInOrder) {
  WorkerPool pool(1, 1);
  StreamLog log;
  Gate first;
  std::atomic<bool> expired{false};
  IngestPipeline pipeline(&pool, 8,
                          {.deliver = Accept(&log), .expired = [&] { return expired.load(); }});
  ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 0, &first)), Admission::kQueued);
  // Queued once the worker holds frame 0: the queue is then full.
  ASSERT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 1)), Admission::kQueued);
  Admission third = Admission::kQueued;
  std::thread reader([&] { third = pipeline.Submit(std::make_unique<TestFrame>(&log, 2)); });
  expired = true;
  reader.join();
  EXPECT_EQ(third, Admission::kGaveUp);
  EXPECT_EQ(pipeline.AwaitRoom(), Room::kClosed);
  {
    std::lock_guard lock(log.mutex);
    EXPECT_TRUE(log.completed.empty());  // frame 2 waits for frames 0 and 1
  }
  first.Open();
  pipeline.Close();
  EXPECT_EQ(log.answers, (std::vector<std::string>{"0:ok", "1:ok", "2:gave up"}));
}

TEST(IngestPipelineTest, AStoppedPoolRefusesAndTheFrameIsAnsweredByTheReader) {
  WorkerPool pool(1, 1);
  pool.Stop();
  StreamLog log;
  std::thread::id completed_on;
  IngestPipeline pipeline(&pool, 4, {.deliver = [&](IngestPipeline::Frame& frame) {
    completed_on = static_cast<TestFrame&>(frame).completed_on();
    return Accept(&log)(frame);
  }});
  EXPECT_EQ(pipeline.Submit(std::make_unique<TestFrame>(&log, 0)), Admission::kPoolStopped);
  pipeline.Close();
  EXPECT_EQ(log.answers, (std::vector<std::string>{"0:pool stopped"}));
  EXPECT_EQ(completed_on, std::this_thread::get_id());
}

}  // namespace
}  // namespace placedb::server
