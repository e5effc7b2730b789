"""The placedb client: one gRPC channel to a placedb server and a method per operation.

Every call raises a :class:`placedb.Error` subclass on failure (the gRPC code and the server's
message). Every call takes ``timeout=``: seconds, or None for no deadline. By default unary calls
use the client's (``Client(timeout=...)``, default 30 s); ingest streams, snapshot creation,
restore and transfers have none, because their duration grows with the data (the server closes
idle ingest streams, see docs/service.md).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import grpc

from placedb._pb import health_pb2, health_pb2_grpc
from placedb._pb import placedb_pb2 as pb
from placedb._pb import placedb_pb2_grpc as pb_grpc
from placedb.errors import Error, InvalidArgument, from_rpc_error
from placedb import snapshots
from placedb.frames import Camera, Frame, ImageLike, MatchOptions, as_frame, to_observation
from placedb.results import (
    Dynamics,
    IngestResult,
    LoopConstraint,
    MapDamage,
    MapInfo,
    MapVocabulary,
    MapSummary,
    Place,
    PlacePage,
    QueryResult,
    ScrubReport,
    ServerInfo,
    Snapshot,
)
from placedb.settings import MapSettings, enum_value


@dataclass
class TLS:
    """Transport security, as the CLI's ``--tls --ca-cert --cert --key``: PEM file paths.

    ``ca_cert``: the CA bundle that signed the server's certificate (None: the system roots).
    ``cert`` + ``key``: this client's certificate and key, for servers that ask for mutual TLS.
    """

    ca_cert: Optional[str] = None
    cert: Optional[str] = None
    key: Optional[str] = None


def _read_pem(path: Optional[str], flag: str) -> Optional[bytes]:
    if path is None:
        return None
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise InvalidArgument(f"tls.{flag}: cannot read {path}: {e.strerror}") from None


def _credentials(tls: Union[bool, TLS]) -> grpc.ChannelCredentials:
    if tls is True:
        tls = TLS()
    assert isinstance(tls, TLS)
    if (tls.cert is None) != (tls.key is None):
        raise InvalidArgument("tls: cert and key go together")
    return grpc.ssl_channel_credentials(
        root_certificates=_read_pem(tls.ca_cert, "ca_cert"),
        private_key=_read_pem(tls.key, "key"),
        certificate_chain=_read_pem(tls.cert, "cert"),
    )


class _ClientTimeout:
    """The default ``timeout`` of unary calls: the client's (``Client(timeout=...)``)."""

    def __repr__(self) -> str:
        return "CLIENT_TIMEOUT"


#: A call's ``timeout=`` default that means "the client's timeout".
CLIENT_TIMEOUT: Any = _ClientTimeout()
#: Seconds, None (no deadline) or :data:`CLIENT_TIMEOUT`.
Timeout = Union[None, float, _ClientTimeout]

_WEEKDAYS = ("monday", "tuesday", "wednesday", "thursday", "friday", "saturday", "sunday")


def _set(request: Any, name: str, value: Any) -> None:
    """Sets a request field; :class:`InvalidArgument` naming it for a value of the wrong type or
    out of its range (e.g. a negative limit)."""
    try:
        setattr(request, name, value)
    except (TypeError, ValueError) as e:
        raise InvalidArgument(f"{name}: {value!r} ({e})") from None


def _weekday_bits(weekdays: Iterable[Union[str, int]]) -> int:
    """Bit 0 = Monday .. bit 6 = Sunday from names (``"mon"``, ``"Monday"``) or 0..6."""
    if isinstance(weekdays, (str, bytes)):
        weekdays = [weekdays] if isinstance(weekdays, str) else [weekdays.decode()]
    names = {name: i for i, name in enumerate(_WEEKDAYS)}
    names.update({name[:3]: i for i, name in enumerate(_WEEKDAYS)})
    bits = 0
    for day in weekdays:
        if isinstance(day, str) and day.strip().lower() in names:
            bits |= 1 << names[day.strip().lower()]
        elif isinstance(day, int) and not isinstance(day, bool) and 0 <= day <= 6:
            bits |= 1 << day
        else:
            raise InvalidArgument(
                f"weekdays: {day!r} is not a day (expected mon..sun or 0 = Monday .. 6 = Sunday)"
            )
    if bits == 0:
        raise InvalidArgument("weekdays: empty (None means every day)")
    return bits


# Keepalive pings every 5 s, 5 s to answer: a server whose host vanished (no reset ever comes) is
# found within ~10 s, also under a long Ingest stream (the server allows pings every 4 s:
# server/server.cc).
CHANNEL_OPTIONS = [
    ("grpc.max_receive_message_length", -1),
    ("grpc.max_send_message_length", -1),
    ("grpc.keepalive_time_ms", 5000),
    ("grpc.keepalive_timeout_ms", 5000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
]


def token_metadata(token: Optional[str]) -> Sequence[Tuple[str, str]]:
    """The call metadata carrying a bearer token (none without one)."""
    return (("authorization", f"Bearer {token}"),) if token else ()


def check_timeout(timeout: Optional[float]) -> Optional[float]:
    if timeout is not None and not timeout > 0:
        raise InvalidArgument(f"timeout: {timeout}, expected seconds > 0 or None")
    return timeout


# The requests, built the same way by Client and placedb.aio.AsyncClient.


def create_map_request(
    name: str, settings: Union[None, MapSettings, pb.MapConfig]
) -> pb.CreateMapRequest:
    if isinstance(settings, MapSettings):
        config = settings.to_proto()
    else:
        config = settings if settings is not None else pb.MapConfig()
    return pb.CreateMapRequest(name=name, config=config)


def query_request(
    map: str,
    image: Union[Frame, ImageLike],
    top_k: int,
    verify: bool,
    exclude_same_agent: bool,
    agent_id: str,
    correspondences: bool,
) -> pb.QueryRequest:
    if as_frame(image).matches is not None:
        raise InvalidArgument(
            "observation.matches: ingest only; give a query's options as its arguments"
        )
    return pb.QueryRequest(
        map=map,
        observation=to_observation(image, agent_id, 0),
        options=MatchOptions(top_k, verify, exclude_same_agent, correspondences).to_proto(
            "options"
        ),
    )


def ingest_header(
    map: str,
    top_k: int,
    verify: bool,
    exclude_same_agent: bool,
    loop_closure: bool,
    max_in_flight: int,
    camera: Optional[Camera] = None,
) -> pb.IngestHeader:
    """The header of an Ingest stream (after checking ``max_in_flight``)."""
    if max_in_flight < 1:
        raise InvalidArgument(f"max_in_flight: {max_in_flight}, expected >= 1")
    header = pb.IngestHeader(map=map, loop_closure=loop_closure)
    if camera is not None:
        camera.to_proto(header.camera)
    if top_k:
        header.matches.CopyFrom(
            MatchOptions(top_k, verify, exclude_same_agent).to_proto("header.matches")
        )
    return header


def list_places_request(
    map: str,
    agent_id: Optional[str],
    from_ns: Optional[int],
    to_ns: Optional[int],
    limit: int,
    before: Optional[int],
) -> pb.ListPlacesRequest:
    if limit is None or isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        # 0 would mean the server's default, not "no places": refuse it here.
        raise InvalidArgument(f"limit: {limit!r}, expected 1..1000")
    request = pb.ListPlacesRequest(map=map)
    _set(request, "limit", limit)
    if agent_id is not None:
        _set(request, "agent_id", agent_id)
    if from_ns is not None:
        _set(request, "from_timestamp_ns", from_ns)
    if to_ns is not None:
        _set(request, "to_timestamp_ns", to_ns)
    if before is not None:
        _set(request, "before_place_id", before)
    return request


def watch_loop_closures_request(
    map: str,
    from_sequence: int,
    follow: bool,
    agents: Iterable[str],
    inter_agent_only: bool,
    min_sequence_gap: int,
) -> pb.WatchLoopClosuresRequest:
    return pb.WatchLoopClosuresRequest(
        map=map,
        from_sequence=from_sequence,
        follow=follow,
        agents=list(agents),
        inter_agent_only=inter_agent_only,
        min_sequence_gap=min_sequence_gap,
    )


def dynamics_request(
    map: str,
    measure: Optional[str],
    class_name: Optional[str],
    class_id: Optional[int],
    hours: Optional[Tuple[int, int]],
    weekdays: Optional[Iterable[Union[str, int]]],
    limit: int,
    offset: int,
    min_observations: int,
    include_statistics: bool,
) -> pb.GetDynamicsRequest:
    request = pb.GetDynamicsRequest(map=map, include_statistics=include_statistics)
    _set(request, "limit", limit)
    _set(request, "offset", offset)
    _set(request, "min_observations", min_observations)
    if measure is None:
        if class_name is not None or class_id is not None:
            measure = "class_share"
        elif hours is not None:
            measure = "hour_window"
        else:
            measure = "mean_coverage"
    request.measure = enum_value(pb.DynamicsMeasure.DESCRIPTOR, measure, "measure")
    if class_name is not None:
        _set(request, "class_name", class_name)
    if class_id is not None:
        _set(request, "class_id", class_id)
    if hours is not None:
        try:
            first, last = (int(h) for h in hours)
            request.first_hour, request.last_hour = first, last
        except (TypeError, ValueError):
            raise InvalidArgument(f"hours: {hours!r}, expected (first, last) hours 0..23") from None
    if weekdays is not None:
        request.weekdays = _weekday_bits(weekdays)
    return request


def health_status(response: health_pb2.HealthCheckResponse) -> str:
    return health_pb2.HealthCheckResponse.ServingStatus.Name(response.status).lower()


class Client:
    """A connection to a placedb server.

    ``target``: ``host:port`` (e.g. ``"127.0.0.1:50051"``). ``token``: a bearer token from
    ``placedb-server tokens add`` (sent as ``authorization: Bearer <token>``). ``tls``: ``None``
    for plaintext, ``True`` for TLS with the system roots, or a :class:`TLS` with PEM paths.
    ``timeout``: seconds per unary call (None: no deadline; each call's ``timeout=`` overrides
    it). ``wait_for_ready``: calls made while the server is unreachable wait for it (up to their
    deadline: :class:`DeadlineExceeded`) instead of failing at once with :class:`Unavailable`;
    for agents that start before the server.

    Usable as a context manager; :meth:`close` closes the channel.
    """

    def __init__(
        self,
        target: str,
        token: Optional[str] = None,
        tls: Union[None, bool, TLS] = None,
        timeout: Optional[float] = 30.0,
        wait_for_ready: bool = False,
    ) -> None:
        self._timeout = self._check_timeout(timeout)  # before the channel: nothing to close
        if tls:
            self._channel = grpc.secure_channel(target, _credentials(tls), options=CHANNEL_OPTIONS)
        else:
            self._channel = grpc.insecure_channel(target, options=CHANNEL_OPTIONS)
        self._metadata = token_metadata(token)
        self._wait_for_ready = wait_for_ready
        self._stub = pb_grpc.PlaceDbStub(self._channel)
        self._health = health_pb2_grpc.HealthStub(self._channel)

    def close(self) -> None:
        """Closes the channel; calls in flight are cancelled."""
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @staticmethod
    def _check_timeout(timeout: Optional[float]) -> Optional[float]:
        return check_timeout(timeout)

    def _deadline(self, timeout: Timeout) -> Optional[float]:
        if isinstance(timeout, _ClientTimeout):
            return self._timeout
        return self._check_timeout(timeout)

    def _options(self, timeout: Timeout) -> dict:
        """The keyword arguments of a stub call: deadline, token, wait_for_ready."""
        return {
            "timeout": self._deadline(timeout),
            "metadata": self._metadata,
            "wait_for_ready": self._wait_for_ready,
        }

    def _call(self, method: Any, request: Any, timeout: Timeout = CLIENT_TIMEOUT) -> Any:
        options = self._options(timeout)
        try:
            return method(request, **options)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None

    # ---- Maps ----------------------------------------------------------------------------------

    def create_map(
        self,
        name: str,
        settings: Union[None, MapSettings, pb.MapConfig] = None,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> MapInfo:
        """Creates a durable map; returns it with its effective configuration.

        ``settings``: a :class:`MapSettings` (or a ``placedb.v1.MapConfig``); None = defaults.
        Raises :class:`AlreadyExists` if the name is taken, :class:`InvalidArgument` for a bad
        name (1-64 of ``[A-Za-z0-9_.-]``, starting with a letter or digit), an unknown
        vocabulary or a bad setting.
        """
        response = self._call(self._stub.CreateMap, create_map_request(name, settings), timeout)
        return MapInfo.from_proto(response)

    def get_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> MapInfo:
        """A map's state, configuration and statistics (:class:`NotFound` if absent)."""
        return MapInfo.from_proto(
            self._call(self._stub.GetMap, pb.GetMapRequest(name=name), timeout)
        )

    def list_maps(self, timeout: Timeout = CLIENT_TIMEOUT) -> List[MapSummary]:
        """Every map the caller may read, including those that could not be opened (and why)."""
        response = self._call(self._stub.ListMaps, pb.ListMapsRequest(), timeout)
        return [MapSummary.from_proto(m) for m in response.maps]

    def delete_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """Deletes a map and all its places, durably (:class:`NotFound` if absent)."""
        self._call(self._stub.DeleteMap, pb.DeleteMapRequest(name=name), timeout)

    def recover_map(
        self, name: str, accept_data_loss: bool, timeout: Timeout = CLIENT_TIMEOUT
    ) -> Tuple[MapInfo, MapDamage]:
        """Reopens a damaged map, accepting what was lost (docs/storage.md, "Damage").

        Returns the map and what this recovery accepted as lost. :class:`InvalidArgument`
        without ``accept_data_loss``; :class:`FailedPrecondition` when the map is not damaged
        or cannot be recovered this way.
        """
        response = self._call(
            self._stub.RecoverMap,
            pb.RecoverMapRequest(name=name, accept_data_loss=accept_data_loss),
            timeout,
        )
        return MapInfo.from_proto(response.map), MapDamage.from_proto(response.accepted)

    def scrub_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> ScrubReport:
        """Reads and checks every place and SST block of a map; damage is reported, not raised."""
        return ScrubReport.from_proto(
            self._call(self._stub.ScrubMap, pb.ScrubMapRequest(name=name), timeout)
        )

    def adapt_vocabulary(
        self,
        name: str,
        seed: int = 0,
        max_sample_descriptors: int = 0,
        branching: int = 0,
        depth: int = 0,
        timeout: Timeout = None,
    ) -> MapVocabulary:
        """Learns a vocabulary from the map's own stored places and switches the map to it online.

        0 keeps the server's default for each option. No deadline by default: a large map takes
        minutes. :class:`FailedPrecondition` when the map is too small to learn from or already
        switching; the map keeps its vocabulary on any error.
        """
        request = pb.AdaptVocabularyRequest(
            name=name,
            seed=seed,
            max_sample_descriptors=max_sample_descriptors,
            branching=branching,
            depth=depth,
        )
        return MapVocabulary.from_proto(self._call(self._stub.AdaptVocabulary, request, timeout))

    def revert_vocabulary(self, name: str, timeout: Timeout = None) -> MapVocabulary:
        """Switches the map back to its previous vocabulary (:class:`FailedPrecondition` if none)."""
        request = pb.RevertVocabularyRequest(name=name)
        return MapVocabulary.from_proto(self._call(self._stub.RevertVocabulary, request, timeout))

    # ---- Query and ingest ----------------------------------------------------------------------

    def query(
        self,
        map: str,
        image: Union[Frame, ImageLike],
        top_k: int = 10,
        verify: bool = False,
        exclude_same_agent: bool = False,
        agent_id: str = "",
        correspondences: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> QueryResult:
        """Ranked matches of one frame against a map; nothing is stored.

        ``image``: any frame form (see :mod:`placedb.frames`). ``top_k``: at most this many
        matches (0 = the server's 10). ``verify``: keep only candidates that pass geometric
        verification (the map's verification mode). ``exclude_same_agent``: skip places stored by
        ``agent_id``. ``correspondences``: each verified match's inliers
        (:attr:`Match.correspondences`, indices into :attr:`QueryResult.query_keypoints` and
        the place's keypoints), with the query's kept and dropped keypoints and image size
        (costs the keypoints' bytes in the answer). Raises :class:`NotFound` for an unknown
        map, :class:`InvalidArgument` for a frame the server or the SDK refuses (also a
        :class:`Frame` with ``matches``, which is for ingest: a query's options are these
        arguments).
        """
        request = query_request(
            map, image, top_k, verify, exclude_same_agent, agent_id, correspondences
        )
        return QueryResult.from_proto(self._call(self._stub.Query, request, timeout))

    def ingest(
        self,
        map: str,
        frames: Iterable[Union[Frame, ImageLike]],
        agent_id: str = "agent",
        top_k: int = 0,
        verify: bool = False,
        exclude_same_agent: bool = False,
        loop_closure: bool = False,
        max_in_flight: int = 8,
        timeout: Timeout = None,
        camera: Optional[Camera] = None,
    ) -> Iterator[IngestResult]:
        """Streams frames into a map; yields one :class:`IngestResult` per frame, in order.

        A generator: nothing is sent until it is iterated. ``frames`` is consumed lazily, with
        at most ``max_in_flight`` frames sent and not yet answered, so a long sequence (a folder,
        a video) is never held in memory. Each frame's sequence defaults to its 0-based position.

        ``top_k`` > 0: every result carries its frame's matches against the map as it was before
        the frame (``verify`` and ``exclude_same_agent`` as for :meth:`query`); a
        :class:`Frame`'s ``matches`` overrides these for that frame. ``loop_closure``:
        the map's Bayesian loop closure per agent (:attr:`IngestResult.loop_closure`).
        ``camera``: the stream's :class:`Camera`, for every frame without its own (verified
        matches then carry :attr:`Match.relative_pose`; the stored places keep it).

        A frame the server refuses is answered with :attr:`IngestResult.error` set and the stream
        goes on. A frame the SDK cannot convert (:class:`InvalidArgument`), or an exception from
        ``frames`` itself, ends the stream: the results of the frames before it are yielded,
        then it is raised. Stream-level failures (unknown map: :class:`NotFound`; too many
        streams: :class:`ResourceExhausted`) raise when iterated. Breaking out of the loop
        cancels the stream (frames in flight may or may not have been stored). ``timeout``: a
        deadline for the whole stream (default: none).
        """
        header = ingest_header(
            map, top_k, verify, exclude_same_agent, loop_closure, max_in_flight, camera
        )
        window = threading.Semaphore(max_in_flight)
        finished = threading.Event()
        failure: List[BaseException] = []

        def requests() -> Iterator[pb.IngestRequest]:
            yield pb.IngestRequest(header=header)
            try:
                for index, item in enumerate(frames):
                    observation = to_observation(item, agent_id, index, f"frames[{index}]")
                    while not window.acquire(timeout=0.1):
                        if finished.is_set():
                            return
                    if finished.is_set():
                        return
                    yield pb.IngestRequest(observation=observation)
            except Exception as e:  # reported to the caller after the answered frames
                failure.append(e)

        call = self._stub.Ingest(requests(), **self._options(timeout))
        try:
            for response in call:
                window.release()
                yield IngestResult.from_proto(response)
        except grpc.RpcError as e:
            if failure:
                raise failure[0] from None
            raise from_rpc_error(e) from None
        finally:
            finished.set()
            call.cancel()
        if failure:
            raise failure[0]

    # ---- Places --------------------------------------------------------------------------------

    def get_place(
        self,
        map: str,
        place_id: int,
        include_features: bool = False,
        thumbnail: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Place:
        """One stored place with its dynamic-object statistics; ``include_features`` adds its
        static keypoints and descriptors, ``thumbnail`` its :class:`Thumbnail` (when the map was
        created with ``MapSettings(thumbnails=ThumbnailSettings(enabled=True))`` and kept one
        for this place; else :attr:`Place.thumbnail` is None).

        :class:`NotFound` if the map or the place does not exist.
        """
        request = pb.GetPlaceRequest(
            map=map,
            place_id=place_id,
            include_features=include_features,
            include_thumbnail=thumbnail,
        )
        return Place.from_proto(self._call(self._stub.GetPlace, request, timeout))

    def list_places(
        self,
        map: str,
        agent_id: Optional[str] = None,
        from_ns: Optional[int] = None,
        to_ns: Optional[int] = None,
        limit: int = 100,
        before: Optional[int] = None,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> PlacePage:
        """One page of the map's places, newest (highest id) first, with metadata, counts and
        boxes (no features, statistics or thumbnails: :meth:`get_place` has them).

        ``agent_id``: only this agent's places. ``from_ns`` / ``to_ns``: only places observed at
        or after / before these Unix nanoseconds. ``limit``: at most this many places (1..1000).
        ``before``: resume below this place id (the previous page's
        :attr:`PlacePage.next_before`; None = from the newest). A page may be short or even
        empty while ``next_before`` is not 0: keep paging until it is 0, or use
        :meth:`iter_places`.

        :class:`NotFound` for an unknown map; :class:`InvalidArgument` naming the field for a
        bad limit or paging value.
        """
        request = list_places_request(map, agent_id, from_ns, to_ns, limit, before)
        return PlacePage.from_proto(self._call(self._stub.ListPlaces, request, timeout))

    def iter_places(
        self,
        map: str,
        agent_id: Optional[str] = None,
        from_ns: Optional[int] = None,
        to_ns: Optional[int] = None,
        limit: int = 100,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Iterator[Place]:
        """Every place of the map (filtered as :meth:`list_places`), newest first, each once.

        A generator calling :meth:`list_places` page by page (``limit`` per call, ``timeout``
        per call) until the server's ``next_before`` is 0, across short and empty pages.
        Places stored meanwhile have higher ids and are not visited.
        """
        before: Optional[int] = None
        while True:
            page = self.list_places(map, agent_id, from_ns, to_ns, limit, before, timeout)
            yield from page.places
            if page.next_before == 0:
                return
            before = page.next_before

    def watch_loop_closures(
        self,
        map: str,
        from_sequence: int = 1,
        follow: bool = False,
        agents: Iterable[str] = (),
        inter_agent_only: bool = False,
        min_sequence_gap: int = 0,
        timeout: Timeout = None,
    ) -> Iterator[LoopConstraint]:
        """The map's loop-closure log from ``from_sequence`` on, in order: every verified match
        found while ingesting (and every loop an agent's detector accepted), each once, with
        T_place_query and its information when both frames had cameras (:class:`LoopConstraint`).

        ``follow``: keep waiting for new constraints (each arrives once it is durable, before
        its frame's Ingest answer); close the generator (or break out of the loop) to stop.
        After a disconnect, resume with the last ``sequence`` received + 1: nothing is missed or
        repeated. ``agents``: only constraints with one of these agents on either side;
        ``inter_agent_only``: only between two agents; ``min_sequence_gap``: within one agent,
        only frames this many sequence numbers apart (a frame matching its agent's previous
        frames is odometry, not a loop).

        :class:`NotFound` for an unknown map (or one deleted while followed);
        :class:`Unavailable` when the server shuts down.
        """
        request = watch_loop_closures_request(
            map, from_sequence, follow, agents, inter_agent_only, min_sequence_gap
        )
        call = self._stub.WatchLoopClosures(request, **self._options(timeout))
        try:
            for message in call:
                if message.sequence == 0:
                    continue  # caught up: nothing to hand over
                yield LoopConstraint.from_proto(message)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None
        finally:
            call.cancel()

    def delete_place(self, map: str, place_id: int, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """Removes a place durably; its id is never reused (:class:`NotFound` if absent)."""
        self._call(
            self._stub.DeletePlace, pb.DeletePlaceRequest(map=map, place_id=place_id), timeout
        )

    def get_dynamics(
        self,
        map: str,
        measure: Optional[str] = None,
        class_name: Optional[str] = None,
        class_id: Optional[int] = None,
        hours: Optional[Tuple[int, int]] = None,
        weekdays: Optional[Iterable[Union[str, int]]] = None,
        limit: int = 50,
        offset: int = 0,
        min_observations: int = 0,
        include_statistics: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Dynamics:
        """Dynamic-object statistics (issue 16): the map's and a page of its places, ranked.

        ``measure``: ``"mean_coverage"`` (share of the image on dynamic objects),
        ``"class_share"`` (share of observations that saw a class: ``class_name``, a COCO name
        such as ``"person"``, or ``class_id``) or ``"hour_window"`` (mean coverage in
        ``hours=(first, last)``, UTC, inclusive, wrapping midnight when first > last, on
        ``weekdays``: names ``"mon"``..``"sun"`` or 0 = Monday .. 6 = Sunday; None = every
        day). None: ``"class_share"`` when a class is given, ``"hour_window"`` when hours are,
        else ``"mean_coverage"``. ``min_observations``: places with fewer (in the window) are
        not ranked. Pages: ``limit`` (1..1000) entries from ``offset``; pass
        :attr:`Dynamics.next_offset` for the next one (0: this was the last). A page past the
        end is empty. ``include_statistics``: each entry's full statistics.

        :class:`NotFound` for an unknown map; :class:`InvalidArgument` naming the field for a
        bad class, hours, weekdays, limit or measure.
        """
        request = dynamics_request(
            map,
            measure,
            class_name,
            class_id,
            hours,
            weekdays,
            limit,
            offset,
            min_observations,
            include_statistics,
        )
        return Dynamics.from_proto(self._call(self._stub.GetDynamics, request, timeout))

    # ---- Snapshots (admin) ---------------------------------------------------------------------

    def create_snapshot(self, map: str, timeout: Timeout = None) -> Snapshot:
        """A consistent, verified copy of ``map``, kept by the server; ingest may go on.

        The server keeps ``storage.snapshots_keep_per_map`` snapshots per map (the oldest
        beyond go). Takes as long as flushing, copying and verifying the map (``timeout``:
        default none). :class:`NotFound` for an unknown map; :class:`PermissionDenied` unless
        the caller is an admin.
        """
        response = self._call(
            self._stub.CreateSnapshot, pb.CreateSnapshotRequest(map=map), timeout
        )
        return Snapshot.from_proto(response)

    def list_snapshots(
        self, map: Optional[str] = None, timeout: Timeout = CLIENT_TIMEOUT
    ) -> List[Snapshot]:
        """Every snapshot (of ``map``, when given; by its source map's name), newest first."""
        response = self._call(self._stub.ListSnapshots, pb.ListSnapshotsRequest(), timeout)
        found = [Snapshot.from_proto(s) for s in response.snapshots]
        return [s for s in found if map is None or s.map == map]

    def delete_snapshot(self, snapshot_id: str, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """Deletes a snapshot (:class:`NotFound` if absent); its map is not touched."""
        self._call(self._stub.DeleteSnapshot, pb.DeleteSnapshotRequest(id=snapshot_id), timeout)

    def download_snapshot(
        self,
        snapshot_id: str,
        dest: snapshots.PathOrFile,
        progress: Optional[snapshots.Progress] = None,
        overwrite: bool = False,
        timeout: Timeout = None,
    ) -> Snapshot:
        """Downloads a snapshot's archive into ``dest`` (a path or a binary file object).

        A path is written as ``<dest>.partial`` and renamed once the size the server announced
        and the archive's trailing SHA-256 both check out; an existing ``dest`` is never
        replaced unless ``overwrite`` (else :class:`AlreadyExists`, before anything is sent).
        A mismatch raises :class:`DataLoss`, a broken stream its error (e.g.
        :class:`Unavailable` when the server shuts down); in every failure nothing is left at
        ``dest`` or ``<dest>.partial``. A file object gets the bytes as they arrive (the checks
        still raise, but what arrived stays written). ``progress(done, total)`` is called after
        every chunk, in this thread. Returns the snapshot with ``archive_bytes`` and
        ``archive_sha256``.
        """
        options = self._options(timeout)
        return snapshots.download(
            lambda: self._stub.DownloadSnapshot(
                pb.DownloadSnapshotRequest(id=snapshot_id), **options
            ),
            dest,
            progress,
            overwrite,
        )

    def upload_snapshot(
        self,
        src: snapshots.PathOrFile,
        progress: Optional[snapshots.Progress] = None,
        timeout: Timeout = None,
    ) -> Snapshot:
        """Uploads an archive (from :meth:`download_snapshot`) as a new snapshot of this server.

        ``src``: a path or a binary file object (read from its position). The size is announced
        when known, and the archive streamed in 256 KiB chunks; ``progress(done, total)`` is
        called in this thread as they go (``total`` 0: unknown). The server checks the format,
        the SHA-256, the vocabulary and that it opens and scrubs clean as a map before keeping
        it: a truncated or corrupted archive raises :class:`DataLoss`, a foreign one
        :class:`InvalidArgument`, an unknown vocabulary :class:`FailedPrecondition`, and
        nothing is kept. The snapshot keeps the archive's id unless that is taken.
        """
        options = self._options(timeout)
        return snapshots.upload(
            lambda requests: self._stub.UploadSnapshot.future(requests, **options),
            src,
            progress,
        )

    def restore_snapshot(
        self, snapshot_id: str, new_map: str, timeout: Timeout = None
    ) -> MapInfo:
        """The snapshot as a new map ``new_map``, served at once.

        :class:`AlreadyExists` when the name is taken, :class:`NotFound` for an unknown
        snapshot. Copies the snapshot's files (``timeout``: default none).
        """
        response = self._call(
            self._stub.RestoreSnapshot,
            pb.RestoreSnapshotRequest(id=snapshot_id, new_map=new_map),
            timeout,
        )
        return MapInfo.from_proto(response)

    # ---- Server --------------------------------------------------------------------------------

    def server_info(self, timeout: Timeout = CLIENT_TIMEOUT) -> ServerInfo:
        """The server's version, vocabularies, detector and limits."""
        return ServerInfo.from_proto(
            self._call(self._stub.GetServerInfo, pb.GetServerInfoRequest(), timeout)
        )

    def health(self, service: str = "", timeout: Timeout = CLIENT_TIMEOUT) -> str:
        """The grpc.health.v1 status: ``"serving"``, ``"not_serving"``, ``"service_unknown"``
        or ``"unknown"`` (``service``: "" = the whole server, or ``"placedb.v1.PlaceDb"``).

        :class:`Unavailable` when the server cannot be reached.
        """
        response = self._call(
            self._health.Check, health_pb2.HealthCheckRequest(service=service), timeout
        )
        return health_status(response)


__all__ = ["CLIENT_TIMEOUT", "Client", "TLS", "Error"]
