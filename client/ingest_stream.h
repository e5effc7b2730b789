// One agent's Ingest stream: the header, then observations written by one thread while responses
// are read on the calling thread, with at most `window` observations unanswered (so a frame's
// round trip measures the server, not a transport buffer full of earlier frames).
//
//   IngestStream::Run(connection, header, /*window=*/8,
//       [&](Outgoing* next) { ...; return more; },           // writer thread; may block (pacing)
//       [&](const Answered& answered) { ... });               // reader (this) thread, in order
#pragma once

#include <chrono>
#include <functional>
#include <string>

#include "client/connection.h"

namespace placedb::client {

struct Outgoing {
  v1::Observation observation;
  size_t tag = 0;  // the caller's frame identity, handed back with its response
  // When the frame was due (paced runs); latency is measured from here when it is set, so a
  // server that falls behind the target rate shows in the latency (no coordinated omission).
  std::optional<Clock::time_point> due;
};

struct Answered {
  size_t tag = 0;
  double latency_ms = 0;  // from the write (or from `due`) to the response
  v1::IngestResponse response;
};

class IngestStream {
 public:
  // Returns false when there is nothing more to send. Called on the writer thread.
  using NextFn = std::function<bool(Outgoing*)>;
  using AnsweredFn = std::function<void(const Answered&)>;

  // Runs the stream to its end and returns its final status. `on_broken` (optional) is called
  // once if the stream ends while the writer may still be blocked in `next`, so the caller can
  // unblock it (e.g. close the queue `next` reads).
  static grpc::Status Run(const Connection& connection, const v1::IngestHeader& header,
                          size_t window, const NextFn& next, const AnsweredFn& answered,
                          const std::function<void()>& on_broken = nullptr);
};

}  // namespace placedb::client
