"""Frames: what :meth:`placedb.Client.ingest` and :meth:`placedb.Client.query` take.

A frame is one of:

* a numpy image as OpenCV gives it: ``uint8`` H x W (gray) or H x W x 3 (BGR), sent uncompressed;
* encoded bytes (a JPEG or PNG file's contents), sent as they are;
* a file path (``str`` or ``os.PathLike``) to a JPEG or PNG, read and sent as bytes;
* a :class:`Frame`, which holds one of the above or precomputed keypoints + descriptors (e.g.
  from ``cv2.ORB_create().detectAndCompute``), plus the optional timestamp, pose, boxes, mask and
  depth.

Input the server would refuse for its form (a wrong dtype or shape, descriptors that do not
match the keypoints) raises :class:`placedb.InvalidArgument` naming the field before anything is
sent; the server checks the rest (sizes, limits, keypoints inside the image).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from placedb._pb import placedb_pb2 as pb
from placedb.errors import InvalidArgument
from placedb.png import encode_gray_png
from placedb.results import Pose

#: A numpy image, encoded image bytes or an image file's path.
ImageLike = Union[np.ndarray, bytes, bytearray, memoryview, str, "os.PathLike[str]"]


@dataclass
class Box:
    """A dynamic object the agent detected: a COCO class (id 0-79 or name such as ``"person"``),
    its confidence in [0, 1] and its rect (x, y, width, height) in full-resolution pixels."""

    label: Union[int, str]
    confidence: float
    rect: Tuple[float, float, float, float]


@dataclass
class Depth:
    """A depth image registered to the colour image (same aspect ratio; it may be smaller).

    ``image``: ``uint16`` H x W (units of ``scale`` metres, by default millimetres), ``float32``
    H x W (by default metres), or a 16-bit PNG's bytes. Invalid pixels are 0 (or NaN).
    ``scale``: metres per unit, 0 = the map's default. ``intrinsics``: (fx, fy, cx, cy) of the
    colour image in pixels, needed when the map measures range.
    """

    image: Union[np.ndarray, bytes]
    scale: float = 0.0
    intrinsics: Optional[Tuple[float, float, float, float]] = None


@dataclass
class Camera:
    """The camera that took a frame: verified matches then carry their relative pose
    (:attr:`placedb.Match.relative_pose`), and stored places keep it (with each stored
    keypoint's depth when the frame has depth).

    The fields are ROS ``sensor_msgs/CameraInfo``'s: ``width`` x ``height`` the image the
    intrinsics refer to (both 0 = the frame's size), focal lengths and principal point in
    pixels, ``distortion_model`` ``""``/``"none"``, ``"plumb_bob"`` (k1 k2 p1 p2 [k3]) or
    ``"equidistant"`` (k1 k2 k3 k4) and its coefficients.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 0
    height: int = 0
    distortion_model: str = ""
    distortion: Sequence[float] = ()

    @staticmethod
    def from_camera_info(message: Any) -> "Camera":
        """From a ROS ``sensor_msgs/CameraInfo`` message (K, D, distortion_model, size).

        ``rational_polynomial`` whose k4-k6 are 0 is ``plumb_bob``; any other model the server
        does not know raises :class:`InvalidArgument` naming it.
        """
        k = message.K
        model = message.distortion_model or ""
        coefficients = [float(v) for v in message.D]
        if model == "rational_polynomial" and not any(coefficients[5:]):
            model, coefficients = "plumb_bob", coefficients[:5]
        if model in ("plumb_bob", "equidistant") and not any(coefficients):
            model, coefficients = "", []
        if model not in ("", "none", "plumb_bob", "equidistant"):
            raise InvalidArgument(
                f"CameraInfo distortion_model {model!r}: placedb takes plumb_bob or equidistant"
            )
        return Camera(
            fx=float(k[0]),
            fy=float(k[4]),
            cx=float(k[2]),
            cy=float(k[5]),
            width=int(message.width),
            height=int(message.height),
            distortion_model=model,
            distortion=coefficients,
        )

    def to_proto(self, target: pb.Camera) -> None:
        target.width, target.height = int(self.width), int(self.height)
        target.fx, target.fy = float(self.fx), float(self.fy)
        target.cx, target.cy = float(self.cx), float(self.cy)
        target.distortion_model = self.distortion_model
        target.distortion[:] = [float(v) for v in self.distortion]


@dataclass
class MatchOptions:
    """What an ingested frame's result reports about the map's existing places.

    ``top_k``: at most this many matches (0 = the server's 10). ``verify``: keep only candidates
    that pass geometric verification. ``exclude_same_agent``: skip places stored by the frame's
    own agent. ``correspondences``: each verified match's inliers; in an ingest stream their
    query indices are those of the frame's own stored place (``get_place(include_features=True)``).
    """

    top_k: int = 10
    verify: bool = False
    exclude_same_agent: bool = False
    #: Each verified match's inlier correspondences (:attr:`placedb.Match.correspondences`).
    correspondences: bool = False

    def to_proto(self, path: str = "matches") -> pb.MatchOptions:
        """The ``placedb.v1.MatchOptions``; :class:`placedb.InvalidArgument` for a negative
        ``top_k``."""
        if self.top_k < 0:
            raise InvalidArgument(f"{path}.top_k: {self.top_k} is negative")
        return pb.MatchOptions(
            top_k=self.top_k,
            verified_only=self.verify,
            exclude_same_agent=self.exclude_same_agent,
            include_correspondences=self.correspondences,
        )


@dataclass
class Frame:
    """One observation: an image, or keypoints + descriptors, and optional metadata.

    With ``keypoints`` (``cv2.KeyPoint`` objects, or an N x 6 array of x, y, size, angle,
    response, octave) and ``descriptors`` (N x 32 ``uint8`` for ORB maps, N x 128 ``float32``
    for SIFT maps), the image size comes from ``image_size`` (width, height) or from ``image``
    when that is a numpy array; the image itself is then not sent.
    """

    image: Optional[ImageLike] = None
    keypoints: Optional[Any] = None
    descriptors: Optional[np.ndarray] = None
    #: (width, height) of the image the keypoints were found in.
    image_size: Optional[Tuple[int, int]] = None
    #: Unix nanoseconds (stored as metadata).
    timestamp_ns: Optional[int] = None
    #: The agent's frame number (default: the frame's position in the ingest call).
    sequence: Optional[int] = None
    #: A :class:`placedb.Pose` or (x, y, z, qx, qy, qz, qw).
    pose: Optional[Union[Pose, Sequence[float]]] = None
    boxes: Sequence[Union[Box, Tuple[Union[int, str], float, Sequence[float]]]] = field(
        default_factory=list
    )
    #: Dynamic-object mask the size of the image: H x W (non-zero or True = dynamic), or a PNG.
    mask: Optional[Union[np.ndarray, bytes]] = None
    #: A :class:`Depth`, or a depth array / 16-bit PNG with the default scale.
    depth: Optional[Union[Depth, np.ndarray, bytes]] = None
    #: Overrides the ingest call's agent_id for this frame.
    agent_id: Optional[str] = None
    #: The frame's :class:`Camera` (overrides the ingest call's ``camera``).
    camera: Optional[Camera] = None
    #: Ingest only: this frame's result carries its matches against the map as it was before
    #: the frame, with these options (overrides the ingest call's ``top_k``, ``verify``, ...).
    matches: Optional[MatchOptions] = None


def as_frame(item: Union[Frame, ImageLike]) -> Frame:
    """A :class:`Frame` for anything a frame may be given as."""
    return item if isinstance(item, Frame) else Frame(image=item)


def _raw_image(image: np.ndarray, path: str) -> pb.RawImage:
    if image.dtype != np.uint8:
        raise InvalidArgument(
            f"{path}: dtype {image.dtype}, expected uint8 (8-bit gray or BGR as OpenCV gives them)"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        pixel_format = pb.PIXEL_FORMAT_GRAY8
    elif image.ndim == 3 and image.shape[2] == 3:
        pixel_format = pb.PIXEL_FORMAT_BGR8
    else:
        raise InvalidArgument(
            f"{path}: shape {tuple(image.shape)}, expected H x W (gray) or H x W x 3 (BGR)"
        )
    height, width = image.shape[:2]
    if width == 0 or height == 0:
        raise InvalidArgument(f"{path}: empty image {tuple(image.shape)}")
    return pb.RawImage(
        width=width,
        height=height,
        format=pixel_format,
        data=np.ascontiguousarray(image).tobytes(),
    )


def _read_file(file: Union[str, "os.PathLike[str]"], path: str) -> bytes:
    try:
        with open(file, "rb") as f:
            return f.read()
    except OSError as e:
        raise InvalidArgument(f"{path}: cannot read {os.fspath(file)}: {e.strerror}") from None


def _keypoints(keypoints: Any, sift: bool, path: str) -> list:
    """``placedb.v1.Keypoint`` messages from cv2.KeyPoint objects or an N x 6 array."""
    if isinstance(keypoints, np.ndarray):
        if keypoints.ndim != 2 or keypoints.shape[1] != 6:
            raise InvalidArgument(
                f"{path}: shape {tuple(keypoints.shape)}, expected N x 6 "
                "(x, y, size, angle, response, octave)"
            )
        return [
            pb.Keypoint(x=r[0], y=r[1], size=r[2], angle=r[3], response=r[4], octave=int(r[5]))
            for r in keypoints.astype(np.float64)
        ]
    out = []
    for i, k in enumerate(keypoints):
        try:
            x, y = k.pt
            octave = int(k.octave)
        except (AttributeError, TypeError, ValueError):
            raise InvalidArgument(
                f"{path}[{i}]: not a keypoint (expected cv2.KeyPoint or an N x 6 array)"
            ) from None
        if sift:
            # OpenCV's SIFT packs octave | layer << 8 | ...; the API wants the signed octave + 1.
            octave = (octave & 0xFF) - 256 if (octave & 0xFF) >= 128 else (octave & 0xFF)
            octave += 1
        out.append(
            pb.Keypoint(x=x, y=y, size=k.size, angle=k.angle, response=k.response, octave=octave)
        )
    return out


def _features(frame: Frame, observation: pb.Observation, path: str) -> None:
    descriptors = frame.descriptors
    if descriptors is None or frame.keypoints is None:
        raise InvalidArgument(
            f"{path}: keypoints and descriptors go together (OpenCV's detectAndCompute returns "
            "None descriptors when it finds no keypoints)"
        )
    descriptors = np.asarray(descriptors)
    if descriptors.dtype == np.uint8 and descriptors.ndim == 2 and descriptors.shape[1] == 32:
        sift = False
        target, name = observation.features, "features"
    elif descriptors.dtype == np.float32 and descriptors.ndim == 2 and descriptors.shape[1] == 128:
        sift = True
        target, name = observation.sift_features, "sift_features"
    else:
        raise InvalidArgument(
            f"{path}.descriptors: {descriptors.dtype} {tuple(descriptors.shape)}, expected "
            "N x 32 uint8 (ORB) or N x 128 float32 (SIFT)"
        )
    keypoints = _keypoints(frame.keypoints, sift, f"{path}.{name}.keypoints")
    if len(keypoints) != descriptors.shape[0]:
        raise InvalidArgument(
            f"{path}.{name}.descriptors: {descriptors.shape[0]} rows for {len(keypoints)} keypoints"
        )
    size = frame.image_size
    if size is None and isinstance(frame.image, np.ndarray) and frame.image.ndim >= 2:
        size = (frame.image.shape[1], frame.image.shape[0])
    if size is None:
        raise InvalidArgument(
            f"{path}.{name}.image_width: unknown; give image_size or the image array"
        )
    target.image_width, target.image_height = int(size[0]), int(size[1])
    target.keypoints.extend(keypoints)
    target.descriptors = np.ascontiguousarray(
        descriptors, dtype="<f4" if sift else np.uint8
    ).tobytes()


def _mask(mask: Union[np.ndarray, bytes], path: str) -> bytes:
    if isinstance(mask, (bytes, bytearray, memoryview)):
        return bytes(mask)
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype not in (np.uint8, np.bool_):
        raise InvalidArgument(
            f"{path}: {mask.dtype} {tuple(mask.shape)}, expected H x W uint8 or bool"
        )
    return encode_gray_png(mask.astype(np.uint8) * 255 if mask.dtype == np.bool_ else mask)


def _depth(depth: Union[Depth, np.ndarray, bytes], target: pb.DepthImage, path: str) -> None:
    if not isinstance(depth, Depth):
        depth = Depth(image=depth)
    image = depth.image
    if isinstance(image, (bytes, bytearray, memoryview)):
        target.png16 = bytes(image)
    else:
        image = np.asarray(image)
        if image.ndim != 2 or image.dtype not in (np.uint16, np.float32):
            raise InvalidArgument(
                f"{path}: {image.dtype} {tuple(image.shape)}, expected H x W uint16 or float32"
            )
        if image.dtype == np.uint16:
            target.png16 = encode_gray_png(image)
        else:
            target.raw_float32.width = image.shape[1]
            target.raw_float32.height = image.shape[0]
            target.raw_float32.data = np.ascontiguousarray(image, dtype="<f4").tobytes()
    target.scale = depth.scale
    if depth.intrinsics is not None:
        fx, fy, cx, cy = depth.intrinsics
        target.intrinsics.fx, target.intrinsics.fy = fx, fy
        target.intrinsics.cx, target.intrinsics.cy = cx, cy


def to_observation(
    item: Union[Frame, ImageLike], agent_id: str, sequence: int, path: str = "observation"
) -> pb.Observation:
    """The ``placedb.v1.Observation`` for a frame (``sequence``: used when the frame has none)."""
    frame = as_frame(item)
    observation = pb.Observation(
        agent_id=frame.agent_id if frame.agent_id is not None else agent_id,
        sequence=frame.sequence if frame.sequence is not None else sequence,
    )
    if frame.timestamp_ns is not None:
        observation.timestamp_ns = int(frame.timestamp_ns)
    if frame.pose is not None:
        pose = frame.pose if isinstance(frame.pose, Pose) else Pose(*frame.pose)
        observation.pose.CopyFrom(pose.to_proto())

    image = frame.image
    if frame.keypoints is not None or frame.descriptors is not None:
        _features(frame, observation, path)
    elif image is None:
        raise InvalidArgument(f"{path}: a frame needs an image or keypoints + descriptors")
    elif isinstance(image, np.ndarray):
        observation.raw_image.CopyFrom(_raw_image(image, f"{path}.raw_image"))
    elif isinstance(image, (bytes, bytearray, memoryview)):
        observation.encoded_image.data = bytes(image)
    elif isinstance(image, (str, os.PathLike)):
        observation.encoded_image.data = _read_file(image, f"{path}.encoded_image")
    else:
        raise InvalidArgument(
            f"{path}: a {type(image).__name__} is not a frame (expected a numpy image, encoded "
            "bytes, a file path or a placedb.Frame)"
        )

    for i, box in enumerate(frame.boxes):
        if not isinstance(box, Box):
            box = Box(*box)
        message = observation.boxes.add(confidence=box.confidence)
        if isinstance(box.label, str):
            message.class_name = box.label
        else:
            message.class_id = int(box.label)
        if len(box.rect) != 4:
            raise InvalidArgument(f"{path}.boxes[{i}].rect: expected (x, y, width, height)")
        r = message.rect
        r.x, r.y, r.width, r.height = (float(v) for v in box.rect)
    if frame.mask is not None:
        observation.dynamic_mask_png = _mask(frame.mask, f"{path}.dynamic_mask_png")
    if frame.depth is not None:
        _depth(frame.depth, observation.depth, f"{path}.depth")
    if frame.camera is not None:
        frame.camera.to_proto(observation.camera)
    if frame.matches is not None:
        observation.matches.CopyFrom(frame.matches.to_proto(f"{path}.matches"))
    return observation
