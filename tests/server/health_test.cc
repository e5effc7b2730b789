// The standard health service, server reflection, GetServerInfo and deadlines.
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <future>
#include <string>
#include <thread>
#include <vector>

#include "tests/server/server_fixture.h"

namespace placedb::server_testing {
namespace {

// The standard health service says SERVING; tiny deadlines end calls with DEADLINE_EXCEEDED.
TEST_F(ServerTest, HealthServingAndDeadlines) {
  ASSERT_NO_FATAL_FAILURE(StartServer(Config()));
  auto check = [&](const std::string& service) {
    grpc::GenericStub generic(channel_);
    std::string request;  // grpc.health.v1.HealthCheckRequest { string service = 1; }
    if (!service.empty()) request = std::string("\x0A", 1) + char(service.size()) + service;
    grpc::Slice slice(request);
    grpc::ByteBuffer request_buffer(&slice, 1), response_buffer;
    grpc::ClientContext context;
    std::promise<grpc::Status> done;
    generic.UnaryCall(&context, "/grpc.health.v1.Health/Check", grpc::StubOptions(),
                      &request_buffer, &response_buffer,
                      [&](grpc::Status status) { done.set_value(status); });
    const grpc::Status status = done.get_future().get();
    EXPECT_TRUE(status.ok()) << status.error_message();
    std::vector<grpc::Slice> slices;
    (void)response_buffer.Dump(&slices);
    std::string bytes;
    for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    return bytes;  // HealthCheckResponse { ServingStatus status = 1; } SERVING = 1
  };
  EXPECT_EQ(check(""), std::string("\x08\x01", 2));
  EXPECT_EQ(check("placedb.v1.PlaceDb"), std::string("\x08\x01", 2));

  // Server reflection lists the API (ServerReflectionRequest { list_services = 7 }).
  {
    grpc::GenericStub generic(channel_);
    grpc::CompletionQueue cq;
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    auto call = generic.PrepareCall(
        &context, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", &cq);
    auto next = [&](intptr_t expected) {
      void* tag = nullptr;
      bool ok = false;
      EXPECT_TRUE(cq.Next(&tag, &ok));
      EXPECT_EQ(reinterpret_cast<intptr_t>(tag), expected);
      return ok;
    };
    call->StartCall(reinterpret_cast<void*>(1));
    ASSERT_TRUE(next(1));
    grpc::Slice slice(std::string("\x3a\x00", 2));
    grpc::ByteBuffer request(&slice, 1), reply;
    call->Write(request, reinterpret_cast<void*>(2));
    ASSERT_TRUE(next(2));
    call->Read(&reply, reinterpret_cast<void*>(3));
    ASSERT_TRUE(next(3));
    std::vector<grpc::Slice> slices;
    (void)reply.Dump(&slices);
    std::string bytes;
    for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    EXPECT_NE(bytes.find("placedb.v1.PlaceDb"), std::string::npos);
    EXPECT_NE(bytes.find("grpc.health.v1.Health"), std::string::npos);
    call->WritesDone(reinterpret_cast<void*>(4));
    next(4);
    grpc::Status status;
    call->Finish(&status, reinterpret_cast<void*>(5));
    next(5);
    EXPECT_TRUE(status.ok()) << status.error_message();
  }

  CreateMap("m");
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::microseconds(1));
    v1::QueryRequest request;
    request.set_map("m");
    *request.mutable_observation() = RtabmapObservation(1, "a");
    v1::QueryResponse response;
    EXPECT_EQ(stub_->Query(&context, request, &response).error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    // A stream whose deadline passes while it sends.
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(400));
    auto stream = stub_->Ingest(&context);
    std::thread writer([&] {
      v1::IngestRequest header;
      header.mutable_header()->set_map("m");
      if (!stream->Write(header)) return;
      for (int i = 0; i < 10000; ++i) {
        v1::IngestRequest request;
        *request.mutable_observation() = RtabmapObservation(1 + i % 40, "a");
        if (!stream->Write(request)) return;
      }
    });
    v1::IngestResponse response;
    while (stream->Read(&response)) {
    }
    writer.join();
    EXPECT_EQ(stream->Finish().error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  // The server is still healthy and serving afterwards.
  v1::QueryResponse response;
  EXPECT_TRUE(Query("m", RtabmapObservation(2, "a"), &response).ok());
  grpc::ClientContext context;
  v1::ServerInfo info;
  ASSERT_TRUE(stub_->GetServerInfo(&context, {}, &info).ok());
  EXPECT_EQ(info.version(), PLACEDB_VERSION);
  ASSERT_EQ(info.vocabularies_size(), 1);
  EXPECT_EQ(info.vocabularies(0).checksum(), vocabulary_->checksum_hex());
  EXPECT_EQ(info.detector(), "off");
  EXPECT_EQ(info.limits().max_boxes_per_frame(), 16u);
  EXPECT_EQ(info.limits().worker_threads(), 2u);
}

}  // namespace
}  // namespace placedb::server_testing
