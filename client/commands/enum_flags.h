// The CLI spellings of the placedb.v1 enums (`maps create --filter exact_coverage`), name ->
// value. Kept in one file so that deriving them from the proto's descriptors changes only this.
#pragma once

#include <map>
#include <string>

#include "proto/placedb.pb.h"

namespace placedb::client {

namespace v1 = ::placedb::v1;

const std::map<std::string, v1::BoxRefinement>& BoxRefinementNames();
const std::map<std::string, v1::FilterMethod>& FilterNames();
const std::map<std::string, v1::Scoring>& ScoringNames();
const std::map<std::string, v1::VerificationMode>& VerifyNames();
const std::map<std::string, v1::FeatureType>& FeatureTypeNames();
const std::map<std::string, v1::BandPolicy>& BandPolicyNames();
const std::map<std::string, v1::BoxSource>& BoxSourceNames();

}  // namespace placedb::client
