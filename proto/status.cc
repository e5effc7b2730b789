#include "proto/status.h"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <vector>

#include "core/base/text.h"

namespace placedb::wire {

grpc::StatusCode ToGrpcCode(StatusCode code) {
  switch (code) {
    case StatusCode::kOk:
      return grpc::StatusCode::OK;
    case StatusCode::kInvalidArgument:
      return grpc::StatusCode::INVALID_ARGUMENT;
    case StatusCode::kNotFound:
      return grpc::StatusCode::NOT_FOUND;
    case StatusCode::kAlreadyExists:
      return grpc::StatusCode::ALREADY_EXISTS;
    case StatusCode::kFailedPrecondition:
      return grpc::StatusCode::FAILED_PRECONDITION;
    case StatusCode::kResourceExhausted:
      return grpc::StatusCode::RESOURCE_EXHAUSTED;
    case StatusCode::kCorruption:
      return grpc::StatusCode::DATA_LOSS;
    case StatusCode::kIoError:
      return grpc::StatusCode::UNAVAILABLE;
    case StatusCode::kInternal:
      return grpc::StatusCode::INTERNAL;
    case StatusCode::kCancelled:
      return grpc::StatusCode::CANCELLED;
  }
  return grpc::StatusCode::INTERNAL;
}

grpc::Status ToGrpc(const Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(ToGrpcCode(status.code()), status.message());
}

grpc::Status ToGrpc(const Status& status, const std::string& context) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(ToGrpcCode(status.code()), context + ": " + status.message());
}

StatusCode FromGrpcCode(int code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return StatusCode::kOk;
    case grpc::StatusCode::CANCELLED:
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return StatusCode::kCancelled;
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::OUT_OF_RANGE:
      return StatusCode::kInvalidArgument;
    case grpc::StatusCode::NOT_FOUND:
      return StatusCode::kNotFound;
    case grpc::StatusCode::ALREADY_EXISTS:
      return StatusCode::kAlreadyExists;
    case grpc::StatusCode::FAILED_PRECONDITION:
    case grpc::StatusCode::ABORTED:
    case grpc::StatusCode::PERMISSION_DENIED:
    case grpc::StatusCode::UNAUTHENTICATED:
      return StatusCode::kFailedPrecondition;
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return StatusCode::kResourceExhausted;
    case grpc::StatusCode::DATA_LOSS:
      return StatusCode::kCorruption;
    case grpc::StatusCode::UNAVAILABLE:
      return StatusCode::kIoError;
    default:  // UNKNOWN, UNIMPLEMENTED, INTERNAL and numbers outside the enum
      return StatusCode::kInternal;
  }
}

namespace {

Status FromCode(int code, const std::string& message, const std::string& context) {
  if (code == grpc::StatusCode::OK) return Status::Ok();
  const StatusCode core = FromGrpcCode(code);
  std::string text = context.empty() ? "" : context + ": ";
  if (ToGrpcCode(core) != code) text += GrpcCodeName(code) + ": ";
  return Status(core, text + message);
}

}  // namespace

Status FromGrpc(const grpc::Status& status) {
  return FromCode(status.error_code(), status.error_message(), "");
}

Status FromGrpc(const grpc::Status& status, const std::string& context) {
  return FromCode(status.error_code(), status.error_message(), context);
}

Status FromProto(const v1::ErrorStatus& error, const std::string& context) {
  return FromCode(error.code(), error.message(), context);
}

std::string GrpcCodeName(int code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return "OK";
    case grpc::StatusCode::CANCELLED:
      return "CANCELLED";
    case grpc::StatusCode::UNKNOWN:
      return "UNKNOWN";
    case grpc::StatusCode::INVALID_ARGUMENT:
      return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND:
      return "NOT_FOUND";
    case grpc::StatusCode::ALREADY_EXISTS:
      return "ALREADY_EXISTS";
    case grpc::StatusCode::PERMISSION_DENIED:
      return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::FAILED_PRECONDITION:
      return "FAILED_PRECONDITION";
    case grpc::StatusCode::ABORTED:
      return "ABORTED";
    case grpc::StatusCode::OUT_OF_RANGE:
      return "OUT_OF_RANGE";
    case grpc::StatusCode::UNIMPLEMENTED:
      return "UNIMPLEMENTED";
    case grpc::StatusCode::INTERNAL:
      return "INTERNAL";
    case grpc::StatusCode::UNAVAILABLE:
      return "UNAVAILABLE";
    case grpc::StatusCode::DATA_LOSS:
      return "DATA_LOSS";
    case grpc::StatusCode::UNAUTHENTICATED:
      return "UNAUTHENTICATED";
    default:
      return "CODE_" + std::to_string(code);
  }
}

std::string GrpcCodeLabel(int code) {
  return AsciiLower(GrpcCodeName(code));
}

namespace {

// Where a path token may start: the message's start or after a separator.
bool TokenBoundary(char c) {
  return std::isspace(static_cast<unsigned char>(c)) || c == '(' || c == '[' || c == '\'' ||
         c == '"' || c == '=' || c == ',' || c == '`';
}

// Where a path token ends: a separator, or ':' / '.' / ',' followed by a space or the end
// ("/data/x/CURRENT: No such file", "cannot open /data/x.").
size_t TokenEnd(const std::string& s, size_t start) {
  size_t i = start;
  while (i < s.size()) {
    const char c = s[i];
    if (std::isspace(static_cast<unsigned char>(c)) || c == '\'' || c == '"' || c == ')' ||
        c == ']' || c == '`') {
      break;
    }
    if ((c == ':' || c == '.' || c == ',' || c == ';') &&
        (i + 1 == s.size() || std::isspace(static_cast<unsigned char>(s[i + 1])))) {
      break;
    }
    ++i;
  }
  return i;
}

// The absolute spellings of the data directory, longest first, without a trailing '/'.
std::vector<std::string> DataDirSpellings(const std::string& data_dir) {
  std::vector<std::string> out;
  if (data_dir.empty()) return out;
  namespace fs = std::filesystem;
  std::error_code error;
  auto add = [&](std::string path) {
    while (path.size() > 1 && path.back() == '/') path.pop_back();
    if (path.size() > 1 && path[0] == '/' && std::find(out.begin(), out.end(), path) == out.end()) {
      out.push_back(std::move(path));
    }
  };
  add(data_dir);
  const fs::path absolute = fs::absolute(data_dir, error);
  if (!error) add(absolute.lexically_normal().string());
  const fs::path canonical = fs::weakly_canonical(data_dir, error);
  if (!error) add(canonical.string());
  std::sort(out.begin(), out.end(),
            [](const std::string& a, const std::string& b) { return a.size() > b.size(); });
  return out;
}

std::string ClientPath(const std::string& path, const std::vector<std::string>& data_dirs) {
  for (const std::string& dir : data_dirs) {
    if (path == dir || path == dir + "/") return "<data_dir>";
    if (path.size() > dir.size() && path.compare(0, dir.size(), dir) == 0 &&
        path[dir.size()] == '/') {
      return path.substr(dir.size() + 1);
    }
  }
  std::string trimmed = path;
  while (trimmed.size() > 1 && trimmed.back() == '/') trimmed.pop_back();
  return trimmed.substr(trimmed.rfind('/') + 1);
}

}  // namespace

std::string HidePaths(const std::string& message, const std::string& data_dir) {
  if (message.find('/') == std::string::npos) return message;  // the common case: nothing to do
  const std::vector<std::string> data_dirs = DataDirSpellings(data_dir);
  std::string out;
  out.reserve(message.size());
  size_t i = 0;
  while (i < message.size()) {
    const bool starts_token = i == 0 || TokenBoundary(message[i - 1]);
    const bool absolute = message[i] == '/' && i + 1 < message.size() &&
                          !std::isspace(static_cast<unsigned char>(message[i + 1]));
    if (starts_token && absolute) {
      const size_t end = TokenEnd(message, i);
      out += ClientPath(message.substr(i, end - i), data_dirs);
      i = end;
      continue;
    }
    out += message[i++];
  }
  return out;
}

grpc::Status HidePaths(const grpc::Status& status, const std::string& data_dir) {
  if (status.ok()) return status;
  return grpc::Status(status.error_code(), HidePaths(status.error_message(), data_dir),
                      status.error_details());
}

}  // namespace placedb::wire
