"""Relative poses of verified matches (issue 32) through the SDK, against a real server:
slambook2's RGB-D frames ingested with a stream camera, a query with its depth and camera, each
match's :class:`placedb.RelativePose` (a 4 x 4 transform and a 6 x 6 information) against
pose.txt, and the camera and keypoint depths the places keep."""

from __future__ import annotations

from typing import Any, Dict, List

import cv2
import numpy as np
import pytest

import placedb

# slambook2's camera: fx, fy, cx, cy (640 x 480, no distortion).
INTRINSICS = (518.0, 519.0, 325.5, 253.5)


def _camera_to_world(pose) -> np.ndarray:
    """pose.txt's "x y z qx qy qz qw" as a 4 x 4 camera-to-world transform."""
    x, y, z, qx, qy, qz, qw = pose
    q = np.array([qx, qy, qz, qw]) / np.linalg.norm([qx, qy, qz, qw])
    qx, qy, qz, qw = q
    rotation = np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = (x, y, z)
    return t


@pytest.fixture(scope="module")
def frames(slambook_rgbd) -> List[Dict[str, Any]]:
    out = []
    for colour, depth, pose in slambook_rgbd:
        gray = cv2.imread(str(colour), cv2.IMREAD_GRAYSCALE)
        mm = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
        assert gray is not None and mm is not None and mm.dtype == np.uint16
        out.append({"gray": gray, "mm": mm, "T_w": _camera_to_world(pose)})
    return out


def test_matches_carry_poses_that_agree_with_the_ground_truth(
    client: placedb.Client, frames: List[Dict[str, Any]]
) -> None:
    settings = placedb.MapSettings(
        max_features=2000,  # slambook2's wide pairs need them (docs/poses.md)
        verification="exhaustive",
        depth=placedb.DepthSettings(stream_filter=False),
    )
    client.create_map("poses", settings)
    camera = placedb.Camera(*INTRINSICS)
    stored = [0, 2, 4]
    results = list(
        client.ingest(
            "poses",
            [placedb.Frame(image=frames[i]["gray"], depth=frames[i]["mm"]) for i in stored],
            agent_id="robot",
            camera=camera,
        )
    )
    assert all(r.stored for r in results), [r.error or r.rejection for r in results]
    frame_of_place = {r.place_id: i for r, i in zip(results, stored)}

    # Each place keeps the stream's camera (at the frame's size) and its keypoints' depths.
    place = client.get_place("poses", results[0].place_id, include_features=True)
    assert place.camera == placedb.Camera(*INTRINSICS, width=640, height=480, distortion_model="none")
    assert place.keypoint_depth_m is not None
    assert place.keypoint_depth_m.shape == (len(place.keypoints),)
    assert (place.keypoint_depth_m > 0).mean() > 0.5

    query = placedb.Frame(image=frames[1]["gray"], depth=frames[1]["mm"], camera=camera)
    answer = client.query("poses", query, top_k=3, verify=True)
    assert len(answer.matches) >= 2
    assert answer.timings.pose_ms > 0
    for match in answer.matches:
        pose = match.relative_pose
        assert pose is not None, match.pose_unavailable
        assert match.pose_unavailable == ""
        assert pose.transform.shape == (4, 4) and pose.information.shape == (6, 6)
        assert pose.metric and pose.solver.startswith("pnp_") and pose.inliers >= 12
        assert np.allclose(pose.information, pose.information.T, rtol=1e-6, atol=1e-9)
        # T_place_query = inv(T_w_place) @ T_w_query.
        truth = np.linalg.inv(frames[frame_of_place[match.place_id]]["T_w"]) @ frames[1]["T_w"]
        delta = truth[:3, :3].T @ pose.transform[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1)))
        assert angle < 2.0, (match.place_id, angle)
        assert np.linalg.norm(truth[:3, 3] - pose.transform[:3, 3]) < 0.12

    # Without a camera: no pose, and the reason.
    plain = client.query("poses", frames[1]["gray"], top_k=3, verify=True)
    assert plain.matches
    assert all(m.relative_pose is None for m in plain.matches)
    assert all("no camera" in m.pose_unavailable for m in plain.matches)


def test_a_bad_camera_is_refused_naming_the_field(client: placedb.Client, frames) -> None:
    client.create_map("bad-camera")
    frame = placedb.Frame(image=frames[0]["gray"], camera=placedb.Camera(0, 519, 325.5, 253.5))
    with pytest.raises(placedb.InvalidArgument, match=r"observation\.camera\.fx"):
        client.query("bad-camera", frame)
    assert client.get_map("bad-camera").places == 0


def test_the_loop_log_streams_every_constraint_once_and_resumes(
    client: placedb.Client, frames: List[Dict[str, Any]]
) -> None:
    """WatchLoopClosures through the SDK: a second agent's verified matches against the first's
    places are in the map's log with their poses (checked against pose.txt), a reader resumes
    from a sequence, and a follower receives a constraint found after it started."""
    settings = placedb.MapSettings(
        max_features=2000,
        verification="exhaustive",
        depth=placedb.DepthSettings(stream_filter=False),
    )
    client.create_map("loop-log", settings)
    camera = placedb.Camera(*INTRINSICS)

    def ingest(agent: str, indices: List[int], top_k: int) -> List[placedb.IngestResult]:
        results = list(
            client.ingest(
                "loop-log",
                [placedb.Frame(image=frames[i]["gray"], depth=frames[i]["mm"]) for i in indices],
                agent_id=agent,
                camera=camera,
                top_k=top_k,
                verify=top_k > 0,
            )
        )
        assert all(r.stored for r in results), [r.error or r.rejection for r in results]
        return results

    first = ingest("robot", [0, 2, 4], top_k=0)
    frame_of_place = {r.place_id: i for r, i in zip(first, [0, 2, 4])}
    second = ingest("visitor", [1, 3], top_k=3)
    frame_of_place.update({r.place_id: i for r, i in zip(second, [1, 3])})
    announced = [
        (r.place_id, m.place_id)
        for r in second
        for m in r.matches
        if m.verified
    ]
    assert announced

    log = list(client.watch_loop_closures("loop-log", timeout=60))
    assert [c.sequence for c in log] == list(range(1, len(log) + 1))
    assert sorted((c.query_place_id, c.place_id) for c in log) == sorted(announced)
    for c in log:
        assert c.source == "match" and c.query.agent_id == "visitor"
        assert c.inter_agent == (c.place.agent_id == "robot")
        pose = c.relative_pose
        assert pose is not None and pose.metric, c.pose_unavailable
        truth = (
            np.linalg.inv(frames[frame_of_place[c.place_id]]["T_w"])
            @ frames[frame_of_place[c.query_place_id]]["T_w"]
        )
        delta = truth[:3, :3].T @ pose.transform[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1)))
        assert angle < 2.0, (c.sequence, angle)
        assert np.linalg.norm(truth[:3, 3] - pose.transform[:3, 3]) < 0.12

    # Resuming after the second constraint gives the rest, nothing twice.
    assert list(client.watch_loop_closures("loop-log", from_sequence=3, timeout=60)) == log[2:]
    robot_only = list(client.watch_loop_closures("loop-log", agents=["robot"], timeout=60))
    assert robot_only == [c for c in log if c.place.agent_id == "robot"]

    # A follower from the log's end gets the next constraint once it is found.
    follower = client.watch_loop_closures(
        "loop-log", from_sequence=len(log) + 1, follow=True, timeout=60
    )
    later = ingest("third", [2], top_k=1)
    new = next(follower)
    follower.close()
    assert new.sequence == len(log) + 1
    assert new.query.agent_id == "third" and new.query_place_id == later[0].place_id
