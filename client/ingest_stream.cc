#include "client/ingest_stream.h"

#include <condition_variable>
#include <deque>
#include <mutex>
#include <thread>

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

  std::mutex mutex;
  std::condition_variable changed;
  std::deque<Pending> pending;
  bool reader_done = false;
  bool writer_done = false;
  window = std::max<size_t>(window, 1);

  std::thread writer([&] {
    v1::IngestRequest request;
    *request.mutable_header() = header;
    if (stream->Write(request)) {
      while (true) {
        {
          std::unique_lock lock(mutex);
          changed.wait(lock, [&] { return pending.size() < window || reader_done; });
          if (reader_done) break;
        }
        Outgoing outgoing;
        if (!next(&outgoing)) {
          {
            std::lock_guard lock(mutex);
            writer_done = true;
          }
          stream->WritesDone();
          break;
        }
        request.Clear();
        *request.mutable_observation() = std::move(outgoing.observation);
        {
          std::lock_guard lock(mutex);
          if (reader_done) break;
          pending.push_back({outgoing.tag, outgoing.due.value_or(Clock::now())});
        }
        if (!stream->Write(request)) break;  // the stream is over; Finish() says why
      }
    }
    std::lock_guard lock(mutex);
    writer_done = true;
  });

  v1::IngestResponse response;
  while (stream->Read(&response)) {
    Answered out;
    {
      std::lock_guard lock(mutex);
      if (pending.empty()) continue;  // a response for nothing sent: the server's bug, not ours
      out.tag = pending.front().tag;
      out.latency_ms =
          std::chrono::duration<double, std::milli>(Clock::now() - pending.front().start).count();
      pending.pop_front();
    }
    changed.notify_all();
    out.response = std::move(response);
    answered(out);
    response.Clear();
  }
  bool call_broken = false;
  {
    std::lock_guard lock(mutex);
    reader_done = true;
    call_broken = !writer_done;
  }
  changed.notify_all();
  // The server ended the stream before we were done sending: the writer's Write fails and the
  // window wait ends by themselves; `next` may be blocked in the caller's code.
  if (call_broken && on_broken) on_broken();
  writer.join();
  return stream->Finish();
}

}  // namespace placedb::client
