#include "client/commands/loops.h"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <ostream>
#include <set>

#include "client/commands/common.h"
#include "client/format.h"

namespace placedb::client {

namespace {

// Reads the log (WatchLoopClosures) and hands each constraint to `each` (false: stop).
grpc::Status ReadLog(const Connection& connection, const LoopsFlags& flags, bool follow,
                     const std::function<bool(const v1::LoopConstraint&)>& each) {
  auto context = connection.NewContext(/*unary=*/false);
  v1::WatchLoopClosuresRequest request;
  request.set_map(flags.map);
  request.set_from_sequence(flags.from);
  request.set_follow(follow);
  for (const std::string& agent : flags.agents) request.add_agents(agent);
  request.set_inter_agent_only(flags.inter_agent_only);
  request.set_min_sequence_gap(flags.min_sequence_gap);
  auto reader = connection.stub()->WatchLoopClosures(context.get(), request);
  v1::LoopConstraint constraint;
  bool stopped = false;
  while (reader->Read(&constraint)) {
    if (constraint.sequence() == 0) continue;  // caught up: nothing to show
    if (!each(constraint)) {
      stopped = true;
      context->TryCancel();
      break;
    }
  }
  const grpc::Status status = reader->Finish();
  return stopped ? grpc::Status::OK : status;
}

std::string FrameText(const v1::PlaceMetadata& frame, uint32_t place) {
  return (frame.agent_id().empty() ? std::string("-") : frame.agent_id()) + "/" +
         std::to_string(frame.sequence()) + " (place " + std::to_string(place) + ")";
}

const char* SourceName(v1::LoopSource source) {
  return source == v1::LOOP_SOURCE_LOOP_CLOSURE ? "loop" : "match";
}

// A place's pose as its agent sent it: x y z qx qy qz qw (identity when none).
std::array<double, 7> VertexPose(const v1::PlaceMetadata& frame) {
  if (!frame.has_pose()) return {0, 0, 0, 0, 0, 0, 1};
  const v1::Pose& p = frame.pose();
  if (p.qx() == 0 && p.qy() == 0 && p.qz() == 0 && p.qw() == 0) {
    return {p.x(), p.y(), p.z(), 0, 0, 0, 1};  // all-zero quaternion: identity
  }
  return {p.x(), p.y(), p.z(), p.qx(), p.qy(), p.qz(), p.qw()};
}

bool Metric(const v1::LoopConstraint& c) {
  return c.has_relative_pose() && c.relative_pose().metric() &&
         c.relative_pose().transform_size() == 16 && c.relative_pose().information_size() == 36;
}

std::string Number(double value) {
  char text[32];
  std::snprintf(text, sizeof text, "%.9g", value);
  return text;
}

void WriteG2o(const std::vector<v1::LoopConstraint>& log, std::ostream& out) {
  std::map<uint32_t, std::array<double, 7>> vertices;
  for (const v1::LoopConstraint& c : log) {
    if (!Metric(c)) continue;
    vertices.emplace(c.place_id(), VertexPose(c.place()));
    vertices.emplace(c.query_place_id(), VertexPose(c.query()));
  }
  out << "# placedb loop constraints: vertices are place ids at the poses their agents sent "
         "(identity when none); edges T_place_query\n";
  for (const auto& [id, p] : vertices) {
    out << "VERTEX_SE3:QUAT " << id;
    for (double v : p) out << ' ' << Number(v);
    out << '\n';
  }
  for (const v1::LoopConstraint& c : log) {
    if (!Metric(c)) continue;
    const auto& t = c.relative_pose().transform();
    const auto q = QuaternionOf(t.data());
    out << "EDGE_SE3:QUAT " << c.place_id() << ' ' << c.query_place_id() << ' ' << Number(t[3])
        << ' ' << Number(t[7]) << ' ' << Number(t[11]);
    for (double v : q) out << ' ' << Number(v);
    // g2o's rotation error is the quaternion's vector part, about half the rotation vector: the
    // rotation rows and columns scale by 2.
    const auto& info = c.relative_pose().information();
    for (int i = 0; i < 6; ++i) {
      for (int j = i; j < 6; ++j) {
        const double scale = (i >= 3 ? 2.0 : 1.0) * (j >= 3 ? 2.0 : 1.0);
        out << ' ' << Number(info[i * 6 + j] * scale);
      }
    }
    out << '\n';
  }
}

void WriteTum(const std::vector<v1::LoopConstraint>& log, std::ostream& out) {
  out << "# placedb loop constraints: t_place t_query tx ty tz qx qy qz qw (T_place_query; "
         "capture times in seconds)\n";
  for (const v1::LoopConstraint& c : log) {
    if (!Metric(c)) continue;
    const auto& t = c.relative_pose().transform();
    const auto q = QuaternionOf(t.data());
    char times[64];
    std::snprintf(times, sizeof times, "%.6f %.6f", double(c.place().timestamp_ns()) * 1e-9,
                  double(c.query().timestamp_ns()) * 1e-9);
    out << times << ' ' << Number(t[3]) << ' ' << Number(t[7]) << ' ' << Number(t[11]);
    for (double v : q) out << ' ' << Number(v);
    out << '\n';
  }
}

std::string CsvField(const std::string& text) {
  if (text.find_first_of(",\"\n") == std::string::npos) return text;
  std::string quoted = "\"";
  for (char ch : text) quoted += ch == '"' ? std::string("\"\"") : std::string(1, ch);
  return quoted + "\"";
}

void WriteCsv(const std::vector<v1::LoopConstraint>& log, std::ostream& out) {
  out << "sequence,source,query_place_id,merged,query_agent,query_sequence,query_timestamp_ns,"
         "place_id,place_agent,place_sequence,place_timestamp_ns,score,inliers,metric,solver,tx,"
         "ty,tz,qx,qy,qz,qw,rms_error_px";
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < 6; ++j) out << ",info_" << i << j;
  }
  out << ",pose_unavailable\n";
  for (const v1::LoopConstraint& c : log) {
    out << c.sequence() << ',' << SourceName(c.source()) << ',' << c.query_place_id() << ','
        << (c.merged() ? 1 : 0) << ',' << CsvField(c.query().agent_id()) << ','
        << c.query().sequence() << ',' << c.query().timestamp_ns() << ',' << c.place_id() << ','
        << CsvField(c.place().agent_id()) << ',' << c.place().sequence() << ','
        << c.place().timestamp_ns() << ',' << Number(c.score()) << ',' << c.inliers();
    const bool posed = c.has_relative_pose() && c.relative_pose().transform_size() == 16 &&
                       c.relative_pose().information_size() == 36;
    if (posed) {
      const v1::RelativePose& p = c.relative_pose();
      const auto q = QuaternionOf(p.transform().data());
      out << ',' << (p.metric() ? 1 : 0) << ',' << p.solver() << ',' << Number(p.transform(3))
          << ',' << Number(p.transform(7)) << ',' << Number(p.transform(11));
      for (double v : q) out << ',' << Number(v);
      out << ',' << Number(p.rms_error_px());
      for (double v : p.information()) out << ',' << Number(v);
    } else {
      out << ",,";
      for (int i = 0; i < 8 + 36; ++i) out << ',';
    }
    out << ',' << CsvField(c.pose_unavailable()) << '\n';
  }
}

}  // namespace

std::array<double, 4> QuaternionOf(const double* m) {
  // Shepperd's method on R = m[0..2], m[4..6], m[8..10]: the largest of 4 candidates divides.
  const double r00 = m[0], r01 = m[1], r02 = m[2], r10 = m[4], r11 = m[5], r12 = m[6], r20 = m[8],
               r21 = m[9], r22 = m[10];
  const double trace = r00 + r11 + r22;
  double qx, qy, qz, qw;
  if (trace > r00 && trace > r11 && trace > r22) {
    const double s = std::sqrt(1.0 + trace) * 2;
    qw = 0.25 * s;
    qx = (r21 - r12) / s;
    qy = (r02 - r20) / s;
    qz = (r10 - r01) / s;
  } else if (r00 > r11 && r00 > r22) {
    const double s = std::sqrt(1.0 + r00 - r11 - r22) * 2;
    qw = (r21 - r12) / s;
    qx = 0.25 * s;
    qy = (r01 + r10) / s;
    qz = (r02 + r20) / s;
  } else if (r11 > r22) {
    const double s = std::sqrt(1.0 + r11 - r00 - r22) * 2;
    qw = (r02 - r20) / s;
    qx = (r01 + r10) / s;
    qy = 0.25 * s;
    qz = (r12 + r21) / s;
  } else {
    const double s = std::sqrt(1.0 + r22 - r00 - r11) * 2;
    qw = (r10 - r01) / s;
    qx = (r02 + r20) / s;
    qy = (r12 + r21) / s;
    qz = 0.25 * s;
  }
  const double norm = std::sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
  const double sign = qw < 0 ? -1.0 : 1.0;
  return {sign * qx / norm, sign * qy / norm, sign * qz / norm, sign * qw / norm};
}

LoopsCommands RegisterLoops(CLI::App& app, LoopsFlags* flags) {
  LoopsCommands commands;
  CLI::App* loops = app.add_subcommand("loops",
                                       "a map's loop-closure constraints (verified matches found "
                                       "while ingesting, with relative poses)");
  loops->require_subcommand(1);
  auto add_filters = [flags](CLI::App* command) {
    command->add_option("MAP", flags->map, "map name")->required();
    command->add_option("--from", flags->from, "the first sequence (default 1: the log's start)");
    command->add_option("--agent", flags->agents,
                        "only constraints with this agent on either side (repeatable)");
    command->add_flag("--inter-agent-only", flags->inter_agent_only,
                      "only constraints between two different agents");
    command->add_option("--min-sequence-gap", flags->min_sequence_gap,
                        "within one agent, only frames at least this many sequence numbers "
                        "apart (0: all)");
  };
  commands.watch = loops->add_subcommand("watch", "print the constraints (--json: JSON lines)");
  add_filters(commands.watch);
  commands.watch->add_flag("--follow", flags->follow,
                           "keep waiting for new constraints (Ctrl-C to stop)");
  commands.export_ =
      loops->add_subcommand("export", "write the constraints for a pose-graph optimiser");
  add_filters(commands.export_);
  commands.export_->add_option("--format", flags->format, "g2o, tum or csv")
      ->required()
      ->check(CLI::IsMember({"g2o", "tum", "csv"}));
  commands.export_->add_option("--out", flags->out, "the file to write (default: stdout)");
  return commands;
}

int LoopsWatch(const Connection& connection, const LoopsFlags& flags, bool json, CliIo& io) {
  const grpc::Status status =
      ReadLog(connection, flags, flags.follow, [&](const v1::LoopConstraint& c) {
        if (json) {
          io.out << ProtoJson(c, /*one_line=*/true) << '\n';
        } else {
          io.out << '#' << c.sequence() << ' ' << SourceName(c.source()) << ' '
                 << FrameText(c.query(), c.query_place_id()) << " -> "
                 << FrameText(c.place(), c.place_id()) << ", score " << FormatDouble(c.score(), 3)
                 << ", " << c.inliers() << " inliers, "
                 << (c.has_relative_pose() ? "pose " + FormatRelativePose(c.relative_pose())
                                           : "no pose: " + c.pose_unavailable())
                 << '\n';
        }
        io.out.flush();
        return bool(io.out);
      });
  if (!status.ok()) return RpcFailed(io, status);
  return kExitOk;
}

int LoopsExport(const Connection& connection, const LoopsFlags& flags, CliIo& io) {
  std::vector<v1::LoopConstraint> log;
  const grpc::Status status =
      ReadLog(connection, flags, /*follow=*/false, [&](const v1::LoopConstraint& c) {
        log.push_back(c);
        return true;
      });
  if (!status.ok()) return RpcFailed(io, status);
  std::ofstream file;
  const bool to_stdout = flags.out.empty() || flags.out == "-";
  if (!to_stdout) {
    file.open(flags.out, std::ios::binary | std::ios::trunc);
    if (!file) return UsageError(io, "cannot write " + flags.out);
  }
  std::ostream& out = to_stdout ? io.out : file;
  if (flags.format == "g2o") {
    WriteG2o(log, out);
  } else if (flags.format == "tum") {
    WriteTum(log, out);
  } else {
    WriteCsv(log, out);
  }
  out.flush();
  if (!out) return UsageError(io, "writing " + (to_stdout ? std::string("stdout") : flags.out));
  const size_t metric = size_t(std::count_if(log.begin(), log.end(), Metric));
  io.err << "exported " << (flags.format == "csv" ? log.size() : metric) << " of " << log.size()
         << " constraints of map '" << flags.map << "'";
  if (flags.format != "csv" && metric < log.size()) {
    io.err << " (" << log.size() - metric
           << " without a metric pose left out: no camera, or no depth on either side; csv "
              "has them all)";
  }
  io.err << '\n';
  return kExitOk;
}

}  // namespace placedb::client
