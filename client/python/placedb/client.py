"""The placedb client: one gRPC channel to a placedb server and a method per operation.

Every call raises a :class:`placedb.Error` subclass on failure (the gRPC code and the server's
message). Unary calls have a deadline (``Client(timeout=...)``, default 30 s); ingest streams
have none (the server closes idle streams, see docs/service.md).
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
from placedb.frames import Frame, ImageLike, to_observation
from placedb.results import (
    IngestResult,
    MapDamage,
    MapInfo,
    MapSummary,
    Place,
    QueryResult,
    ScrubReport,
    ServerInfo,
)
from placedb.settings import MapSettings


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


def _match_options(top_k: int, verify: bool, exclude_same_agent: bool) -> pb.MatchOptions:
    if top_k < 0:
        raise InvalidArgument(f"top_k: {top_k} is negative")
    return pb.MatchOptions(top_k=top_k, verified_only=verify, exclude_same_agent=exclude_same_agent)


class Client:
    """A connection to a placedb server.

    ``target``: ``host:port`` (e.g. ``"127.0.0.1:50051"``). ``token``: a bearer token from
    ``placedb-server tokens add`` (sent as ``authorization: Bearer <token>``). ``tls``: ``None``
    for plaintext, ``True`` for TLS with the system roots, or a :class:`TLS` with PEM paths.
    ``timeout``: seconds per unary call (None: no deadline). ``wait_for_ready``: calls made while
    the server is unreachable wait for it (up to their deadline: :class:`DeadlineExceeded`)
    instead of failing at once with :class:`Unavailable`; for agents that start before the
    server.

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
        options = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]
        if tls:
            self._channel = grpc.secure_channel(target, _credentials(tls), options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        self._metadata: Sequence[Tuple[str, str]] = (
            (("authorization", f"Bearer {token}"),) if token else ()
        )
        self._timeout = timeout
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

    def _call(self, method: Any, request: Any) -> Any:
        try:
            return method(
                request,
                timeout=self._timeout,
                metadata=self._metadata,
                wait_for_ready=self._wait_for_ready,
            )
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None

    # ---- Maps ----------------------------------------------------------------------------------

    def create_map(
        self, name: str, settings: Union[None, MapSettings, pb.MapConfig] = None
    ) -> MapInfo:
        """Creates a durable map; returns it with its effective configuration.

        ``settings``: a :class:`MapSettings` (or a ``placedb.v1.MapConfig``); None = defaults.
        Raises :class:`AlreadyExists` if the name is taken, :class:`InvalidArgument` for a bad
        name (1-64 of ``[A-Za-z0-9_.-]``, starting with a letter or digit), an unknown
        vocabulary or a bad setting.
        """
        if isinstance(settings, MapSettings):
            config = settings.to_proto()
        else:
            config = settings if settings is not None else pb.MapConfig()
        response = self._call(self._stub.CreateMap, pb.CreateMapRequest(name=name, config=config))
        return MapInfo.from_proto(response)

    def get_map(self, name: str) -> MapInfo:
        """A map's state, configuration and statistics (:class:`NotFound` if absent)."""
        return MapInfo.from_proto(self._call(self._stub.GetMap, pb.GetMapRequest(name=name)))

    def list_maps(self) -> List[MapSummary]:
        """Every map the caller may read, including those that could not be opened (and why)."""
        response = self._call(self._stub.ListMaps, pb.ListMapsRequest())
        return [MapSummary.from_proto(m) for m in response.maps]

    def delete_map(self, name: str) -> None:
        """Deletes a map and all its places, durably (:class:`NotFound` if absent)."""
        self._call(self._stub.DeleteMap, pb.DeleteMapRequest(name=name))

    def recover_map(self, name: str, accept_data_loss: bool) -> Tuple[MapInfo, MapDamage]:
        """Reopens a damaged map, accepting what was lost (docs/storage.md, "Damage").

        Returns the map and what this recovery accepted as lost. :class:`InvalidArgument`
        without ``accept_data_loss``; :class:`FailedPrecondition` when the map is not damaged
        or cannot be recovered this way.
        """
        response = self._call(
            self._stub.RecoverMap,
            pb.RecoverMapRequest(name=name, accept_data_loss=accept_data_loss),
        )
        return MapInfo.from_proto(response.map), MapDamage.from_proto(response.accepted)

    def scrub_map(self, name: str) -> ScrubReport:
        """Reads and checks every place and SST block of a map; damage is reported, not raised."""
        return ScrubReport.from_proto(
            self._call(self._stub.ScrubMap, pb.ScrubMapRequest(name=name))
        )

    # ---- Query and ingest ----------------------------------------------------------------------

    def query(
        self,
        map: str,
        image: Union[Frame, ImageLike],
        top_k: int = 10,
        verify: bool = False,
        exclude_same_agent: bool = False,
        agent_id: str = "",
    ) -> QueryResult:
        """Ranked matches of one frame against a map; nothing is stored.

        ``image``: any frame form (see :mod:`placedb.frames`). ``top_k``: at most this many
        matches (0 = the server's 10). ``verify``: keep only candidates that pass geometric
        verification (the map's verification mode). ``exclude_same_agent``: skip places stored by
        ``agent_id``. Raises :class:`NotFound` for an unknown map, :class:`InvalidArgument` for
        a frame the server or the SDK refuses.
        """
        request = pb.QueryRequest(
            map=map,
            observation=to_observation(image, agent_id, 0),
            options=_match_options(top_k, verify, exclude_same_agent),
        )
        return QueryResult.from_proto(self._call(self._stub.Query, request))

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
    ) -> Iterator[IngestResult]:
        """Streams frames into a map; yields one :class:`IngestResult` per frame, in order.

        A generator: nothing is sent until it is iterated. ``frames`` is consumed lazily, with
        at most ``max_in_flight`` frames sent and not yet answered, so a long sequence (a folder,
        a video) is never held in memory. Each frame's sequence defaults to its 0-based position.

        ``top_k`` > 0: every result carries its frame's matches against the map as it was before
        the frame (``verify`` and ``exclude_same_agent`` as for :meth:`query`). ``loop_closure``:
        the map's Bayesian loop closure per agent (:attr:`IngestResult.loop_closure`).

        A frame the server refuses is answered with :attr:`IngestResult.error` set and the stream
        goes on. A frame the SDK cannot convert (:class:`InvalidArgument`), or an exception from
        ``frames`` itself, ends the stream: the results of the frames before it are yielded,
        then it is raised. Stream-level failures (unknown map: :class:`NotFound`; too many
        streams: :class:`ResourceExhausted`) raise when iterated. Breaking out of the loop
        cancels the stream (frames in flight may or may not have been stored).
        """
        if max_in_flight < 1:
            raise InvalidArgument(f"max_in_flight: {max_in_flight}, expected >= 1")
        header = pb.IngestHeader(map=map, loop_closure=loop_closure)
        if top_k:
            header.matches.CopyFrom(_match_options(top_k, verify, exclude_same_agent))
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

        call = self._stub.Ingest(
            requests(), metadata=self._metadata, wait_for_ready=self._wait_for_ready
        )
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

    def get_place(self, map: str, place_id: int, include_features: bool = False) -> Place:
        """One stored place; ``include_features`` adds its static keypoints and descriptors.

        :class:`NotFound` if the map or the place does not exist.
        """
        request = pb.GetPlaceRequest(map=map, place_id=place_id, include_features=include_features)
        return Place.from_proto(self._call(self._stub.GetPlace, request))

    def delete_place(self, map: str, place_id: int) -> None:
        """Removes a place durably; its id is never reused (:class:`NotFound` if absent)."""
        self._call(self._stub.DeletePlace, pb.DeletePlaceRequest(map=map, place_id=place_id))

    # ---- Server --------------------------------------------------------------------------------

    def server_info(self) -> ServerInfo:
        """The server's version, vocabularies, detector and limits."""
        return ServerInfo.from_proto(
            self._call(self._stub.GetServerInfo, pb.GetServerInfoRequest())
        )

    def health(self, service: str = "") -> str:
        """The grpc.health.v1 status: ``"serving"``, ``"not_serving"``, ``"service_unknown"``
        or ``"unknown"`` (``service``: "" = the whole server, or ``"placedb.v1.PlaceDb"``).

        :class:`Unavailable` when the server cannot be reached.
        """
        response = self._call(self._health.Check, health_pb2.HealthCheckRequest(service=service))
        return health_pb2.HealthCheckResponse.ServingStatus.Name(response.status).lower()


__all__ = ["Client", "TLS", "Error"]
