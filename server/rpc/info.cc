// GetServerInfo: the version, the configured vocabularies, the detector, the limits, the role.
#include "proto/convert_config.h"
#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

using wire::FeatureTypeToProto;
using wire::HidePaths;

grpc::Status PlaceDbService::GetServerInfo(grpc::ServerContext* context,
                                           const v1::GetServerInfoRequest*,
                                           v1::ServerInfo* response) {
  CallScope scope(this);
  response->set_version(PLACEDB_VERSION);
  for (const VocabularyEntry& entry : maps_->vocabularies()) {
    v1::VocabularyInfo* info = response->add_vocabularies();
    info->set_name(entry.name);
    info->set_path(HidePaths(entry.path, config_.data_dir));  // the file name: no server paths
    info->set_checksum(entry.vocabulary.checksum_hex());
    info->set_words(entry.vocabulary.word_count());
    info->set_nodes(entry.vocabulary.node_count());
    info->set_branching(entry.vocabulary.branching());
    info->set_depth(entry.vocabulary.depth());
    info->set_memory_bytes(entry.vocabulary.memory_bytes());
    info->set_feature_type(FeatureTypeToProto(entry.vocabulary.feature_type()));
  }
  response->set_detector(
      HidePaths(detector_ ? detector_->Describe() : detector_status_, config_.data_dir));
  response->set_console_url(console_url_);
  response->set_role(backend_->role());
  const Limits& l = config_.limits;
  v1::Limits* limits = response->mutable_limits();
  limits->set_max_message_bytes(l.max_message_bytes);
  limits->set_max_image_pixels(l.max_image_pixels);
  limits->set_max_descriptors_per_frame(l.max_descriptors_per_frame);
  limits->set_max_boxes_per_frame(l.max_boxes_per_frame);
  limits->set_max_concurrent_streams(l.max_concurrent_streams);
  limits->set_max_queued_frames(l.max_queued_frames);
  limits->set_max_inflight_per_stream(l.max_inflight_per_stream);
  limits->set_worker_threads(uint32_t(pool_->threads()));
  return Finish("GetServerInfo", context, grpc::Status::OK);
}

}  // namespace placedb::server
