// Status and Result<T>: how errors cross every placedb boundary.
//
// Errors are values, never exceptions and never strings thrown across modules. A Status carries a
// code (mapped 1:1 onto gRPC codes by the server) and a message a user can act on, naming the bad
// field where there is one. Result<T> holds either a T or a non-OK Status.
#pragma once

#include <cassert>
#include <string>
#include <utility>
#include <variant>

namespace placedb {

enum class StatusCode {
  kOk = 0,
  kInvalidArgument,     // the caller sent something malformed; the message names the field
  kNotFound,            // a map, place or file that does not exist
  kAlreadyExists,       // creating something that exists
  kFailedPrecondition,  // valid request, wrong state (e.g. vocabulary mismatch)
  kResourceExhausted,   // a configured limit was hit
  kCorruption,          // stored data failed a format or checksum check
  kIoError,             // the operating system refused a read or write
  kInternal,            // a bug: an invariant did not hold
  kCancelled,           // the caller gave up (deadline or cancellation)
};

const char* StatusCodeName(StatusCode code);

class [[nodiscard]] Status {
 public:
  Status() = default;
  Status(StatusCode code, std::string message) : code_(code), message_(std::move(message)) {}

  static Status Ok() { return {}; }
  static Status InvalidArgument(std::string m) {
    return {StatusCode::kInvalidArgument, std::move(m)};
  }
  static Status NotFound(std::string m) { return {StatusCode::kNotFound, std::move(m)}; }
  static Status AlreadyExists(std::string m) { return {StatusCode::kAlreadyExists, std::move(m)}; }
  static Status FailedPrecondition(std::string m) {
    return {StatusCode::kFailedPrecondition, std::move(m)};
  }
  static Status ResourceExhausted(std::string m) {
    return {StatusCode::kResourceExhausted, std::move(m)};
  }
  static Status Corruption(std::string m) { return {StatusCode::kCorruption, std::move(m)}; }
  static Status IoError(std::string m) { return {StatusCode::kIoError, std::move(m)}; }
  static Status Internal(std::string m) { return {StatusCode::kInternal, std::move(m)}; }
  static Status Cancelled(std::string m) { return {StatusCode::kCancelled, std::move(m)}; }

  bool ok() const { return code_ == StatusCode::kOk; }
  StatusCode code() const { return code_; }
  const std::string& message() const { return message_; }
  // "INVALID_ARGUMENT: keypoints[3].x = 700 lies outside the 640x480 image"
  std::string ToString() const;

  // Prefixes context to the message, keeping the code: "loading vocab.pdbv: <message>".
  Status WithContext(const std::string& context) const;

 private:
  StatusCode code_ = StatusCode::kOk;
  std::string message_;
};

// Either a value or a non-OK Status.
template <typename T>
class [[nodiscard]] Result {
 public:
  Result(T value) : state_(std::move(value)) {}        // NOLINT: implicit by design
  Result(Status status) : state_(std::move(status)) {  // NOLINT: implicit by design
    assert(!std::get<Status>(state_).ok() && "Result built from an OK status has no value");
  }

  bool ok() const { return std::holds_alternative<T>(state_); }
  const Status& status() const {
    static const Status kOk;
    return ok() ? kOk : std::get<Status>(state_);
  }
  T& value() & { return std::get<T>(state_); }
  const T& value() const& { return std::get<T>(state_); }
  T&& value() && { return std::get<T>(std::move(state_)); }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }

 private:
  std::variant<T, Status> state_;
};

}  // namespace placedb

// Returns early from the enclosing function when `expr` yields a non-OK Status.
#define PLACEDB_RETURN_IF_ERROR(expr)                  \
  do {                                                 \
    ::placedb::Status placedb_status_ = (expr);        \
    if (!placedb_status_.ok()) return placedb_status_; \
  } while (false)
