// An Ingest stream as PlaceDbService::IngestStream sees it: gRPC's reader-writer plus why Read()
// returned false. ParsingService (server/rpc/parsing_service.h) implements it over the raw stream,
// parsing each message itself.
#pragma once

#include <grpcpp/grpcpp.h>

#include "proto/placedb.pb.h"

namespace placedb::server {

class IngestStreamIo
    : public grpc::ServerReaderWriterInterface<v1::IngestResponse, v1::IngestRequest> {
 public:
  // OK when the stream simply ended (the client half-closed, or the call is over);
  // INVALID_ARGUMENT naming the message when the last one read was not a valid IngestRequest.
  virtual grpc::Status ReadError() const = 0;
};

}  // namespace placedb::server
