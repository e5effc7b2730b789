"""Recordings (placedb.recordings, placedb-py): ROS 1 bags the tests write with Debian's
python3-rosbag and TUM RGB-D folders they write, from slambook2's real RGB-D frames, ingested into
a real placedb-server: capture times, depth pairing and scale, intrinsics, poses."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import cv2  # python3-opencv: decodes the test's source images
import numpy as np
import pytest
from conftest import unused_loopback_port

import placedb
from placedb.png import encode_gray_png
from placedb.recordings import interpolate_pose, seconds_to_ns

# Capture times: 2023-11-14, nanosecond digits that a float of seconds would lose.
BASE_NS = 1_700_000_000_123_456_789
HOUR_NS = 3_600_000_000_000
MS = 1_000_000
# slambook2's camera (TUM fr1-like Kinect): fx, fy, cx, cy.
INTRINSICS = (518.0, 519.0, 325.5, 253.5)


def _ros() -> Tuple[Any, Any, Any, Any, Any]:
    try:
        import genpy
        import rosbag
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image
    except ImportError as e:
        pytest.fail(
            f"{e}: the bag tests need Debian's python3-rosbag and python3-sensor-msgs "
            "(tools/setup.sh --deps installs them)"
        )
    return rosbag, genpy, Image, CompressedImage, CameraInfo


def _time(genpy: Any, ns: int) -> Any:
    return genpy.Time(ns // 1_000_000_000, ns % 1_000_000_000)


def _image_message(
    Image: Any,
    genpy: Any,
    stamp_ns: int,
    pixels: np.ndarray,
    encoding: str,
    big_endian: bool = False,
    padding: int = 0,
) -> Any:
    """A sensor_msgs/Image of ``pixels`` (rows padded by ``padding`` junk bytes)."""
    message = Image()
    message.header.stamp = _time(genpy, stamp_ns)
    message.header.frame_id = "camera"
    height, width = pixels.shape[:2]
    message.height, message.width, message.encoding = height, width, encoding
    message.is_bigendian = int(big_endian)
    typed = pixels.astype(pixels.dtype.newbyteorder(">" if big_endian else "<"))
    rows = np.ascontiguousarray(typed).view(np.uint8).reshape(height, -1)
    if padding:
        rows = np.concatenate([rows, np.full((height, padding), 0xAB, np.uint8)], axis=1)
    message.step = rows.shape[1]
    message.data = rows.tobytes()
    return message


def _compressed_message(CompressedImage: Any, genpy: Any, stamp_ns: int, fmt: str, data: bytes):
    message = CompressedImage()
    message.header.stamp = _time(genpy, stamp_ns)
    message.format = fmt
    message.data = data
    return message


def _valid_mean_m(depth_m: np.ndarray) -> float:
    """Algorithm 1's V_current (docs/rgbd.md): the mean of the pixels within 0.1-12 m."""
    valid = depth_m[(depth_m >= 0.1) & (depth_m <= 12.0)]
    return float(valid.astype(np.float64).mean())


@pytest.fixture(scope="module")
def rgbd(slambook_rgbd) -> List[Dict[str, Any]]:
    """slambook2's frames decoded: BGR, gray, depth in mm (uint16), pose, files."""
    frames = []
    for colour, depth, pose in slambook_rgbd:
        bgr = cv2.imread(str(colour), cv2.IMREAD_COLOR)
        mm = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
        assert bgr is not None and mm is not None and mm.dtype == np.uint16
        frames.append(
            {
                "bgr": bgr,
                "gray": cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
                "mm": mm,
                "mean_m": _valid_mean_m(mm.astype(np.float64) / 1000.0),
                "pose": pose,
                "colour_file": colour,
            }
        )
    means = sorted(f["mean_m"] for f in frames)
    # The depth checks below tell frames apart by their mean depth.
    assert min(b - a for a, b in zip(means, means[1:])) > 0.01
    return frames


def _places(client: placedb.Client, map_name: str) -> Dict[int, placedb.Place]:
    return {p.place_id: p for p in client.iter_places(map_name)}


def _range_map(client: placedb.Client, name: str) -> None:
    # use_range: every frame with depth must carry intrinsics (else it is refused), so the
    # camera info's K reaching the server is checked too.
    client.create_map(name, placedb.MapSettings(depth=placedb.DepthSettings(use_range=True)))


# ---- ROS 1 bags ---------------------------------------------------------------------------------


def _write_raw_bag(path: Path, rgbd: List[Dict[str, Any]]) -> Tuple[List[int], List[dict]]:
    """A bag with /camera/image_raw (rgb8, bgr8, padded rows, mono8, bgra8), registered depth on
    /camera/depth/image_raw (16UC1 little and big endian, 32FC1) with stamps a few ms off the
    colour's, a distracting depth image 15 ms off, and /camera/camera_info. Receive times are an
    hour after the header stamps. Returns the colour stamps and, per colour frame, what the
    reference ingest sends (image, depth or None)."""
    rosbag, genpy, Image, _, CameraInfo = _ros()
    c1, c2, c3, c4 = rgbd[0], rgbd[1], rgbd[2], rgbd[3]
    rgb1 = np.ascontiguousarray(c1["bgr"][:, :, ::-1])
    bgra3 = np.dstack([c3["bgr"], np.full(c3["gray"].shape, 200, np.uint8)])
    metres2 = c2["mm"].astype(np.float32) / 1000.0
    # (colour message, encoding, reference image, depth pixels, depth encoding, depth offset ms)
    plan = [
        (c1["bgr"], "bgr8", 0, c1["bgr"], c1["mm"], "16UC1", False, 4),
        (rgb1, "rgb8", 0, c1["bgr"], c1["mm"], "16UC1", True, 4),
        (rgb1, "rgb8", 7, c1["bgr"], metres2, "32FC1", False, -3),
        (c2["gray"], "mono8", 0, c2["gray"], c2["mm"], "16UC1", False, 4),
        (bgra3, "bgra8", 0, c3["bgr"], c3["mm"], "16UC1", False, 4),
        (c4["bgr"], "bgr8", 0, c4["bgr"], c4["mm"], "16UC1", False, 50),  # too far: no depth
    ]
    stamps = [BASE_NS + i * 200 * MS + i for i in range(len(plan))]
    reference = []
    with rosbag.Bag(str(path), "w") as bag:
        info = CameraInfo()
        info.header.stamp = _time(genpy, stamps[0] - 100 * MS)
        info.width, info.height = 640, 480
        info.K = [INTRINSICS[0], 0, INTRINSICS[2], 0, INTRINSICS[1], INTRINSICS[3], 0, 0, 1]
        bag.write("/camera/camera_info", info, _time(genpy, stamps[0] - 100 * MS + HOUR_NS))
        for i, (pixels, encoding, padding, ref, depth, depth_encoding, big, offset) in enumerate(
            plan
        ):
            stamp = stamps[i]
            message = _image_message(Image, genpy, stamp, pixels, encoding, padding=padding)
            bag.write("/camera/image_raw", message, _time(genpy, stamp + HOUR_NS))
            depth_stamp = stamp + offset * MS
            depth_message = _image_message(Image, genpy, depth_stamp, depth, depth_encoding, big)
            bag.write("/camera/depth/image_raw", depth_message, _time(genpy, depth_stamp + HOUR_NS))
            if i == 3:  # another frame's depth, 15 ms off: the nearest (4 ms) must win
                other = _image_message(Image, genpy, stamp + 15 * MS, rgbd[4]["mm"], "16UC1")
                bag.write("/camera/depth/image_raw", other, _time(genpy, stamp + 15 * MS + HOUR_NS))
            paired = abs(offset) <= 20
            reference.append({"image": ref, "depth": depth if paired else None})
    return stamps, reference


def test_bag_raw_images_keep_header_stamps_depth_and_pixels(
    client: placedb.Client, rgbd: List[Dict[str, Any]], tmp_path: Path
) -> None:
    bag_path = tmp_path / "run.bag"
    stamps, reference = _write_raw_bag(bag_path, rgbd)
    recording = placedb.read_bag(
        bag_path,
        "/camera/image_raw",
        depth_topic="/camera/depth/image_raw",
        camera_info_topic="/camera/camera_info",
    )
    assert len(recording) == len(stamps)

    _range_map(client, "bag-raw")
    results = list(client.ingest("bag-raw", recording, agent_id="robot-1"))
    assert [r.error for r in results] == [None] * len(stamps)
    assert all(r.stored for r in results), [r.rejection for r in results]
    stats = recording.stats
    assert (stats.frames, stats.depth_paired, stats.depth_missing) == (6, 5, 1)
    assert (stats.first_ns, stats.last_ns, stats.receive_time_stamps) == (stamps[0], stamps[-1], 0)

    # Capture times: the header stamps, to the nanosecond (not the receive times an hour later).
    places = _places(client, "bag-raw")
    assert [places[r.place_id].timestamp_ns for r in results] == stamps

    # Depth: each frame's own depth image (the nearest), in metres whatever its encoding.
    expected_means = [0, 0, 1, 1, 2]
    for result, frame in zip(results[:5], expected_means):
        assert result.depth is not None
        assert result.depth.mean_depth_m == pytest.approx(rgbd[frame]["mean_m"], rel=1e-5)
    assert results[5].depth is None  # its depth was 50 ms away

    # Pixels: the same features as the frames sent directly as BGR / gray arrays.
    _range_map(client, "bag-raw-reference")
    direct = [
        placedb.Frame(
            image=ref["image"],
            timestamp_ns=stamp,
            depth=(
                None
                if ref["depth"] is None
                else placedb.Depth(
                    ref["depth"],
                    scale=0.001 if ref["depth"].dtype == np.uint16 else 1.0,
                    intrinsics=INTRINSICS,
                )
            ),
        )
        for ref, stamp in zip(reference, stamps)
    ]
    expected = list(client.ingest("bag-raw-reference", direct, agent_id="robot-1"))
    for got, want in zip(results, expected):
        assert got.counts == want.counts
        a = client.get_place("bag-raw", got.place_id, include_features=True)
        b = client.get_place("bag-raw-reference", want.place_id, include_features=True)
        assert a.image_size == b.image_size
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        np.testing.assert_array_equal(a.descriptors, b.descriptors)


def _write_compressed_bag(path: Path, rgbd: List[Dict[str, Any]], jpeg: bytes) -> List[int]:
    """/camera/image/compressed (PNG and JPEG CompressedImages) with image_transport
    compressedDepth on /camera/depth/compressedDepth; the JPEG's header stamp is 0."""
    rosbag, genpy, _, CompressedImage, CameraInfo = _ros()
    stamps = [BASE_NS + i * 100 * MS for i in range(4)]
    with rosbag.Bag(str(path), "w") as bag:
        for i in range(3):
            colour = rgbd[i]["colour_file"].read_bytes()
            message = _compressed_message(
                CompressedImage, genpy, stamps[i], "rgb8; png compressed bgr8", colour
            )
            bag.write("/camera/image/compressed", message, _time(genpy, stamps[i]))
            # compressedDepth: a 12-byte header (format, quantisation) before the 16-bit PNG.
            header = np.array([0], "<i4").tobytes() + np.array([0, 0], "<f4").tobytes()
            depth = _compressed_message(
                CompressedImage,
                genpy,
                stamps[i] + 2 * MS,
                "16UC1; compressedDepth png",
                header + encode_gray_png(rgbd[i]["mm"]),
            )
            bag.write("/camera/depth/compressedDepth", depth, _time(genpy, stamps[i] + 2 * MS))
        receive = stamps[3] + 5 * MS
        unstamped = _compressed_message(CompressedImage, genpy, 0, "jpeg", jpeg)
        bag.write("/camera/image/compressed", unstamped, _time(genpy, receive))
    return stamps[:3] + [receive]


def test_bag_compressed_images_and_compressed_depth(
    client: placedb.Client, rgbd: List[Dict[str, Any]], rtabmap_frames: List[Path], tmp_path: Path
) -> None:
    bag_path = tmp_path / "compressed.bag"
    expected_stamps = _write_compressed_bag(bag_path, rgbd, rtabmap_frames[0].read_bytes())
    recording = placedb.read_bag(
        bag_path, "/camera/image/compressed", depth_topic="/camera/depth/compressedDepth"
    )
    client.create_map("bag-compressed")
    results = list(client.ingest("bag-compressed", recording, agent_id="robot-2"))
    assert all(r.stored and r.error is None for r in results), results
    places = _places(client, "bag-compressed")
    # A header stamp of 0 falls back to the bag's receive time, and is counted.
    assert [places[r.place_id].timestamp_ns for r in results] == expected_stamps
    stats = recording.stats
    assert (stats.depth_paired, stats.depth_missing, stats.receive_time_stamps) == (3, 1, 1)
    for i in range(3):
        assert results[i].depth.mean_depth_m == pytest.approx(rgbd[i]["mean_m"], rel=1e-5)
    assert results[3].depth is None
    # The frames were sent as their encoded bytes: the same features as the files themselves.
    direct = list(
        client.ingest("bag-compressed", [rgbd[0]["colour_file"]], agent_id="other")
    )
    a = client.get_place("bag-compressed", results[0].place_id, include_features=True)
    b = client.get_place("bag-compressed", direct[0].place_id, include_features=True)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)

    # Read twice: a Recording is an iterable that reads the bag again each time.
    assert [f.timestamp_ns for f in recording] == expected_stamps


def test_bag_refusals_say_what_is_wrong(rgbd: List[Dict[str, Any]], tmp_path: Path) -> None:
    rosbag, genpy, Image, _, _ = _ros()
    bag_path = tmp_path / "bayer.bag"
    with rosbag.Bag(str(bag_path), "w") as bag:
        message = _image_message(Image, genpy, BASE_NS, rgbd[0]["gray"], "bayer_rggb8")
        bag.write("/camera/image_raw", message, _time(genpy, BASE_NS))

    with pytest.raises(placedb.InvalidArgument, match=r"topic /cam: not in .*bayer\.bag; "
                       r"its topics: /camera/image_raw \(sensor_msgs/Image, 1\)"):
        placedb.read_bag(bag_path, "/cam")
    with pytest.raises(placedb.InvalidArgument, match="depth_topic /camera/image_raw: the colour"):
        placedb.read_bag(bag_path, "/camera/image_raw", depth_topic="/camera/image_raw")
    with pytest.raises(placedb.InvalidArgument, match="camera_info_topic /camera/image_raw: "
                       "sensor_msgs/Image, expected sensor_msgs/CameraInfo"):
        placedb.read_bag(bag_path, "/camera/image_raw", camera_info_topic="/camera/image_raw")
    # Checked when read: an encoding without a conversion, named with the message.
    frames = iter(placedb.read_bag(bag_path, "/camera/image_raw"))
    with pytest.raises(placedb.InvalidArgument, match=r"/camera/image_raw message 0: encoding "
                       r"'bayer_rggb8'; colour frames may be rgb8, bgr8"):
        next(frames)

    # ROS 2: MCAP, rosbag2 SQLite and a rosbag2 directory are refused, saying what is missing.
    mcap = tmp_path / "run.mcap"
    mcap.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    sqlite = tmp_path / "run_0.db3"
    sqlite.write_bytes(b"SQLite format 3\x00" + bytes(64))
    rosbag2 = tmp_path / "rosbag2_run"
    rosbag2.mkdir()
    (rosbag2 / "metadata.yaml").write_text("rosbag2_bagfile_information:\n")
    for path, kind in ((mcap, "MCAP"), (sqlite, "SQLite"), (rosbag2, "rosbag2 directory")):
        with pytest.raises(placedb.FailedPrecondition) as refused:
            placedb.read_bag(path, "/camera/image_raw")
        assert kind in refused.value.message and "Debian 12 packages no reader" in str(
            refused.value
        ), refused.value
    not_a_bag = tmp_path / "notes.txt"
    not_a_bag.write_text("hello\n")
    with pytest.raises(placedb.InvalidArgument, match="not a ROS 1 bag"):
        placedb.read_bag(not_a_bag, "/camera/image_raw")
    with pytest.raises(placedb.InvalidArgument, match="cannot read"):
        placedb.read_bag(tmp_path / "missing.bag", "/camera/image_raw")


# ---- TUM RGB-D folders --------------------------------------------------------------------------


def _tum_time(ns: int) -> str:
    """TUM's notation: seconds with microseconds."""
    assert ns % 1000 == 0
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000 // 1000:06d}"


def _write_tum(folder: Path, rgbd: List[Dict[str, Any]]) -> Tuple[List[int], List[Any]]:
    """A TUM RGB-D folder of slambook2's frames: colour PNGs, depth as TUM's 16-bit PNGs (5000
    per metre) 7 ms after each colour frame, ground truth at the colour times except frame 5
    (two samples around it), and a sixth frame 2 s later with neither depth nor pose near.
    Returns the colour times and the expected poses."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    base = 1_305_031_102_175_304_000
    times = [base + i * 200 * MS for i in range(5)] + [base + 4 * 200 * MS + 2_000 * MS]
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    truth_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    expected_poses: List[Any] = []
    for i, t in enumerate(times):
        frame = rgbd[i % 5]
        name = f"{_tum_time(t)}.png"
        shutil.copyfile(frame["colour_file"], folder / "rgb" / name)
        rgb_lines.append(f"{_tum_time(t)} rgb/{name}")
        if i == 5:
            expected_poses.append(None)
            continue
        depth_t = t + 7 * MS
        tum_units = (frame["mm"].astype(np.uint32) * 5).astype(np.uint16)  # 5000 per metre
        (folder / "depth" / f"{_tum_time(depth_t)}.png").write_bytes(encode_gray_png(tum_units))
        depth_lines.append(f"{_tum_time(depth_t)} depth/{_tum_time(depth_t)}.png")
        x, y, z, qx, qy, qz, qw = frame["pose"]
        if i < 4:
            truth_lines.append(f"{_tum_time(t)} {x!r} {y!r} {z!r} {qx!r} {qy!r} {qz!r} {qw!r}")
            expected_poses.append(placedb.Pose(x, y, z, qx, qy, qz, qw))
        else:
            # 10 ms before at x - 0.1, 30 ms after at x + 0.3, same orientation: x at the frame,
            # the orientation normalised (the file's quaternion is rounded).
            for dt, dx in ((-10, -0.1), (30, 0.3)):
                truth_lines.append(
                    f"{_tum_time(t + dt * MS)} {x + dx!r} {y!r} {z!r} {qx!r} {qy!r} {qz!r} {qw!r}"
                )
            n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
            expected_poses.append(placedb.Pose(x, y, z, qx / n, qy / n, qz / n, qw / n))
    for name, lines in (("rgb", rgb_lines), ("depth", depth_lines), ("groundtruth", truth_lines)):
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n")
    return times, expected_poses


def _assert_pose(got: Optional[placedb.Pose], want: placedb.Pose) -> None:
    assert got is not None
    for field in ("x", "y", "z", "qx", "qy", "qz", "qw"):
        assert getattr(got, field) == pytest.approx(getattr(want, field), abs=1e-9), field


def test_tum_folder_times_depth_and_poses(
    client: placedb.Client, rgbd: List[Dict[str, Any]], tmp_path: Path
) -> None:
    folder = tmp_path / "rgbd_dataset_slambook"
    times, poses = _write_tum(folder, rgbd)
    recording = placedb.read_tum(folder, intrinsics=INTRINSICS)
    assert len(recording) == 6
    _range_map(client, "tum")
    results = list(client.ingest("tum", recording, agent_id="kinect"))
    assert all(r.stored and r.error is None for r in results), results
    stats = recording.stats
    assert (stats.frames, stats.depth_paired, stats.depth_missing) == (6, 5, 1)
    assert (stats.poses, stats.poses_missing) == (5, 1)

    places = _places(client, "tum")
    stored = [places[r.place_id] for r in results]
    assert [p.timestamp_ns for p in stored] == times
    for place, pose in zip(stored[:4], poses[:4]):
        assert place.pose == pose  # exactly the ground truth's numbers
    _assert_pose(stored[4].pose, poses[4])  # interpolated between its two samples
    assert stored[5].pose is None
    # TUM's 1/5000 m per unit: the same metres as slambook2's millimetres.
    for i in range(5):
        assert results[i].depth.mean_depth_m == pytest.approx(rgbd[i]["mean_m"], rel=1e-5)
    assert results[5].depth is None

    # Without intrinsics a range map refuses the frames with depth: they were sent above.
    refused = list(client.ingest("tum", placedb.read_tum(folder), agent_id="no-intrinsics"))
    assert refused[0].error is not None and refused[5].error is None

    # depth=False / poses=False ignore the lists.
    bare = list(placedb.read_tum(folder, depth=False, poses=False))
    assert all(f.depth is None and f.pose is None for f in bare)
    assert [f.timestamp_ns for f in bare] == times


def test_tum_refusals_name_the_file(rgbd: List[Dict[str, Any]], tmp_path: Path) -> None:
    folder = tmp_path / "tum"
    _write_tum(folder, rgbd)
    with pytest.raises(placedb.InvalidArgument, match="no rgb.txt"):
        placedb.read_tum(tmp_path)
    with pytest.raises(placedb.InvalidArgument, match="no groundtruth.txt"):
        empty = tmp_path / "only-rgb"
        empty.mkdir()
        (empty / "rgb.txt").write_text((folder / "rgb.txt").read_text())
        placedb.read_tum(empty, poses=True)
    with pytest.raises(placedb.InvalidArgument, match=r"intrinsics: .*expected \(fx, fy, cx, cy\)"):
        placedb.read_tum(folder, intrinsics=(1.0, 2.0))

    lines = (folder / "rgb.txt").read_text().splitlines()
    (folder / "rgb.txt").write_text("\n".join(lines + ["1305031200.5x rgb/x.png"]) + "\n")
    with pytest.raises(placedb.InvalidArgument, match=rf"rgb\.txt:{len(lines) + 1}: "):
        placedb.read_tum(folder)
    (folder / "rgb.txt").write_text("\n".join(lines + ["1305031200.5 rgb/missing.png"]) + "\n")
    with pytest.raises(placedb.InvalidArgument, match="rgb/missing.png .* does not exist"):
        placedb.read_tum(folder)
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")

    # An 8-bit depth PNG is refused when that frame is read, naming the file.
    first_depth = sorted((folder / "depth").iterdir())[0]
    first_depth.write_bytes(encode_gray_png(np.zeros((48, 64), np.uint8)))
    frames = iter(placedb.read_tum(folder))
    with pytest.raises(placedb.InvalidArgument, match=rf"{first_depth.name}: a PNG of bit depth 8"):
        next(frames)


def test_timestamps_and_pose_interpolation() -> None:
    assert seconds_to_ns("1305031102.175304") == 1_305_031_102_175_304_000
    assert seconds_to_ns("1700000000.123456789") == 1_700_000_000_123_456_789
    assert seconds_to_ns("42") == 42_000_000_000
    for bad in ("1.2.3", "1e9", "", "12.1234567891"):
        with pytest.raises(ValueError):
            seconds_to_ns(bad)

    half = math.sin(math.pi / 4)
    identity = placedb.Pose(0, 0, 0, 0, 0, 0, 1)
    quarter_turn = placedb.Pose(2, 4, 6, 0, 0, half, half)  # 90 degrees about z
    times = [1_000, 3_000]
    eighth = placedb.Pose(1, 2, 3, 0, 0, math.sin(math.pi / 8), math.cos(math.pi / 8))
    _assert_pose(interpolate_pose(times, [identity, quarter_turn], 2_000, 0, 10_000), eighth)
    # -q is the same rotation: slerp takes the short way either way.
    negated = placedb.Pose(2, 4, 6, 0, 0, -half, -half)
    got = interpolate_pose(times, [identity, negated], 2_000, 0, 10_000)
    assert got is not None and got.qw > 0
    _assert_pose(got, eighth)
    # Samples too far apart: the nearest within the offset, else none.
    assert interpolate_pose(times, [identity, quarter_turn], 1_100, 200, 1_000) == identity
    assert interpolate_pose(times, [identity, quarter_turn], 2_000, 200, 1_000) is None
    assert interpolate_pose(times, [identity, quarter_turn], 3_000, 0, 0) == quarter_turn


# ---- placedb-py ---------------------------------------------------------------------------------


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "placedb", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ),
    )


def test_cli_ingests_a_bag_and_a_tum_folder(
    client: placedb.Client, server, rgbd: List[Dict[str, Any]], tmp_path: Path
) -> None:
    stamps, _ = _write_raw_bag(tmp_path / "run.bag", rgbd)
    done = _cli(
        "ingest-bag", "cli-bag", str(tmp_path / "run.bag"), "--topic", "/camera/image_raw",
        "--depth-topic", "/camera/depth/image_raw", "--camera-info-topic", "/camera/camera_info",
        "--create", "--agent", "robot-9", "--address", server.address, "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "6 frames into map cli-bag (agent robot-9): 6 stored" in done.stdout, done.stdout
    assert "depth: 5 paired, 1 without" in done.stdout
    assert "2023-11-14T22:13:20.123Z" in done.stdout  # the first header stamp, not today
    assert sorted(p.timestamp_ns for p in client.iter_places("cli-bag")) == stamps

    times, _ = _write_tum(tmp_path / "tum", rgbd)
    done = _cli(
        "ingest-tum", "cli-tum", str(tmp_path / "tum"), "--create", "--limit", "3",
        "--address", server.address, "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "3 frames into map cli-tum" in done.stdout and "poses: 3" in done.stdout, done.stdout
    assert sorted(p.timestamp_ns for p in client.iter_places("cli-tum")) == times[:3]

    # Usage and input errors exit 2 with the reason; a server that is not there exits 1.
    done = _cli("ingest-bag", "m", str(tmp_path / "run.bag"), "--topic", "/nope",
                "--address", server.address)  # fmt: skip
    assert done.returncode == 2 and "topic /nope: not in" in done.stderr, done.stderr
    mcap = tmp_path / "run.mcap"
    mcap.write_bytes(b"\x89MCAP0\r\n" + bytes(8))
    done = _cli("ingest-bag", "m", str(mcap), "--topic", "/camera/image_raw")
    assert done.returncode == 2 and "a ROS 2 bag (MCAP)" in done.stderr, done.stderr
    done = _cli("ingest-tum", "no-such-map", str(tmp_path / "tum"), "--address", server.address)
    assert done.returncode == 1 and "NOT_FOUND" in done.stderr, done.stderr
    assert "(--create creates the map)" in done.stderr
    port = str(unused_loopback_port())
    done = _cli("ingest-tum", "m", str(tmp_path / "tum"), "--address", port, "--quiet")
    assert done.returncode == 1, done.stderr
    assert "UNAVAILABLE" in done.stderr and f"running at localhost:{port}?" in done.stderr


def test_bags_without_python3_rosbag_say_what_to_install(
    rgbd: List[Dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _write_raw_bag(tmp_path / "run.bag", rgbd)
    monkeypatch.setitem(sys.modules, "rosbag", None)  # as if python3-rosbag were not installed
    with pytest.raises(placedb.FailedPrecondition, match="apt-get install python3-rosbag"):
        placedb.read_bag(tmp_path / "run.bag", "/camera/image_raw")
