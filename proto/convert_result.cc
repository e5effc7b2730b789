#include "proto/convert_result.h"

#include <algorithm>
#include <cstring>
#include <optional>
#include <string>

#include "core/detect/detector.h"

namespace placedb::wire {

void CountsToProto(const FrameCounts& counts, v1::FrameCounts* out) {
  out->set_total(counts.total);
  out->set_dynamic(counts.dynamic);
  out->set_kept(counts.static_);
  out->set_dynamic_coverage(counts.dynamic_coverage);
  out->set_depth_removed(counts.depth_removed);
}

void BoxesToProto(const std::vector<DynamicBox>& boxes,
                  google::protobuf::RepeatedPtrField<v1::UsedBox>* out) {
  out->Reserve(int(boxes.size()));
  for (const DynamicBox& box : boxes) {
    v1::UsedBox* b = out->Add();
    b->set_class_id(box.class_id);
    b->set_class_name(CocoClassName(box.class_id));
    b->set_confidence(box.confidence);
    b->mutable_rect()->set_x(box.rect.x);
    b->mutable_rect()->set_y(box.rect.y);
    b->mutable_rect()->set_width(box.rect.width);
    b->mutable_rect()->set_height(box.rect.height);
  }
}

void MetadataToProto(const PlaceMetadata& metadata, v1::PlaceMetadata* out) {
  out->set_agent_id(metadata.agent_id);
  out->set_sequence(metadata.sequence);
  out->set_timestamp_ns(metadata.timestamp_ns);
  if (metadata.pose) {
    v1::Pose* p = out->mutable_pose();
    p->set_x(metadata.pose->position[0]);
    p->set_y(metadata.pose->position[1]);
    p->set_z(metadata.pose->position[2]);
    p->set_qx(metadata.pose->orientation[0]);
    p->set_qy(metadata.pose->orientation[1]);
    p->set_qz(metadata.pose->orientation[2]);
    p->set_qw(metadata.pose->orientation[3]);
  }
}

void MatchesToProto(const std::vector<Match>& matches,
                    google::protobuf::RepeatedPtrField<v1::Match>* out) {
  out->Reserve(int(matches.size()));
  for (const Match& match : matches) {
    v1::Match* m = out->Add();
    m->set_place_id(match.place);
    m->set_score(match.score);
    m->set_inliers(match.inliers);
    m->set_verified(match.verified);
    MetadataToProto(match.metadata, m->mutable_metadata());
    m->mutable_correspondences()->Reserve(int(match.correspondences.size()));
    for (const InlierPair& pair : match.correspondences) {
      v1::Correspondence* c = m->add_correspondences();
      c->set_query_keypoint(pair.query);
      c->set_place_keypoint(pair.candidate);
    }
    if (match.relative_pose) RelativePoseToProto(*match.relative_pose, m->mutable_relative_pose());
    m->set_pose_unavailable(match.pose_unavailable);
  }
}

void RelativePoseToProto(const RelativePose& pose, v1::RelativePose* out) {
  out->mutable_transform()->Add(pose.transform.begin(), pose.transform.end());
  out->set_metric(pose.metric);
  out->mutable_information()->Add(pose.information.begin(), pose.information.end());
  out->set_solver(PoseSolverName(pose.solver));
  out->set_correspondences(pose.correspondences);
  out->set_inliers(pose.inliers);
  out->set_rms_error_px(pose.rms_error_px);
}

void TimingsToProto(const StageTimings& t, double queue_ms, v1::StageTimings* out) {
  out->set_queue_ms(queue_ms);
  out->set_decode_ms(t.decode_ms);
  out->set_detect_ms(t.detect_ms);
  out->set_extract_ms(t.extract_ms);
  out->set_filter_ms(t.filter_ms);
  out->set_depth_ms(t.depth_ms);
  out->set_transform_ms(t.transform_ms);
  out->set_search_ms(t.search_ms);
  out->set_verify_ms(t.verify_ms);
  out->set_pose_ms(t.pose_ms);
  out->set_store_ms(t.store_ms);
  out->set_loop_closure_ms(t.loop_closure_ms);
  out->set_refine_ms(t.refine_ms);
  out->set_total_ms(t.total_ms);
}

void PlaceRecordToProto(const PlaceRecord& record, v1::Place* out) {
  out->set_place_id(record.id);
  MetadataToProto(record.metadata, out->mutable_metadata());
  CountsToProto(record.counts, out->mutable_counts());
  BoxesToProto(record.boxes_used, out->mutable_boxes_used());
}

void DepthStateToProto(const DepthFrameState& state, v1::DepthState* out) {
  out->set_frame(state.frame);
  out->set_mean_depth_m(state.mean_depth_m);
  out->set_static_level_m(state.static_level_m);
  out->set_difference_m(state.difference_m);
  out->set_count(state.count);
  out->set_warming_up(state.warming_up);
  out->set_deviating(state.deviating);
  out->set_removing(state.removing);
  if (state.removing) {
    out->set_band_near_m(state.band.near_m);
    out->set_band_far_m(state.band.far_m);
  }
  out->set_band_source(state.band_source);
  out->set_valid_fraction(state.valid_fraction);
}

void ThumbnailToProto(const Thumbnail& thumbnail, v1::Thumbnail* out) {
  out->set_jpeg(thumbnail.jpeg);
  out->set_width(thumbnail.width);
  out->set_height(thumbnail.height);
  out->set_source_width(thumbnail.source_width);
  out->set_source_height(thumbnail.source_height);
  KeypointListToProto(thumbnail.dropped_keypoints, out->mutable_dropped_keypoints());
}

void LoopClosureToProto(const LoopClosureOutcome& outcome, v1::LoopClosure* out) {
  out->set_merged(outcome.merged);
  out->set_place_id(outcome.place);
  out->set_loop_found(outcome.loop.has_value());
  if (outcome.loop) {
    out->set_loop_place_id(*outcome.loop);
    out->set_loop_posterior(outcome.loop_posterior);
  }
  out->set_best_place_id(outcome.best);
  out->set_best_posterior(outcome.best_posterior);
  out->set_candidates(uint32_t(outcome.candidates));
  out->set_retrieved(uint32_t(outcome.retrieved));
  out->set_transferred(uint32_t(outcome.transferred));
  out->set_replayed(uint32_t(outcome.replayed));
  out->set_loop_inliers(outcome.loop_inliers);
  out->set_loop_rejected(outcome.loop_rejected);
  out->set_rejected_place_id(outcome.rejected_loop);
  if (outcome.loop && outcome.loop_pose)
    RelativePoseToProto(*outcome.loop_pose, out->mutable_loop_pose());
  if (outcome.loop) out->set_loop_pose_unavailable(outcome.loop_pose_unavailable);
}

std::vector<Match> MatchesFromProto(const google::protobuf::RepeatedPtrField<v1::Match>& matches) {
  std::vector<Match> out;
  for (const v1::Match& in : matches) {
    Match& match = out.emplace_back();
    match.place = in.place_id();
    match.score = in.score();
    match.inliers = in.inliers();
    match.verified = in.verified();
    const v1::PlaceMetadata& m = in.metadata();
    match.metadata.agent_id = m.agent_id();
    match.metadata.sequence = m.sequence();
    match.metadata.timestamp_ns = m.timestamp_ns();
    if (m.has_pose()) {
      const v1::Pose& p = m.pose();
      match.metadata.pose = Pose{{p.x(), p.y(), p.z()}, {p.qx(), p.qy(), p.qz(), p.qw()}};
    }
    match.pose_unavailable = in.pose_unavailable();
    if (!in.has_relative_pose()) continue;
    const v1::RelativePose& p = in.relative_pose();
    std::optional<PoseSolver> solver;
    for (PoseSolver s :
         {PoseSolver::kPnpPlaceDepth, PoseSolver::kPnpQueryDepth, PoseSolver::kEssential}) {
      if (p.solver() == PoseSolverName(s)) solver = s;
    }
    if (p.transform_size() != 16 || p.information_size() != 36 || !solver) continue;
    RelativePose pose;
    std::copy(p.transform().begin(), p.transform().end(), pose.transform.begin());
    std::copy(p.information().begin(), p.information().end(), pose.information.begin());
    pose.metric = p.metric();
    pose.solver = *solver;
    pose.correspondences = p.correspondences();
    pose.inliers = p.inliers();
    pose.rms_error_px = p.rms_error_px();
    match.relative_pose = pose;
  }
  return out;
}

void LoopConstraintToProto(const LoopConstraint& c, v1::LoopConstraint* out) {
  out->set_sequence(c.sequence);
  out->set_source(c.source == LoopSource::kLoopClosure ? v1::LOOP_SOURCE_LOOP_CLOSURE
                                                       : v1::LOOP_SOURCE_MATCH);
  out->set_query_place_id(c.query_place);
  out->set_merged(c.merged);
  MetadataToProto(c.query, out->mutable_query());
  out->set_place_id(c.place);
  MetadataToProto(c.place_metadata, out->mutable_place());
  out->set_score(c.score);
  out->set_inliers(c.inliers);
  if (c.pose) {
    RelativePoseToProto(*c.pose, out->mutable_relative_pose());
  } else {
    out->set_pose_unavailable(c.pose_unavailable);
  }
  out->set_found_unix_ns(c.found_unix_ns);
}

}  // namespace placedb::wire
