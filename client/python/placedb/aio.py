"""The asyncio client: :class:`AsyncClient`, over ``grpc.aio``, beside the blocking
:class:`placedb.Client`.

    import asyncio, placedb.aio

    async def main():
        async with placedb.aio.AsyncClient("127.0.0.1:50051") as client:
            await client.create_map("lab")
            async for result in client.ingest("lab", ["1.jpg", "2.jpg"], agent_id="robot-1"):
                print(result.index, result.stored, result.place_id)
            print((await client.query("lab", "3.jpg", top_k=5)).matches)

    asyncio.run(main())

The methods have the blocking client's names, arguments, results and errors (each a coroutine;
``ingest`` and ``iter_places`` are async generators). Snapshots and their transfers are the
blocking client's only. Create the client inside the event loop that uses it.
"""

from __future__ import annotations

import asyncio
from typing import (
    Any,
    AsyncIterable,
    AsyncIterator,
    Iterable,
    List,
    Optional,
    Tuple,
    Union,
)

import grpc
import grpc.aio

from placedb._pb import health_pb2, health_pb2_grpc
from placedb._pb import placedb_pb2 as pb
from placedb._pb import placedb_pb2_grpc as pb_grpc
from placedb.client import (
    CHANNEL_OPTIONS,
    CLIENT_TIMEOUT,
    TLS,
    Timeout,
    _ClientTimeout,
    _credentials,
    check_timeout,
    create_map_request,
    dynamics_request,
    health_status,
    ingest_header,
    list_places_request,
    query_request,
    token_metadata,
    watch_loop_closures_request,
)
from placedb.errors import from_rpc_error
from placedb.frames import Frame, ImageLike, to_observation
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
)
from placedb.settings import MapSettings

FrameLike = Union[Frame, ImageLike]


async def _frames(frames: Union[Iterable[FrameLike], AsyncIterable[FrameLike]]):
    if hasattr(frames, "__aiter__"):
        async for item in frames:  # type: ignore[union-attr]
            yield item
    else:
        for item in frames:  # type: ignore[union-attr]
            yield item


class AsyncClient:
    """A connection to a placedb server for asyncio code; the arguments are
    :class:`placedb.Client`'s. Usable as ``async with``; :meth:`close` closes the channel."""

    def __init__(
        self,
        target: str,
        token: Optional[str] = None,
        tls: Union[None, bool, TLS] = None,
        timeout: Optional[float] = 30.0,
        wait_for_ready: bool = False,
    ) -> None:
        self._timeout = check_timeout(timeout)
        if tls:
            self._channel = grpc.aio.secure_channel(
                target, _credentials(tls), options=CHANNEL_OPTIONS
            )
        else:
            self._channel = grpc.aio.insecure_channel(target, options=CHANNEL_OPTIONS)
        self._metadata = token_metadata(token)
        self._wait_for_ready = wait_for_ready
        self._stub = pb_grpc.PlaceDbStub(self._channel)
        self._health = health_pb2_grpc.HealthStub(self._channel)

    async def close(self) -> None:
        """Closes the channel; calls in flight are cancelled."""
        await self._channel.close()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    def _options(self, timeout: Timeout) -> dict:
        deadline = self._timeout if isinstance(timeout, _ClientTimeout) else check_timeout(timeout)
        return {
            "timeout": deadline,
            "metadata": self._metadata,
            "wait_for_ready": self._wait_for_ready,
        }

    async def _call(self, method: Any, request: Any, timeout: Timeout = CLIENT_TIMEOUT) -> Any:
        options = self._options(timeout)
        try:
            return await method(request, **options)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None

    # ---- Maps ----------------------------------------------------------------------------------

    async def create_map(
        self,
        name: str,
        settings: Union[None, MapSettings, pb.MapConfig] = None,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> MapInfo:
        """As :meth:`placedb.Client.create_map`."""
        response = await self._call(
            self._stub.CreateMap, create_map_request(name, settings), timeout
        )
        return MapInfo.from_proto(response)

    async def get_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> MapInfo:
        """As :meth:`placedb.Client.get_map`."""
        response = await self._call(self._stub.GetMap, pb.GetMapRequest(name=name), timeout)
        return MapInfo.from_proto(response)

    async def list_maps(self, timeout: Timeout = CLIENT_TIMEOUT) -> List[MapSummary]:
        """As :meth:`placedb.Client.list_maps`."""
        response = await self._call(self._stub.ListMaps, pb.ListMapsRequest(), timeout)
        return [MapSummary.from_proto(m) for m in response.maps]

    async def delete_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> None:
        """As :meth:`placedb.Client.delete_map`."""
        await self._call(self._stub.DeleteMap, pb.DeleteMapRequest(name=name), timeout)

    async def recover_map(
        self, name: str, accept_data_loss: bool, timeout: Timeout = CLIENT_TIMEOUT
    ) -> Tuple[MapInfo, MapDamage]:
        """As :meth:`placedb.Client.recover_map`."""
        response = await self._call(
            self._stub.RecoverMap,
            pb.RecoverMapRequest(name=name, accept_data_loss=accept_data_loss),
            timeout,
        )
        return MapInfo.from_proto(response.map), MapDamage.from_proto(response.accepted)

    async def scrub_map(self, name: str, timeout: Timeout = CLIENT_TIMEOUT) -> ScrubReport:
        """As :meth:`placedb.Client.scrub_map`."""
        response = await self._call(self._stub.ScrubMap, pb.ScrubMapRequest(name=name), timeout)
        return ScrubReport.from_proto(response)

    async def adapt_vocabulary(
        self,
        name: str,
        seed: int = 0,
        max_sample_descriptors: int = 0,
        branching: int = 0,
        depth: int = 0,
        timeout: Timeout = None,
    ) -> MapVocabulary:
        """As :meth:`placedb.Client.adapt_vocabulary`."""
        request = pb.AdaptVocabularyRequest(
            name=name,
            seed=seed,
            max_sample_descriptors=max_sample_descriptors,
            branching=branching,
            depth=depth,
        )
        response = await self._call(self._stub.AdaptVocabulary, request, timeout)
        return MapVocabulary.from_proto(response)

    async def revert_vocabulary(self, name: str, timeout: Timeout = None) -> MapVocabulary:
        """As :meth:`placedb.Client.revert_vocabulary`."""
        request = pb.RevertVocabularyRequest(name=name)
        response = await self._call(self._stub.RevertVocabulary, request, timeout)
        return MapVocabulary.from_proto(response)

    # ---- Query and ingest ----------------------------------------------------------------------

    async def query(
        self,
        map: str,
        image: FrameLike,
        top_k: int = 10,
        verify: bool = False,
        exclude_same_agent: bool = False,
        agent_id: str = "",
        correspondences: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> QueryResult:
        """As :meth:`placedb.Client.query`."""
        request = query_request(
            map, image, top_k, verify, exclude_same_agent, agent_id, correspondences
        )
        return QueryResult.from_proto(await self._call(self._stub.Query, request, timeout))

    async def ingest(
        self,
        map: str,
        frames: Union[Iterable[FrameLike], AsyncIterable[FrameLike]],
        agent_id: str = "agent",
        top_k: int = 0,
        verify: bool = False,
        exclude_same_agent: bool = False,
        loop_closure: bool = False,
        max_in_flight: int = 8,
        timeout: Timeout = None,
        camera: Optional[Camera] = None,
    ) -> AsyncIterator[IngestResult]:
        """As :meth:`placedb.Client.ingest`, an async generator: ``async for result in
        client.ingest(...)``. ``frames``: an iterable or an async iterable (e.g. frames arriving
        from a camera callback through an ``asyncio.Queue``), consumed lazily with at most
        ``max_in_flight`` frames sent and not yet answered. A frame the SDK cannot convert, or an
        exception from ``frames``, ends the stream: the results before it are yielded, then it is
        raised. Leaving the loop early cancels the stream.
        """
        header = ingest_header(
            map, top_k, verify, exclude_same_agent, loop_closure, max_in_flight, camera
        )
        window = asyncio.Semaphore(max_in_flight)
        failure: List[BaseException] = []

        async def requests() -> AsyncIterator[pb.IngestRequest]:
            yield pb.IngestRequest(header=header)
            try:
                index = 0
                async for item in _frames(frames):
                    observation = to_observation(item, agent_id, index, f"frames[{index}]")
                    await window.acquire()
                    yield pb.IngestRequest(observation=observation)
                    index += 1
            except Exception as e:  # reported to the caller after the answered frames
                failure.append(e)

        call = self._stub.Ingest(requests(), **self._options(timeout))
        try:
            async for response in call:
                window.release()
                yield IngestResult.from_proto(response)
        except grpc.RpcError as e:
            if failure:
                raise failure[0] from None
            raise from_rpc_error(e) from None
        finally:
            call.cancel()
        if failure:
            raise failure[0]

    # ---- Places --------------------------------------------------------------------------------

    async def get_place(
        self,
        map: str,
        place_id: int,
        include_features: bool = False,
        thumbnail: bool = False,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> Place:
        """As :meth:`placedb.Client.get_place`."""
        request = pb.GetPlaceRequest(
            map=map,
            place_id=place_id,
            include_features=include_features,
            include_thumbnail=thumbnail,
        )
        return Place.from_proto(await self._call(self._stub.GetPlace, request, timeout))

    async def list_places(
        self,
        map: str,
        agent_id: Optional[str] = None,
        from_ns: Optional[int] = None,
        to_ns: Optional[int] = None,
        limit: int = 100,
        before: Optional[int] = None,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> PlacePage:
        """As :meth:`placedb.Client.list_places`."""
        request = list_places_request(map, agent_id, from_ns, to_ns, limit, before)
        return PlacePage.from_proto(await self._call(self._stub.ListPlaces, request, timeout))

    async def iter_places(
        self,
        map: str,
        agent_id: Optional[str] = None,
        from_ns: Optional[int] = None,
        to_ns: Optional[int] = None,
        limit: int = 100,
        timeout: Timeout = CLIENT_TIMEOUT,
    ) -> AsyncIterator[Place]:
        """As :meth:`placedb.Client.iter_places`, an async generator."""
        before: Optional[int] = None
        while True:
            page = await self.list_places(map, agent_id, from_ns, to_ns, limit, before, timeout)
            for place in page.places:
                yield place
            if page.next_before == 0:
                return
            before = page.next_before

    async def watch_loop_closures(
        self,
        map: str,
        from_sequence: int = 1,
        follow: bool = False,
        agents: Iterable[str] = (),
        inter_agent_only: bool = False,
        min_sequence_gap: int = 0,
        timeout: Timeout = None,
    ) -> AsyncIterator[LoopConstraint]:
        """As :meth:`placedb.Client.watch_loop_closures`, an async generator."""
        request = watch_loop_closures_request(
            map, from_sequence, follow, agents, inter_agent_only, min_sequence_gap
        )
        call = self._stub.WatchLoopClosures(request, **self._options(timeout))
        try:
            async for message in call:
                if message.sequence == 0:
                    continue  # caught up: nothing to hand over
                yield LoopConstraint.from_proto(message)
        except grpc.RpcError as e:
            raise from_rpc_error(e) from None
        finally:
            call.cancel()

    async def delete_place(
        self, map: str, place_id: int, timeout: Timeout = CLIENT_TIMEOUT
    ) -> None:
        """As :meth:`placedb.Client.delete_place`."""
        await self._call(
            self._stub.DeletePlace, pb.DeletePlaceRequest(map=map, place_id=place_id), timeout
        )

    async def get_dynamics(
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
        """As :meth:`placedb.Client.get_dynamics`."""
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
        return Dynamics.from_proto(await self._call(self._stub.GetDynamics, request, timeout))

    # ---- Server --------------------------------------------------------------------------------

    async def server_info(self, timeout: Timeout = CLIENT_TIMEOUT) -> ServerInfo:
        """As :meth:`placedb.Client.server_info`."""
        response = await self._call(self._stub.GetServerInfo, pb.GetServerInfoRequest(), timeout)
        return ServerInfo.from_proto(response)

    async def health(self, service: str = "", timeout: Timeout = CLIENT_TIMEOUT) -> str:
        """As :meth:`placedb.Client.health`."""
        response = await self._call(
            self._health.Check, health_pb2.HealthCheckRequest(service=service), timeout
        )
        return health_status(response)


__all__ = ["AsyncClient"]
