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
