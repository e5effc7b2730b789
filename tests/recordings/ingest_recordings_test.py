#!/usr/bin/env python3
"""`placedb ingest` of recordings, end to end: ROS 1 bags this test writes itself with Debian's
python3-rosbag (uncompressed, bz2 and lz4 chunks) and a TUM RGB-D folder it writes, from
slambook2's real RGB-D frames (../shared/data/slambook2-rgbd), ingested by the real `placedb`
CLI into a real placedb-server on a loopback port. The places must carry the recordings' capture
times (header stamps; TUM timestamps), the camera info's camera, and the TUM ground truth's
poses; bad recordings must be usage errors (exit 2) naming what is wrong. With the Python SDK
built (PLACEDB_PYTHON_PACKAGE_DIR), the SDK's placedb.read_bag / read_tum must read the same
recordings into the same capture times, depth pairing, cameras and poses as the CLI.

ctest (tests/CMakeLists.txt, ingest_recordings_test) sets PLACEDB_SERVER_BINARY,
PLACEDB_CLI_BINARY, PLACEDB_DEFAULT_VOCABULARY, PLACEDB_SHARED_DIR and, when the SDK is built,
PLACEDB_PYTHON_PACKAGE_DIR.
"""

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

BASE_S = 1_700_000_000  # 2023-11-14
HOUR_S = 3600
# slambook2's camera (its Kinect): fx, fy, cx, cy.
K = (518.0, 519.0, 325.5, 253.5)


def fail(message):
    print("FAIL: " + message, file=sys.stderr)
    sys.exit(1)


def env(name):
    value = os.environ.get(name)
    if not value:
        fail(name + " is not set (run this test through ctest)")
    return value


try:
    import cv2  # python3-opencv
    import genpy
    import numpy as np
    import rosbag
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image
except ImportError as e:
    fail(f"{e}: this test needs Debian's python3-rosbag, python3-sensor-msgs, python3-roslz4 and "
         "python3-opencv (tools/setup.sh --deps --tests installs them)")

SERVER = env("PLACEDB_SERVER_BINARY")
CLI = env("PLACEDB_CLI_BINARY")
SLAMBOOK = os.path.join(env("PLACEDB_SHARED_DIR"), "data", "slambook2-rgbd")
if not os.path.isdir(SLAMBOOK):
    fail(SLAMBOOK + " is missing (../shared/data, see ../shared/README.md)")


def ros_time(ns):
    return genpy.Time(ns // 1_000_000_000, ns % 1_000_000_000)


def stamp_ns(frame, offset_ms=0):
    """Frame i's capture time: nanosecond digits a float of seconds would lose."""
    return (BASE_S + 10 * frame) * 1_000_000_000 + 123_456_789 + offset_ms * 1_000_000


def frames():
    out = []
    for i in range(1, 6):
        bgr = cv2.imread(os.path.join(SLAMBOOK, "color", f"{i}.png"), cv2.IMREAD_COLOR)
        mm = cv2.imread(os.path.join(SLAMBOOK, "depth", f"{i}.pgm"), cv2.IMREAD_UNCHANGED)
        if bgr is None or mm is None or mm.dtype != np.uint16:
            fail(f"cannot read slambook2 frame {i}")
        out.append({"bgr": bgr, "mm": mm})
    return out


def image_message(stamp, pixels, encoding, padding=0):
    message = Image()
    message.header.stamp = ros_time(stamp)
    message.header.frame_id = "camera"
    message.height, message.width = pixels.shape[:2]
    message.encoding = encoding
    rows = np.ascontiguousarray(pixels).view(np.uint8).reshape(message.height, -1)
    if padding:
        rows = np.concatenate([rows, np.full((message.height, padding), 0xAB, np.uint8)], axis=1)
    message.step = rows.shape[1]
    message.data = rows.tobytes()
    return message


def camera_info(stamp):
    info = CameraInfo()
    info.header.stamp = ros_time(stamp)
    info.height, info.width = 480, 640
    info.distortion_model = "plumb_bob"
    info.D = [0.0] * 5
    info.K = [K[0], 0, K[2], 0, K[1], K[3], 0, 0, 1]
    info.P = [K[0], 0, K[2], 0, 0, K[1], K[3], 0, 0, 0, 1, 0]
    return info


def write_bag(path, compression, data, compressed_colour=False):
    """Five colour frames (bgr8, rgb8 with padded rows, mono8, bgra8 with a header stamp of 0,
    bgr8; or PNG CompressedImages), depth 4 ms after each (16UC1; frame 5's 32FC1) but frame 3's
    30 ms off (unpaired at --max-offset 0.02), and camera info first. Receive times are an hour
    after the stamps. Returns each frame's expected capture time."""
    expected = []
    with rosbag.Bag(path, "w", compression=compression) as bag:
        bag.write("/camera/camera_info", camera_info(stamp_ns(0)),
                  ros_time(stamp_ns(0) + HOUR_S * 10**9))
        for i, frame in enumerate(data, 1):
            stamp = stamp_ns(i)
            receive = stamp + HOUR_S * 10**9
            bgr = frame["bgr"]
            if compressed_colour:
                message = CompressedImage()
                message.header.stamp = ros_time(stamp)
                message.format = "png"
                message.data = cv2.imencode(".png", bgr)[1].tobytes()
            elif i == 2:
                message = image_message(stamp, bgr[:, :, ::-1], "rgb8", padding=7)
            elif i == 3:
                message = image_message(stamp, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), "mono8")
            elif i == 4:
                bgra = np.dstack([bgr, np.full(bgr.shape[:2], 200, np.uint8)])
                message = image_message(0, bgra, "bgra8")
                stamp = receive  # a header stamp of 0: the receive time stands in
            else:
                message = image_message(stamp, bgr, "bgr8")
            expected.append(stamp)
            bag.write("/camera/image_raw", message, ros_time(receive))
            depth_stamp = stamp + (30 if i == 3 else 4) * 1_000_000
            if i == 5:
                depth = image_message(depth_stamp, frame["mm"].astype(np.float32) / 1000, "32FC1")
            else:
                depth = image_message(depth_stamp, frame["mm"], "16UC1")
            bag.write("/camera/depth/image_raw", depth, ros_time(receive + 1_000_000))
    return expected


class Server:
    def __init__(self, root):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.address = f"127.0.0.1:{s.getsockname()[1]}"
        self.process = subprocess.Popen([
            SERVER, "--listen", self.address, "--data-dir", os.path.join(root, "data"),
            "--metrics-listen", "off", "--console-listen", "off",
            "--vocabulary", "default=" + env("PLACEDB_DEFAULT_VOCABULARY"), "--log-level", "warn"])
        deadline = time.monotonic() + 60
        while self.cli(["health"], check=False).returncode != 0:
            if self.process.poll() is not None or time.monotonic() > deadline:
                fail("placedb-server did not start")
            time.sleep(0.2)

    def cli(self, args, check=True, expect=0):
        run = subprocess.run([CLI, "--address", self.address] + args, capture_output=True,
                             text=True, timeout=300)
        if check and run.returncode != expect:
            fail(f"placedb {' '.join(args)}: exit {run.returncode}, expected {expect}\n"
                 f"stdout: {run.stdout}\nstderr: {run.stderr}")
        return run

    def json(self, args):
        return json.loads(self.cli(["--json"] + args).stdout)

    def stop(self):
        self.process.terminate()
        self.process.wait(timeout=60)


def sdk():
    """The build tree's Python SDK, or None when it is not built."""
    package_dir = os.environ.get("PLACEDB_PYTHON_PACKAGE_DIR")
    if not package_dir:
        return None
    sys.path.insert(0, package_dir)
    import placedb

    return placedb


def check_same_as_sdk(recording, summary, server, map_name, cameras=True):
    """The SDK's frames of `recording` (placedb.read_bag / read_tum) against what the CLI stored:
    capture times, depth pairing, cameras (a bag's camera info; without `cameras` the server
    derives the places' cameras from the depth's intrinsics) and poses, frame by frame."""
    frames = list(recording)
    results = summary["results"]
    if len(frames) != len(results):
        fail(f"{recording}: the SDK reads {len(frames)} frames, the CLI sent {len(results)}")
    stats, cli = recording.stats, summary["recording"]
    for key in ("depth_paired", "depth_missing", "poses", "poses_missing", "receive_time_stamps"):
        if getattr(stats, key) != cli[key]:
            fail(f"{recording}: SDK {key} {getattr(stats, key)}, CLI {cli[key]}")
    for i, (frame, result) in enumerate(zip(frames, results)):
        place = server.json(["place", "get", map_name, str(result["place_id"]), "--features"])
        if int(place["metadata"]["timestamp_ns"]) != frame.timestamp_ns:
            fail(f"{recording}: frame {i}: CLI stored {place['metadata']['timestamp_ns']}, the "
                 f"SDK reads {frame.timestamp_ns}")
        camera = place.get("camera")
        if cameras and ((frame.camera is None) != (camera is None) or (
                camera and (camera["fx"], camera["cy"]) != (frame.camera.fx, frame.camera.cy))):
            fail(f"{recording}: frame {i}: CLI camera {camera}, SDK {frame.camera}")
        pose = place["metadata"].get("pose")
        if (frame.pose is None) != (pose is None) or (
                pose and abs(pose.get("x", 0.0) - frame.pose.x) > 1e-9):
            fail(f"{recording}: frame {i}: CLI pose {pose}, SDK {frame.pose}")


def check_places(server, map_name, summary, expected_stamps, camera=True, poses=None):
    """Every frame stored, its place carrying the frame's capture time (and camera, pose)."""
    results = summary["results"]
    if len(results) != len(expected_stamps):
        fail(f"{map_name}: {len(results)} results for {len(expected_stamps)} frames")
    for i, (result, stamp) in enumerate(zip(results, expected_stamps)):
        if not result.get("stored"):
            fail(f"{map_name}: frame {i} not stored: {result}")
        place = server.json(["place", "get", map_name, str(result["place_id"]), "--features"])
        got = int(place["metadata"]["timestamp_ns"])
        if got != stamp:
            fail(f"{map_name}: frame {i}: timestamp {got}, expected the recording's {stamp}")
        if camera:
            fx, fy = place["camera"]["fx"], place["camera"]["fy"]
            cx, cy = place["camera"]["cx"], place["camera"]["cy"]
            if (fx, fy, cx, cy) != K:
                fail(f"{map_name}: frame {i}: camera {place['camera']}, expected K {K}")
        if poses is not None:
            want = poses[i]
            pose = place["metadata"].get("pose")
            if want is None:
                if pose and any(abs(v) > 0 for v in pose.values()):
                    fail(f"{map_name}: frame {i} has a pose {pose}, expected none")
            else:
                got_pose = [pose.get(k, 0.0) for k in ("x", "y", "z", "qx", "qy", "qz", "qw")]
                if max(abs(a - b) for a, b in zip(got_pose, want)) > 1e-6:
                    fail(f"{map_name}: frame {i}: pose {got_pose}, expected {want}")
    listed = server.json(["place", "list", map_name])
    listed_stamps = sorted(int(p["metadata"]["timestamp_ns"]) for p in listed["places"])
    if listed_stamps != sorted(expected_stamps):
        fail(f"{map_name}: ListPlaces timestamps {listed_stamps}, expected {expected_stamps}")


def test_bags(server, root, data):
    for compression, compressed_colour in (("none", False), ("bz2", True), ("lz4", False)):
        path = os.path.join(root, f"run-{compression}.bag")
        expected = write_bag(path, compression, data, compressed_colour)
        map_name = "bag-" + compression
        server.cli(["maps", "create", map_name])
        summary = server.json(["ingest", map_name, path, "--topic", "/camera/image_raw",
                               "--depth-topic", "/camera/depth/image_raw",
                               "--camera-info-topic", "/camera/camera_info"])
        recording = summary["recording"]
        want = {"frames": 5, "depth_paired": 4, "depth_missing": 1, "cameras": 5,
                "receive_time_stamps": 0 if compressed_colour else 1}
        for key, value in want.items():
            if recording[key] != value:
                fail(f"{path}: recording.{key} = {recording[key]}, expected {value}: {recording}")
        check_places(server, map_name, summary, expected)
        print(f"ok: {compression} bag: 5 places with the bag's stamps and camera")
        placedb = sdk()
        if placedb:
            check_same_as_sdk(
                placedb.read_bag(path, "/camera/image_raw", depth_topic="/camera/depth/image_raw",
                                 camera_info_topic="/camera/camera_info"),
                summary, server, map_name)
            print(f"ok: {compression} bag: the SDK's read_bag gives the same frames")
    # The human summary says where the times came from.
    text = server.cli(["ingest", "bag-none", os.path.join(root, "run-none.bag"), "--topic",
                       "/camera/image_raw"]).stdout
    if "captured   2023-11-14T22:13:30.123Z" not in text:
        fail("the summary does not show the capture times:\n" + text)


def test_bad_bags(server, root):
    good = os.path.join(root, "run-none.bag")
    missing = server.cli(["ingest", "bag-none", good, "--topic", "/camera/rgb"], expect=2)
    if ("/camera/rgb" not in missing.stderr
            or "/camera/image_raw (sensor_msgs/Image, 5 messages)" not in missing.stderr):
        fail("an unknown topic must list the bag's image topics: " + missing.stderr)
    wrong = server.cli(["ingest", "bag-none", good, "--topic", "/camera/image_raw",
                        "--camera-info-topic", "/camera/depth/image_raw"], expect=2)
    if "expected sensor_msgs/CameraInfo" not in wrong.stderr:
        fail("a camera-info topic of another type must say so: " + wrong.stderr)
    no_topic = server.cli(["ingest", "bag-none", good], expect=2)
    if "--topic" not in no_topic.stderr:
        fail("a bag without --topic must ask for it: " + no_topic.stderr)
    with open(good, "rb") as f:
        content = f.read()
    truncated = os.path.join(root, "truncated.bag")
    with open(truncated, "wb") as f:
        f.write(content[: len(content) // 2])
    cut = server.cli(["ingest", "bag-none", truncated, "--topic", "/camera/image_raw"], expect=2)
    if "truncated.bag: truncated" not in cut.stderr:
        fail("a truncated bag must say so: " + cut.stderr)
    zstd = os.path.join(root, "zstd.bag")
    with open(zstd, "wb") as f:
        f.write(content.replace(b"compression=none", b"compression=zstd"))
    unknown = server.cli(["ingest", "bag-none", zstd, "--topic", "/camera/image_raw"], expect=2)
    if "'zstd'" not in unknown.stderr:
        fail("an unknown chunk compression must be named: " + unknown.stderr)
    print("ok: bad bags are usage errors naming the problem")


def test_tum(server, root, data):
    folder = os.path.join(root, "tum")
    os.makedirs(os.path.join(folder, "rgb"))
    os.makedirs(os.path.join(folder, "depth"))
    with open(os.path.join(SLAMBOOK, "pose.txt")) as f:
        poses = [[float(v) for v in line.split()] for line in f if line.strip()]
    rgb, depth, truth = ["# colour"], ["# depth"], ["# timestamp tx ty tz qx qy qz qw"]
    expected, expected_poses = [], []
    for i, frame in enumerate(data, 1):
        stamp = stamp_ns(i)
        seconds = f"{stamp // 10**9}.{stamp % 10**9:09d}"
        shutil.copy(os.path.join(SLAMBOOK, "color", f"{i}.png"),
                    os.path.join(folder, "rgb", f"{seconds}.png"))
        rgb.append(f"{seconds} rgb/{seconds}.png")
        # TUM's depth: 5000 units per metre.
        units = (frame["mm"].astype(np.float64) * 5).clip(0, 65535).astype(np.uint16)
        cv2.imwrite(os.path.join(folder, "depth", f"{seconds}.png"), units)
        depth_s = f"{(stamp + 5_000_000) // 10**9}.{(stamp + 5_000_000) % 10**9:09d}"
        depth.append(f"{depth_s} depth/{seconds}.png")
        pose = poses[i - 1]
        if i == 5:  # no ground truth near the last frame
            expected_poses.append(None)
        elif i == 2:  # samples 10 ms either side, 0.2 m apart in x: interpolated halfway
            for offset, dx in ((-10, 0.0), (10, 0.2)):
                t = stamp + offset * 1_000_000
                values = [pose[0] + dx] + pose[1:]
                truth.append(f"{t // 10**9}.{t % 10**9:09d} " + " ".join(map(repr, values)))
            q = np.array(pose[3:]) / np.linalg.norm(pose[3:])  # slerp's result is unit length
            expected_poses.append([pose[0] + 0.1] + pose[1:3] + list(q))
        else:
            truth.append(f"{seconds} " + " ".join(map(repr, pose)))
            expected_poses.append(pose)
        expected.append(stamp)
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", truth)):
        with open(os.path.join(folder, name), "w") as f:
            f.write("\n".join(lines) + "\n")
    server.cli(["maps", "create", "tum"])
    summary = server.json(["ingest", "tum", folder, "--intrinsics", ",".join(map(str, K))])
    recording = summary["recording"]
    want = {"frames": 5, "depth_paired": 5, "depth_missing": 0, "poses": 4, "poses_missing": 1}
    for key, value in want.items():
        if recording[key] != value:
            fail(f"{folder}: recording.{key} = {recording[key]}, expected {value}: {recording}")
    # Slerp between two equal orientations is that orientation; only x moves.
    check_places(server, "tum", summary, expected, camera=False, poses=expected_poses)
    placedb = sdk()
    if placedb:
        check_same_as_sdk(placedb.read_tum(folder, intrinsics=K), summary, server, "tum",
                          cameras=False)
        print("ok: TUM folder: the SDK's read_tum gives the same frames")
    os.remove(os.path.join(folder, "rgb", os.listdir(os.path.join(folder, "rgb"))[0]))
    gone = server.cli(["ingest", "tum", folder], expect=2)
    if "rgb.txt" not in gone.stderr or "does not exist" not in gone.stderr:
        fail("a frame rgb.txt names but the folder lacks must be named: " + gone.stderr)
    print("ok: TUM folder: timestamps, depth and interpolated poses")


def main():
    data = frames()
    with tempfile.TemporaryDirectory(prefix="placedb-recordings-") as root:
        server = Server(root)
        try:
            test_bags(server, root, data)
            test_bad_bags(server, root)
            test_tum(server, root, data)
        finally:
            server.stop()
    print("all recording ingest checks passed")


if __name__ == "__main__":
    main()
