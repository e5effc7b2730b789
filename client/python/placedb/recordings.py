"""Recordings as frames: ROS 1 bags and TUM RGB-D folders, with their capture times and poses.

    import placedb
    with placedb.Client("127.0.0.1:50051") as client:
        run = placedb.read_bag("run.bag", "/camera/image_raw",
                               depth_topic="/camera/depth/image_raw",
                               camera_info_topic="/camera/camera_info")
        for result in client.ingest("lab", run, agent_id="robot-1"):
            print(result.index, result.stored, result.place_id)
        print(run.stats)

        for result in client.ingest("lab", placedb.read_tum("rgbd_dataset_freiburg1_xyz")):
            ...

Each frame's ``timestamp_ns`` is its capture time (a bag's header stamps, a TUM list's
timestamps), never the wall clock, so a replayed recording keeps its own hours in the map's
dynamics. Depth is paired with the nearest colour frame within ``max_offset`` seconds (a frame
without one is sent without depth and counted); TUM poses come from ``groundtruth.txt``.

ROS 1 bags are read with Debian's ``python3-rosbag`` (a venv made with
``--system-site-packages`` sees it). No Debian 12 package reads ROS 2 bags (rosbag2's SQLite
``.db3`` or MCAP): they are refused with :class:`placedb.FailedPrecondition` saying so.
"""

from __future__ import annotations

import bisect
import math
import os
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Deque, Iterator, List, Optional, Tuple, Union

import numpy as np

from placedb.errors import FailedPrecondition, InvalidArgument
from placedb.frames import Camera, Depth, Frame
from placedb.results import Pose

PathLike = Union[str, "os.PathLike[str]"]
Intrinsics = Tuple[float, float, float, float]

#: TUM RGB-D's depth PNGs: 5000 units per metre.
TUM_DEPTH_SCALE = 1.0 / 5000.0

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_ROS1_MAGIC = b"#ROSBAG V2.0\n"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"

_IMAGE = "sensor_msgs/Image"
_COMPRESSED = "sensor_msgs/CompressedImage"
_CAMERA_INFO = "sensor_msgs/CameraInfo"

# sensor_msgs/Image encodings: channels and sample type (REP 118: 16UC1 millimetres, 32FC1 m).
_COLOUR_ENCODINGS = {
    "rgb8": 3,
    "bgr8": 3,
    "rgba8": 4,
    "bgra8": 4,
    "mono8": 1,
    "8uc1": 1,
}
_DEPTH_ENCODINGS = {"16uc1": np.uint16, "mono16": np.uint16, "32fc1": np.float32}

# Colour frames held while waiting for the depth image that may pair with them.
_MAX_PENDING = 64
# Depth images held for colour frames still to come.
_MAX_DEPTHS = 256


@dataclass
class RecordingStats:
    """What one pass over a :class:`Recording` read."""

    #: Colour frames read (each one a :class:`placedb.Frame`).
    frames: int = 0
    #: Frames with a depth image within ``max_offset``.
    depth_paired: int = 0
    #: Frames sent without depth although the recording has depth: none within ``max_offset``.
    depth_missing: int = 0
    #: Frames with a pose (TUM: from groundtruth.txt).
    poses: int = 0
    #: Frames without a pose although the recording has poses (outside the ground truth's times).
    poses_missing: int = 0
    #: Bag frames whose header stamp was 0: the bag's receive time was used instead.
    receive_time_stamps: int = 0
    #: Capture times of the first and the last frame (Unix nanoseconds).
    first_ns: Optional[int] = None
    last_ns: Optional[int] = None

    def count(self, frame: Frame) -> None:
        self.frames += 1
        if self.first_ns is None:
            self.first_ns = frame.timestamp_ns
        self.last_ns = frame.timestamp_ns


class Recording:
    """A recording's colour frames (:class:`placedb.Frame`), read lazily in capture order.

    An iterable: pass it to :meth:`placedb.Client.ingest` (or iterate it yourself), as often as
    needed; each pass reads the recording again. The recording was checked when it was opened
    (format, topics, lists, files); a frame that cannot be read raises
    :class:`placedb.InvalidArgument` naming it. ``expected_frames``: the colour frames the
    recording holds. ``stats``: what the latest pass read (:class:`RecordingStats`).
    """

    def __init__(
        self,
        source: str,
        expected_frames: int,
        read: Callable[[RecordingStats], Iterator[Frame]],
    ) -> None:
        self.source = source
        self.expected_frames = expected_frames
        self.stats = RecordingStats()
        self._read = read

    def __iter__(self) -> Iterator[Frame]:
        self.stats = RecordingStats()
        return self._read(self.stats)

    def __len__(self) -> int:
        return self.expected_frames

    def __repr__(self) -> str:
        return f"Recording({self.source!r}, {self.expected_frames} frames)"


def _check_offset(max_offset: float) -> int:
    if not (isinstance(max_offset, (int, float)) and max_offset >= 0 and math.isfinite(max_offset)):
        raise InvalidArgument(f"max_offset: {max_offset!r}, expected seconds >= 0")
    return int(round(max_offset * 1e9))


def _check_intrinsics(intrinsics: Optional[Intrinsics], name: str) -> Optional[Intrinsics]:
    if intrinsics is None:
        return None
    try:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
    except (TypeError, ValueError):
        raise InvalidArgument(f"{name}: {intrinsics!r}, expected (fx, fy, cx, cy)") from None
    if not (fx > 0 and fy > 0):
        raise InvalidArgument(f"{name}: {intrinsics!r}, focal lengths must be > 0")
    return fx, fy, cx, cy


def _png16(data: bytes, what: str) -> bytes:
    """``data`` if it is a 16-bit grayscale PNG (what the server takes as depth)."""
    if not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise InvalidArgument(f"{what}: not a PNG (depth must be a 16-bit grayscale PNG)")
    bit_depth, colour_type = data[24], data[25]
    if bit_depth != 16 or colour_type != 0:
        raise InvalidArgument(
            f"{what}: a PNG of bit depth {bit_depth}, colour type {colour_type}; depth must be "
            "a 16-bit grayscale PNG"
        )
    return data


# ---- ROS 1 bags ---------------------------------------------------------------------------------


def _rosbag_module() -> Any:
    try:
        import rosbag  # Debian's python3-rosbag
    except ImportError as e:
        raise FailedPrecondition(
            f"reading ROS 1 bags needs Debian's python3-rosbag ({e}): apt-get install "
            "python3-rosbag, and in a venv create it with --system-site-packages so it is seen"
        ) from None
    return rosbag


def _ros2_refusal(path: PathLike, kind: str) -> FailedPrecondition:
    return FailedPrecondition(
        f"{os.fspath(path)}: a ROS 2 bag ({kind}). placedb reads ROS 1 bags (Debian's "
        "python3-rosbag); Debian 12 packages no reader of ROS 2 bags (rosbag2_py or mcap are "
        "missing). Convert it to a ROS 1 bag, or export its images to a TUM-style folder "
        "(rgb.txt, depth.txt) and use read_tum"
    )


def _check_bag_file(path: PathLike) -> None:
    """Refuses what is not a ROS 1 bag, saying what it is."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file() or any(p.glob("*.db3")) or any(p.glob("*.mcap")):
            raise _ros2_refusal(path, "a rosbag2 directory")
        raise InvalidArgument(f"{p}: a directory, not a ROS 1 bag file")
    try:
        with open(p, "rb") as f:
            head = f.read(16)
    except OSError as e:
        raise InvalidArgument(f"{p}: cannot read: {e.strerror}") from None
    if head.startswith(_MCAP_MAGIC):
        raise _ros2_refusal(path, "MCAP")
    if head.startswith(_SQLITE_MAGIC):
        raise _ros2_refusal(path, "rosbag2 SQLite .db3")
    if not head.startswith(_ROS1_MAGIC):
        raise InvalidArgument(f"{p}: not a ROS 1 bag (it does not start with '#ROSBAG V2.0')")


def _stamp_ns(message: Any, receive_time: Any, stats: RecordingStats) -> int:
    stamp = message.header.stamp.to_nsec()
    if stamp == 0:
        stats.receive_time_stamps += 1
        return int(receive_time.to_nsec())
    return int(stamp)


def _pixels(message: Any, channels: int, dtype: Any, what: str) -> np.ndarray:
    """A sensor_msgs/Image's pixels as H x W (x C) ``dtype``, rows unpadded, native order."""
    dtype = np.dtype(dtype)
    height, width, step = int(message.height), int(message.width), int(message.step)
    row = width * channels * dtype.itemsize
    data = message.data
    if isinstance(data, (list, tuple)):
        data = bytes(data)
    if width == 0 or height == 0:
        raise InvalidArgument(f"{what}: an empty image ({width} x {height})")
    if step < row or len(data) < step * (height - 1) + row:
        raise InvalidArgument(
            f"{what}: {len(data)} bytes with step {step} for {width} x {height} "
            f"{message.encoding} (rows need {row} bytes)"
        )
    raw = np.frombuffer(data, np.uint8, count=step * (height - 1) + row)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(height, row), strides=(step, 1))
    order = ">" if message.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(dtype.newbyteorder(order)).astype(dtype)
    return pixels.reshape(height, width, channels) if channels > 1 else pixels


def _colour_image(message: Any, kind: str, what: str) -> Union[np.ndarray, bytes]:
    """A colour frame: a gray / BGR array (Image) or the encoded bytes (CompressedImage)."""
    if kind == _COMPRESSED:
        data = bytes(message.data)
        if not (data.startswith(b"\xff\xd8") or data.startswith(_PNG_SIGNATURE)):
            raise InvalidArgument(
                f"{what}: CompressedImage format {message.format!r} is neither JPEG nor PNG"
            )
        return data
    encoding = message.encoding.lower()
    channels = _COLOUR_ENCODINGS.get(encoding)
    if channels is None:
        raise InvalidArgument(
            f"{what}: encoding {message.encoding!r}; colour frames may be rgb8, bgr8, rgba8, "
            "bgra8, mono8 (or 8UC1), or a sensor_msgs/CompressedImage (JPEG / PNG)"
        )
    pixels = _pixels(message, channels, np.uint8, what)
    if encoding in ("rgb8", "rgba8"):
        return np.ascontiguousarray(pixels[:, :, 2::-1])  # RGB(A) -> BGR
    if encoding == "bgra8":
        return np.ascontiguousarray(pixels[:, :, :3])
    return pixels


def _depth_image(message: Any, kind: str, what: str) -> Tuple[Union[np.ndarray, bytes], float]:
    """A depth image and its metres per unit (16-bit: millimetres, 32FC1: metres)."""
    if kind == _COMPRESSED:
        data = bytes(message.data)
        # image_transport's compressedDepth: a 12-byte header (format, depth quantisation), then a
        # PNG; for 16UC1 that PNG holds the millimetres themselves.
        depth_format = message.format.lower().startswith(("16uc1", "mono16"))
        if data[12:20] == _PNG_SIGNATURE and depth_format:
            return _png16(data[12:], what), 0.001
        if data.startswith(_PNG_SIGNATURE):
            return _png16(data, what), 0.001
        raise InvalidArgument(
            f"{what}: CompressedImage format {message.format!r}: depth may be 16UC1 PNG "
            "(compressedDepth or png); 32FC1 compressedDepth (quantised inverse depth) is not read"
        )
    encoding = message.encoding.lower()
    dtype = _DEPTH_ENCODINGS.get(encoding)
    if dtype is None:
        raise InvalidArgument(
            f"{what}: encoding {message.encoding!r}; depth images may be 16UC1 or mono16 "
            "(millimetres) or 32FC1 (metres)"
        )
    return _pixels(message, 1, dtype, what), (0.001 if dtype == np.uint16 else 1.0)


def read_bag(
    path: PathLike,
    topic: str,
    depth_topic: Optional[str] = None,
    camera_info_topic: Optional[str] = None,
    max_offset: float = 0.02,
) -> Recording:
    """The colour frames of ``topic`` in a ROS 1 bag, with their header stamps as capture times.

    ``topic``: ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or
    ``sensor_msgs/CompressedImage`` (JPEG, PNG). ``depth_topic``: ``sensor_msgs/Image`` 16UC1 /
    mono16 (millimetres) or 32FC1 (metres), or a 16-bit PNG ``CompressedImage`` (also
    image_transport's compressedDepth), registered to the colour image; each frame gets the depth
    image whose stamp is nearest its own, within ``max_offset`` seconds. ``camera_info_topic``:
    ``sensor_msgs/CameraInfo`` of the colour camera; its K gives the depth's intrinsics (the
    latest one read). A header stamp of 0 is replaced by the bag's receive time (counted in
    :attr:`RecordingStats.receive_time_stamps`).

    Raises :class:`placedb.FailedPrecondition` without python3-rosbag or for a ROS 2 bag,
    :class:`placedb.InvalidArgument` for a file that is not a bag, a topic the bag lacks (naming
    the ones it has) or of another type.
    """
    offset_ns = _check_offset(max_offset)
    _check_bag_file(path)
    rosbag = _rosbag_module()
    path = os.fspath(path)
    try:
        with rosbag.Bag(path) as bag:
            topics = bag.get_type_and_topic_info().topics
    except Exception as e:  # rosbag raises its own ROSBagException and others
        raise InvalidArgument(f"{path}: cannot read the bag: {e}") from None

    def kind_of(role: str, name: str, allowed: Tuple[str, ...]) -> str:
        if name not in topics:
            have = ", ".join(
                f"{t} ({info.msg_type}, {info.message_count})" for t, info in sorted(topics.items())
            )
            raise InvalidArgument(f"{role} {name}: not in {path}; its topics: {have or 'none'}")
        kind = topics[name].msg_type
        if kind not in allowed:
            raise InvalidArgument(f"{role} {name}: {kind}, expected {' or '.join(allowed)}")
        return kind

    colour_kind = kind_of("topic", topic, (_IMAGE, _COMPRESSED))
    depth_kind = kind_of("depth_topic", depth_topic, (_IMAGE, _COMPRESSED)) if depth_topic else ""
    if camera_info_topic:
        kind_of("camera_info_topic", camera_info_topic, (_CAMERA_INFO,))
    if depth_topic == topic:
        raise InvalidArgument(f"depth_topic {depth_topic}: the colour topic itself")
    expected = topics[topic].message_count

    def frames(stats: RecordingStats) -> Iterator[Frame]:
        colours: Deque[Tuple[int, Any, int]] = deque()  # (stamp, message, index in the topic)
        depths: Deque[Tuple[int, Any]] = deque()
        intrinsics: List[Optional[Intrinsics]] = [None]
        camera: List[Optional[Camera]] = [None]  # the whole CameraInfo: relative poses
        count = [0]

        def ready(final: bool) -> Iterator[Frame]:
            while colours:
                stamp = colours[0][0]
                # A later depth image has a later stamp: once one lies beyond stamp + offset,
                # no better one for this frame can come.
                waiting = depth_topic and not final and len(colours) <= _MAX_PENDING
                if waiting and not (depths and depths[-1][0] > stamp + offset_ns):
                    return
                _, message, index = colours.popleft()
                what = f"{path}: {topic} message {index}"
                frame = Frame(
                    image=_colour_image(message, colour_kind, what),
                    timestamp_ns=stamp,
                    camera=camera[0],
                )
                if depth_topic:
                    nearest = min(depths, key=lambda d: abs(d[0] - stamp), default=None)
                    if nearest is not None and abs(nearest[0] - stamp) <= offset_ns:
                        image, scale = _depth_image(
                            nearest[1], depth_kind, f"{path}: {depth_topic} at {nearest[0]} ns"
                        )
                        frame.depth = Depth(image=image, scale=scale, intrinsics=intrinsics[0])
                        stats.depth_paired += 1
                    else:
                        stats.depth_missing += 1
                    while depths and depths[0][0] < stamp - offset_ns:
                        depths.popleft()
                stats.count(frame)
                yield frame

        wanted = [t for t in (topic, depth_topic, camera_info_topic) if t]
        with rosbag.Bag(path) as bag:
            for name, message, receive_time in bag.read_messages(topics=wanted):
                if name == camera_info_topic:
                    k = message.K
                    if k[0] > 0 and k[4] > 0:
                        intrinsics[0] = (float(k[0]), float(k[4]), float(k[2]), float(k[5]))
                        try:
                            camera[0] = Camera.from_camera_info(message)
                        except InvalidArgument:
                            camera[0] = None  # frames still go in, without relative poses
                    continue
                stamp = _stamp_ns(message, receive_time, stats)
                if name == topic:
                    colours.append((stamp, message, count[0]))
                    count[0] += 1
                else:
                    depths.append((stamp, message))
                    if len(depths) > _MAX_DEPTHS:
                        depths.popleft()
                yield from ready(final=False)
        yield from ready(final=True)

    return Recording(f"{path} {topic}", expected, frames)


# ---- TUM RGB-D folders --------------------------------------------------------------------------


def seconds_to_ns(text: str) -> int:
    """Exact Unix nanoseconds of a decimal seconds string such as ``"1305031102.175304"``."""
    whole, _, fraction = text.strip().partition(".")
    negative = whole.startswith("-")
    digits = whole.lstrip("+-")
    if not digits.isdigit() or (fraction and not fraction.isdigit()) or len(fraction) > 9:
        raise ValueError(f"{text!r} is not a timestamp in seconds")
    ns = int(digits) * 1_000_000_000 + int(fraction.ljust(9, "0") or 0)
    return -ns if negative else ns


def _read_list(path: Path, columns: int) -> List[Tuple[int, List[str]]]:
    """A TUM list's rows (timestamp, the other columns), sorted by time; '#' lines skipped."""
    try:
        text = path.read_text()
    except OSError as e:
        raise InvalidArgument(f"{path}: cannot read: {e.strerror}") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < columns + 1:
            raise InvalidArgument(
                f"{path}:{number}: {len(fields)} columns, expected a timestamp and {columns} more"
            )
        try:
            rows.append((seconds_to_ns(fields[0]), fields[1 : columns + 1]))
        except ValueError as e:
            raise InvalidArgument(f"{path}:{number}: {e}") from None
    rows.sort(key=lambda r: r[0])
    return rows


def _nearest(times: List[int], t: int, offset_ns: int) -> Optional[int]:
    """Index of the time nearest ``t`` in sorted ``times``, if within ``offset_ns``."""
    i = bisect.bisect_left(times, t)
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(times) and abs(times[j] - t) <= offset_ns:
            if best is None or abs(times[j] - t) < abs(times[best] - t):
                best = j
    return best


def interpolate_pose(
    times: List[int], poses: List[Pose], t: int, offset_ns: int, max_gap_ns: int
) -> Optional[Pose]:
    """The pose at ``t`` from sorted samples: between two samples at most ``max_gap_ns`` apart,
    position interpolated linearly and orientation by slerp; else the nearest sample within
    ``offset_ns``; else None."""
    i = bisect.bisect_left(times, t)
    if i < len(times) and times[i] == t:
        return poses[i]
    if 0 < i < len(times) and times[i] - times[i - 1] <= max_gap_ns:
        a, b = poses[i - 1], poses[i]
        u = (t - times[i - 1]) / (times[i] - times[i - 1])
        qa = np.array([a.qx, a.qy, a.qz, a.qw], np.float64)
        qb = np.array([b.qx, b.qy, b.qz, b.qw], np.float64)
        qa /= np.linalg.norm(qa) or 1.0
        qb /= np.linalg.norm(qb) or 1.0
        dot = float(np.dot(qa, qb))
        if dot < 0:  # the shorter way round
            qb, dot = -qb, -dot
        if dot > 0.9995:
            q = qa + u * (qb - qa)
        else:
            angle = math.acos(dot)
            q = (math.sin((1 - u) * angle) * qa + math.sin(u * angle) * qb) / math.sin(angle)
        q /= np.linalg.norm(q)
        return Pose(
            x=a.x + u * (b.x - a.x),
            y=a.y + u * (b.y - a.y),
            z=a.z + u * (b.z - a.z),
            qx=float(q[0]),
            qy=float(q[1]),
            qz=float(q[2]),
            qw=float(q[3]),
        )
    j = _nearest(times, t, offset_ns)
    return poses[j] if j is not None else None


def read_tum(
    folder: PathLike,
    depth: Optional[bool] = None,
    poses: Optional[bool] = None,
    max_offset: float = 0.02,
    max_pose_gap: float = 0.1,
    depth_scale: float = TUM_DEPTH_SCALE,
    intrinsics: Optional[Intrinsics] = None,
) -> Recording:
    """The colour frames of a TUM RGB-D folder: ``rgb.txt`` (``timestamp file`` lines) with its
    timestamps as capture times, ``depth.txt`` and ``groundtruth.txt`` (``timestamp tx ty tz qx
    qy qz qw``) when present.

    ``depth`` / ``poses``: None = use depth.txt / groundtruth.txt when the folder has them, True
    = required, False = ignored. A frame gets the depth image nearest in time within
    ``max_offset`` seconds (16-bit PNGs, ``depth_scale`` metres per unit: TUM's 1/5000), and its
    pose interpolated between ground-truth samples at most ``max_pose_gap`` seconds apart (else
    the nearest within ``max_offset``). ``intrinsics``: (fx, fy, cx, cy) of the colour camera,
    sent with the depth (TUM's fr1, fr2 and fr3 cameras differ; None: not sent).

    Raises :class:`placedb.InvalidArgument` naming the file and line for a missing list or file,
    a malformed line or a depth image that is not a 16-bit PNG.
    """
    root = Path(folder)
    offset_ns = _check_offset(max_offset)
    gap_ns = _check_offset(max_pose_gap)
    intrinsics = _check_intrinsics(intrinsics, "intrinsics")
    if not (depth_scale > 0 and math.isfinite(depth_scale)):
        raise InvalidArgument(f"depth_scale: {depth_scale!r}, expected metres per unit > 0")
    if not (root / "rgb.txt").is_file():
        raise InvalidArgument(
            f"{root}: no rgb.txt (a TUM RGB-D folder lists its colour frames there)"
        )
    colours = _read_list(root / "rgb.txt", 1)
    if not colours:
        raise InvalidArgument(f"{root / 'rgb.txt'}: lists no frames")

    def optional_list(
        name: str, wanted: Optional[bool], columns: int
    ) -> List[Tuple[int, List[str]]]:
        present = (root / name).is_file()
        if wanted and not present:
            raise InvalidArgument(f"{root}: no {name}")
        return _read_list(root / name, columns) if present and wanted is not False else []

    depth_rows = optional_list("depth.txt", depth, 1)
    pose_rows = optional_list("groundtruth.txt", poses, 7)
    depth_times = [t for t, _ in depth_rows]
    pose_times = [t for t, _ in pose_rows]
    pose_values = []
    for t, values in pose_rows:
        try:
            pose_values.append(Pose(*(float(v) for v in values)))
        except ValueError:
            raise InvalidArgument(
                f"{root / 'groundtruth.txt'}: {values!r} at {t} ns is not tx ty tz qx qy qz qw"
            ) from None

    # Every file a frame will read must exist before anything is sent.
    plan: List[Tuple[int, Path, Optional[Path]]] = []
    for t, (name,) in colours:
        image = root / name
        if not image.is_file():
            raise InvalidArgument(f"{root / 'rgb.txt'}: {name} (at {t} ns) does not exist")
        paired = None
        j = _nearest(depth_times, t, offset_ns)
        if j is not None:
            paired = root / depth_rows[j][1][0]
            if not paired.is_file():
                raise InvalidArgument(
                    f"{root / 'depth.txt'}: {depth_rows[j][1][0]} does not exist"
                )
        plan.append((t, image, paired))

    def frames(stats: RecordingStats) -> Iterator[Frame]:
        for t, image, paired in plan:
            frame = Frame(image=image, timestamp_ns=t)
            if paired is not None:
                try:
                    data = paired.read_bytes()
                except OSError as e:
                    raise InvalidArgument(f"{paired}: cannot read: {e.strerror}") from None
                frame.depth = Depth(
                    image=_png16(data, str(paired)), scale=depth_scale, intrinsics=intrinsics
                )
                stats.depth_paired += 1
            elif depth_rows:
                stats.depth_missing += 1
            if pose_rows:
                frame.pose = interpolate_pose(pose_times, pose_values, t, offset_ns, gap_ns)
                if frame.pose is not None:
                    stats.poses += 1
                else:
                    stats.poses_missing += 1
            stats.count(frame)
            yield frame

    return Recording(str(root), len(plan), frames)


__all__ = [
    "Recording",
    "RecordingStats",
    "TUM_DEPTH_SCALE",
    "interpolate_pose",
    "read_bag",
    "read_tum",
    "seconds_to_ns",
]
