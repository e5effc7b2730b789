"""Issue 20's API in the SDK against a real placedb-server: list_places / iter_places, query
correspondences, place thumbnails, per-agent activity and the new map settings."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import pytest

import placedb

try:
    import cv2
except ImportError:  # the JPEG checks fall back to parsing the header
    cv2 = None

# RTAB-Map frames 30-41 by agent-a, 42-53 by agent-b; timestamps 1 s apart from 100 s.
_AGENTS = {"agent-a": range(30, 42), "agent-b": range(42, 54)}


def _timestamp(frame: int) -> int:
    return (100 + frame) * 1_000_000_000


@pytest.fixture(scope="module")
def fleet(server, rtabmap_frames: List[Path]) -> Dict[str, List[Tuple[int, int]]]:
    """Map "fleet20": two agents' frames; agent -> [(place id, timestamp_ns)] of stored ones."""
    stored: Dict[str, List[Tuple[int, int]]] = {}
    with placedb.Client(server.address) as c:
        c.create_map("fleet20")
        for agent, frames in _AGENTS.items():
            items = [
                placedb.Frame(image=rtabmap_frames[i], timestamp_ns=_timestamp(i)) for i in frames
            ]
            results = list(c.ingest("fleet20", items, agent_id=agent))
            assert all(r.error is None for r in results)
            stored[agent] = [
                (r.place_id, _timestamp(frames[r.index])) for r in results if r.stored
            ]
            assert stored[agent]
    return stored


# ---- list_places / iter_places ------------------------------------------------------------------


def test_list_places_pages_visit_every_place_once_newest_first(
    client: placedb.Client, fleet: Dict[str, List[Tuple[int, int]]]
) -> None:
    every = sorted((p for places in fleet.values() for p, _ in places), reverse=True)
    seen: List[int] = []
    before = None
    pages = 0
    while True:
        page = client.list_places("fleet20", limit=5, before=before)
        assert isinstance(page, placedb.PlacePage)
        assert len(page.places) <= 5
        seen += [p.place_id for p in page.places]
        pages += 1
        if page.next_before == 0:
            break
        before = page.next_before
    assert seen == every
    assert pages >= len(every) // 5
    assert [p.place_id for p in client.iter_places("fleet20", limit=3)] == every
    assert [p.place_id for p in client.iter_places("fleet20")] == every

    # Pages carry metadata and counts, not features, statistics or thumbnails.
    newest = client.list_places("fleet20", limit=1).places[0]
    assert newest.place_id == every[0]
    assert newest.agent_id == "agent-b"
    assert newest.counts.kept > 0
    assert newest.keypoints is None and newest.thumbnail is None


def test_list_places_filters_by_agent_and_time(
    client: placedb.Client, fleet: Dict[str, List[Tuple[int, int]]]
) -> None:
    for agent, places in fleet.items():
        listed = list(client.iter_places("fleet20", agent_id=agent, limit=2))
        assert [p.place_id for p in listed] == sorted((p for p, _ in places), reverse=True)
        assert {p.agent_id for p in listed} == {agent}
    assert list(client.iter_places("fleet20", agent_id="nobody")) == []

    everything = [(p, t) for places in fleet.values() for p, t in places]
    lo, hi = _timestamp(36), _timestamp(48)  # [lo, hi): spans both agents
    window = [p.place_id for p in client.iter_places("fleet20", from_ns=lo, to_ns=hi)]
    assert window == sorted((p for p, t in everything if lo <= t < hi), reverse=True)
    assert all(lo <= p.timestamp_ns < hi for p in client.iter_places("fleet20", from_ns=lo,
                                                                      to_ns=hi))
    both = client.iter_places("fleet20", agent_id="agent-a", from_ns=lo)
    assert [p.place_id for p in both] == sorted(
        (p for p, t in fleet["agent-a"] if t >= lo), reverse=True
    )


def test_list_places_bad_arguments(client: placedb.Client, fleet) -> None:
    with pytest.raises(placedb.InvalidArgument, match="limit"):
        client.list_places("fleet20", limit=1001)  # the server's range is 1..1000
    for bad in (0, -1):
        with pytest.raises(placedb.InvalidArgument, match="limit"):
            client.list_places("fleet20", limit=bad)
    with pytest.raises(placedb.InvalidArgument, match="before_place_id"):
        client.list_places("fleet20", before=-5)
    with pytest.raises(placedb.NotFound):
        client.list_places("no-such-map")
    with pytest.raises(placedb.NotFound):
        list(client.iter_places("no-such-map"))


def test_list_places_skips_deleted_places(client: placedb.Client,
                                          rtabmap_frames: List[Path]) -> None:
    client.create_map("listed-deleted")
    results = list(client.ingest("listed-deleted", rtabmap_frames[:6], agent_id="d"))
    ids = [r.place_id for r in results if r.stored]
    assert len(ids) >= 2
    client.delete_place("listed-deleted", ids[0])
    assert [p.place_id for p in client.iter_places("listed-deleted")] == sorted(ids[1:],
                                                                                reverse=True)


def test_iter_places_pages_past_short_and_empty_pages(
    client: placedb.Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server may answer short or empty pages before the end: iteration goes on until
    next_before is 0, resuming from each page's next_before."""

    def place(place_id: int) -> placedb.Place:
        return placedb.Place(place_id, "a", 0, 0, None, placedb.Counts(), [])

    pages = {
        None: placedb.PlacePage([place(90), place(80)], 70),
        70: placedb.PlacePage([], 40),
        40: placedb.PlacePage([place(30)], 20),
        20: placedb.PlacePage([], 10),
        10: placedb.PlacePage([place(5)], 0),
    }
    calls = []

    def list_places(map, agent_id, from_ns, to_ns, limit, before, timeout):
        calls.append((map, agent_id, limit, before))
        return pages[before]

    monkeypatch.setattr(client, "list_places", list_places)
    assert [p.place_id for p in client.iter_places("m", agent_id="a", limit=2)] == [90, 80, 30, 5]
    assert calls == [("m", "a", 2, b) for b in (None, 70, 40, 20, 10)]


# ---- Query correspondences ----------------------------------------------------------------------


def test_query_correspondences_index_both_keypoint_sets(
    client: placedb.Client, rtabmap_frames: List[Path]
) -> None:
    client.create_map("corr", placedb.MapSettings(verification="exhaustive"))
    results = list(client.ingest("corr", rtabmap_frames[:8], agent_id="c"))
    stored = {r.index: r.place_id for r in results if r.stored}
    index = sorted(stored)[len(stored) // 2]

    plain = client.query("corr", rtabmap_frames[index], top_k=3, verify=True)
    assert plain.query_keypoints is None and plain.image_size is None
    assert plain.matches and plain.matches[0].correspondences.shape == (0, 2)

    answer = client.query("corr", rtabmap_frames[index], top_k=3, verify=True,
                          correspondences=True)
    assert answer.valid
    assert answer.image_size == (512, 384)
    assert answer.query_keypoints is not None and answer.query_dropped_keypoints is not None
    assert answer.query_keypoints.shape == (answer.counts.kept, 6)
    assert answer.query_keypoints.dtype == np.float32
    assert answer.query_dropped_keypoints.shape[1] == 6
    keypoints = answer.query_keypoints
    assert ((keypoints[:, 0] >= 0) & (keypoints[:, 0] < 512)).all()
    assert ((keypoints[:, 1] >= 0) & (keypoints[:, 1] < 384)).all()

    best = answer.matches[0]
    assert best.place_id == stored[index]
    assert best.verified and best.inliers > 0
    c = best.correspondences
    assert c.shape == (best.inliers, 2)
    assert np.issubdtype(c.dtype, np.integer)
    place = client.get_place("corr", best.place_id, include_features=True)
    assert place.keypoints is not None
    assert c[:, 0].min() >= 0 and c[:, 0].max() < len(answer.query_keypoints)
    assert c[:, 1].min() >= 0 and c[:, 1].max() < len(place.keypoints)
    # Each query keypoint and each place keypoint is used by at most one inlier.
    assert len(set(c[:, 0].tolist())) == len(c) and len(set(c[:, 1].tolist())) == len(c)
    # The same frame: matched keypoints lie (almost) on top of each other.
    offsets = np.abs(keypoints[c[:, 0], :2] - place.keypoints[c[:, 1], :2])
    assert np.median(offsets) < 2.0
    for other in answer.matches:
        if not other.verified:
            assert other.correspondences.shape == (0, 2)


# ---- Thumbnails, agents, settings ---------------------------------------------------------------


def _jpeg_size(data: bytes) -> Tuple[int, int]:
    """(width, height) from a JPEG's first SOFn segment."""
    assert data[:2] == b"\xff\xd8", "no JPEG SOI marker"
    i = 2
    while i + 4 <= len(data):
        assert data[i] == 0xFF
        marker = data[i + 1]
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE,
                      0xCF):
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        i += 2 + length
    raise AssertionError("no SOF segment")


def test_thumbnails(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    settings = placedb.MapSettings(
        thumbnails=placedb.ThumbnailSettings(enabled=True, max_side=256, jpeg_quality=80)
    )
    info = client.create_map("thumbs", settings)
    assert info.config.thumbnails.enabled
    assert (info.config.thumbnails.max_side, info.config.thumbnails.jpeg_quality) == (256, 80)
    results = list(client.ingest("thumbs", rtabmap_frames[:3], agent_id="t"))
    place_id = next(r.place_id for r in results if r.stored)

    assert client.get_place("thumbs", place_id).thumbnail is None  # only when asked for
    place = client.get_place("thumbs", place_id, thumbnail=True)
    thumb = place.thumbnail
    assert isinstance(thumb, placedb.Thumbnail)
    assert (thumb.source_width, thumb.source_height) == (512, 384)
    assert (thumb.width, thumb.height) == (256, 192)
    assert thumb.dropped_keypoints.ndim == 2 and thumb.dropped_keypoints.shape[1] == 6
    assert thumb.jpeg[:2] == b"\xff\xd8" and thumb.jpeg[-2:] == b"\xff\xd9"
    assert _jpeg_size(thumb.jpeg) == (256, 192)
    if cv2 is not None:
        image = cv2.imdecode(np.frombuffer(thumb.jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[:2] == (192, 256)

    # A map without thumbnails answers None.
    client.create_map("no-thumbs")
    plain = list(client.ingest("no-thumbs", rtabmap_frames[:2], agent_id="t"))
    plain_id = next(r.place_id for r in plain if r.stored)
    assert client.get_place("no-thumbs", plain_id, thumbnail=True).thumbnail is None


def test_agents_after_a_two_agent_ingest(
    client: placedb.Client, fleet: Dict[str, List[Tuple[int, int]]]
) -> None:
    agents = {a.agent_id: a for a in client.get_map("fleet20").agents}
    assert set(agents) == set(_AGENTS)
    for agent_id, activity in agents.items():
        assert isinstance(activity, placedb.AgentActivity)
        assert activity.frames == len(_AGENTS[agent_id])
        assert activity.places == len(fleet[agent_id])
        assert activity.last_place_id == fleet[agent_id][-1][0]
        assert activity.last_frame_unix_ms > 0
        assert activity.frames_per_second >= 0
    assert client.list_maps()  # ListMaps has no agents; GetMap does
    client.create_map("idle")
    assert client.get_map("idle").agents == []


def test_count_query_hits_above_setting(client: placedb.Client) -> None:
    info = client.create_map("hits", placedb.MapSettings(count_query_hits_above=0.25))
    assert info.config.dynamics.count_query_hits_above == pytest.approx(0.25)
    with pytest.raises(placedb.InvalidArgument, match="count_query_hits_above"):
        placedb.MapSettings(count_query_hits_above="high").to_proto()
    with pytest.raises(placedb.InvalidArgument, match=r"config\.thumbnails\.max_side"):
        placedb.MapSettings(thumbnails=placedb.ThumbnailSettings(max_side=-1)).to_proto()


def test_results_with_arrays_compare_by_value() -> None:
    """Match, QueryResult, Place and Thumbnail hold numpy arrays; == compares their values."""
    match = placedb.Match(1, 0.5, 12, True, "a", 0, 0, None, np.array([[1, 2], [3, 4]]))
    same = placedb.Match(1, 0.5, 12, True, "a", 0, 0, None, np.array([[1, 2], [3, 4]]))
    other = placedb.Match(1, 0.5, 12, True, "a", 0, 0, None, np.array([[1, 2]]))
    assert match == same and [match] == [same] and hash(match) == hash(same)
    assert match != other
    thumb = placedb.Thumbnail(b"\xff\xd8", 2, 1, 4, 2, np.zeros((0, 6), np.float32))
    assert thumb == placedb.Thumbnail(b"\xff\xd8", 2, 1, 4, 2, np.zeros((0, 6), np.float32))
    assert thumb != placedb.Thumbnail(b"\xff\xd8", 2, 1, 4, 2, np.ones((1, 6), np.float32))
