// Maps: CreateMap, GetMap, ListMaps, DeleteMap, RecoverMap, ScrubMap, AdaptVocabulary,
// RevertVocabulary. The request is checked and resolved here; the backend does the rest.
#include <spdlog/spdlog.h>

#include "core/base/map_name.h"
#include "proto/convert_config.h"
#include "proto/status.h"
#include "server/rpc/call_support.h"

namespace placedb::server {

using wire::MapOptionsFromProto;
using wire::MapVocabulary;
using wire::ToGrpc;

grpc::Status PlaceDbService::CreateMap(grpc::ServerContext* context,
                                       const v1::CreateMapRequest* request,
                                       v1::MapDescription* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("CreateMap", context, Unavailable());
  // The name before anything else: a bad one is the caller's first problem to hear about.
  if (Status valid = ValidateMapName(request->name()); !valid.ok()) {
    return Finish("CreateMap", context, ToGrpc(valid.WithContext("name")));
  }
  // The vocabulary next: its kind is the map's feature type.
  auto vocabulary = maps_->ResolveVocabulary(request->config().vocabulary());
  if (!vocabulary.ok()) return Finish("CreateMap", context, ToGrpc(vocabulary.status()));
  MapCreation creation;
  creation.name = request->name();
  creation.vocabulary_requested = request->config().vocabulary();
  creation.vocabulary = (*vocabulary)->name;
  auto options = MapOptionsFromProto(
      request->config(), config_.limits.max_descriptors_per_frame,
      MapVocabulary{(*vocabulary)->name, (*vocabulary)->vocabulary.feature_type()},
      &creation.settings);
  if (!options.ok()) return Finish("CreateMap", context, ToGrpc(options.status()));
  creation.options = std::move(options).value();
  ServiceMapSettings& settings = creation.settings;
  // Unspecified box source: the server's detector when it has one, else the agent's boxes. The
  // choice is stored with the map, so it does not change if the server's detector does.
  if (request->config().detection().box_source() == v1::BOX_SOURCE_UNSPECIFIED && detector_ &&
      settings.detection_enabled) {
    settings.box_source = BoxSource::kServer;
  }
  if (settings.detection_enabled && settings.box_source != BoxSource::kAgent && !detector_) {
    return Finish("CreateMap", context,
                  grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                               "config.detection.box_source: " +
                                   std::string(BoxSourceName(settings.box_source)) +
                                   " needs server-side detection, which is off on this server "
                                   "(configure detector.model)"));
  }
  const grpc::Status created = backend_->CreateMap(creation, DeadlineOf(context), response);
  if (created.ok()) {
    spdlog::info("map '{}' created ({}): vocabulary '{}', features {}, box source {}, peer={}",
                 ForLog(request->name()), backend_->role(), creation.vocabulary,
                 FeatureTypeName(creation.options.database.feature_type),
                 BoxSourceName(settings.box_source), Peer(context));
  }
  return Finish("CreateMap", context, created);
}

grpc::Status PlaceDbService::GetMap(grpc::ServerContext* context, const v1::GetMapRequest* request,
                                    v1::MapDescription* response) {
  CallScope scope(this);
  const grpc::Status described = backend_->GetMap(request->name(), DeadlineOf(context), response);
  if (!described.ok()) return Finish("GetMap", context, described);
  // The agents this server's Ingest streams served.
  for (const AgentActivitySnapshot& agent : activity_.Of(request->name(), Clock::now())) {
    v1::AgentActivity* out = response->add_agents();
    out->set_agent_id(agent.agent_id);
    out->set_frames(agent.frames);
    out->set_places(agent.places);
    out->set_frames_per_second(agent.frames_per_second);
    out->set_last_place_id(agent.last_place_id);
    out->set_last_frame_unix_ms(agent.last_frame_unix_ms);
  }
  return Finish("GetMap", context, grpc::Status::OK);
}

grpc::Status PlaceDbService::ListMaps(grpc::ServerContext* context, const v1::ListMapsRequest*,
                                      v1::ListMapsResponse* response) {
  CallScope scope(this);
  return Finish("ListMaps", context, backend_->ListMaps(DeadlineOf(context), response));
}

grpc::Status PlaceDbService::DeleteMap(grpc::ServerContext* context,
                                       const v1::DeleteMapRequest* request,
                                       v1::DeleteMapResponse*) {
  CallScope scope(this);
  if (draining_flag_) return Finish("DeleteMap", context, Unavailable());
  const grpc::Status deleted = backend_->DeleteMap(request->name(), DeadlineOf(context));
  if (deleted.ok()) {
    activity_.Forget(request->name());
    spdlog::info("map '{}' deleted, peer={}", ForLog(request->name()), Peer(context));
  }
  return Finish("DeleteMap", context, deleted);
}

grpc::Status PlaceDbService::RecoverMap(grpc::ServerContext* context,
                                        const v1::RecoverMapRequest* request,
                                        v1::RecoverMapResponse* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("RecoverMap", context, Unavailable());
  const grpc::Status recovered = backend_->RecoverMap(*request, response);
  if (recovered.ok()) {
    spdlog::info("map '{}' recovered, peer={}", ForLog(request->name()), Peer(context));
  }
  return Finish("RecoverMap", context, recovered);
}

grpc::Status PlaceDbService::ScrubMap(grpc::ServerContext* context,
                                      const v1::ScrubMapRequest* request,
                                      v1::ScrubReport* response) {
  CallScope scope(this);
  return Finish("ScrubMap", context, backend_->ScrubMap(request->name(), response));
}

grpc::Status PlaceDbService::AdaptVocabulary(grpc::ServerContext* context,
                                             const v1::AdaptVocabularyRequest* request,
                                             v1::MapVocabulary* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("AdaptVocabulary", context, Unavailable());
  spdlog::info("map '{}': adapting its vocabulary ({}), peer={}", ForLog(request->name()),
               backend_->role(), Peer(context));
  // A shutdown cancels it: the map keeps its vocabulary.
  return Finish(
      "AdaptVocabulary", context,
      backend_->AdaptVocabulary(*request, DeadlineOf(context), &draining_flag_, response));
}

grpc::Status PlaceDbService::RevertVocabulary(grpc::ServerContext* context,
                                              const v1::RevertVocabularyRequest* request,
                                              v1::MapVocabulary* response) {
  CallScope scope(this);
  if (draining_flag_) return Finish("RevertVocabulary", context, Unavailable());
  spdlog::info("map '{}': reverting its vocabulary ({}), peer={}", ForLog(request->name()),
               backend_->role(), Peer(context));
  return Finish(
      "RevertVocabulary", context,
      backend_->RevertVocabulary(request->name(), DeadlineOf(context), &draining_flag_, response));
}

}  // namespace placedb::server
