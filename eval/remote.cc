#include "eval/remote.h"

#include <unistd.h>

#include <chrono>
#include <opencv2/imgcodecs.hpp>
#include <optional>

#include "client/connection.h"
#include "client/ingest_stream.h"
#include "core/base/files.h"
#include "core/base/timing.h"
#include "proto/convert_config.h"
#include "proto/convert_frame.h"
#include "proto/status.h"

namespace placedb::eval {

namespace {

namespace v1 = ::placedb::v1;

// The grid point's whole configuration, so the server runs what the in-process backend runs
// (scoring, refinement, short-term tier, ...). Boxes always come with the observations, as in
// process: the harness supplies them (oracle files or its own detector), so the box source is the
// agent's; filtering off is detection off.
v1::MapConfig ToProto(const DatabaseConfig& config, bool filtering) {
  MapOptions options;
  options.database = config;
  const wire::ServiceMapSettings settings{.box_source = BoxSource::kAgent,
                                          .detection_enabled = filtering};
  v1::MapConfig map;
  wire::MapConfigToProto(options, settings, /*vocabulary_name=*/"", &map);
  return map;
}

class ServerBackend final : public Backend {
 public:
  explicit ServerBackend(client::Connection connection) : connection_(std::move(connection)) {}

  std::string Name() const override { return "server " + connection_.options().address; }

  Status Prepare(const EvalInputs& inputs, int /*features*/) override {
    if (prepared_) return Status::Ok();
    const Dataset& dataset = *inputs.dataset;
    for (int list = 0; list < 2; ++list) {
      const std::vector<Entry>& entries = list == 0 ? dataset.database : dataset.queries;
      const std::vector<DynamicObjects>& dynamic =
          list == 0 ? inputs.database_dynamic : inputs.query_dynamic;
      auto& images = list == 0 ? database_images_ : query_images_;
      auto& masks = list == 0 ? database_masks_ : query_masks_;
      for (size_t i = 0; i < entries.size(); ++i) {
        auto bytes = ReadWholeFile(dataset.Resolve(entries[i].image));
        if (!bytes.ok()) return bytes.status();
        images.push_back(std::move(bytes).value());
        std::string png;
        if (!dynamic[i].mask.empty()) {
          std::vector<uchar> encoded;
          if (!cv::imencode(".png", dynamic[i].mask, encoded)) {
            return Status::Internal("cannot encode the mask of " + entries[i].id);
          }
          png.assign(encoded.begin(), encoded.end());
        }
        masks.push_back(std::move(png));
      }
    }
    prepared_ = true;
    return Status::Ok();
  }

  Result<MethodRun> Run(const EvalInputs& inputs, const DatabaseConfig& config, bool filtering,
                        size_t top_k) override {
    const Dataset& dataset = *inputs.dataset;
    const std::string map =
        "placedb-eval-" + std::to_string(::getpid()) + "-" + std::to_string(counter_++);
    {
      auto context = connection_.NewContext();
      v1::CreateMapRequest request;
      request.set_name(map);
      *request.mutable_config() = ToProto(config, filtering);
      v1::MapDescription description;
      PLACEDB_RETURN_IF_ERROR(wire::FromGrpc(
          connection_.stub()->CreateMap(context.get(), request, &description), "CreateMap " + map));
    }
    Status result = Fill(inputs, map, filtering);
    MethodRun run;
    if (result.ok()) {
      auto context = connection_.NewContext();
      v1::GetMapRequest request;
      request.set_name(map);
      v1::MapDescription description;
      result = wire::FromGrpc(connection_.stub()->GetMap(context.get(), request, &description),
                              "GetMap " + map);
      const v1::MapStats& stats = description.stats();
      run.database.places = stats.places();
      run.database.invalid = stats.invalid_rejected();
      run.database.descriptors_kept = stats.descriptors_kept();
      run.database.descriptors_dropped = stats.descriptors_dropped();
      run.database.disk_bytes = stats.bytes_on_disk();
      run.database.memory_bytes = stats.bytes_in_memory();
      run.database.build_seconds = build_seconds_;
    }
    const bool verification = config.verification.mode != VerificationMode::kDisabled;
    for (size_t q = 0; result.ok() && q < dataset.queries.size(); ++q) {
      auto context = connection_.NewContext();
      v1::QueryRequest request;
      request.set_map(map);
      *request.mutable_observation() = Observe(inputs, q, true, filtering);
      request.mutable_options()->set_top_k(uint32_t(top_k));
      v1::QueryResponse response;
      Stopwatch watch;
      result = wire::FromGrpc(connection_.stub()->Query(context.get(), request, &response),
                              "Query " + dataset.queries[q].id);
      const double ms = watch.ElapsedMs();
      if (!result.ok()) break;
      std::vector<RankedMatch> ranked;
      for (const v1::Match& match : response.matches()) {
        ranked.push_back(
            {int(match.metadata().sequence()), match.score(), match.verified(), match.inliers()});
      }
      QueryOutcome outcome = ScoreQuery(ranked, inputs.truth[q], verification);
      outcome.valid = response.valid();
      outcome.latency_ms = ms;
      outcome.match_ms = response.timings().search_ms() + response.timings().verify_ms();
      outcome.kept = response.counts().kept();
      outcome.dropped = response.counts().dynamic();
      run.queries.push_back(outcome);
    }
    {
      auto context = connection_.NewContext();
      v1::DeleteMapRequest request;
      request.set_name(map);
      v1::DeleteMapResponse response;
      const Status deleted = wire::FromGrpc(
          connection_.stub()->DeleteMap(context.get(), request, &response), "DeleteMap " + map);
      if (result.ok()) result = deleted;
    }
    if (!result.ok()) return result;
    return run;
  }

 private:
  v1::Observation Observe(const EvalInputs& inputs, size_t i, bool query, bool filtering) const {
    const Entry& entry = query ? inputs.dataset->queries[i] : inputs.dataset->database[i];
    v1::Observation o;
    o.set_agent_id(entry.agent);
    o.set_sequence(uint64_t(i));  // the database index: how matches map back
    o.set_timestamp_ns(entry.timestamp_ns);
    o.mutable_encoded_image()->set_data(query ? query_images_[i] : database_images_[i]);
    if (filtering) {
      const DynamicObjects& dynamic = query ? inputs.query_dynamic[i] : inputs.database_dynamic[i];
      for (const DynamicBox& box : dynamic.boxes) wire::AgentBoxToProto(box, o.add_boxes());
      const std::string& mask = query ? query_masks_[i] : database_masks_[i];
      if (!mask.empty()) o.set_dynamic_mask_png(mask);
    }
    return o;
  }

  // One Ingest stream with every database entry, in order. The window is the whole database: the
  // server's backpressure alone paces the stream, so build_seconds measures the server.
  Status Fill(const EvalInputs& inputs, const std::string& map, bool filtering) {
    const Dataset& dataset = *inputs.dataset;
    const size_t count = dataset.database.size();
    v1::IngestHeader header;
    header.set_map(map);
    size_t sent = 0;
    size_t answered = 0;
    Status first_error;
    Stopwatch watch;
    const grpc::Status finished = client::IngestStream::Run(
        connection_, header, /*window=*/count,
        [&](client::Outgoing* next) {
          if (sent == count) return false;
          next->observation = Observe(inputs, sent, false, filtering);
          next->tag = sent++;
          return true;
        },
        [&](const client::Answered& answer) {
          ++answered;
          if (answer.response.has_error() && first_error.ok()) {
            first_error = wire::FromProto(answer.response.error(),
                                          "ingesting " + dataset.database[answer.tag].id);
          }
        });
    build_seconds_ = watch.ElapsedMs() / 1000.0;
    PLACEDB_RETURN_IF_ERROR(wire::FromGrpc(finished, "Ingest into " + map));
    PLACEDB_RETURN_IF_ERROR(first_error);
    if (answered != count) {
      return Status::Internal("Ingest into " + map + ": " + std::to_string(answered) + " of " +
                              std::to_string(count) + " answered");
    }
    return Status::Ok();
  }

  const client::Connection connection_;
  bool prepared_ = false;
  std::vector<std::string> database_images_, query_images_;
  std::vector<std::string> database_masks_, query_masks_;
  int counter_ = 0;
  double build_seconds_ = 0;
};

}  // namespace

Result<std::unique_ptr<Backend>> MakeServerBackend(
    const std::string& address, std::shared_ptr<const Vocabulary> local_vocabulary,
    const std::function<void(const std::string&)>& log) {
  client::ConnectionOptions options;
  options.address = address;
  return MakeServerBackend(std::move(options), std::move(local_vocabulary), log);
}

Result<std::unique_ptr<Backend>> MakeServerBackend(
    client::ConnectionOptions options, std::shared_ptr<const Vocabulary> local_vocabulary,
    const std::function<void(const std::string&)>& log) {
  // No deadline on the backend's calls (a query takes what it takes); only the first call waits
  // at most 10 s for the server to come up.
  const std::string address = options.address;
  options.timeout_s = 0;
  std::string error;
  std::optional<client::Connection> connection = client::Connection::Open(options, &error);
  if (!connection) return Status::FailedPrecondition(error);
  auto context = connection->NewContext();
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  context->set_wait_for_ready(true);
  v1::GetServerInfoRequest request;
  v1::ServerInfo info;
  const grpc::Status status = connection->stub()->GetServerInfo(context.get(), request, &info);
  if (!status.ok()) {
    return Status::FailedPrecondition("placedb-server at " + address +
                                      " does not answer: " + status.error_message());
  }
  if (local_vocabulary && log) {
    for (const v1::VocabularyInfo& vocabulary : info.vocabularies()) {
      if (vocabulary.name() == "default" &&
          vocabulary.checksum() != local_vocabulary->checksum_hex()) {
        log("warning: the server's default vocabulary (" + vocabulary.checksum() +
            ") is not the local one (" + local_vocabulary->checksum_hex() +
            "): figures will not compare with in-process runs");
      }
    }
  }
  return std::unique_ptr<Backend>(new ServerBackend(std::move(*connection)));
}

}  // namespace placedb::eval
