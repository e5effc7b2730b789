#!/usr/bin/python3
"""A minimal placedb client for deploy/test-image.sh (Debian's python3-grpcio + python3-protobuf).

  grpc_probe.py health ADDRESS [--service NAME] [--wait SECONDS]
      grpc.health.v1.Health/Check; exit 0 only when SERVING (what `placedb health` does).
  grpc_probe.py load ADDRESS --proto-root DIR --map NAME --images DIR [--frames N] [--streams S]
      [--queries Q]: a small bounded load (resource measurements, deploy/README.md).
  grpc_probe.py smoke ADDRESS --proto-root DIR --map NAME --ingest IMG... --query IMG --expect IMG
      CreateMap, one Ingest stream of the --ingest images (encoded JPEG/PNG), then one Query;
      exit 0 when every frame was stored and the query's best match is the --expect image.
  grpc_probe.py places ADDRESS --proto-root DIR --map NAME
      prints the number of places of a map.
  grpc_probe.py call ADDRESS --proto-root DIR METHOD [--map NAME] --expect CODE
      one unary call (CreateMap, GetMap, DeleteMap, ListMaps, GetServerInfo) naming --map;
      exit 0 when it ends with the gRPC status CODE (OK, UNAUTHENTICATED, PERMISSION_DENIED...).

Every command takes the connection options: --tls (implied by --ca-cert) with --ca-cert PEM
(default: the system's roots), --cert/--key (a client certificate, for mutual TLS),
--server-name (the name the server certificate must carry, default the host of ADDRESS) and
--token (sent as `authorization: Bearer TOKEN`; default $PLACEDB_TOKEN).

The health check needs no generated code (the request and response are hand-encoded: both are
a single proto field). The other commands compile proto/placedb.proto with protoc into a
temporary directory. Traffic goes only to ADDRESS (use loopback addresses).
"""

import argparse
import atexit
import importlib
import os
import shutil
import subprocess
import sys
import tempfile
import time

import grpc

SERVING = 1
STATUS_NAMES = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}


def open_channel(args) -> grpc.Channel:
    """Plaintext, or TLS when --tls/--ca-cert/--cert is given."""
    if not (args.tls or args.ca_cert or args.cert):
        return grpc.insecure_channel(args.address)

    def read(path):
        if not path:
            return None
        with open(path, "rb") as f:
            return f.read()

    credentials = grpc.ssl_channel_credentials(root_certificates=read(args.ca_cert),
                                               private_key=read(args.key),
                                               certificate_chain=read(args.cert))
    options = []
    if args.server_name:
        options.append(("grpc.ssl_target_name_override", args.server_name))
    return grpc.secure_channel(args.address, credentials, options=options)


def call_metadata(args):
    """The bearer token of --token / $PLACEDB_TOKEN, as gRPC metadata (or none)."""
    return [("authorization", f"Bearer {args.token}")] if args.token else None


def encode_health_request(service: str) -> bytes:
    data = service.encode()
    if not data:
        return b""
    assert len(data) < 128
    return b"\x0a" + bytes([len(data)]) + data  # field 1 (string), length-delimited


def decode_health_response(data: bytes) -> int:
    # HealthCheckResponse { ServingStatus status = 1; }: tag 0x08 then a varint; absent = 0.
    if len(data) >= 2 and data[0] == 0x08:
        return data[1]
    return 0


def health(args) -> int:
    deadline = time.monotonic() + args.wait
    last = "no answer"
    while True:
        # A fresh channel per attempt: a channel that failed to connect backs off for seconds.
        with open_channel(args) as channel:
            check = channel.unary_unary(
                "/grpc.health.v1.Health/Check",
                request_serializer=lambda b: b,
                response_deserializer=lambda b: b,
            )
            try:
                status = decode_health_response(
                    check(encode_health_request(args.service), timeout=3))
                last = STATUS_NAMES.get(status, str(status))
                if status == SERVING:
                    print(f"health {args.address} service '{args.service}': SERVING")
                    return 0
            except grpc.RpcError as e:
                last = f"{e.code().name}: {e.details()}"
        if time.monotonic() >= deadline:
            break
        time.sleep(0.25)
    print(f"health {args.address} service '{args.service}': {last}", file=sys.stderr)
    return 1


def load_proto(proto_root: str):
    out = tempfile.mkdtemp(prefix="placedb-proto-")
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    subprocess.run(["protoc", f"--proto_path={proto_root}", f"--python_out={out}",
                    os.path.join(proto_root, "proto", "placedb.proto")], check=True)
    sys.path.insert(0, out)
    return importlib.import_module("proto.placedb_pb2")


def smoke(args) -> int:
    pb = load_proto(args.proto_root)
    service = "/placedb.v1.PlaceDb/"
    metadata = call_metadata(args)
    with open_channel(args) as channel:
        def unary(method, response_type):
            call = channel.unary_unary(service + method,
                                       request_serializer=lambda m: m.SerializeToString(),
                                       response_deserializer=response_type.FromString)
            return lambda request, timeout: call(request, timeout=timeout, metadata=metadata)

        info = unary("GetServerInfo", pb.ServerInfo)(pb.GetServerInfoRequest(), timeout=10)
        print(f"server {info.version}: vocabularies "
              f"{[(v.name, v.words) for v in info.vocabularies]}, detector '{info.detector}', "
              f"{info.limits.worker_threads} workers")
        created = unary("CreateMap", pb.MapDescription)(pb.CreateMapRequest(name=args.map),
                                                          timeout=30)
        print(f"CreateMap {created.name}: vocabulary {created.config.vocabulary} "
              f"(checksum {created.vocabulary_checksum})")

        def observation(path, sequence):
            with open(path, "rb") as f:
                return pb.Observation(agent_id="test-image", sequence=sequence,
                                      timestamp_ns=time.time_ns(),
                                      encoded_image=pb.EncodedImage(data=f.read()))

        def requests():
            yield pb.IngestRequest(header=pb.IngestHeader(map=args.map))
            for i, path in enumerate(args.ingest):
                yield pb.IngestRequest(observation=observation(path, i))

        ingest = channel.stream_stream(service + "Ingest",
                                       request_serializer=lambda m: m.SerializeToString(),
                                       response_deserializer=pb.IngestResponse.FromString)
        place_of = {}
        failures = 0
        for response in ingest(requests(), timeout=120, metadata=metadata):
            path = args.ingest[response.index]
            if response.stored:
                place_of[response.place_id] = path
                print(f"Ingest {os.path.basename(path)}: place {response.place_id}, "
                      f"{response.counts.kept}/{response.counts.total} descriptors kept, "
                      f"{response.timings.total_ms:.1f} ms")
            else:
                failures += 1
                why = response.rejection or response.error.message
                print(f"Ingest {os.path.basename(path)}: NOT stored: {why}", file=sys.stderr)
        if failures or len(place_of) != len(args.ingest):
            print(f"smoke: {len(place_of)} of {len(args.ingest)} frames stored", file=sys.stderr)
            return 1

        result = unary("Query", pb.QueryResponse)(
            pb.QueryRequest(map=args.map, observation=observation(args.query, 0),
                            options=pb.MatchOptions(top_k=3)), timeout=60)
        ranked = [(place_of.get(m.place_id, "?"), m.score) for m in result.matches]
        print(f"Query {os.path.basename(args.query)}: " + ", ".join(
            f"{os.path.basename(p)} {s:.3f}" for p, s in ranked) +
            f" ({result.timings.total_ms:.1f} ms)")
        if not ranked or os.path.basename(ranked[0][0]) != os.path.basename(args.expect):
            print(f"smoke: expected {args.expect} first", file=sys.stderr)
            return 1

        described = unary("GetMap", pb.MapDescription)(pb.GetMapRequest(name=args.map),
                                                         timeout=10)
        print(f"GetMap {args.map}: {described.stats.places} places, "
              f"{described.stats.bytes_on_disk} bytes on disk")
        if described.stats.places != len(args.ingest):
            print("smoke: GetMap disagrees with the ingest", file=sys.stderr)
            return 1
    return 0


def places(args) -> int:
    """Prints the number of places of a map (after a restart: durability)."""
    pb = load_proto(args.proto_root)
    with open_channel(args) as channel:
        get = channel.unary_unary("/placedb.v1.PlaceDb/GetMap",
                                  request_serializer=lambda m: m.SerializeToString(),
                                  response_deserializer=pb.MapDescription.FromString)
        print(get(pb.GetMapRequest(name=args.map), timeout=10,
                  metadata=call_metadata(args)).stats.places)
    return 0


def call(args) -> int:
    """One unary call; exit 0 when its status code is --expect."""
    pb = load_proto(args.proto_root)
    requests = {
        "CreateMap": (pb.CreateMapRequest(name=args.map), pb.MapDescription),
        "GetMap": (pb.GetMapRequest(name=args.map), pb.MapDescription),
        "DeleteMap": (pb.DeleteMapRequest(name=args.map), pb.DeleteMapResponse),
        "ListMaps": (pb.ListMapsRequest(), pb.ListMapsResponse),
        "GetServerInfo": (pb.GetServerInfoRequest(), pb.ServerInfo),
    }
    request, response_type = requests[args.method]
    with open_channel(args) as channel:
        unary = channel.unary_unary("/placedb.v1.PlaceDb/" + args.method,
                                    request_serializer=lambda m: m.SerializeToString(),
                                    response_deserializer=response_type.FromString)
        try:
            unary(request, timeout=30, metadata=call_metadata(args))
            code, details = "OK", ""
        except grpc.RpcError as e:
            code, details = e.code().name, e.details()
    print(f"{args.method} {args.map}: {code}{': ' + details if details else ''}")
    if code != args.expect:
        print(f"call: expected {args.expect}", file=sys.stderr)
        return 1
    return 0


def load(args) -> int:
    """Small, bounded load: --streams Ingest streams splitting --frames images of --images between
    them, and --queries Query calls (after the ingest) cycling over the same images."""
    import threading
    pb = load_proto(args.proto_root)
    images = sorted(os.path.join(args.images, f) for f in os.listdir(args.images)
                    if f.lower().endswith((".jpg", ".jpeg", ".png")))[: args.frames]
    data = [open(p, "rb").read() for p in images]
    service = "/placedb.v1.PlaceDb/"
    stored = [0] * args.streams
    metadata = call_metadata(args)
    with open_channel(args) as channel:
        create = channel.unary_unary(service + "CreateMap",
                                     request_serializer=lambda m: m.SerializeToString(),
                                     response_deserializer=pb.MapDescription.FromString)
        try:
            create(pb.CreateMapRequest(name=args.map), timeout=30, metadata=metadata)
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.ALREADY_EXISTS:
                raise

        def stream(k):
            def requests():
                yield pb.IngestRequest(header=pb.IngestHeader(map=args.map))
                for i in range(k, len(data), args.streams):
                    yield pb.IngestRequest(observation=pb.Observation(
                        agent_id=f"load-{k}", sequence=i,
                        encoded_image=pb.EncodedImage(data=data[i])))
            ingest = channel.stream_stream(service + "Ingest",
                                           request_serializer=lambda m: m.SerializeToString(),
                                           response_deserializer=pb.IngestResponse.FromString)
            for response in ingest(requests(), timeout=args.timeout, metadata=metadata):
                stored[k] += response.stored

        start = time.monotonic()
        threads = [threading.Thread(target=stream, args=(k,)) for k in range(args.streams)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        ingest_s = time.monotonic() - start
        query = channel.unary_unary(service + "Query",
                                    request_serializer=lambda m: m.SerializeToString(),
                                    response_deserializer=pb.QueryResponse.FromString)
        start = time.monotonic()
        for i in range(args.queries):
            query(pb.QueryRequest(map=args.map, observation=pb.Observation(
                encoded_image=pb.EncodedImage(data=data[(i * 7) % len(data)])),
                options=pb.MatchOptions(top_k=5)), timeout=30, metadata=metadata)
        query_s = time.monotonic() - start
    print(f"load: {sum(stored)}/{len(data)} frames stored by {args.streams} streams in "
          f"{ingest_s:.1f} s ({len(data) / ingest_s:.1f} frames/s); {args.queries} queries in "
          f"{query_s:.1f} s ({args.queries / max(query_s, 1e-9):.1f} /s)")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    h = sub.add_parser("health")
    h.add_argument("address")
    h.add_argument("--service", default="")
    h.add_argument("--wait", type=float, default=0, help="retry for this many seconds")
    s = sub.add_parser("smoke")
    s.add_argument("address")
    s.add_argument("--proto-root", required=True)
    s.add_argument("--map", required=True)
    s.add_argument("--ingest", nargs="+", required=True)
    s.add_argument("--query", required=True)
    s.add_argument("--expect", required=True)
    p = sub.add_parser("places")
    p.add_argument("address")
    p.add_argument("--proto-root", required=True)
    p.add_argument("--map", required=True)
    lo = sub.add_parser("load")
    lo.add_argument("address")
    lo.add_argument("--proto-root", required=True)
    lo.add_argument("--map", required=True)
    lo.add_argument("--images", required=True, help="a directory of JPEG/PNG frames")
    lo.add_argument("--frames", type=int, default=200)
    lo.add_argument("--streams", type=int, default=2)
    lo.add_argument("--queries", type=int, default=50)
    lo.add_argument("--timeout", type=float, default=600)
    c = sub.add_parser("call")
    c.add_argument("address")
    c.add_argument("--proto-root", required=True)
    c.add_argument("method", choices=["CreateMap", "GetMap", "DeleteMap", "ListMaps",
                                      "GetServerInfo"])
    c.add_argument("--map", default="")
    c.add_argument("--expect", required=True, help="a gRPC status code name, e.g. OK")
    for command in (h, s, p, lo, c):
        command.add_argument("--tls", action="store_true", help="connect with TLS")
        command.add_argument("--ca-cert", help="PEM roots for TLS (implies --tls)")
        command.add_argument("--cert", help="PEM client certificate (mutual TLS)")
        command.add_argument("--key", help="PEM key of --cert")
        command.add_argument("--server-name", help="the name the server certificate must carry")
        command.add_argument("--token", default=os.environ.get("PLACEDB_TOKEN", ""),
                             help="bearer token (default: $PLACEDB_TOKEN)")
    args = parser.parse_args()
    return {"health": health, "smoke": smoke, "places": places, "load": load,
            "call": call}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
