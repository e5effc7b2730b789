// The record codec of cluster mode (issue 18): what a worker publishes to a map's JetStream
// stream, and what a shard applies (PlaceMap::ApplyAt), as placedb.cluster.v1.MapRecord bytes
// (proto/cluster.proto). The payloads are the map's own storage encodings (core/storage/codec.h,
// core/dynamics/place_dynamics.h), so a replica stores the bytes a single-node map would.
//
// Decoding never trusts its input: bytes that are not a MapRecord, a record without a kind, or a
// payload that does not decode (each payload's own bounds-checked decoder) is CORRUPTION naming
// the field; a payload of the other feature family (ORB vs SIFT) too. Nothing is partially
// returned on failure.
//
// Thread safety: free functions without shared state.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/base/status.h"
#include "core/pipeline/place_database.h"
#include "core/storage/map_store.h"
#include "proto/cluster.pb.h"

namespace placedb::cluster {

// The current time in unix nanoseconds: the default `now_unix_ns` of the encoders below.
int64_t NowUnixNs();

// A stored place: `frame` must be valid (its SC bow, static features, direct index, counts,
// boxes used, thumbnail when present, DC part when present) with `metadata`. The frame's
// statistics operand is made here from its coverage, boxes and metadata.timestamp_ns, arriving
// at `now_unix_ns` (core/dynamics MakeObservation), once: every replica stores the same bytes.
std::string EncodeAddPlace(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                           int64_t now_unix_ns = NowUnixNs());
std::string EncodeDeletePlace(PlaceId place);
// Issue 29: a vocabulary for every replica, as records of at most `part_bytes` of its bytes
// each (a stream message is smaller than a vocabulary), in order; then the switch, naming it by
// `source.checksum` with the number of parts before it (0: the replicas store it already).
std::vector<std::string> EncodeVocabularyParts(const AnyVocabulary& vocabulary, size_t part_bytes);
std::string EncodeSwitchVocabulary(const VocabularySource& source, uint32_t parts);
// Between them: the replicas start building the switch while they go on applying records.
std::string EncodePrepareVocabulary(uint64_t checksum, uint32_t parts);
// One more observation of `place` (a frame merged by rehearsal, a counted query hit; 0: the
// map's aggregate only): `frame`'s statistics as EncodeAddPlace makes them.
std::string EncodeCountObservation(PlaceId place, const ProcessedFrame& frame,
                                   const PlaceMetadata& metadata,
                                   int64_t now_unix_ns = NowUnixNs());
// A frame refused as invalid: its counts, boxes used, rejection and metadata, and statistics.
std::string EncodeInvalidFrame(const ProcessedFrame& frame, const PlaceMetadata& metadata,
                               int64_t now_unix_ns = NowUnixNs());

// Issue 32: an ingested frame's loop constraints, query_place set (published after its place).
std::string EncodeLoopConstraints(const std::vector<LoopConstraint>& loops);

// `bytes` (one stream message) back into the record PlaceMap::ApplyAt takes. `type` is the map's
// feature type. A decoded AddPlace frame is valid with its SC/DC parts, counts, boxes and
// thumbnail; an InvalidFrame's reason is in frame.rejection. CORRUPTION as described above.
Result<MapLogRecord> DecodeMapRecord(std::string_view bytes, FeatureType type);

// The Shard.Search request's frame (proto/cluster.proto SearchRequest): the worker's processed
// query frame's SC part (bow, static features + direct index) and DC part (short-term tier).
// Other request fields (map, min_sequence, options, agent, time) are the caller's.
void FrameToSearchRequest(const ProcessedFrame& frame, v1::SearchRequest* request);
// And back on the shard, for PlaceMap::Search: CORRUPTION naming the field when a payload does
// not decode (or is of the other feature family than `type`); `frame` is then unspecified.
Status FrameFromSearchRequest(const v1::SearchRequest& request, FeatureType type,
                              ProcessedFrame* frame);

}  // namespace placedb::cluster
