"""Typed map settings (:class:`MapSettings`) and the API's enum names.

Enum values are named as in the CLI and the server's reports (proto/names.h): the lowercase value
name without the enum's prefix (``"keypoint_in_box"`` for ``FILTER_METHOD_KEYPOINT_IN_BOX``), or
the value's ``(name)`` option where the proto gives one (``"chi2"``, ``"dot"``, ``"direct"``).
Both spellings are accepted when parsing. The names come from the generated descriptors, so they
follow the proto.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, List, Optional, Sequence, Tuple

from google.protobuf.descriptor import EnumDescriptor

from placedb._pb import placedb_pb2 as pb
from placedb.errors import InvalidArgument


def _prefix(enum: EnumDescriptor) -> str:
    return enum.values[0].name[: -len("UNSPECIFIED")]


def _option_name(value) -> str:
    return value.GetOptions().Extensions[pb.name]


def enum_name(enum: EnumDescriptor, number: int) -> str:
    """The API name of an enum value (``""`` for UNSPECIFIED values without a ``(name)``)."""
    value = enum.values_by_number.get(number)
    if value is None:
        return str(number)
    if _option_name(value):
        return _option_name(value)
    if value.name.endswith("_UNSPECIFIED"):
        return ""
    return value.name[len(_prefix(enum)) :].lower()


def enum_value(enum: EnumDescriptor, text: str, path: str) -> int:
    """Parses an API enum name; :class:`InvalidArgument` naming ``path`` and the choices."""
    wanted = text.strip().lower()
    choices: List[str] = []
    for value in enum.values:
        if value.name.endswith("_UNSPECIFIED"):
            continue
        suffix = value.name[len(_prefix(enum)) :].lower()
        names = [n for n in (_option_name(value), suffix) if n]
        if wanted in names:
            return value.number
        choices.append(names[0])
    raise InvalidArgument(f"{path}: unknown value '{text}' (expected one of {', '.join(choices)})")


def _apply(settings: Any, message: Any, path: str) -> None:
    """Sets every field of ``settings`` that is not None on ``message`` (same field names): enum
    fields from their API names, (near, far) tuples into band messages."""
    for f in fields(settings):
        value = getattr(settings, f.name)
        if value is None:
            continue
        descriptor = message.DESCRIPTOR.fields_by_name[f.name]
        where = f"{path}.{f.name}"
        if descriptor.enum_type is not None:
            setattr(message, f.name, enum_value(descriptor.enum_type, value, where))
        elif descriptor.message_type is not None:
            try:
                near, far = value
            except (TypeError, ValueError):
                raise InvalidArgument(f"{where}: {value!r}, expected (near_m, far_m)") from None
            band = getattr(message, f.name)
            band.near_m, band.far_m = float(near), float(far)
        else:
            try:
                setattr(message, f.name, value)
            except (TypeError, ValueError) as e:
                raise InvalidArgument(f"{where}: {value!r} ({e})") from None


@dataclass
class DepthSettings:
    """Depth handling (docs/rgbd.md, ``placedb.v1.DepthSettings``). None = the server default."""

    #: Only an object's own depth layer is dynamic (True).
    refine_boxes: Optional[bool] = None
    #: Algorithm 1 on ingest streams with depth (True).
    stream_filter: Optional[bool] = None
    #: Metres per png16 unit (0.001).
    scale: Optional[float] = None
    min_depth_m: Optional[float] = None
    max_depth_m: Optional[float] = None
    #: Mean over all pixels, as the paper (False: over valid pixels).
    mean_all_pixels: Optional[bool] = None
    threshold_m: Optional[float] = None
    #: Deviating frames before removal starts (5).
    persistence: Optional[int] = None
    #: Frames of the static level (10).
    static_window: Optional[int] = None
    #: "fixed", "nearest_layer" or "appeared_layer".
    band_policy: Optional[str] = None
    #: (near_m, far_m) of the rise band (1.8, 4.5).
    rise_band: Optional[Tuple[float, float]] = None
    #: (near_m, far_m) of the fall band (0, 0.8).
    fall_band: Optional[Tuple[float, float]] = None
    remove_features_without_depth: Optional[bool] = None
    #: Range instead of depth (needs intrinsics on every frame).
    use_range: Optional[bool] = None
    #: Frames after which the static level is re-learnt (0 = never).
    rebaseline_after: Optional[int] = None


@dataclass
class LoopClosureSettings:
    """The Bayesian loop closure of ingest streams that ask for it (``ingest(loop_closure=True)``,
    ``placedb.v1.LoopClosureSettings``). None = the server default."""

    #: T_loop (0.12).
    loop_threshold: Optional[float] = None
    #: T_rehearsal (0.20; > 1 disables rehearsal).
    rehearsal_threshold: Optional[float] = None
    #: Places (30).
    short_term_memory: Optional[int] = None
    #: Places (0 = unbounded).
    max_working_memory: Optional[int] = None
    #: Per update (0 = none).
    time_budget_ms: Optional[float] = None
    min_candidates: Optional[int] = None
    #: A loop is kept only if it verifies geometrically (True).
    verify: Optional[bool] = None


@dataclass
class ShortTermSettings:
    """The short-term tier (``placedb.v1.ShortTermSettings``): recent places' dynamic words stay
    in memory for ``horizon_s``. None = the server default."""

    enabled: Optional[bool] = None
    horizon_s: Optional[float] = None
    max_places: Optional[int] = None
    weight: Optional[float] = None


@dataclass
class SiftSettings:
    """SIFT extraction on SIFT maps (``placedb.v1.SiftSettings``). None = the server default."""

    #: 1000 (0 = all).
    max_features: Optional[int] = None
    octave_layers: Optional[int] = None
    contrast_threshold: Optional[float] = None
    edge_threshold: Optional[float] = None
    sigma: Optional[float] = None


@dataclass
class ThumbnailSettings:
    """Per-place thumbnails (issue 20, ``placedb.v1.ThumbnailSettings``): a small JPEG of each
    place's frame, dynamic objects blurred, for ``get_place(..., thumbnail=True)`` and the
    console. None = the server default (off; 320 px; quality 75)."""

    enabled: Optional[bool] = None
    #: Longest side in pixels (0 = the server's default, 320).
    max_side: Optional[int] = None
    #: 1-100 (0 = the server's default, 75).
    jpeg_quality: Optional[int] = None


@dataclass
class MapSettings:
    """A map's configuration at :meth:`placedb.Client.create_map`. ``None`` = the server default.

    The common settings are fields here, with typed groups for depth, loop closure, the
    short-term tier and SIFT; anything else (ORB details, verification levels, ...) goes into
    ``config``, a ``placedb.v1.MapConfig`` these fields are laid over. The server fills in and
    reports the effective configuration (:attr:`MapInfo.config`).
    """

    #: A vocabulary name from the server's configuration ("" = "default").
    vocabulary: str = ""
    #: "orb" or "sift"; must agree with the vocabulary (None: the vocabulary's kind).
    feature_type: Optional[str] = None
    #: Features extracted per frame: orb.max_features, or sift.max_features when feature_type
    #: is "sift" (with a SIFT vocabulary but no feature_type, set config.sift instead).
    max_features: Optional[int] = None
    #: "l1", "l2", "chi2", "kl", "bhattacharyya" or "dot".
    scoring: Optional[str] = None
    #: Geometric verification: "disabled", "direct" or "exhaustive".
    verification: Optional[str] = None
    #: Inliers a verified match needs (>= 8).
    min_inliers: Optional[int] = None
    #: Dynamic-object filter: "none", "keypoint_in_box", "corner_distance", "exact_coverage".
    filter_method: Optional[str] = None
    #: A frame is a valid place iff its static descriptors exceed this.
    place_threshold: Optional[int] = None
    #: Box refinement without depth: "none", "shape" or "grabcut".
    box_refinement: Optional[str] = None
    #: COCO names of the dynamic classes (empty: the server's default list).
    dynamic_classes: Sequence[str] = field(default_factory=list)
    #: Boxes below this confidence are ignored.
    min_confidence: Optional[float] = None
    #: Where boxes come from: "agent", "server" or "both".
    box_source: Optional[str] = None
    #: Keep invalid observations as metadata.
    store_invalid: bool = False
    #: Depth handling and Algorithm 1.
    depth: Optional[DepthSettings] = None
    #: Loop closure of the streams that ask for it.
    loop_closure: Optional[LoopClosureSettings] = None
    #: The short-term tier of dynamic words.
    short_term: Optional[ShortTermSettings] = None
    #: SIFT extraction (SIFT maps).
    sift: Optional[SiftSettings] = None
    #: Per-place thumbnails (off by default).
    thumbnails: Optional[ThumbnailSettings] = None
    #: A query whose best match scores above this counts as one more observation of that place
    #: in its dynamic-object statistics (dynamics.count_query_hits_above; 0 = off, the default).
    count_query_hits_above: Optional[float] = None
    #: The base configuration the fields above are laid over.
    config: Optional[pb.MapConfig] = None

    def to_proto(self) -> pb.MapConfig:
        """The ``placedb.v1.MapConfig`` these settings describe."""
        config = pb.MapConfig()
        if self.config is not None:
            config.CopyFrom(self.config)
        if self.vocabulary:
            config.vocabulary = self.vocabulary
        if self.feature_type is not None:
            config.feature_type = enum_value(
                pb.FeatureType.DESCRIPTOR, self.feature_type, "config.feature_type"
            )
        if self.max_features is not None:
            sift = config.feature_type == pb.FEATURE_TYPE_SIFT
            (config.sift if sift else config.orb).max_features = self.max_features
        if self.scoring is not None:
            config.scoring = enum_value(pb.Scoring.DESCRIPTOR, self.scoring, "config.scoring")
        if self.verification is not None:
            config.verification.mode = enum_value(
                pb.VerificationMode.DESCRIPTOR, self.verification, "config.verification.mode"
            )
        if self.min_inliers is not None:
            config.verification.min_inliers = self.min_inliers
        if self.filter_method is not None:
            config.filter.method = enum_value(
                pb.FilterMethod.DESCRIPTOR, self.filter_method, "config.filter.method"
            )
        if self.place_threshold is not None:
            config.filter.place_threshold = self.place_threshold
        if self.box_refinement is not None:
            config.filter.box_refinement = enum_value(
                pb.BoxRefinement.DESCRIPTOR, self.box_refinement, "config.filter.box_refinement"
            )
        if self.dynamic_classes:
            del config.detection.classes[:]
            config.detection.classes.extend(self.dynamic_classes)
        if self.min_confidence is not None:
            config.detection.min_confidence = self.min_confidence
        if self.box_source is not None:
            config.detection.box_source = enum_value(
                pb.BoxSource.DESCRIPTOR, self.box_source, "config.detection.box_source"
            )
        if self.store_invalid:
            config.store_invalid = True
        if self.depth is not None:
            _apply(self.depth, config.depth, "config.depth")
        if self.loop_closure is not None:
            _apply(self.loop_closure, config.loop_closure, "config.loop_closure")
        if self.short_term is not None:
            _apply(self.short_term, config.filter.short_term, "config.filter.short_term")
        if self.sift is not None:
            _apply(self.sift, config.sift, "config.sift")
        if self.thumbnails is not None:
            _apply(self.thumbnails, config.thumbnails, "config.thumbnails")
        if self.count_query_hits_above is not None:
            try:
                config.dynamics.count_query_hits_above = self.count_query_hits_above
            except (TypeError, ValueError) as e:
                raise InvalidArgument(
                    f"config.dynamics.count_query_hits_above: {self.count_query_hits_above!r} ({e})"
                ) from None
        return config
