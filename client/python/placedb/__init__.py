"""placedb: the Python SDK of the placedb place-recognition database (placedb.v1 over gRPC).

    import placedb
    with placedb.Client("127.0.0.1:50051") as client:
        client.create_map("lab")
        for result in client.ingest("lab", ["1.jpg", "2.jpg"], agent_id="robot-1"):
            print(result.index, result.stored, result.place_id)
        print(client.query("lab", "3.jpg", top_k=5).matches)

See client/python/README.md. The generated messages and stubs are in ``placedb._pb``
(``placedb._pb.placedb_pb2``): the SDK's own types are the dataclasses below.
"""

from placedb.client import TLS, Client
from placedb.errors import (
    AlreadyExists,
    Cancelled,
    DataLoss,
    DeadlineExceeded,
    Error,
    FailedPrecondition,
    Internal,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    ResourceExhausted,
    Unauthenticated,
    Unavailable,
)
from placedb.frames import Box, Depth, Frame
from placedb.results import (
    Counts,
    IngestResult,
    MapDamage,
    MapInfo,
    MapSummary,
    Match,
    Place,
    Pose,
    QueryResult,
    ScrubReport,
    ServerInfo,
    Timings,
    UsedBox,
    VocabularyInfo,
)
from placedb.settings import MapSettings

__all__ = [
    "AlreadyExists",
    "Box",
    "Cancelled",
    "Client",
    "Counts",
    "DataLoss",
    "DeadlineExceeded",
    "Depth",
    "Error",
    "FailedPrecondition",
    "Frame",
    "IngestResult",
    "Internal",
    "InvalidArgument",
    "MapDamage",
    "MapInfo",
    "MapSettings",
    "MapSummary",
    "Match",
    "NotFound",
    "PermissionDenied",
    "Place",
    "Pose",
    "QueryResult",
    "ResourceExhausted",
    "ScrubReport",
    "ServerInfo",
    "TLS",
    "Timings",
    "Unauthenticated",
    "Unavailable",
    "UsedBox",
    "VocabularyInfo",
]
