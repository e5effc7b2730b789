// Dynamic-object statistics (core/dynamics) as placedb.v1 messages, and GetDynamics requests
// as ranking options.
#pragma once

#include "core/base/status.h"
#include "core/dynamics/dynamics_ranking.h"
#include "core/dynamics/place_dynamics.h"
#include "proto/placedb.pb.h"

namespace placedb::wire {

namespace v1 = ::placedb::v1;

void DynamicsToProto(const PlaceDynamics& dynamics, v1::DynamicStatistics* out);
// Defaults for zero fields (measure: mean coverage; weekdays: every day; limit: 50;
// min_observations: 1). INVALID_ARGUMENT naming the field (ValidateDynamicsRankOptions).
Result<DynamicsRankOptions> RankOptionsFromProto(const v1::GetDynamicsRequest& request);

}  // namespace placedb::wire
