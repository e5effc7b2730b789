"""What the SDK's calls return: plain dataclasses built from the API's messages.

Enum values are given by their API names (:func:`placedb.settings.enum_name`): map states
``"available"``, ``"unavailable"``, ``"damaged"``, ``"recovered"``; feature types ``"orb"``,
``"sift"``. A map's configuration, a message with many rarely used fields, is handed over as the
``placedb.v1.MapConfig`` itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Dict, List, Optional, Tuple

import numpy as np

from placedb._pb import placedb_pb2 as pb
from placedb.errors import Error, error_from_status_number
from placedb.settings import enum_name

if TYPE_CHECKING:  # frames imports this module: Camera is read when a place is converted
    from placedb.frames import Camera


def _fields(message) -> Dict[str, object]:
    return {f.name: getattr(message, f.name) for f in message.DESCRIPTOR.fields}


def _equal_with_arrays(self, other) -> bool:
    """``__eq__`` of the dataclasses with numpy array fields: arrays compare by shape and
    values (the generated ``__eq__`` would ask an array for its truth value)."""
    if other.__class__ is not self.__class__:
        return NotImplemented
    for f in fields(self):
        a, b = getattr(self, f.name), getattr(other, f.name)
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
                return False
            if not np.array_equal(a, b):
                return False
        elif a != b:
            return False
    return True


@dataclass(frozen=True)
class Pose:
    """Position and orientation quaternion (all-zero quaternion = identity)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0
    qw: float = 0.0

    @staticmethod
    def from_proto(message: pb.Pose) -> "Pose":
        return Pose(**_fields(message))

    def to_proto(self) -> pb.Pose:
        return pb.Pose(
            x=self.x, y=self.y, z=self.z, qx=self.qx, qy=self.qy, qz=self.qz, qw=self.qw
        )


@dataclass(frozen=True)
class Counts:
    """A frame's descriptors: ``total = dynamic + depth_removed + kept``."""

    total: int = 0
    dynamic: int = 0
    kept: int = 0
    depth_removed: int = 0
    #: Fraction of the image's pixels on dynamic objects.
    dynamic_coverage: float = 0.0

    @staticmethod
    def from_proto(message: pb.FrameCounts) -> "Counts":
        return Counts(**_fields(message))


@dataclass(frozen=True)
class Timings:
    """Server-side time per pipeline stage, in milliseconds (``total_ms``: arrival to answer)."""

    queue_ms: float = 0.0
    decode_ms: float = 0.0
    detect_ms: float = 0.0
    extract_ms: float = 0.0
    filter_ms: float = 0.0
    depth_ms: float = 0.0
    transform_ms: float = 0.0
    search_ms: float = 0.0
    verify_ms: float = 0.0
    store_ms: float = 0.0
    loop_closure_ms: float = 0.0
    refine_ms: float = 0.0
    pose_ms: float = 0.0
    total_ms: float = 0.0

    @staticmethod
    def from_proto(message: pb.StageTimings) -> "Timings":
        return Timings(**_fields(message))


@dataclass(frozen=True)
class UsedBox:
    """A dynamic-object box as the filter used it: class, confidence, rect (x, y, w, h)."""

    class_id: int
    class_name: str
    confidence: float
    rect: Tuple[float, float, float, float]

    @staticmethod
    def from_proto(message: pb.UsedBox) -> "UsedBox":
        r = message.rect
        return UsedBox(
            message.class_id, message.class_name, message.confidence, (r.x, r.y, r.width, r.height)
        )


@dataclass(frozen=True)
class DepthState:
    """Algorithm 1's decision for one frame of an agent's stream (docs/rgbd.md)."""

    #: 0-based index in the agent's stream.
    frame: int
    #: V_current.
    mean_depth_m: float
    #: V_static (0 while warming up).
    static_level_m: float
    #: V_current - V_static.
    difference_m: float
    #: Consecutive deviating frames (COUNT).
    count: int
    warming_up: bool
    deviating: bool
    #: Features in [band_near_m, band_far_m] were removed.
    removing: bool
    band_near_m: float
    band_far_m: float
    #: ``"rise"``, ``"fall"``, ``"nearest_layer"``, ``"appeared_layer"`` or ``""``.
    band_source: str
    #: Of the depth image's pixels.
    valid_fraction: float

    @staticmethod
    def from_proto(message: pb.DepthState) -> "DepthState":
        return DepthState(**_fields(message))


@dataclass(frozen=True)
class LoopClosure:
    """The loop-closure answer for one ingested frame (``ingest(..., loop_closure=True)``)."""

    #: Rehearsal merged the frame into ``place_id``: nothing new was stored.
    merged: bool
    #: The place the frame became or was merged into.
    place_id: int
    #: An accepted loop closure.
    loop_found: bool
    #: The revisited place, when ``loop_found``.
    loop_place_id: int
    loop_posterior: float
    #: The best hypothesis, accepted or not (0: none).
    best_place_id: int
    best_posterior: float
    #: Places in the agent's working memory searched.
    candidates: int
    #: Long-term -> working memory in this update.
    retrieved: int
    #: Working -> long-term memory in this update.
    transferred: int
    #: The agent's earlier places loaded into its new detector by this frame, else 0.
    replayed: int
    #: With the map's loop-closure verification: the accepted loop's inliers.
    loop_inliers: int
    #: A loop the filter accepted failed verification (``rejected_place_id`` names the place).
    loop_rejected: bool
    rejected_place_id: int
    #: With the map's loop-closure verification and cameras on both sides: the accepted loop's
    #: :class:`RelativePose` (this frame to ``loop_place_id``), else None and
    #: ``loop_pose_unavailable`` says why.
    loop_pose: Optional["RelativePose"] = None
    loop_pose_unavailable: str = ""

    @staticmethod
    def from_proto(message: pb.LoopClosure) -> "LoopClosure":
        values = _fields(message)
        values["loop_pose"] = (
            RelativePose.from_proto(message.loop_pose) if message.HasField("loop_pose") else None
        )
        return LoopClosure(**values)


@dataclass(frozen=True)
class RelativePose:
    """A verified match's loop-closure constraint, for a pose graph (g2o, GTSAM, Ceres).

    ``transform`` is T_place_query, a 4 x 4 float64 array: it maps a point in the query camera's
    frame into the place camera's (p_place = R p_query + t; OpenCV camera axes, x right, y down,
    z forward). With camera-to-world poses, T_place_query = inv(T_w_place) @ T_w_query.
    ``information``: the 6 x 6 inverse covariance, order [dt (m), dtheta (rad)] (translation
    first, as g2o's EDGE_SE3:QUAT; a perturbation on the right). ``metric`` False (no depth on
    either side): the translation is a unit direction and the information is singular along it.
    """

    transform: np.ndarray
    information: np.ndarray
    metric: bool
    #: ``"pnp_place_depth"``, ``"pnp_query_depth"`` or ``"essential"``.
    solver: str
    #: Inlier pairs the solver used (PnP: those with depth).
    correspondences: int
    inliers: int
    #: Reprojection (PnP) or Sampson (essential) error over the inliers, pixels.
    rms_error_px: float

    __eq__ = _equal_with_arrays

    @staticmethod
    def from_proto(message: pb.RelativePose) -> "RelativePose":
        return RelativePose(
            transform=np.array(message.transform, np.float64).reshape(4, 4),
            information=np.array(message.information, np.float64).reshape(6, 6),
            metric=message.metric,
            solver=message.solver,
            correspondences=message.correspondences,
            inliers=message.inliers,
            rms_error_px=message.rms_error_px,
        )


@dataclass(frozen=True)
class Match:
    """A stored place that matches an observation (best first in every list)."""

    place_id: int
    #: Higher is more similar (the map's scoring).
    score: float
    #: Geometric-verification inliers (0 when not verified).
    inliers: int
    #: ``inliers >= `` the map's ``min_inliers``.
    verified: bool
    agent_id: str
    sequence: int
    timestamp_ns: int
    pose: Optional[Pose]
    #: With ``correspondences=True``, for verified matches: the geometric inliers as an N x 2
    #: int64 array of (query keypoint index, place keypoint index) rows; the first indexes
    #: :attr:`QueryResult.query_keypoints`, the second the place's keypoints
    #: (``get_place(..., include_features=True)``). Empty (0 x 2) otherwise. Against a recent
    #: place the short-term tier verified on dynamic features too, those inliers are left out,
    #: so there may be fewer rows than ``inliers``.
    #: (Not part of the hash; compared by value.)
    correspondences: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 2), np.int64), compare=False
    )
    #: Verified matches whose frame and place both have a camera: the transform from the query
    #: camera to the place's, with its information (:class:`RelativePose`). None otherwise.
    relative_pose: Optional[RelativePose] = None
    #: Why a verified match has no ``relative_pose`` ("" when it has one).
    pose_unavailable: str = ""

    __eq__ = _equal_with_arrays

    @staticmethod
    def from_proto(message: pb.Match) -> "Match":
        m = message.metadata
        return Match(
            place_id=message.place_id,
            score=message.score,
            inliers=message.inliers,
            verified=message.verified,
            agent_id=m.agent_id,
            sequence=m.sequence,
            timestamp_ns=m.timestamp_ns,
            pose=Pose.from_proto(m.pose) if m.HasField("pose") else None,
            correspondences=_correspondences_array(message.correspondences),
            relative_pose=(
                RelativePose.from_proto(message.relative_pose)
                if message.HasField("relative_pose")
                else None
            ),
            pose_unavailable=message.pose_unavailable,
        )


@dataclass(frozen=True)
class FrameRef:
    """One side of a :class:`LoopConstraint`: a frame as its agent sent it."""

    agent_id: str
    sequence: int
    timestamp_ns: int
    pose: Optional[Pose]

    @staticmethod
    def from_proto(message: pb.PlaceMetadata) -> "FrameRef":
        return FrameRef(
            agent_id=message.agent_id,
            sequence=message.sequence,
            timestamp_ns=message.timestamp_ns,
            pose=Pose.from_proto(message.pose) if message.HasField("pose") else None,
        )


@dataclass(frozen=True)
class LoopConstraint:
    """One entry of a map's loop-closure log (:meth:`placedb.Client.watch_loop_closures`): a
    verified match found while ingesting, between the ingested frame (``query_place_id``) and
    an earlier place (``place_id``), with T_place_query when both had cameras."""

    #: The log's position: 1, 2, 3, ... in the order found; resume with ``sequence + 1``.
    sequence: int
    #: ``"match"`` (a verified match of Ingest's matches) or ``"loop_closure"`` (the loop the
    #: agent's Bayesian detector accepted).
    source: str
    query_place_id: int
    #: Rehearsal merged the frame into ``query_place_id``.
    merged: bool
    query: FrameRef
    place_id: int
    place: FrameRef
    score: float
    inliers: int
    relative_pose: Optional[RelativePose]
    pose_unavailable: str
    found_unix_ns: int

    @property
    def inter_agent(self) -> bool:
        return self.query.agent_id != self.place.agent_id

    @staticmethod
    def from_proto(message: pb.LoopConstraint) -> "LoopConstraint":
        return LoopConstraint(
            sequence=message.sequence,
            source=enum_name(pb.LoopSource.DESCRIPTOR, message.source),
            query_place_id=message.query_place_id,
            merged=message.merged,
            query=FrameRef.from_proto(message.query),
            place_id=message.place_id,
            place=FrameRef.from_proto(message.place),
            score=message.score,
            inliers=message.inliers,
            relative_pose=(
                RelativePose.from_proto(message.relative_pose)
                if message.HasField("relative_pose")
                else None
            ),
            pose_unavailable=message.pose_unavailable,
            found_unix_ns=message.found_unix_ns,
        )


@dataclass(frozen=True)
class QueryResult:
    """:meth:`placedb.Client.query`'s answer. Nothing is stored by a query."""

    #: The observation had enough static features to be a place.
    valid: bool
    #: Why it is not valid.
    rejection: str
    matches: List[Match]
    counts: Counts
    timings: Timings
    boxes_used: List[UsedBox]
    #: The agent's Algorithm 1 state applied to the frame (docs/rgbd.md), when it has one.
    depth: Optional[DepthState]
    #: With ``correspondences=True``: the query's static (kept) keypoints as N x 6 float32 rows
    #: (x, y, size, angle, response, octave), in the order :attr:`Match.correspondences`
    #: indexes them. None otherwise.
    query_keypoints: Optional[np.ndarray] = None
    #: With ``correspondences=True``: the query's dynamic (dropped) keypoints, N x 6 as above.
    query_dropped_keypoints: Optional[np.ndarray] = None
    #: With ``correspondences=True``: (width, height) of the query image the keypoints refer to.
    image_size: Optional[Tuple[int, int]] = None

    __eq__ = _equal_with_arrays

    @staticmethod
    def from_proto(message: pb.QueryResponse) -> "QueryResult":
        with_keypoints = message.image_width > 0 or len(message.query_keypoints) > 0
        return QueryResult(
            valid=message.valid,
            rejection=message.rejection,
            matches=[Match.from_proto(m) for m in message.matches],
            counts=Counts.from_proto(message.counts),
            timings=Timings.from_proto(message.timings),
            boxes_used=[UsedBox.from_proto(b) for b in message.boxes_used],
            depth=DepthState.from_proto(message.depth) if message.HasField("depth") else None,
            query_keypoints=(
                _keypoints_array(message.query_keypoints) if with_keypoints else None
            ),
            query_dropped_keypoints=(
                _keypoints_array(message.query_dropped_keypoints) if with_keypoints else None
            ),
            image_size=(
                (message.image_width, message.image_height) if with_keypoints else None
            ),
        )


@dataclass(frozen=True)
class IngestResult:
    """One ingested frame's answer (:meth:`placedb.Client.ingest` yields them in frame order)."""

    #: 0-based position of the frame in this call's frames.
    index: int
    #: The frame's sequence number, echoed.
    sequence: int
    stored: bool
    #: The new place's id, when stored.
    place_id: int
    #: Why a (well-formed) frame was not a valid place.
    rejection: str
    counts: Counts
    timings: Timings
    boxes_used: List[UsedBox]
    #: When matches were asked for: the map as it was before this frame.
    matches: List[Match]
    #: Set when the server refused the frame (nothing stored); the stream goes on.
    error: Optional[Error]
    depth: Optional[DepthState]
    loop_closure: Optional[LoopClosure]

    @staticmethod
    def from_proto(message: pb.IngestResponse) -> "IngestResult":
        error = None
        if message.HasField("error") and message.error.code != 0:
            error = error_from_status_number(message.error.code, message.error.message)
        return IngestResult(
            index=message.index,
            sequence=message.sequence,
            stored=message.stored,
            place_id=message.place_id,
            rejection=message.rejection,
            counts=Counts.from_proto(message.counts),
            timings=Timings.from_proto(message.timings),
            boxes_used=[UsedBox.from_proto(b) for b in message.boxes_used],
            matches=[Match.from_proto(m) for m in message.matches],
            error=error,
            depth=DepthState.from_proto(message.depth) if message.HasField("depth") else None,
            loop_closure=(
                LoopClosure.from_proto(message.loop_closure)
                if message.HasField("loop_closure")
                else None
            ),
        )


@dataclass(frozen=True)
class MapDamage:
    """Acknowledged writes a map lost (``first..last_lost_place``: an upper bound of the ids)."""

    reason: str
    writes_lost: int
    places_lost: int
    first_lost_place: int
    last_lost_place: int
    recovered_unix_ms: int
    records_lost: int = 0
    bow_lost: int = 0
    features_lost: int = 0
    quarantine: str = ""

    @staticmethod
    def from_proto(message: pb.MapDamage) -> "MapDamage":
        return MapDamage(**_fields(message))


@dataclass(frozen=True)
class MapInfo:
    """A map's state, effective configuration and statistics (:meth:`~placedb.Client.get_map`).

    For a map that is not available (state ``"damaged"`` or ``"unavailable"``) only ``name``,
    ``state``, ``unavailable_reason`` and ``damage`` are meaningful.
    """

    name: str
    state: str
    #: ``"orb"`` or ``"sift"``.
    feature_type: str
    vocabulary: str
    #: 16 hex digits.
    vocabulary_checksum: str
    created_unix_ms: int
    places: int
    #: Every ``placedb.v1.MapStats`` field by name (places, descriptors_kept, bytes_on_disk, ...).
    stats: Dict[str, int]
    #: The effective ``placedb.v1.MapConfig`` (defaults filled in).
    config: pb.MapConfig
    unavailable_reason: str
    damage: Optional[MapDamage]
    damage_history: List[MapDamage]
    places_lost: int
    #: :meth:`~placedb.Client.get_map` only: the agents whose ingest frames this server answered
    #: since it started (in memory, at most 64 per map).
    agents: List["AgentActivity"] = field(default_factory=list)
    #: Which vocabulary the map uses and where it came from (available maps).
    vocabulary_info: Optional["MapVocabulary"] = None

    @staticmethod
    def from_proto(message: pb.MapDescription) -> "MapInfo":
        return MapInfo(
            name=message.name,
            state=enum_name(pb.MapState.DESCRIPTOR, message.state),
            feature_type=enum_name(pb.FeatureType.DESCRIPTOR, message.config.feature_type),
            vocabulary=message.config.vocabulary,
            vocabulary_checksum=message.vocabulary_checksum,
            created_unix_ms=message.created_unix_ms,
            places=message.stats.places,
            stats={k: int(v) for k, v in _fields(message.stats).items()},
            config=message.config,
            unavailable_reason=message.unavailable_reason,
            damage=MapDamage.from_proto(message.damage) if message.HasField("damage") else None,
            damage_history=[MapDamage.from_proto(d) for d in message.damage_history],
            places_lost=message.places_lost,
            agents=[AgentActivity.from_proto(a) for a in message.agents],
            vocabulary_info=(
                MapVocabulary.from_proto(message.vocabulary)
                if message.HasField("vocabulary")
                else None
            ),
        )


@dataclass(frozen=True)
class MapVocabulary:
    """A map's vocabulary and the one before it (docs/storage.md, "A map's own vocabulary").

    ``current`` and ``previous`` are ``placedb.v1.VocabularySource`` messages: ``origin``
    (``"file"`` or ``"learned"``), ``checksum``, ``branching``, ``depth``, ``words`` and, for a
    learned one, when and from how many places and descriptors it was learned.
    """

    map: str
    #: 0: the vocabulary the map was created with; each switch makes the next.
    generation: int
    current: pb.VocabularySource
    previous: Optional[pb.VocabularySource]
    since_unix_ms: int
    places_reindexed: int
    reindex_ms: float
    switching: bool

    @staticmethod
    def from_proto(message: pb.MapVocabulary) -> "MapVocabulary":
        return MapVocabulary(
            map=message.map,
            generation=message.generation,
            current=message.current,
            previous=message.previous if message.HasField("previous") else None,
            since_unix_ms=message.since_unix_ms,
            places_reindexed=message.places_reindexed,
            reindex_ms=message.reindex_ms,
            switching=message.switching,
        )


@dataclass(frozen=True)
class AgentActivity:
    """What one agent did to a map since the server started (:attr:`MapInfo.agents`; not
    persisted, forgotten when the map is deleted)."""

    agent_id: str
    #: Ingested frames answered (stored, merged, invalid or refused).
    frames: int
    #: Of those, stored as places.
    places: int
    #: Frames answered in the last 10 s / 10.
    frames_per_second: float
    #: The last place stored or merged into; 0 = none yet.
    last_place_id: int
    #: Server clock.
    last_frame_unix_ms: int

    @staticmethod
    def from_proto(message: pb.AgentActivity) -> "AgentActivity":
        return AgentActivity(**_fields(message))


@dataclass(frozen=True)
class MapSummary:
    """One entry of :meth:`placedb.Client.list_maps`."""

    name: str
    #: State ``"available"`` or ``"recovered"``.
    available: bool
    state: str
    vocabulary: str
    places: int
    feature_type: str
    unavailable_reason: str
    places_lost: int

    @staticmethod
    def from_proto(message: pb.MapSummary) -> "MapSummary":
        return MapSummary(
            name=message.name,
            available=message.available,
            state=enum_name(pb.MapState.DESCRIPTOR, message.state),
            vocabulary=message.vocabulary,
            places=message.places,
            feature_type=enum_name(pb.FeatureType.DESCRIPTOR, message.feature_type),
            unavailable_reason=message.unavailable_reason,
            places_lost=message.places_lost,
        )


@dataclass(frozen=True)
class ClassCount:
    """How often one COCO class (contiguous id: person 0, car 2, ...) was seen."""

    class_id: int
    #: Observations in which the class was seen.
    frames: int
    #: Its boxes over all observations.
    boxes: int


@dataclass(frozen=True)
class HourCoverage:
    """One bin of the hour-of-day x day-of-week histogram (UTC)."""

    #: 0 = Monday .. 6 = Sunday.
    weekday: int
    #: 0..23.
    hour: int
    observations: int
    mean_coverage: float


@dataclass(frozen=True)
class DynamicStatistics:
    """Dynamic-object statistics of a place, a map or its invalid frames (issue 16).

    Coverage is the share of an image's pixels on dynamic objects, 0..1.
    """

    observations: int = 0
    mean_coverage: float = 0.0
    max_coverage: float = 0.0
    #: Of the newest timed observation.
    last_coverage: float = 0.0
    #: 0 when no observation had a usable timestamp.
    last_timestamp_ns: int = 0
    #: Observations with a zero or negative timestamp (not in ``hours``).
    untimed: int = 0
    #: Observations with a timestamp over a day past the server's clock (not in ``hours``).
    future: int = 0
    unknown_class_boxes: int = 0
    #: Ascending class id.
    classes: List[ClassCount] = field(default_factory=list)
    #: Non-empty bins only, by weekday then hour.
    hours: List[HourCoverage] = field(default_factory=list)

    @staticmethod
    def from_proto(message: pb.DynamicStatistics) -> "DynamicStatistics":
        values = _fields(message)
        values["classes"] = [ClassCount(**_fields(c)) for c in message.classes]
        values["hours"] = [HourCoverage(**_fields(h)) for h in message.hours]
        return DynamicStatistics(**values)


@dataclass(frozen=True)
class RankedPlace:
    """One place of a :meth:`placedb.Client.get_dynamics` page."""

    place_id: int
    #: The measure's value.
    score: float
    #: Observations the score rests on.
    support: int
    #: With ``include_statistics``.
    statistics: Optional[DynamicStatistics]

    @staticmethod
    def from_proto(message: pb.RankedPlace) -> "RankedPlace":
        return RankedPlace(
            place_id=message.place_id,
            score=message.score,
            support=message.support,
            statistics=(
                DynamicStatistics.from_proto(message.statistics)
                if message.HasField("statistics")
                else None
            ),
        )


@dataclass(frozen=True)
class Dynamics:
    """:meth:`placedb.Client.get_dynamics`: the map's statistics and a ranked page of places."""

    #: Every acknowledged frame of the map, also of places removed since.
    map: DynamicStatistics
    #: Best first; ties by ascending place id.
    places: List[RankedPlace]
    #: Places ranked in all (for paging).
    ranked: int
    #: The next page's ``offset``; 0 when this is the last page.
    next_offset: int
    #: The frames refused as invalid (no place; often objects covered the view); not in ``map``.
    invalid: DynamicStatistics

    @staticmethod
    def from_proto(message: pb.GetDynamicsResponse) -> "Dynamics":
        return Dynamics(
            map=DynamicStatistics.from_proto(message.map),
            places=[RankedPlace.from_proto(p) for p in message.places],
            ranked=message.ranked,
            next_offset=message.next_offset,
            invalid=DynamicStatistics.from_proto(message.invalid),
        )


@dataclass(frozen=True)
class Snapshot:
    """A snapshot: a consistent, verified copy of a map kept by the server (admin calls).

    ``archive_bytes`` and ``archive_sha256`` describe the archive a
    :meth:`~placedb.Client.download_snapshot` or :meth:`~placedb.Client.upload_snapshot`
    moved (its size and its trailing SHA-256, checked); they are 0 and ``""`` otherwise.
    """

    #: ``"<map>-<unix ms>[-n]"``, assigned by the server.
    id: str
    #: The map it was taken of.
    map: str
    created_unix_ms: int
    #: ``"orb"`` or ``"sift"``.
    feature_type: str
    #: 16 hex digits, as :attr:`MapInfo.vocabulary_checksum`.
    vocabulary_checksum: str
    places: int
    #: On the server's disk.
    bytes: int
    archive_bytes: int = 0
    archive_sha256: str = ""

    @staticmethod
    def from_proto(message: pb.Snapshot) -> "Snapshot":
        return Snapshot(
            id=message.id,
            map=message.map,
            created_unix_ms=message.created_unix_ms,
            feature_type=message.feature_type,
            vocabulary_checksum=f"{message.vocabulary_checksum:016x}",
            places=message.places,
            bytes=message.bytes,
        )


def _keypoints_array(keypoints) -> np.ndarray:
    rows = [(k.x, k.y, k.size, k.angle, k.response, k.octave) for k in keypoints]
    return np.array(rows, dtype=np.float32).reshape(len(rows), 6)


def _camera(message: pb.Camera) -> "Camera":
    from placedb.frames import Camera

    return Camera(
        fx=message.fx,
        fy=message.fy,
        cx=message.cx,
        cy=message.cy,
        width=message.width,
        height=message.height,
        distortion_model=message.distortion_model,
        distortion=tuple(message.distortion),
    )


def _correspondences_array(correspondences) -> np.ndarray:
    rows = [(c.query_keypoint, c.place_keypoint) for c in correspondences]
    return np.array(rows, dtype=np.int64).reshape(len(rows), 2)


@dataclass(frozen=True)
class Thumbnail:
    """A place's frame, reduced, with its dynamic-object boxes blurred
    (``get_place(..., thumbnail=True)`` on a map created with thumbnails enabled).

    Keypoints and boxes stay in the source frame's pixels: scale them by
    ``width / source_width`` (and ``height / source_height``) to draw on the thumbnail.
    """

    #: The JPEG file's bytes (``cv2.imdecode(np.frombuffer(jpeg, np.uint8), ...)``).
    jpeg: bytes
    width: int
    height: int
    source_width: int
    source_height: int
    #: Keypoints the filter dropped as dynamic: N x 6 float32 rows as :attr:`Place.keypoints`.
    dropped_keypoints: np.ndarray

    __eq__ = _equal_with_arrays

    @staticmethod
    def from_proto(message: pb.Thumbnail) -> "Thumbnail":
        return Thumbnail(
            jpeg=bytes(message.jpeg),
            width=message.width,
            height=message.height,
            source_width=message.source_width,
            source_height=message.source_height,
            dropped_keypoints=_keypoints_array(message.dropped_keypoints),
        )


@dataclass(frozen=True)
class Place:
    """A stored place (:meth:`placedb.Client.get_place`)."""

    place_id: int
    agent_id: str
    sequence: int
    timestamp_ns: int
    pose: Optional[Pose]
    counts: Counts
    boxes_used: List[UsedBox]
    #: With ``include_features``: the image size (width, height) the keypoints refer to.
    image_size: Optional[Tuple[int, int]] = None
    #: With ``include_features``: N x 6 float32 rows (x, y, size, angle, response, octave).
    keypoints: Optional[np.ndarray] = None
    #: With ``include_features``: N x 32 uint8 (ORB) or N x 128 float32 (SIFT), static only.
    descriptors: Optional[np.ndarray] = None
    #: Every frame stored at or merged into the place (None for places stored before the map
    #: kept statistics).
    dynamics: Optional[DynamicStatistics] = None
    #: With ``thumbnail=True``, when the map kept one for this place.
    thumbnail: Optional[Thumbnail] = None
    #: With ``include_features``: the :class:`placedb.Camera` the place was stored with (None
    #: when its frame had none).
    camera: Optional[Camera] = None
    #: With ``include_features``: each stored keypoint's depth in metres (float32, keypoint
    #: order, 0 = none); None when the frame had no depth.
    keypoint_depth_m: Optional[np.ndarray] = None

    __eq__ = _equal_with_arrays

    @staticmethod
    def from_proto(message: pb.Place) -> "Place":
        m = message.metadata
        image_size = keypoints = descriptors = None
        if message.HasField("features"):
            f = message.features
            image_size = (f.image_width, f.image_height)
            keypoints = _keypoints_array(f.keypoints)
            descriptors = np.frombuffer(f.descriptors, np.uint8).reshape(-1, 32)
        elif message.HasField("sift_features"):
            f = message.sift_features
            image_size = (f.image_width, f.image_height)
            keypoints = _keypoints_array(f.keypoints)
            descriptors = np.frombuffer(f.descriptors, "<f4").astype(np.float32).reshape(-1, 128)
        return Place(
            place_id=message.place_id,
            agent_id=m.agent_id,
            sequence=m.sequence,
            timestamp_ns=m.timestamp_ns,
            pose=Pose.from_proto(m.pose) if m.HasField("pose") else None,
            counts=Counts.from_proto(message.counts),
            boxes_used=[UsedBox.from_proto(b) for b in message.boxes_used],
            image_size=image_size,
            keypoints=keypoints,
            descriptors=descriptors,
            dynamics=(
                DynamicStatistics.from_proto(message.dynamics)
                if message.HasField("dynamics")
                else None
            ),
            thumbnail=(
                Thumbnail.from_proto(message.thumbnail)
                if message.HasField("thumbnail")
                else None
            ),
            camera=_camera(message.camera) if message.HasField("camera") else None,
            keypoint_depth_m=(
                np.array(message.keypoint_depth_m, np.float32)
                if len(message.keypoint_depth_m)
                else None
            ),
        )


@dataclass(frozen=True)
class PlacePage:
    """One page of :meth:`placedb.Client.list_places`: places newest (highest id) first, with
    metadata, counts and boxes (no features, statistics or thumbnail: ``get_place`` has them).

    A page may hold fewer places than asked for, even none, while ``next_before`` is not 0 (one
    call examines at most 10 000 place ids): keep paging until it is 0
    (:meth:`placedb.Client.iter_places` does).
    """

    places: List[Place]
    #: Pass as ``before=`` for the next page; 0 when this is the last page.
    next_before: int

    @staticmethod
    def from_proto(message: pb.ListPlacesResponse) -> "PlacePage":
        return PlacePage(
            places=[Place.from_proto(p) for p in message.places],
            next_before=message.next_before_place_id,
        )


@dataclass(frozen=True)
class VocabularyInfo:
    """A vocabulary the server serves (``path`` and ``memory_bytes``: admins only)."""

    name: str
    path: str
    checksum: str
    words: int
    nodes: int
    branching: int
    depth: int
    memory_bytes: int
    feature_type: str

    @staticmethod
    def from_proto(message: pb.VocabularyInfo) -> "VocabularyInfo":
        values = _fields(message)
        values["feature_type"] = enum_name(pb.FeatureType.DESCRIPTOR, message.feature_type)
        return VocabularyInfo(**values)


@dataclass(frozen=True)
class ServerInfo:
    """:meth:`placedb.Client.server_info`: version, vocabularies, detector and limits."""

    version: str
    vocabularies: List[VocabularyInfo]
    #: ``"off"`` or the model's description (admins only).
    detector: str
    #: Every ``placedb.v1.Limits`` field by name (max_message_bytes, max_image_pixels, ...).
    limits: Dict[str, int] = field(default_factory=dict)

    @staticmethod
    def from_proto(message: pb.ServerInfo) -> "ServerInfo":
        return ServerInfo(
            version=message.version,
            vocabularies=[VocabularyInfo.from_proto(v) for v in message.vocabularies],
            detector=message.detector,
            limits={k: int(v) for k, v in _fields(message.limits).items()},
        )


@dataclass(frozen=True)
class ScrubReport:
    """:meth:`placedb.Client.scrub_map`: what a full read of a map found (nothing changes)."""

    places_checked: int
    files_checked: int
    #: (place id, reason) per damaged place.
    damaged_places: List[Tuple[int, str]]
    #: (file relative to the data directory, reason) per damaged file.
    damaged_files: List[Tuple[str, str]]
    clean: bool
    #: Cluster mode: (shard, that replica's own report or None, error) per live replica; the
    #: fields above cover them all. Empty on a single server.
    replicas: List[Tuple[str, Optional["ScrubReport"], str]] = field(default_factory=list)

    @staticmethod
    def from_proto(message: pb.ScrubReport) -> "ScrubReport":
        return ScrubReport(
            places_checked=message.places_checked,
            files_checked=message.files_checked,
            damaged_places=[(p.place_id, p.reason) for p in message.damaged_places],
            damaged_files=[(f.file, f.reason) for f in message.damaged_files],
            clean=message.clean,
            replicas=[
                (
                    r.shard,
                    ScrubReport.from_proto(r.report) if r.HasField("report") else None,
                    r.error,
                )
                for r in message.replicas
            ],
        )
