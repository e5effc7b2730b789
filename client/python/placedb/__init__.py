"""placedb: the Python SDK of the placedb place-recognition database (placedb.v1 over gRPC).

    import placedb
    with placedb.Client("127.0.0.1:50051") as client:
        client.create_map("lab")
        for result in client.ingest("lab", ["1.jpg", "2.jpg"], agent_id="robot-1"):
            print(result.index, result.stored, result.place_id)
        print(client.query("lab", "3.jpg", top_k=5).matches)

See client/python/README.md. The generated messages and stubs are in ``placedb._pb``
(``placedb._pb.placedb_pb2``): the SDK's own types are the dataclasses below. The asyncio client
is :class:`placedb.aio.AsyncClient`; recordings (ROS 1 bags, TUM RGB-D folders) are read by
:func:`read_bag` and :func:`read_tum` (:mod:`placedb.recordings`).
"""

#: The package's version: placedb's (CMakeLists.txt, project(placedb VERSION ...)).
__version__ = "0.1.0"

from placedb.aio import AsyncClient
from placedb.client import CLIENT_TIMEOUT, TLS, Client
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
from placedb.frames import Box, Camera, Depth, Frame, MatchOptions
from placedb.recordings import Recording, RecordingStats, read_bag, read_tum
from placedb.results import (
    AgentActivity,
    ClassCount,
    Counts,
    DepthState,
    Dynamics,
    DynamicStatistics,
    FrameRef,
    HourCoverage,
    IngestResult,
    LoopClosure,
    LoopConstraint,
    MapDamage,
    MapInfo,
    MapVocabulary,
    MapSummary,
    Match,
    Place,
    PlacePage,
    Pose,
    QueryResult,
    RankedPlace,
    RelativePose,
    ScrubReport,
    ServerInfo,
    Snapshot,
    Thumbnail,
    Timings,
    UsedBox,
    VocabularyInfo,
)
from placedb.settings import (
    DepthSettings,
    LoopClosureSettings,
    MapSettings,
    ShortTermSettings,
    SiftSettings,
    ThumbnailSettings,
)

__all__ = [
    "AgentActivity",
    "AlreadyExists",
    "AsyncClient",
    "Box",
    "CLIENT_TIMEOUT",
    "Cancelled",
    "ClassCount",
    "Client",
    "Counts",
    "DataLoss",
    "DeadlineExceeded",
    "Camera",
    "Depth",
    "DepthSettings",
    "DepthState",
    "DynamicStatistics",
    "Dynamics",
    "Error",
    "FailedPrecondition",
    "Frame",
    "FrameRef",
    "HourCoverage",
    "IngestResult",
    "Internal",
    "InvalidArgument",
    "LoopClosure",
    "LoopClosureSettings",
    "LoopConstraint",
    "MapDamage",
    "MapInfo",
    "MapVocabulary",
    "MapSettings",
    "MapSummary",
    "Match",
    "RelativePose",
    "MatchOptions",
    "NotFound",
    "PermissionDenied",
    "Place",
    "PlacePage",
    "Pose",
    "QueryResult",
    "RankedPlace",
    "Recording",
    "RecordingStats",
    "ResourceExhausted",
    "ScrubReport",
    "ServerInfo",
    "ShortTermSettings",
    "SiftSettings",
    "Snapshot",
    "TLS",
    "Thumbnail",
    "ThumbnailSettings",
    "Timings",
    "Unauthenticated",
    "Unavailable",
    "UsedBox",
    "VocabularyInfo",
    "read_bag",
    "read_tum",
]
