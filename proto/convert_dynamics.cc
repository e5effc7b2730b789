#include "proto/convert_dynamics.h"

#include <algorithm>
#include <string>
#include <utility>

#include "core/detect/detector.h"

namespace placedb::wire {

void DynamicsToProto(const PlaceDynamics& d, v1::DynamicStatistics* out) {
  out->set_observations(d.observations);
  out->set_mean_coverage(d.mean_coverage());
  out->set_max_coverage(d.max_coverage());
  out->set_last_coverage(d.last_coverage());
  out->set_last_timestamp_ns(d.last_timestamp_ns);
  out->set_untimed(d.untimed);
  out->set_future(d.future);
  out->set_unknown_class_boxes(d.unknown_class_boxes);
  for (const auto& [id, count] : d.classes) {
    v1::DynamicClassCount* c = out->add_classes();
    c->set_class_id(id);
    c->set_frames(count.frames);
    c->set_boxes(count.boxes);
  }
  for (int bin = 0; bin < kHourBins; ++bin) {
    const HourBin& h = d.hours[size_t(bin)];
    if (h.observations == 0) continue;
    v1::HourCoverage* hour = out->add_hours();
    hour->set_weekday(uint32_t(bin / kHours));
    hour->set_hour(uint32_t(bin % kHours));
    hour->set_observations(h.observations);
    hour->set_mean_coverage(double(h.coverage_ppm_sum) / double(h.observations) /
                            double(kCoverageScale));
  }
}

Result<DynamicsRankOptions> RankOptionsFromProto(const v1::GetDynamicsRequest& request) {
  DynamicsRankOptions options;
  switch (request.measure()) {
    case v1::DYNAMICS_MEASURE_UNSPECIFIED:
    case v1::DYNAMICS_MEASURE_MEAN_COVERAGE:
      options.measure = DynamicsMeasure::kMeanCoverage;
      break;
    case v1::DYNAMICS_MEASURE_CLASS_SHARE:
      options.measure = DynamicsMeasure::kClassShare;
      break;
    case v1::DYNAMICS_MEASURE_HOUR_WINDOW:
      options.measure = DynamicsMeasure::kHourWindow;
      break;
    default:
      return Status::InvalidArgument("measure: unknown value " +
                                     std::to_string(int(request.measure())));
  }
  options.class_id = request.class_id();
  if (!request.class_name().empty()) {
    auto named = CocoClassId(request.class_name());
    if (!named.ok()) {
      return Status::InvalidArgument("class_name: '" + request.class_name() +
                                     "' is not a COCO class name");
    }
    if (request.class_id() != 0 && request.class_id() != *named) {
      return Status::InvalidArgument("class_id " + std::to_string(request.class_id()) +
                                     " and class_name '" + request.class_name() + "' disagree");
    }
    options.class_id = *named;
  }
  if (options.measure == DynamicsMeasure::kHourWindow) {
    for (const auto& [field, hour] : {std::pair{"first_hour", request.first_hour()},
                                      std::pair{"last_hour", request.last_hour()}}) {
      if (hour > 23) {
        return Status::InvalidArgument(std::string(field) + ": " + std::to_string(hour) +
                                       " is not an hour of the day (0..23)");
      }
    }
  }
  options.first_hour = int(std::min<uint32_t>(request.first_hour(), 23));
  options.last_hour = int(std::min<uint32_t>(request.last_hour(), 23));
  if (request.weekdays() > 0x7f) {
    return Status::InvalidArgument("weekdays: only bits 0..6 (Monday..Sunday) exist");
  }
  options.weekdays = request.weekdays() == 0 ? uint8_t(0x7f) : uint8_t(request.weekdays());
  options.min_observations = std::max<uint64_t>(1, request.min_observations());
  options.offset = request.offset();
  options.limit = request.limit() == 0 ? 50 : request.limit();
  if (request.has_near() != (request.near_radius() != 0)) {
    return Status::InvalidArgument(request.has_near() ? "near_radius: must be > 0 with near"
                                                      : "near: is required with near_radius");
  }
  if (request.has_near()) {
    options.near.centre = {request.near().x(), request.near().y(), request.near().z()};
    options.near.radius = request.near_radius();
    if (!(options.near.radius > 0)) {
      return Status::InvalidArgument("near_radius: must be a finite distance > 0");
    }
  }
  PLACEDB_RETURN_IF_ERROR(ValidateDynamicsRankOptions(options));
  return options;
}

}  // namespace placedb::wire
