"""The typed spec each stage task receives as its ``config`` parameter.

A run's settings (``flows._settings.RunSettings``) are resolved once from the catalog; ``flows._settings.stage_specs``
cuts them into one frozen dataclass per stage, defined here. A task reads its spec's attributes and never parses a
mapping of its own: :func:`as_spec` accepts the spec itself or its mapping form (a deployment parameter, a test's
dict) and rejects an unknown or missing key with a ``ConfigError`` naming it. A spec's ``to_mapping`` form is what
the task's cache key hashes (``tasks._cache.stage_cache_key``), so a changed setting recomputes exactly the stages
whose spec holds it.

Stages whose spec is one config of their own module take that config directly: ``features``
(``predictor.features.FeatureConfig``), ``filter`` (``pseudo_labels.PseudoLabelFilterConfig``), ``collection`` /
``test`` (``predictor.collection.CollectionConfig``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from bat3r_core.cameras import PinholeCamera
from bat3r_core.config_utils import ConfigError, from_mapping
from bat3r_core.fitting.augment import AugmentConfig
from bat3r_core.fitting.config import FittingConfig
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.features import FeatureConfig
from bat3r_core.poses import RandomPoseConfig
from bat3r_core.predictor.mirror import CanonicalMirror
from bat3r_core.render.config import RenderConfig, SceneAssets
from bat3r_core.viewpoints import CameraPriorConfig

__all__ = ["as_spec", "SampledPlanSpec", "RenderSpec", "GeneratedCollectionSpec", "TrainSpec", "InferSpec",
           "CropCamera", "FitSpec", "PlanViewsSpec", "TruthSpec", "EvaluateSpec", "CollectionEvaluationSpec",
           "RawImagesSpec"]

S = TypeVar("S")


def as_spec(cls: type[S], value: Any, name: str) -> S:
    """``value`` as a ``cls``: the spec itself, or built strictly from its mapping form (``config_utils.from_mapping``;
    an error names ``name`` and the key). Anything else is a ``ConfigError`` naming ``name`` and the expected spec."""
    if isinstance(value, cls):
        return value
    if isinstance(value, dict) or value is None:
        return from_mapping(cls, value, name)
    raise ConfigError(f"{name}: expected a {cls.__name__} (or its mapping), got {type(value).__name__}")


_BODY_FRAME_KEYS = ("origin", "forward", "horizontal")


def _check_body_frame(body_frame: dict[str, Any], name: str) -> None:
    missing = [k for k in _BODY_FRAME_KEYS if k not in body_frame]
    if missing:
        raise ConfigError(f"{name}.body_frame: missing key(s) {missing}; expected {list(_BODY_FRAME_KEYS)} "
                          "(joint names: the mid-spine joint, (tail side, head side), (left, right))")


@dataclass(frozen=True)
class SampledPlanSpec:
    """``plan`` (iteration 0): render jobs sampled around the rest-pose rig (``datasets.canonical_jobs``) or, for
    the random-poses baseline, of random poses (``datasets.random_pose_jobs``).

    Attributes:
        kind: ``canonical`` or ``random_pose``. n: jobs. seed: their seed. resolution: image side, pixels.
        shard_size: jobs per render shard. body_frame: the catalog's body-frame joints
        (``{origin, forward, horizontal}``). prior: the category's camera prior. num_textures / num_envmaps: ids
        are drawn from ``[0, num)`` (0 environment maps: the procedural sky). random_poses: the random-pose
        sampler's settings (``random_pose`` only).
    """

    kind: Literal["canonical", "random_pose"]
    n: int
    seed: int
    resolution: int
    shard_size: int
    body_frame: dict[str, Any]
    prior: CameraPriorConfig = field(default_factory=CameraPriorConfig)
    num_textures: int = 1
    num_envmaps: int = 0
    random_poses: RandomPoseConfig = field(default_factory=RandomPoseConfig)

    def __post_init__(self) -> None:
        if self.kind not in ("canonical", "random_pose"):
            raise ConfigError(f"plan.kind: expected 'canonical' or 'random_pose', got {self.kind!r}")
        for name in ("n", "resolution", "shard_size"):
            if getattr(self, name) < 1:
                raise ConfigError(f"plan.{name}: must be >= 1, got {getattr(self, name)}")
        _check_body_frame(self.body_frame, "plan")


@dataclass(frozen=True)
class RenderSpec:
    """``render``: the render settings and the files a worker renders with."""

    render: RenderConfig
    assets: SceneAssets


@dataclass(frozen=True)
class GeneratedCollectionSpec:
    """``generated_collection``: an image collection rendered from a rig (``generated_collections.ensure_collection``).

    Attributes:
        n, seed, resolution: images, their seed, their side in pixels. render: the render settings.
        ground_truth_dir: where the hidden truth goes (None: ``<out_dir>_ground_truth``).
        asset ... prefix: for any rig but the embedded toy (None: the toy, built in code): the rigged GLB, its body
        frame, its textures (``()``: the asset's own), environment maps, the pose sampler (``random`` /
        ``toy_natural``) and the sample-id prefix.
        pose_families: pose family → relative frequency of the ``toy_natural`` sampler (None: every family,
            uniformly).
    """

    n: int
    seed: int
    resolution: int
    render: RenderConfig
    ground_truth_dir: str | None = None
    asset: str | None = None
    body_frame: dict[str, Any] | None = None
    textures: tuple[str, ...] | None = None
    envmaps: tuple[str, ...] | None = None
    pose_sampler: str | None = None
    prefix: str | None = None
    pose_families: dict[str, float] | None = None

    def collection_options(self) -> dict[str, Any]:
        """The keyword arguments of ``ensure_collection`` this spec sets (those left None take its defaults)."""
        names = ("asset", "body_frame", "textures", "envmaps", "pose_sampler", "prefix", "pose_families")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}


@dataclass(frozen=True)
class TrainSpec:
    """``train``: the network, the optimisation, the features it reads (when a batch computes them itself) and,
    for a warm start, the ``predictor.pt`` whose weights initialise it (part of the cache key); ``mirror``, the
    rig's sagittal plane when ``train.mirror_probability > 0``."""

    model: ModelConfig
    train: TrainConfig
    features: FeatureConfig
    init_from: str | None = None
    mirror: CanonicalMirror | None = None


@dataclass(frozen=True)
class InferSpec:
    """``infer`` / ``collection_infer`` / ``test_infer``: the features the model reads and the images per forward
    pass (the run preset's ``infer_batch_size``)."""

    features: FeatureConfig
    batch_size: int = 16

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ConfigError(f"infer.batch_size: must be >= 1, got {self.batch_size}")


@dataclass(frozen=True)
class CropCamera:
    """The nominal camera of the model's crops, in which predictions live: the training renders' horizontal field
    of view at the model resolution, principal point at the centre."""

    fov_deg: float
    resolution: int

    def pinhole(self) -> PinholeCamera:
        return PinholeCamera.from_fov(self.fov_deg, self.resolution, self.resolution)


@dataclass(frozen=True)
class FitSpec:
    """``fit``: the fitting settings, the crops' camera and the folder of cached geodesics (None: computed per
    process)."""

    fitting: FittingConfig
    camera: CropCamera
    geodesic_cache: str | None = None


@dataclass(frozen=True)
class PlanViewsSpec:
    """``plan_views``: viewpoint augmentation, the body-frame joints and the run seed (shard ``index`` draws with
    ``seed * 1_000_003 + index``)."""

    augment: AugmentConfig
    body_frame: dict[str, Any]
    seed: int = 0

    def __post_init__(self) -> None:
        _check_body_frame(self.body_frame, "plan_views")


@dataclass(frozen=True)
class TruthSpec:
    """``pseudo_labels`` / ``filter_check``: the rig and the collection's hidden truth (``ground_truth.npz``)."""

    asset: str
    ground_truth: str


@dataclass(frozen=True)
class EvaluateSpec:
    """``evaluate``: the rig, the split's ground truth (``ground_truth.npz``), the body-frame joints, the split's
    name, the iteration the rows belong to and the seed of the evaluation's point sampling."""

    asset: str
    ground_truth: str
    body_frame: dict[str, Any]
    split: str
    iteration: int
    seed: int = 0

    def __post_init__(self) -> None:
        _check_body_frame(self.body_frame, "evaluate")


@dataclass(frozen=True)
class CollectionEvaluationSpec:
    """``evaluate_collection``: the rig (to reproject the fits) and the iteration the rows belong to."""

    asset: str
    iteration: int


@dataclass(frozen=True)
class RawImagesSpec:
    """``raw_images``: the number of layers K of the pseudo-labels ray-cast from each fit."""

    layers: int

    def __post_init__(self) -> None:
        if self.layers < 1:
            raise ConfigError(f"raw_images.layers: must be >= 1, got {self.layers}")
