"""The SDK against a real placedb-server: every RPC's round trip, bad input, a 2-agent ingest."""

from __future__ import annotations

import dataclasses
import os
import threading
from concurrent import futures
from pathlib import Path
from typing import Dict, List

import grpc
import numpy as np
import pytest
from conftest import textured_image, unused_loopback_port

import placedb
from placedb._pb import placedb_pb2 as pb
from placedb._pb import placedb_pb2_grpc as pb_grpc

# ---- Server, maps -------------------------------------------------------------------------------


def test_unreachable_server_fails_fast_or_waits_for_its_deadline() -> None:
    address = f"127.0.0.1:{unused_loopback_port()}"  # nothing listens there
    with placedb.Client(address, timeout=5) as client:
        with pytest.raises(placedb.Unavailable):
            client.list_maps()
    with placedb.Client(address, timeout=0.3, wait_for_ready=True) as client:
        with pytest.raises(placedb.DeadlineExceeded):
            client.list_maps()


class _Stalling(pb_grpc.PlaceDbServicer):
    """Answers nothing until its caller's deadline has passed (or 20 s: ABORTED, so an ignored
    deadline fails the test instead of hanging it)."""

    def __init__(self) -> None:
        self.released = threading.Event()

    def _stall(self, context) -> None:
        self.released.wait(timeout=20)
        context.abort(grpc.StatusCode.ABORTED, "no deadline came")

    def ListMaps(self, request, context):
        self._stall(context)

    def Ingest(self, requests, context):
        self._stall(context)
        yield pb.IngestResponse()

    def DownloadSnapshot(self, request, context):
        self._stall(context)
        yield pb.SnapshotChunk()


def test_per_call_timeout_overrides_the_clients(server, tmp_path: Path) -> None:
    stalling = _Stalling()
    fake = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    pb_grpc.add_PlaceDbServicer_to_server(stalling, fake)
    address = f"127.0.0.1:{unused_loopback_port()}"
    fake.add_insecure_port(address)
    fake.start()
    try:
        with placedb.Client(address, timeout=None) as client:
            with pytest.raises(placedb.DeadlineExceeded):
                client.list_maps(timeout=0.2)
            with pytest.raises(placedb.DeadlineExceeded):
                list(client.ingest("m", [textured_image(seed=1)], timeout=0.2))
            dest = tmp_path / "s.pdbsnap"
            with pytest.raises(placedb.DeadlineExceeded):
                client.download_snapshot("s", dest, timeout=0.2)
            assert list(tmp_path.iterdir()) == []
        with placedb.Client(address, timeout=0.2) as client:
            with pytest.raises(placedb.DeadlineExceeded):
                client.list_maps()  # the client's timeout
    finally:
        stalling.released.set()
        fake.stop(None)

    # A longer per-call timeout on a client whose own would expire before any answer.
    with placedb.Client(server.address, timeout=1e-9) as client:
        client.create_map("timeouts", timeout=30)
        assert client.get_map("timeouts", timeout=30).name == "timeouts"
        assert client.health(timeout=None) == "serving"
        for bad in (0, -1.0):
            with pytest.raises(placedb.InvalidArgument, match="timeout"):
                client.get_map("timeouts", timeout=bad)
    with pytest.raises(placedb.InvalidArgument, match="timeout"):
        placedb.Client(server.address, timeout=0)


def test_health_and_server_info(client: placedb.Client) -> None:
    assert client.health() == "serving"
    assert client.health("placedb.v1.PlaceDb") == "serving"
    info = client.server_info()
    assert info.version
    default = [v for v in info.vocabularies if v.name == "default"]
    assert len(default) == 1
    assert default[0].feature_type == "orb"
    assert len(default[0].checksum) == 16
    assert default[0].words > 0
    assert info.limits["max_boxes_per_frame"] > 0
    assert info.limits["max_message_bytes"] > 0


def test_map_round_trip(client: placedb.Client) -> None:
    settings = placedb.MapSettings(
        scoring="chi2",
        verification="direct",
        min_inliers=12,
        filter_method="corner_distance",
        place_threshold=10,
        dynamic_classes=["person", "car"],
        max_features=800,
    )
    created = client.create_map("maps-rt", settings)
    assert created.name == "maps-rt"
    assert created.state == "available"
    assert created.feature_type == "orb"
    assert created.places == 0
    assert len(created.vocabulary_checksum) == 16
    assert created.config.scoring == pb.SCORING_CHI_SQUARE
    assert created.config.verification.mode == pb.VERIFICATION_MODE_DIRECT_INDEX
    assert created.config.verification.min_inliers == 12
    assert created.config.filter.method == pb.FILTER_METHOD_CORNER_DISTANCE
    assert created.config.filter.place_threshold == 10
    assert created.config.orb.max_features == 800
    assert list(created.config.detection.classes) == ["person", "car"]

    fetched = client.get_map("maps-rt")
    assert fetched.config == created.config
    assert fetched.created_unix_ms == created.created_unix_ms
    summaries = {m.name: m for m in client.list_maps()}
    assert summaries["maps-rt"].available
    assert summaries["maps-rt"].state == "available"
    assert summaries["maps-rt"].feature_type == "orb"

    with pytest.raises(placedb.AlreadyExists) as taken:
        client.create_map("maps-rt")
    assert taken.value.code.name == "ALREADY_EXISTS"
    assert "maps-rt" in taken.value.message

    client.delete_map("maps-rt")
    assert "maps-rt" not in {m.name for m in client.list_maps()}
    with pytest.raises(placedb.NotFound):
        client.get_map("maps-rt")
    with pytest.raises(placedb.NotFound):
        client.delete_map("maps-rt")


def test_bad_map_settings(client: placedb.Client) -> None:
    with pytest.raises(placedb.InvalidArgument, match="config.scoring: unknown value 'cosine'"):
        client.create_map("bad-settings", placedb.MapSettings(scoring="cosine"))
    with pytest.raises(placedb.InvalidArgument, match="name"):
        client.create_map("bad name!")
    with pytest.raises(placedb.InvalidArgument, match="nope"):
        client.create_map("bad-vocabulary", placedb.MapSettings(vocabulary="nope"))
    assert not {"bad-settings", "bad-vocabulary"} & {m.name for m in client.list_maps()}


def test_typed_setting_groups(client: placedb.Client) -> None:
    settings = placedb.MapSettings(
        depth=placedb.DepthSettings(stream_filter=False, threshold_m=0.3, band_policy="fixed",
                                    rise_band=(1.5, 4.0)),
        loop_closure=placedb.LoopClosureSettings(loop_threshold=0.2, verify=False),
        short_term=placedb.ShortTermSettings(horizon_s=30, max_places=100),
    )
    config = client.create_map("groups", settings).config
    assert not config.depth.stream_filter
    assert config.depth.threshold_m == pytest.approx(0.3)
    assert config.depth.band_policy == pb.BAND_POLICY_FIXED
    assert (config.depth.rise_band.near_m, config.depth.rise_band.far_m) == (1.5, 4.0)
    assert config.loop_closure.loop_threshold == pytest.approx(0.2)
    assert not config.loop_closure.verify
    assert (config.filter.short_term.horizon_s, config.filter.short_term.max_places) == (30, 100)
    sift = placedb.MapSettings(vocabulary="sift", sift=placedb.SiftSettings(max_features=300))
    assert client.create_map("groups-sift", sift).config.sift.max_features == 300

    # Each group has exactly its message's fields, so the two cannot drift apart.
    groups = {
        placedb.DepthSettings: pb.DepthSettings,
        placedb.LoopClosureSettings: pb.LoopClosureSettings,
        placedb.ShortTermSettings: pb.ShortTermSettings,
        placedb.SiftSettings: pb.SiftSettings,
        placedb.ThumbnailSettings: pb.ThumbnailSettings,
    }
    for group, message in groups.items():
        assert {f.name for f in dataclasses.fields(group)} == {
            f.name for f in message.DESCRIPTOR.fields
        }, group.__name__

    bad = [
        (placedb.DepthSettings(band_policy="sideways"), "config.depth.band_policy"),
        (placedb.DepthSettings(rise_band=(1.0,)), "config.depth.rise_band"),
        (placedb.DepthSettings(persistence="often"), "config.depth.persistence"),
    ]
    for depth, field in bad:
        with pytest.raises(placedb.InvalidArgument, match=field.replace(".", r"\.")):
            client.create_map("groups-bad", placedb.MapSettings(depth=depth))
    assert "groups-bad" not in [m.name for m in client.list_maps()]


def test_scrub_and_recover(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    client.create_map("scrubbed")
    results = list(client.ingest("scrubbed", rtabmap_frames[:4], agent_id="a"))
    stored = sum(r.stored for r in results)
    assert stored > 0
    report = client.scrub_map("scrubbed")
    assert report.clean
    assert report.places_checked == stored
    assert report.damaged_places == [] and report.damaged_files == []
    with pytest.raises(placedb.InvalidArgument, match="accept_data_loss"):
        client.recover_map("scrubbed", accept_data_loss=False)
    with pytest.raises(placedb.FailedPrecondition):
        client.recover_map("scrubbed", accept_data_loss=True)
    with pytest.raises(placedb.NotFound):
        client.scrub_map("no-such-map")


def test_adapt_and_revert_vocabulary(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    client.create_map("learns")
    results = list(client.ingest("learns", rtabmap_frames[:30], agent_id="a"))
    before = client.get_map("learns")
    assert before.vocabulary_info is not None
    assert before.vocabulary_info.generation == 0
    assert before.vocabulary_info.current.origin == "file"
    adapted = client.adapt_vocabulary("learns", branching=8, depth=4, max_sample_descriptors=20000)
    assert adapted.map == "learns" and adapted.generation == 1
    assert adapted.current.origin == "learned"
    assert adapted.current.branching == 8 and adapted.current.depth == 4
    assert adapted.previous is not None
    assert adapted.previous.checksum == before.vocabulary_checksum
    after = client.get_map("learns")
    assert after.vocabulary_checksum == adapted.current.checksum
    assert after.vocabulary == "learned"
    # Each stored frame still finds its own place with the learned vocabulary.
    stored = [(i, r.place_id) for i, r in enumerate(results) if r.stored]
    for index, place in stored[::5]:
        assert client.query("learns", rtabmap_frames[index], top_k=1).matches[0].place_id == place
    reverted = client.revert_vocabulary("learns")
    assert reverted.generation == 2
    assert reverted.current.checksum == before.vocabulary_checksum
    client.create_map("tiny")
    list(client.ingest("tiny", rtabmap_frames[:2], agent_id="a"))
    with pytest.raises(placedb.FailedPrecondition, match="too small to learn a vocabulary"):
        client.adapt_vocabulary("tiny")
    with pytest.raises(placedb.FailedPrecondition, match="no previous vocabulary"):
        client.revert_vocabulary("tiny")


# ---- Ingest, query, places ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def loop_map(server) -> Dict[int, int]:
    """Map "loop": RTAB-Map frames 1-20 ingested by agent robot-1; frame index -> place id."""
    with placedb.Client(server.address) as c:
        c.create_map("loop")
        frames = [
            placedb.Frame(image=path, timestamp_ns=(10 + i) * 100_000_000, sequence=100 + i)
            for i, path in enumerate(_frames()[:20])
        ]
        places = {}
        for result in c.ingest("loop", frames, agent_id="robot-1", max_in_flight=3):
            assert result.error is None, result.error
            if result.stored:
                places[result.index] = result.place_id
        return places


def _frames() -> List[Path]:
    folder = Path(os.environ["PLACEDB_SHARED_DIR"]) / "data" / "rtabmap-loop"
    return sorted(folder.glob("*.jpg"), key=lambda p: int(p.stem))


def test_ingest_yields_results_in_order(client: placedb.Client, loop_map: Dict[int, int]) -> None:
    assert len(loop_map) >= 15  # most frames of the loop are valid places
    assert client.get_map("loop").places == len(loop_map)
    place = client.get_place("loop", loop_map[5])
    assert place.agent_id == "robot-1"
    assert place.sequence == 105
    assert place.timestamp_ns == 1_500_000_000
    assert place.pose is None
    assert place.counts.kept > 0
    assert place.keypoints is None and place.descriptors is None


def test_ingest_results_carry_index_sequence_and_counts(
    client: placedb.Client, rtabmap_frames: List[Path]
) -> None:
    client.create_map("ordered")
    frames = [placedb.Frame(image=p.read_bytes(), pose=(1.0, 2.0, 3.0, 0, 0, 0, 1)) for p in
              rtabmap_frames[20:30]]
    results = list(client.ingest("ordered", frames, agent_id="r", max_in_flight=1))
    assert [r.index for r in results] == list(range(10))
    assert [r.sequence for r in results] == list(range(10))
    for r in results:
        assert r.counts.total == r.counts.dynamic + r.counts.depth_removed + r.counts.kept
        assert r.matches == []
    stored = [r for r in results if r.stored]
    assert stored
    place = client.get_place("ordered", stored[0].place_id)
    assert place.pose == placedb.Pose(1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)


def test_query_finds_the_same_frame(
    client: placedb.Client, loop_map: Dict[int, int], rtabmap_frames: List[Path]
) -> None:
    for index in (3, 12):
        if index not in loop_map:
            continue
        by_path = client.query("loop", rtabmap_frames[index], top_k=5)
        assert by_path.valid
        assert 1 <= len(by_path.matches) <= 5
        best = by_path.matches[0]
        assert best.place_id == loop_map[index]
        assert best.agent_id == "robot-1"
        assert best.sequence == 100 + index
        scores = [m.score for m in by_path.matches]
        assert scores == sorted(scores, reverse=True)
        by_bytes = client.query("loop", rtabmap_frames[index].read_bytes(), top_k=5)
        assert [m.place_id for m in by_bytes.matches] == [m.place_id for m in by_path.matches]
    assert client.get_map("loop").places == len(loop_map)  # queries store nothing


def test_query_verify_keeps_verified_matches_only(client: placedb.Client, server) -> None:
    frames = _frames()
    client.create_map("verified", placedb.MapSettings(verification="exhaustive"))
    results = list(client.ingest("verified", frames[:6], agent_id="v"))
    first = results[0]
    assert first.stored
    answer = client.query("verified", frames[0], top_k=10, verify=True)
    assert answer.matches
    assert all(m.verified and m.inliers > 0 for m in answer.matches)
    assert answer.matches[0].place_id == first.place_id


def test_ingest_with_matches_against_the_map_before_each_frame(
    client: placedb.Client, loop_map: Dict[int, int], rtabmap_frames: List[Path]
) -> None:
    client.create_map("revisit")
    indices = sorted(loop_map)[:5]
    first = list(client.ingest("revisit", [rtabmap_frames[i] for i in indices], agent_id="a"))
    second = list(
        client.ingest("revisit", [rtabmap_frames[i] for i in indices], agent_id="a", top_k=3)
    )
    assert first[0].matches == []
    for before, again in zip(first, second):
        assert again.matches, "a revisited frame matches its earlier place"
        assert again.matches[0].place_id == before.place_id
        assert len(again.matches) <= 3


def test_per_frame_match_options_override_the_streams(
    client: placedb.Client, loop_map: Dict[int, int], rtabmap_frames: List[Path]
) -> None:
    client.create_map("per-frame")
    indices = sorted(loop_map)[:6]
    first = list(client.ingest("per-frame", [rtabmap_frames[i] for i in indices], agent_id="a"))
    places = [r.place_id for r in first]
    frames = [
        placedb.Frame(image=rtabmap_frames[indices[0]]),
        placedb.Frame(image=rtabmap_frames[indices[1]], matches=placedb.MatchOptions(top_k=2)),
    ]
    plain, asked = client.ingest("per-frame", frames, agent_id="a")
    assert plain.matches == []  # the stream asked for none
    assert 1 <= len(asked.matches) <= 2 and asked.matches[0].place_id == places[1]
    frames = [
        placedb.Frame(image=rtabmap_frames[indices[2]]),
        placedb.Frame(image=rtabmap_frames[indices[3]], matches=placedb.MatchOptions(top_k=1)),
        placedb.Frame(
            image=rtabmap_frames[indices[4]],
            matches=placedb.MatchOptions(top_k=5, exclude_same_agent=True),
        ),
    ]
    wide, narrow, others = client.ingest("per-frame", frames, agent_id="a", top_k=5)
    assert len(wide.matches) > 1 and wide.matches[0].place_id == places[2]
    assert [m.place_id for m in narrow.matches] == [places[3]]
    assert others.matches == []  # every place is agent a's
    bad = [placedb.Frame(image=rtabmap_frames[0], matches=placedb.MatchOptions(top_k=-1))]
    with pytest.raises(placedb.InvalidArgument, match=r"frames\[0\]\.matches\.top_k"):
        list(client.ingest("per-frame", bad))
    with pytest.raises(placedb.InvalidArgument, match="ingest only"):
        client.query("per-frame", placedb.Frame(image=rtabmap_frames[0],
                                                matches=placedb.MatchOptions()))


def test_depth_state_and_loop_closure_are_dataclasses(client: placedb.Client) -> None:
    config = pb.MapConfig()
    config.depth.stream_filter = True  # Algorithm 1 on ingest streams with depth
    client.create_map("depth-stream", placedb.MapSettings(config=config))
    frames = [
        placedb.Frame(image=textured_image(seed=40 + i),
                      depth=np.full((120, 160), 2000, dtype=np.uint16))
        for i in range(3)
    ]
    results = list(client.ingest("depth-stream", frames, agent_id="d", loop_closure=True))
    for i, r in enumerate(results):
        assert r.stored, r.rejection
        assert isinstance(r.depth, placedb.DepthState)
        assert r.depth.frame == i
        assert r.depth.mean_depth_m == pytest.approx(2.0, abs=0.01)
        assert r.depth.warming_up and not r.depth.removing
        assert r.depth.valid_fraction == pytest.approx(1.0)
        assert isinstance(r.loop_closure, placedb.LoopClosure)
        assert r.loop_closure.place_id == r.place_id and not r.loop_closure.merged
    answer = client.query("depth-stream", frames[0])
    assert answer.depth is None  # a query has no stream state


def test_ingest_with_loop_closure_finds_the_revisit(
    client: placedb.Client, rtabmap_frames: List[Path]
) -> None:
    """The RTAB-Map loop's second half revisits its first: loops point back to early places."""
    client.create_map("loops")
    results = list(client.ingest("loops", rtabmap_frames, agent_id="r", loop_closure=True))
    valid = [r for r in results if r.stored]
    assert valid and all(r.loop_closure is not None for r in valid)
    loops = [r for r in valid if r.loop_closure.loop_found]
    assert len(loops) >= 10
    for r in loops:
        assert r.index >= len(rtabmap_frames) // 2
        # A place seen about a lap earlier, not one of the frames just before.
        assert r.loop_closure.loop_place_id + 30 < r.place_id
        assert r.loop_closure.place_id == r.place_id
    assert client.get_map("loops").stats["loops_accepted"] == len(loops)


def test_get_place_features_and_query_with_them(
    client: placedb.Client, loop_map: Dict[int, int]
) -> None:
    place_id = loop_map[min(loop_map)]
    place = client.get_place("loop", place_id, include_features=True)
    assert place.image_size == (512, 384)
    assert place.keypoints is not None and place.descriptors is not None
    assert place.keypoints.shape == (place.counts.kept, 6)
    assert place.descriptors.shape == (place.counts.kept, 32)
    assert place.descriptors.dtype == np.uint8
    frame = placedb.Frame(
        keypoints=place.keypoints, descriptors=place.descriptors, image_size=place.image_size
    )
    answer = client.query("loop", frame, top_k=3)
    assert answer.valid
    assert answer.counts.total == place.counts.kept
    assert answer.matches[0].place_id == place_id


def test_cv2_style_keypoints(client: placedb.Client, loop_map: Dict[int, int]) -> None:
    """Keypoints as objects with OpenCV's cv2.KeyPoint attributes."""

    class KeyPoint:
        def __init__(self, row: np.ndarray) -> None:
            self.pt = (float(row[0]), float(row[1]))
            self.size, self.angle, self.response = float(row[2]), float(row[3]), float(row[4])
            self.octave = int(row[5])

    place_id = loop_map[max(loop_map)]
    place = client.get_place("loop", place_id, include_features=True)
    keypoints = [KeyPoint(row) for row in place.keypoints]
    frame = placedb.Frame(keypoints=keypoints, descriptors=place.descriptors, image_size=(512, 384))
    assert client.query("loop", frame).matches[0].place_id == place_id


def test_delete_place(client: placedb.Client, rtabmap_frames: List[Path]) -> None:
    client.create_map("deleting")
    results = [r for r in client.ingest("deleting", rtabmap_frames[40:44]) if r.stored]
    victim = results[0].place_id
    client.delete_place("deleting", victim)
    with pytest.raises(placedb.NotFound):
        client.get_place("deleting", victim)
    with pytest.raises(placedb.NotFound):
        client.delete_place("deleting", victim)
    answer = client.query("deleting", rtabmap_frames[40], top_k=10)
    assert victim not in [m.place_id for m in answer.matches]
    assert client.get_map("deleting").places == len(results) - 1


def test_numpy_images_gray_and_bgr(client: placedb.Client) -> None:
    client.create_map("arrays")
    gray = textured_image(seed=7)
    bgr = np.repeat(gray[:, :, None], 3, axis=2)
    other = textured_image(seed=8)
    results = list(client.ingest("arrays", [bgr, other], agent_id="np"))
    assert all(r.stored for r in results), [r.rejection for r in results]
    answer = client.query("arrays", gray, top_k=2)
    assert answer.matches[0].place_id == results[0].place_id
    answer = client.query("arrays", other[:, :, None], top_k=2)
    assert answer.matches[0].place_id == results[1].place_id


def test_boxes_mask_and_depth(client: placedb.Client) -> None:
    client.create_map("dynamic")
    gray = textured_image(seed=11)
    height, width = gray.shape
    mask = np.zeros((height, width), dtype=bool)
    mask[:, width // 2 :] = True
    depth = np.full((height // 2, width // 2), 2000, dtype=np.uint16)
    boxed = placedb.Frame(image=gray, boxes=[placedb.Box("person", 0.9, (0, 0, 120, 120))])
    masked = placedb.Frame(image=gray, mask=mask, depth=depth, timestamp_ns=5)
    float_depth = placedb.Frame(
        image=gray,
        depth=placedb.Depth(
            np.full((height, width), 2.0, np.float32), intrinsics=(300, 300, 160, 120)
        ),
    )
    plain, boxed_r, masked_r, float_r = client.ingest(
        "dynamic", [gray, boxed, masked, float_depth], agent_id="d"
    )
    for r in (plain, boxed_r, masked_r, float_r):
        assert r.error is None, r.error
    assert plain.counts.dynamic == 0
    assert boxed_r.boxes_used and boxed_r.boxes_used[0].class_name == "person"
    assert 0 < boxed_r.counts.dynamic < boxed_r.counts.total
    # Half the image is masked: about half the descriptors are dynamic.
    assert masked_r.counts.dynamic_coverage == pytest.approx(0.5, abs=0.05)
    assert masked_r.counts.dynamic > masked_r.counts.total // 4
    assert float_r.counts.total > 0


# ---- Bad input ----------------------------------------------------------------------------------


def test_bad_frames_raise_invalid_argument_before_sending(client: placedb.Client) -> None:
    client.create_map("bad-frames")
    gray = textured_image(seed=3)
    with pytest.raises(placedb.InvalidArgument, match="dtype float32, expected uint8") as e:
        client.query("bad-frames", gray.astype(np.float32))
    assert e.value.code.name == "INVALID_ARGUMENT"
    with pytest.raises(placedb.InvalidArgument, match=r"shape \(240, 320, 4\)"):
        client.query("bad-frames", np.zeros((240, 320, 4), np.uint8))
    with pytest.raises(placedb.InvalidArgument, match="descriptors: int64"):
        client.query(
            "bad-frames",
            placedb.Frame(keypoints=np.zeros((2, 6)), descriptors=np.zeros((2, 32), np.int64),
                          image_size=(320, 240)),
        )
    with pytest.raises(placedb.InvalidArgument, match="3 rows for 2 keypoints"):
        client.query(
            "bad-frames",
            placedb.Frame(keypoints=np.zeros((2, 6)), descriptors=np.zeros((3, 32), np.uint8),
                          image_size=(320, 240)),
        )
    with pytest.raises(placedb.InvalidArgument, match="cannot read"):
        client.query("bad-frames", "/nonexistent/frame.jpg")
    with pytest.raises(placedb.InvalidArgument, match="not a frame"):
        client.query("bad-frames", 42)  # type: ignore[arg-type]
    with pytest.raises(placedb.InvalidArgument, match="mask"):
        client.query("bad-frames", placedb.Frame(image=gray, mask=np.zeros((4, 4), np.float64)))
    assert isinstance(placedb.InvalidArgument("x"), ValueError)


def test_server_refusals_carry_code_and_message(client: placedb.Client) -> None:
    client.create_map("refusals")
    with pytest.raises(placedb.NotFound, match="no-such-map"):
        client.query("no-such-map", textured_image(seed=1))
    with pytest.raises(placedb.NotFound):
        client.get_place("no-such-map", 1)
    with pytest.raises(placedb.NotFound):
        client.get_place("refusals", 12345)
    outside = placedb.Frame(
        keypoints=np.array([[700, 10, 31, 0, 1, 0]], np.float32),
        descriptors=np.zeros((1, 32), np.uint8),
        image_size=(640, 480),
    )
    with pytest.raises(placedb.InvalidArgument, match=r"keypoints\[0\]\.x") as e:
        client.query("refusals", outside)
    assert "700" in e.value.message
    with pytest.raises(placedb.InvalidArgument):
        client.query("refusals", b"not an image")
    # SIFT descriptors on an ORB map.
    with pytest.raises(placedb.InvalidArgument):
        client.query(
            "refusals",
            placedb.Frame(keypoints=np.array([[10, 10, 31, 0, 1, 1]], np.float32),
                          descriptors=np.zeros((1, 128), np.float32), image_size=(64, 64)),
        )


def test_ingest_unknown_map_raises_not_found(client: placedb.Client) -> None:
    with pytest.raises(placedb.NotFound, match="no-such-map"):
        list(client.ingest("no-such-map", [textured_image(seed=1)]))


def test_ingest_refused_frame_does_not_end_the_stream(client: placedb.Client) -> None:
    client.create_map("refused-frame")
    frames = [textured_image(seed=20), b"not an image", textured_image(seed=21)]
    results = list(client.ingest("refused-frame", frames, agent_id="r"))
    assert [r.index for r in results] == [0, 1, 2]
    assert results[0].stored and results[2].stored
    assert not results[1].stored
    assert isinstance(results[1].error, placedb.InvalidArgument)
    assert results[1].error.message


def test_ingest_bad_frame_raises_after_the_frames_before_it(client: placedb.Client) -> None:
    client.create_map("client-refused")
    frames = [textured_image(seed=30), textured_image(seed=31), np.zeros((8, 8), np.float32),
              textured_image(seed=32)]
    seen = []
    with pytest.raises(placedb.InvalidArgument, match=r"frames\[2\]\.raw_image: dtype float32"):
        for result in client.ingest("client-refused", frames, max_in_flight=1):
            seen.append(result.index)
    assert seen == [0, 1]
    assert client.get_map("client-refused").places == 2


def test_ingest_stops_reading_frames_at_the_window(client: placedb.Client) -> None:
    """Frames are pulled lazily: at most max_in_flight beyond the results consumed."""
    client.create_map("window")
    pulled = []

    def frames():
        for i in range(12):
            pulled.append(i)
            yield textured_image(seed=100 + i)

    stream = client.ingest("window", frames(), agent_id="w", max_in_flight=2)
    first = next(stream)
    assert first.index == 0
    # Consumed 1 result: the window lets at most 1 + 2 frames out, plus one converted and waiting.
    assert len(pulled) <= 4
    rest = list(stream)
    assert [r.index for r in rest] == list(range(1, 12))
    assert len(pulled) == 12


# ---- Two agents ---------------------------------------------------------------------------------


@pytest.mark.parametrize("shared_channel", [False, True])
def test_two_agents_ingest_concurrently(
    client: placedb.Client, server, rtabmap_frames: List[Path], shared_channel: bool
) -> None:
    """Two agents stream at once, each with its own Client or both on one (channels are
    thread-safe)."""
    fleet = f"fleet-{int(shared_channel)}"
    client.create_map(fleet)
    halves = {"agent-a": rtabmap_frames[50:62], "agent-b": rtabmap_frames[62:74]}
    outcome: Dict[str, list] = {}
    errors: List[BaseException] = []

    def run(agent: str) -> None:
        try:
            own = client if shared_channel else placedb.Client(server.address)
            outcome[agent] = list(own.ingest(fleet, halves[agent], agent_id=agent,
                                             max_in_flight=4))
            if own is not client:
                own.close()
        except BaseException as e:  # reported below
            errors.append(e)

    threads = [threading.Thread(target=run, args=(agent,)) for agent in halves]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    stored = {a: [r.place_id for r in results if r.stored] for a, results in outcome.items()}
    for agent, results in outcome.items():
        assert [r.index for r in results] == list(range(12))
        assert stored[agent]
    ids = stored["agent-a"] + stored["agent-b"]
    assert len(set(ids)) == len(ids)
    assert client.get_map(fleet).places == len(ids)
    for agent, places in stored.items():
        for place_id in places:
            assert client.get_place(fleet, place_id).agent_id == agent
    # agent-a's own frame, excluding agent-a's places: only agent-b's places come back.
    answer = client.query(fleet, halves["agent-a"][0], top_k=10, agent_id="agent-a",
                          exclude_same_agent=True)
    assert answer.matches
    assert {m.agent_id for m in answer.matches} == {"agent-b"}
