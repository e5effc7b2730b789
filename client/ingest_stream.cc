#include "client/ingest_stream.h"

#include <deque>
#include <thread>

#include "core/base/thread_annotations.h"

namespace placedb::client {

grpc::Status IngestStream::Run(const Connection& connection, const v1::IngestHeader& header,
                               size_t window, const NextFn& next, const AnsweredFn& answered,
                               const std::function<void()>& on_broken) {
  struct Pending {
    size_t tag;
    Clock::time_point start;
  };
  auto context = connection.NewContext(/*unary=*/false);
  auto stream = connection.stub()->Ingest(context.get());

  // Between the writer thread and this (reader) thread; a struct so the analysis knows the lock.
  struct Shared {
    Mutex mutex;
    CondVar changed;
    std::deque<Pending> pending GUARDED_BY(mutex);
    bool reader_done GUARDED_BY(mutex) = false;
    bool writer_done GUARDED_BY(mutex) = false;
  } shared;
  window = std::max<size_t>(window, 1);

  std::thread writer([&] {
    v1::IngestRequest request;
    *request.mutable_header() = header;
    if (stream->Write(request)) {
      while (true) {
        {
          MutexLock lock(shared.mutex);
          while (shared.pending.size() >= window && !shared.reader_done) {
            shared.changed.Wait(shared.mutex);
          }
          if (shared.reader_done) break;
        }
        Outgoing outgoing;
        if (!next(&outgoing)) {
          {
            MutexLock lock(shared.mutex);
            shared.writer_done = true;
          }
          stream->WritesDone();
          break;
        }
        request.Clear();
        *request.mutable_observation() = std::move(outgoing.observation);
        {
          MutexLock lock(shared.mutex);
          if (shared.reader_done) break;
          shared.pending.push_back({outgoing.tag, outgoing.due.value_or(Clock::now())});
        }
        if (!stream->Write(request)) break;  // the stream is over; Finish() says why
      }
    }
    MutexLock lock(shared.mutex);
    shared.writer_done = true;
  });

  v1::IngestResponse response;
  while (stream->Read(&response)) {
    Answered out;
    {
      MutexLock lock(shared.mutex);
      // A response for nothing sent: the server's bug, not ours.
      if (shared.pending.empty()) continue;
      out.tag = shared.pending.front().tag;
      out.latency_ms =
          std::chrono::duration<double, std::milli>(Clock::now() - shared.pending.front().start)
              .count();
      shared.pending.pop_front();
    }
    shared.changed.NotifyAll();
    out.response = std::move(response);
    answered(out);
    response.Clear();
  }
  bool call_broken = false;
  {
    MutexLock lock(shared.mutex);
    shared.reader_done = true;
    call_broken = !shared.writer_done;
  }
  shared.changed.NotifyAll();
  // The server ended the stream before we were done sending: the writer's Write fails and the
  // window wait ends by themselves; `next` may be blocked in the caller's code.
  if (call_broken && on_broken) on_broken();
  writer.join();
  return stream->Finish();
}

}  // namespace placedb::client
