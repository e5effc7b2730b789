#include "server/cluster/map_record.h"

#include <algorithm>
#include <chrono>

#include "core/dynamics/place_dynamics.h"
#include "core/storage/codec.h"
#include "proto/cluster.pb.h"
#include "proto/convert_config.h"

namespace placedb::cluster {

namespace {

std::string OperandOf(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                      int64_t now_unix_ns) {
  return EncodeDynamics(MakeObservation(frame.counts.dynamic_coverage, frame.boxes_used,
                                        metadata.timestamp_ns, now_unix_ns));
}

std::string Serialize(const v1::MapRecord& record) {
  std::string out;
  record.SerializeToString(&out);
  return out;
}

Status Field(Status status, const char* field) {
  return status.ok() ? status
                     : Status::Corruption(std::string("map record: ") + field + ": " +
                                          std::string(status.message()));
}

// Empty bytes: none.
Status DecodeOperand(const std::string& bytes, const char* field,
                     std::optional<PlaceDynamics>* out) {
  if (bytes.empty()) return Status::Ok();
  auto dynamics = DecodeDynamics(bytes);
  PLACEDB_RETURN_IF_ERROR(Field(dynamics.status(), field));
  *out = std::move(dynamics).value();
  return Status::Ok();
}

}  // namespace

int64_t NowUnixNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string EncodeAddPlace(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                           int64_t now_unix_ns) {
  v1::MapRecord record;
  v1::AddPlace* add = record.mutable_add_place();
  PlaceRecord place;
  place.metadata = metadata;
  place.counts = frame.counts;
  place.boxes_used = frame.boxes_used;
  add->set_place_record(EncodePlaceRecord(place));
  add->set_bow(EncodeBow(frame.bow));
  add->set_features(EncodeLocalFeatures(frame.static_features, frame.direct, frame.geometry));
  add->set_dynamics(OperandOf(frame, metadata, now_unix_ns));
  if (frame.thumbnail) add->set_thumbnail(EncodeThumbnail(*frame.thumbnail));
  if (!frame.dynamic_bow.empty()) add->set_dynamic_bow(EncodeBow(frame.dynamic_bow));
  if (!frame.dynamic_features.empty()) {
    add->set_dynamic_features(EncodeLocalFeatures(frame.dynamic_features, frame.dynamic_direct));
  }
  add->set_vocabulary_checksum(frame.vocabulary_checksum);
  return Serialize(record);
}

std::vector<std::string> EncodeVocabularyParts(const AnyVocabulary& vocabulary, size_t part_bytes) {
  const std::string bytes = vocabulary.Serialize();
  part_bytes = std::max<size_t>(part_bytes, 1);
  const size_t count = std::max<size_t>((bytes.size() + part_bytes - 1) / part_bytes, 1);
  std::vector<std::string> parts;
  parts.reserve(count);
  for (size_t i = 0; i < count; ++i) {
    v1::MapRecord record;
    v1::VocabularyPart* part = record.mutable_vocabulary_part();
    part->set_checksum(vocabulary.checksum());
    part->set_index(uint32_t(i));
    part->set_count(uint32_t(count));
    part->set_data(bytes.substr(std::min(i * part_bytes, bytes.size()), part_bytes));
    parts.push_back(Serialize(record));
  }
  return parts;
}

std::string EncodePrepareVocabulary(uint64_t checksum, uint32_t parts) {
  v1::MapRecord record;
  record.mutable_prepare_vocabulary()->set_checksum(checksum);
  record.mutable_prepare_vocabulary()->set_parts(parts);
  return Serialize(record);
}

std::string EncodeSwitchVocabulary(const VocabularySource& source, uint32_t parts) {
  v1::MapRecord record;
  wire::VocabularySourceToProto(source, record.mutable_switch_vocabulary()->mutable_source());
  record.mutable_switch_vocabulary()->set_parts(parts);
  return Serialize(record);
}

std::string EncodeDeletePlace(PlaceId place) {
  v1::MapRecord record;
  record.mutable_delete_place()->set_place_id(place);
  return Serialize(record);
}

std::string EncodeCountObservation(PlaceId place, const ProcessedFrame& frame,
                                   const PlaceMetadata& metadata, int64_t now_unix_ns) {
  v1::MapRecord record;
  v1::CountObservation* count = record.mutable_count_observation();
  count->set_place_id(place);
  count->set_dynamics(OperandOf(frame, metadata, now_unix_ns));
  return Serialize(record);
}

std::string EncodeLoopConstraints(const std::vector<LoopConstraint>& loops) {
  v1::MapRecord record;
  v1::LoopConstraints* out = record.mutable_loop_constraints();
  for (const LoopConstraint& constraint : loops)
    out->add_constraints(EncodeLoopConstraint(constraint));
  return Serialize(record);
}

std::string EncodeInvalidFrame(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                               int64_t now_unix_ns) {
  v1::MapRecord record;
  v1::InvalidFrame* invalid = record.mutable_invalid_frame();
  InvalidObservation observation;
  observation.metadata = metadata;
  observation.counts = frame.counts;
  observation.boxes_used = frame.boxes_used;
  observation.reason = frame.rejection;
  invalid->set_observation(EncodeInvalidObservation(observation));
  invalid->set_dynamics(OperandOf(frame, metadata, now_unix_ns));
  return Serialize(record);
}

Result<MapLogRecord> DecodeMapRecord(std::string_view bytes, FeatureType type) {
  v1::MapRecord record;
  // Protobuf's parser is bounds-checked: it refuses truncated or malformed messages.
  if (!record.ParseFromArray(bytes.data(), int(bytes.size()))) {
    return Status::Corruption("map record: not a placedb.cluster.v1.MapRecord (" +
                              std::to_string(bytes.size()) + " bytes)");
  }
  MapLogRecord out;
  switch (record.record_case()) {
    case v1::MapRecord::kAddPlace: {
      const v1::AddPlace& add = record.add_place();
      out.kind = MapLogRecord::Kind::kAddPlace;
      auto place = DecodePlaceRecord(add.place_record());
      PLACEDB_RETURN_IF_ERROR(Field(place.status(), "add_place.place_record"));
      auto bow = DecodeBow(add.bow());
      PLACEDB_RETURN_IF_ERROR(Field(bow.status(), "add_place.bow"));
      ProcessedFrame& frame = out.frame;
      PLACEDB_RETURN_IF_ERROR(
          Field(DecodeLocalFeatures(add.features(), type, &frame.static_features, &frame.direct,
                                    &frame.geometry),
                "add_place.features"));
      frame.bow = std::move(bow).value();
      frame.valid = true;
      frame.vocabulary_checksum = add.vocabulary_checksum();
      frame.counts = place->counts;
      frame.boxes_used = place->boxes_used;
      out.metadata = place->metadata;
      PLACEDB_RETURN_IF_ERROR(DecodeOperand(add.dynamics(), "add_place.dynamics", &out.dynamics));
      if (!add.thumbnail().empty()) {
        auto thumbnail = DecodeThumbnail(add.thumbnail());
        PLACEDB_RETURN_IF_ERROR(Field(thumbnail.status(), "add_place.thumbnail"));
        frame.thumbnail = std::move(thumbnail).value();
      }
      if (!add.dynamic_bow().empty()) {
        auto dynamic_bow = DecodeBow(add.dynamic_bow());
        PLACEDB_RETURN_IF_ERROR(Field(dynamic_bow.status(), "add_place.dynamic_bow"));
        frame.dynamic_bow = std::move(dynamic_bow).value();
      }
      if (!add.dynamic_features().empty()) {
        PLACEDB_RETURN_IF_ERROR(
            Field(DecodeLocalFeatures(add.dynamic_features(), type, &frame.dynamic_features,
                                      &frame.dynamic_direct),
                  "add_place.dynamic_features"));
      } else {
        frame.dynamic_features = LocalFeatures::Empty(type, frame.static_features.image_width(),
                                                      frame.static_features.image_height());
      }
      return out;
    }
    case v1::MapRecord::kDeletePlace:
      out.kind = MapLogRecord::Kind::kDeletePlace;
      out.place = record.delete_place().place_id();
      if (out.place == 0) return Status::Corruption("map record: delete_place.place_id is 0");
      return out;
    case v1::MapRecord::kCountObservation:
      out.kind = MapLogRecord::Kind::kCountObservation;
      out.place = record.count_observation().place_id();
      PLACEDB_RETURN_IF_ERROR(DecodeOperand(record.count_observation().dynamics(),
                                            "count_observation.dynamics", &out.dynamics));
      return out;
    case v1::MapRecord::kInvalidFrame: {
      out.kind = MapLogRecord::Kind::kInvalidFrame;
      auto observation = DecodeInvalidObservation(record.invalid_frame().observation());
      PLACEDB_RETURN_IF_ERROR(Field(observation.status(), "invalid_frame.observation"));
      out.metadata = observation->metadata;
      out.frame.valid = false;
      out.frame.counts = observation->counts;
      out.frame.boxes_used = observation->boxes_used;
      out.frame.rejection = observation->reason;
      PLACEDB_RETURN_IF_ERROR(DecodeOperand(record.invalid_frame().dynamics(),
                                            "invalid_frame.dynamics", &out.dynamics));
      return out;
    }
    case v1::MapRecord::kVocabularyPart: {
      const v1::VocabularyPart& part = record.vocabulary_part();
      if (part.count() == 0 || part.index() >= part.count()) {
        return Status::Corruption("map record: vocabulary_part: part " +
                                  std::to_string(part.index()) + " of " +
                                  std::to_string(part.count()));
      }
      out.kind = MapLogRecord::Kind::kVocabularyPart;
      out.vocabulary_part = {part.checksum(), part.index(), part.count(), part.data()};
      return out;
    }
    case v1::MapRecord::kSwitchVocabulary: {
      auto source = wire::VocabularySourceFromProto(record.switch_vocabulary().source(),
                                                    "switch_vocabulary.source");
      PLACEDB_RETURN_IF_ERROR(Field(source.status(), "switch_vocabulary"));
      out.kind = MapLogRecord::Kind::kSwitchVocabulary;
      out.vocabulary_source = std::move(source).value();
      out.vocabulary_parts = record.switch_vocabulary().parts();
      return out;
    }
    case v1::MapRecord::kPrepareVocabulary:
      out.kind = MapLogRecord::Kind::kPrepareVocabulary;
      out.vocabulary_source.checksum = record.prepare_vocabulary().checksum();
      out.vocabulary_parts = record.prepare_vocabulary().parts();
      return out;
    case v1::MapRecord::kLoopConstraints: {
      out.kind = MapLogRecord::Kind::kLoopConstraints;
      const auto& constraints = record.loop_constraints().constraints();
      for (int i = 0; i < constraints.size(); ++i) {
        auto constraint = DecodeLoopConstraint(0, constraints[i]);
        const std::string field = "loop_constraints.constraints[" + std::to_string(i) + "]";
        PLACEDB_RETURN_IF_ERROR(Field(constraint.status(), field.c_str()));
        out.loops.push_back(std::move(constraint).value());
      }
      return out;
    }
    case v1::MapRecord::RECORD_NOT_SET:
      break;
  }
  return Status::Corruption("map record: no record kind set (or one this shard does not know)");
}

void FrameToSearchRequest(const ProcessedFrame& frame, v1::SearchRequest* request) {
  request->set_bow(EncodeBow(frame.bow));
  request->set_vocabulary_checksum(frame.vocabulary_checksum);
  request->set_features(EncodeLocalFeatures(frame.static_features, frame.direct, frame.geometry));
  if (!frame.dynamic_bow.empty()) request->set_dynamic_bow(EncodeBow(frame.dynamic_bow));
  if (!frame.dynamic_features.empty()) {
    request->set_dynamic_features(
        EncodeLocalFeatures(frame.dynamic_features, frame.dynamic_direct));
  }
}

Status FrameFromSearchRequest(const v1::SearchRequest& request, FeatureType type,
                              ProcessedFrame* frame) {
  auto bow = DecodeBow(request.bow());
  PLACEDB_RETURN_IF_ERROR(Field(bow.status(), "search.bow"));
  PLACEDB_RETURN_IF_ERROR(
      Field(DecodeLocalFeatures(request.features(), type, &frame->static_features, &frame->direct,
                                &frame->geometry),
            "search.features"));
  frame->bow = std::move(bow).value();
  frame->valid = true;
  frame->vocabulary_checksum = request.vocabulary_checksum();
  if (!request.dynamic_bow().empty()) {
    auto dynamic_bow = DecodeBow(request.dynamic_bow());
    PLACEDB_RETURN_IF_ERROR(Field(dynamic_bow.status(), "search.dynamic_bow"));
    frame->dynamic_bow = std::move(dynamic_bow).value();
  }
  if (!request.dynamic_features().empty()) {
    PLACEDB_RETURN_IF_ERROR(
        Field(DecodeLocalFeatures(request.dynamic_features(), type, &frame->dynamic_features,
                                  &frame->dynamic_direct),
              "search.dynamic_features"));
  } else {
    frame->dynamic_features = LocalFeatures::Empty(type, frame->static_features.image_width(),
                                                   frame->static_features.image_height());
  }
  return Status::Ok();
}

}  // namespace placedb::cluster
