"""placedb.aio.AsyncClient against a real placedb-server: the blocking client's calls under the
same names and with the same answers, concurrent ingest streams, errors, cancellation."""

from __future__ import annotations

import asyncio
import inspect
from pathlib import Path
from typing import Any, AsyncIterator, List

import numpy as np
import pytest
from conftest import textured_image, unused_loopback_port

import placedb
from placedb.aio import AsyncClient

MAIN_CALLS = [
    "create_map",
    "get_map",
    "list_maps",
    "delete_map",
    "recover_map",
    "scrub_map",
    "adapt_vocabulary",
    "revert_vocabulary",
    "query",
    "ingest",
    "get_place",
    "list_places",
    "iter_places",
    "delete_place",
    "watch_loop_closures",
    "get_dynamics",
    "server_info",
    "health",
]


def test_same_names_and_arguments_as_the_blocking_client() -> None:
    for name in MAIN_CALLS:
        blocking = inspect.signature(getattr(placedb.Client, name))
        asynchronous = inspect.signature(getattr(AsyncClient, name))
        assert list(asynchronous.parameters) == list(blocking.parameters), name
        for parameter in blocking.parameters.values():
            assert asynchronous.parameters[parameter.name].default == parameter.default, name
    assert placedb.AsyncClient is AsyncClient


def _run(coroutine: Any) -> Any:
    return asyncio.run(asyncio.wait_for(coroutine, timeout=60))


def test_async_round_trip_matches_the_blocking_client(
    server, client: placedb.Client, rtabmap_frames: List[Path]
) -> None:
    frames = rtabmap_frames[:12]

    async def main() -> dict:
        async with AsyncClient(server.address) as aclient:
            assert await aclient.health() == "serving"
            assert (await aclient.server_info()).version == client.server_info().version
            created = await aclient.create_map("aio")
            assert created.name == "aio" and created.places == 0
            with pytest.raises(placedb.AlreadyExists):
                await aclient.create_map("aio")
            results = [r async for r in aclient.ingest("aio", frames, agent_id="a1")]
            summary = {m.name: m for m in await aclient.list_maps()}["aio"]
            answer = await aclient.query("aio", frames[5], top_k=3)
            place = await aclient.get_place("aio", results[5].place_id, include_features=True)
            page = await aclient.list_places("aio", limit=5)
            every = [p.place_id async for p in aclient.iter_places("aio", limit=5)]
            dynamics = await aclient.get_dynamics("aio")
            scrub = await aclient.scrub_map("aio")
            got = await aclient.get_map("aio")
            return locals()

    out = _run(main())
    results = out["results"]
    assert [r.index for r in results] == list(range(len(frames)))
    assert all(r.stored for r in results)
    assert out["summary"].places == len(frames) == out["got"].places
    # The same answers as the blocking client's on the same map.
    assert out["answer"].matches == client.query("aio", frames[5], top_k=3).matches
    assert out["answer"].matches[0].place_id == results[5].place_id
    assert out["place"] == client.get_place("aio", results[5].place_id, include_features=True)
    assert out["page"] == client.list_places("aio", limit=5)
    assert out["every"] == [p.place_id for p in client.iter_places("aio")]
    assert out["every"] == sorted((r.place_id for r in results), reverse=True)
    assert out["dynamics"] == client.get_dynamics("aio")
    assert out["scrub"].clean and out["scrub"].places_checked == len(frames)

    async def delete() -> None:
        async with AsyncClient(server.address) as aclient:
            await aclient.delete_place("aio", results[0].place_id)
            with pytest.raises(placedb.NotFound):
                await aclient.get_place("aio", results[0].place_id)
            await aclient.delete_map("aio")
            with pytest.raises(placedb.NotFound) as missing:
                await aclient.get_map("aio")
            assert missing.value.code.name == "NOT_FOUND" and "aio" in missing.value.message

    _run(delete())
    assert "aio" not in [m.name for m in client.list_maps()]


def test_async_loop_closure_log_matches_the_blocking_client(
    server, client: placedb.Client, rtabmap_frames: List[Path]
) -> None:
    frames = rtabmap_frames[:6]
    client.create_map("aio-loops", placedb.MapSettings(verification="exhaustive"))
    list(client.ingest("aio-loops", frames, agent_id="a1"))
    list(client.ingest("aio-loops", frames[:3], agent_id="a2", top_k=3))
    blocking = list(client.watch_loop_closures("aio-loops"))
    assert blocking and any(c.inter_agent for c in blocking)

    async def main() -> List[placedb.LoopConstraint]:
        async with AsyncClient(server.address) as aclient:
            return [c async for c in aclient.watch_loop_closures("aio-loops")]

    assert _run(main()) == blocking


def test_concurrent_async_ingest_streams_from_async_sources(server, client: placedb.Client) -> None:
    """Two agents' streams at once on one channel, each fed by an async generator (frames
    arriving over time, as from a camera callback)."""

    async def camera(seed: int, count: int) -> AsyncIterator[np.ndarray]:
        for i in range(count):
            await asyncio.sleep(0)  # another task runs between frames
            yield textured_image(seed * 100 + i)

    async def main() -> List[List[placedb.IngestResult]]:
        async with AsyncClient(server.address) as aclient:
            await aclient.create_map("aio-agents")

            async def agent(seed: int) -> List[placedb.IngestResult]:
                stream = aclient.ingest(
                    "aio-agents", camera(seed, 10), agent_id=f"robot-{seed}", max_in_flight=2
                )
                return [r async for r in stream]

            return await asyncio.gather(agent(1), agent(2))

    first, second = _run(main())
    assert [len(first), len(second)] == [10, 10]
    assert all(r.stored for r in first + second)
    ids = {r.place_id for r in first + second}
    assert len(ids) == 20
    agents = {p.place_id: p.agent_id for p in client.iter_places("aio-agents")}
    assert {agents[r.place_id] for r in first} == {"robot-1"}
    assert {agents[r.place_id] for r in second} == {"robot-2"}


def test_async_ingest_errors_and_cancellation(server, client: placedb.Client) -> None:
    client.create_map("aio-errors")

    async def main() -> None:
        async with AsyncClient(server.address) as aclient:
            # Unknown map: NotFound when iterated.
            with pytest.raises(placedb.NotFound):
                async for _ in aclient.ingest("no-such-map", [textured_image(1)]):
                    pass
            # A frame the SDK refuses ends the stream after the frames before it.
            frames = [textured_image(2), textured_image(3), np.zeros((8, 8), np.float64)]
            seen = []
            with pytest.raises(placedb.InvalidArgument, match=r"frames\[2\]"):
                async for result in aclient.ingest("aio-errors", frames, agent_id="e"):
                    seen.append(result.index)
            assert seen == [0, 1]

            # A failing async source: the same.
            async def broken() -> AsyncIterator[np.ndarray]:
                yield textured_image(4)
                raise RuntimeError("camera unplugged")

            seen = []
            with pytest.raises(RuntimeError, match="camera unplugged"):
                async for result in aclient.ingest("aio-errors", broken(), agent_id="e"):
                    seen.append(result.index)
            assert seen == [0]

            # Leaving the loop early cancels the stream; the channel goes on working.
            endless = (textured_image(1000 + i) for i in range(10_000))
            stream = aclient.ingest("aio-errors", endless, agent_id="e", max_in_flight=2)
            async for result in stream:
                if result.index == 2:
                    break
            await stream.aclose()
            assert (await aclient.get_map("aio-errors")).places < 20
            with pytest.raises(placedb.InvalidArgument, match="max_in_flight"):
                async for _ in aclient.ingest("aio-errors", [], max_in_flight=0):
                    pass
            with pytest.raises(placedb.InvalidArgument, match="limit"):
                await aclient.list_places("aio-errors", limit=0)

    _run(main())

    async def unreachable() -> None:
        address = f"127.0.0.1:{unused_loopback_port()}"
        async with AsyncClient(address, timeout=5) as aclient:
            with pytest.raises(placedb.Unavailable):
                await aclient.list_maps()
        async with AsyncClient(address, timeout=0.3, wait_for_ready=True) as aclient:
            with pytest.raises(placedb.DeadlineExceeded):
                await aclient.list_maps()

    _run(unreachable())


def test_async_ingest_stops_reading_frames_at_the_window(server, client: placedb.Client) -> None:
    """Frames are pulled lazily: at most max_in_flight beyond the results consumed."""
    client.create_map("aio-window")
    pulled: List[int] = []

    async def frames() -> AsyncIterator[np.ndarray]:
        for i in range(12):
            pulled.append(i)
            yield textured_image(seed=200 + i)

    async def main() -> List[int]:
        async with AsyncClient(server.address) as aclient:
            stream = aclient.ingest("aio-window", frames(), agent_id="w", max_in_flight=2)
            first = await stream.__anext__()
            assert first.index == 0
            # 1 result consumed: at most 1 + 2 frames sent, plus one converted and waiting.
            assert len(pulled) <= 4
            return [r.index async for r in stream]

    assert _run(main()) == list(range(1, 12))
    assert len(pulled) == 12
