// The one mapping between the core's Status and gRPC's, each way, and the names of the gRPC codes.
//
// Core -> gRPC is 1:1: INVALID_ARGUMENT, NOT_FOUND, ALREADY_EXISTS, FAILED_PRECONDITION,
// RESOURCE_EXHAUSTED, INTERNAL and CANCELLED keep their names, CORRUPTION -> DATA_LOSS and
// IO_ERROR -> UNAVAILABLE. gRPC -> core inverts it and folds the codes the core has no word for
// into the nearest one (DEADLINE_EXCEEDED -> CANCELLED, OUT_OF_RANGE -> INVALID_ARGUMENT,
// ABORTED / PERMISSION_DENIED / UNAUTHENTICATED -> FAILED_PRECONDITION, UNKNOWN / UNIMPLEMENTED
// -> INTERNAL), so a client of the server keeps the server's code.
#pragma once

#include <grpcpp/support/status.h>

#include <string>

#include "core/base/status.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

grpc::StatusCode ToGrpcCode(StatusCode code);
grpc::Status ToGrpc(const Status& status);
grpc::Status ToGrpc(const Status& status, const std::string& context);  // "context: message"

// `code` is a grpc::StatusCode; numbers outside the enum are INTERNAL.
StatusCode FromGrpcCode(int code);
Status FromGrpc(const grpc::Status& status);
// "context: message"; a gRPC code the core folds keeps its name in the message
// ("Query q1: DEADLINE_EXCEEDED: Deadline Exceeded").
Status FromGrpc(const grpc::Status& status, const std::string& context);
// An IngestResponse.error, the same way.
Status FromProto(const v1::ErrorStatus& error, const std::string& context);

// A grpc::StatusCode's name, "INVALID_ARGUMENT"; "CODE_<n>" for a number outside the enum (codes
// that travel as integers, as in IngestResponse.error, may be a peer's own).
std::string GrpcCodeName(int code);
std::string GrpcCodeLabel(int code);  // "invalid_argument": metric labels

// A message fit for a client: no absolute filesystem path of the server in it. A path inside
// `data_dir` (the server's data directory, in any absolute spelling: as configured, made
// absolute, or canonical) becomes relative to it ("maps/m1/000012.log"; the directory itself
// "<data_dir>"); any other absolute path (a token starting with "/" and a path component)
// becomes its file name ("/opt/models/yolox.onnx" -> "yolox.onnx"). Server logs keep the paths.
std::string HidePaths(const std::string& message, const std::string& data_dir);
grpc::Status HidePaths(const grpc::Status& status, const std::string& data_dir);

}  // namespace placedb::wire
