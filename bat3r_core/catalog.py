"""The data catalog (``data_catalog.yaml``): categories, their assets and image collections, global settings,
fitting presets and named run presets, loaded into frozen dataclasses.

Loading is strict: ``yaml.safe_load``, unknown keys, wrong types and missing required keys raise
:class:`~bat3r_core.config_utils.ConfigError` naming the key path (``categories.horse.body_frame.origin``).
Relative paths resolve against the catalog file's folder. Files are not required to exist at load time (a
catalog lists categories whose assets a user may not have yet): a missing asset is reported when the category is
used (:meth:`Category.require_asset`), with the path and what to provide, and by ``bat3r catalog validate``.

Stage sections (camera prior, fitting presets, model/train/render settings of run presets) are validated at load
time against the stage's own config dataclass and materialised by the accessors (``run_preset.model_config()``).
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml

from .config_utils import ConfigError, from_mapping, replace_path

__all__ = ["Catalog", "Category", "RunPreset", "BodyFrameJoints", "CollectionSpec", "load_catalog",
           "default_catalog_path", "fitting_preset", "ConfigError", "GENERATED_TOY"]

GENERATED_TOY = "generated:toy"
"""Asset/collection value meaning "generate the embedded toy on first use"."""

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff")
ENVMAP_EXTENSIONS = (".hdr", ".exr")


@dataclass(frozen=True)
class BodyFrameJoints:
    """Joints defining the body-centric frame: origin (mid spine), forward pair (tail side, head side), horizontal
    pair (left, right)."""

    origin: str
    forward: tuple[str, str]
    horizontal: tuple[str, str]


@dataclass(frozen=True)
class CollectionSpec:
    """An image collection.

    Attributes:
        kind: ``folder`` (``images/`` + ``masks/`` with matching stems), ``parquet`` (an index with
            ``image_path``, ``mask_path``) or ``generated`` (synthesised on first use from the category's own rig:
            posed, yawed, framed by the camera prior, textured;
            :func:`bat3r_core.generated_collections.make_collection`).
        path: the folder or Parquet index (relative to the catalog file), or where a generated collection is cached.
        n: number of images of a generated collection (0 = the run preset's size).
        seed: seed of a generated collection.
        ground_truth: folder of hidden ground truth (generated collections / test splits only; only evaluation
            reads it).
        pose_sampler: poses of a generated collection: ``random`` (:func:`bat3r_core.poses.sample_random_poses`,
            any rig) or ``toy_natural`` (the toy's gaits, grazing, rearing, …; the toy's joints only). Default:
            ``toy_natural`` for the embedded toy, ``random`` for every other asset.
        pose_families: pose family → relative frequency for the ``toy_natural`` sampler (families of
            :data:`bat3r_core.poses.TOY_POSE_FAMILIES`; absent ones are not drawn). Default: all, uniformly. Set
            the same on ``collection`` and ``test_split``: the test split must come from the collection's sampler.
    """

    kind: Literal["folder", "parquet", "generated"]
    path: str
    n: int = 0
    seed: int = 0
    ground_truth: str | None = None
    pose_sampler: Literal["random", "toy_natural"] | None = None
    pose_families: dict[str, float] | None = None


@dataclass(frozen=True)
class FittingChoice:
    """Which fitting preset a category uses, and per-key overrides of it (dotted keys, e.g. ``weights.edge``)."""

    preset: Literal["synthetic", "real"]
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Category:
    """One object category.

    Attributes:
        name: category name (the key in ``categories``).
        asset: rigged canonical mesh (.glb/.gltf/.fbx/.blend) or ``generated:toy``.
        body_frame: joints of the body-centric frame, or ``"auto"`` to read them off the skeleton
            (:func:`bat3r_core.assets.propose_body_frame`; ``bat3r asset check`` prints the proposal).
        textures: texture image files (or ``procedural:<coat>`` for the toy's procedural coats); empty: the asset's
            own base-colour texture.
        asset_scale: file units → metres (0.01 for an asset in centimetres).
        up_axis: the asset's up axis (``+Y`` for glTF; ``+Z`` for many FBX/Blender-exported files).
        environment_maps: HDR/EXR files; empty means a procedural sky.
        collection: the training image collection.
        test_split: the held-out test collection with ground truth (optional).
        fitting: fitting preset choice and overrides.
        camera_prior: overrides of the global camera prior for this category (mapping, optional).
    """

    name: str
    asset: str
    body_frame: BodyFrameJoints | Literal["auto"]
    collection: CollectionSpec
    fitting: FittingChoice
    textures: tuple[str, ...] = ()
    environment_maps: tuple[str, ...] = ()
    test_split: CollectionSpec | None = None
    camera_prior: dict[str, Any] | None = None
    asset_scale: float = 1.0
    up_axis: Literal["+X", "-X", "+Y", "-Y", "+Z", "-Z"] = "+Y"
    catalog_dir: str = ""

    def __post_init__(self) -> None:
        if isinstance(self.asset_scale, bool) or not isinstance(self.asset_scale, (int, float)) \
                or not self.asset_scale > 0:
            raise ConfigError(f"categories.{self.name}.asset_scale: expected a positive number (file units -> "
                              f"metres, e.g. 0.01 for centimetres), got {self.asset_scale!r}")

    @property
    def is_generated(self) -> bool:
        return self.asset == GENERATED_TOY

    def resolve(self, p: str) -> Path:
        path = Path(os.path.expanduser(p))
        return path if path.is_absolute() else Path(self.catalog_dir) / path

    def missing(self) -> list[str]:
        """Human-readable list of what this category still needs (empty when it is usable)."""
        out = []
        if not self.is_generated and not self.resolve(self.asset).is_file():
            out.append(f"rigged asset {self.resolve(self.asset)} (a rigged, skinned mesh: .glb/.gltf/.fbx/.blend)")
        for t in self.textures:
            if not t.startswith("procedural:") and not self.resolve(t).is_file():
                out.append(f"texture {self.resolve(t)} (an image file)")
        for e in self.environment_maps:
            if not self.resolve(e).is_file():
                out.append(f"environment map {self.resolve(e)} (an .hdr/.exr file)")
        for label, spec in (("collection", self.collection), ("test split", self.test_split)):
            if spec is None or spec.kind == "generated":
                continue
            p = self.resolve(spec.path)
            if spec.kind == "folder" and not (p / "images").is_dir():
                out.append(f"{label} folder {p} (with images/ and masks/ subfolders, matching file stems)")
            elif spec.kind == "parquet" and not p.is_file():
                out.append(f"{label} index {p} (a Parquet file with image_path and mask_path columns)")
        return out

    def require_asset(self) -> Path:
        """Path of the rigged asset; ``FileNotFoundError`` naming it and what to provide if it is missing."""
        if self.is_generated:
            raise ValueError(f"category '{self.name}' uses the generated toy asset; call "
                             f"bat3r_core.catalog.Catalog.asset_path('{self.name}') to generate it")
        p = self.resolve(self.asset)
        if not p.is_file():
            raise FileNotFoundError(
                f"category '{self.name}': rigged asset {p} does not exist. Provide a rigged, skinned canonical "
                f"mesh of the category in metres (.glb/.gltf, or .fbx/.blend converted through Blender) at that "
                f"path, or change categories.{self.name}.asset in the data catalog.")
        return p


@dataclass(frozen=True)
class RunPreset:
    """A named run size (``tiny``, ``demo``, ``paper``).

    Attributes:
        iterations: bootstrap iterations after the canonical initialisation.
        image_size: render and model resolution (pixels, square).
        canonical_samples: renders of the rest-pose mesh for the initial predictor.
        collection_size: size of generated collections (toy).
        test_size: size of generated test splits (toy).
        views_per_fit_max: cap of augmented views per fitted image (the paper: 2).
        infer_batch_size: images per inference forward pass (collection and test predictions).
        render: render settings (a mapping checked against the render worker's config).
        model: network settings (checked against the predictor's ModelConfig).
        train: training settings (checked against the predictor's TrainConfig).
        fitting: overrides of the fitting preset (dotted keys; e.g. ``steps``).
        features: feature extractor name (``rgb`` on CPU, ``dinov2`` with weights).
        pseudo_label_filter: which fits become pseudo-labels (checked against
            ``bat3r_core.pseudo_labels.PseudoLabelFilterConfig``; empty: keep every ok fit).
        name: the preset's key under ``runs`` (set by the loader; kept by overrides, so that the stage configs
            built from an overridden preset name it in their errors).
    """

    iterations: int
    image_size: int
    canonical_samples: int
    collection_size: int
    test_size: int
    render: dict[str, Any] = field(default_factory=dict)
    model: dict[str, Any] = field(default_factory=dict)
    train: dict[str, Any] = field(default_factory=dict)
    fitting: dict[str, Any] = field(default_factory=dict)
    features: str = "rgb"
    views_per_fit_max: int = 2
    infer_batch_size: int = 16
    pseudo_label_filter: dict[str, Any] = field(default_factory=dict)
    name: str = ""


@dataclass(frozen=True)
class Catalog:
    """The whole data catalog.

    Attributes:
        path: the catalog file.
        storage_root: where runs live (``<storage_root>/<category>/<run name>/``).
        image_size: default image size (pixels).
        layers: K, the point-map layers.
        shard_size: samples per shard.
        camera_prior: the global camera prior (mapping checked against ``viewpoints.CameraPriorConfig``).
        fitting_presets: ``synthetic`` and ``real`` fitting settings (checked against ``FittingConfig``).
        runs: named run presets.
        categories: categories by name.
        features: feature extraction settings (mapping checked against ``predictor.features.FeatureConfig``;
            the extractor name comes from the run preset).
    """

    path: str
    storage_root: str
    image_size: int
    layers: int
    shard_size: int
    camera_prior: dict[str, Any]
    fitting_presets: dict[str, dict[str, Any]]
    runs: dict[str, RunPreset]
    categories: dict[str, Category]
    features: dict[str, Any] = field(default_factory=dict)

    @property
    def root(self) -> Path:
        return Path(self.path).parent

    def storage(self) -> Path:
        p = Path(os.path.expanduser(os.environ.get("BAT3R_STORAGE_ROOT", self.storage_root)))
        return p if p.is_absolute() else self.root / p

    def category(self, name: str) -> Category:
        if name not in self.categories:
            raise KeyError(f"unknown category '{name}' in {self.path}; available: {sorted(self.categories)}")
        return self.categories[name]

    def run_preset(self, name: "str | RunPreset") -> RunPreset:
        """The run preset ``name``; a :class:`RunPreset` passes through (e.g. one with run overrides applied)."""
        if isinstance(name, RunPreset):
            return name
        if name not in self.runs:
            raise KeyError(f"unknown run preset '{name}' in {self.path}; available: {sorted(self.runs)}")
        return self.runs[name]

    def asset_path(self, name: str) -> Path:
        """The category's rigged asset as every stage loads it: the embedded toy is generated (once) under the
        storage root; a user's file is normalised once (:func:`bat3r_core.assets.prepare_asset`: bind pose,
        ``asset_scale``, ``up_axis``, its own texture embedded) into ``<storage root>/_assets/``."""
        cat = self.category(name)
        if not cat.is_generated:
            from .assets import prepare_asset

            return prepare_asset(cat.require_asset(), self.storage() / "_assets", cat.asset_scale, cat.up_axis,
                                 name=name).path
        from .rig_io import save_rig_glb
        from .toy import build_toy_rig, toy_coat_texture

        path = self.storage() / "_assets" / "toy.glb"
        if not path.is_file():
            save_rig_glb(build_toy_rig(), path, texture=toy_coat_texture("bay"))
        return path

    def load_rig(self, name: str):
        """Load the category's rig (normalised; generating the toy if needed)."""
        from .rig_io import load_rig

        return load_rig(self.asset_path(name))

    def body_frame(self, name: str) -> BodyFrameJoints:
        """The category's body-frame joints; ``body_frame: auto`` is resolved from its skeleton."""
        cat = self.category(name)
        if isinstance(cat.body_frame, BodyFrameJoints):
            return cat.body_frame
        from .assets import propose_body_frame

        p = propose_body_frame(self.load_rig(name))
        return BodyFrameJoints(origin=p.origin, forward=p.forward, horizontal=p.horizontal)

    # ------------------------------------------------------------------ typed stage configs
    def camera_prior_config(self, category: str | None = None):
        from .viewpoints import CameraPriorConfig

        data = dict(self.camera_prior)
        if category is not None and self.category(category).camera_prior:
            data.update(self.category(category).camera_prior)
        return _stage(CameraPriorConfig, data, "camera_prior")

    def fitting_preset(self, name: str, overrides: Mapping[str, Any] | None = None):
        """The ``FittingConfig`` of ``fitting_presets.<name>`` (``synthetic`` or ``real`` in the shipped catalog: the
        paper's values) with optional ``overrides`` (field names, e.g. ``{"inlier_distance": 0.05}``), strict."""
        from .fitting.config import FittingConfig

        if name not in self.fitting_presets:
            raise ValueError(f"fitting preset must be one of {sorted(self.fitting_presets)}, got {name!r}")
        return _stage(FittingConfig, {**self.fitting_presets[name], **(overrides or {})}, f"fitting_presets.{name}")

    def fitting_config(self, category: str, run: "str | RunPreset | None" = None):
        from .fitting.config import FittingConfig

        cat = self.category(category)
        cfg = _stage(FittingConfig, self.fitting_presets[cat.fitting.preset], f"fitting_presets.{cat.fitting.preset}")
        overrides = dict(cat.fitting.overrides)
        if run is not None:
            overrides.update(self.run_preset(run).fitting)
        for k, v in overrides.items():
            cfg = replace_path(cfg, k, v)
        return cfg

    def model_config(self, run: "str | RunPreset"):
        from .predictor.config import ModelConfig

        preset = self.run_preset(run)
        data = {"resolution": preset.image_size, "layers": self.layers, "feature": preset.features, **preset.model}
        return _stage(ModelConfig, data, f"runs.{preset.name}.model")

    def train_config(self, run: "str | RunPreset"):
        from .predictor.config import TrainConfig

        preset = self.run_preset(run)
        return _stage(TrainConfig, preset.train, f"runs.{preset.name}.train")

    def feature_config(self, run: str | None = None, extractor: str | None = None):
        """``FeatureConfig`` from the ``features`` section; the extractor is ``extractor``, else the run preset's."""
        from .predictor.features import FeatureConfig

        data = dict(self.features)
        if extractor is not None:
            data["extractor"] = extractor
        elif run is not None:
            data["extractor"] = self.run_preset(run).features
        if data.get("cache_dir"):
            data["cache_dir"] = str(self.root / data["cache_dir"]) if not os.path.isabs(data["cache_dir"]) \
                else data["cache_dir"]
        return _stage(FeatureConfig, data, "features")

    def render_config(self, run: "str | RunPreset"):
        from .render.config import RenderConfig

        preset = self.run_preset(run)
        data = {"resolution": preset.image_size, "num_layers": self.layers, **preset.render}
        return _stage(RenderConfig, data, f"runs.{preset.name}.render")

    def pseudo_label_filter_config(self, run: "str | RunPreset"):
        """``PseudoLabelFilterConfig`` from the run preset's ``pseudo_label_filter`` section."""
        from .pseudo_labels import PseudoLabelFilterConfig

        preset = self.run_preset(run)
        return _stage(PseudoLabelFilterConfig, preset.pseudo_label_filter, f"runs.{preset.name}.pseudo_label_filter")

    def validate_stage_sections(self) -> None:
        """Check every stage section against its config class (raises ConfigError naming the key path)."""
        self.camera_prior_config()
        for name in self.categories:
            if self.categories[name].camera_prior:
                self.camera_prior_config(name)
            self.fitting_config(name)
        for run in self.runs:
            self.model_config(run)
            self.train_config(run)
            self.render_config(run)
            self.feature_config(run)
            self.pseudo_label_filter_config(run)


def _stage(cls, data: dict[str, Any], path: str):
    try:
        return from_mapping(cls, data, path)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:  # __post_init__ checks of the stage classes
        raise ConfigError(f"{path}: {e}") from e


_TOP_KEYS = {"storage_root", "image_size", "layers", "shard_size", "camera_prior", "fitting_presets", "runs",
             "categories", "features", "version"}


def default_catalog_path() -> Path:
    """``$BAT3R_CATALOG``, else ``data_catalog.yaml`` in the current folder, else the one beside the package."""
    env = os.environ.get("BAT3R_CATALOG")
    if env:
        return Path(env)
    here = Path.cwd() / "data_catalog.yaml"
    if here.is_file():
        return here
    return Path(__file__).resolve().parent.parent / "data_catalog.yaml"


def load_catalog(path: str | os.PathLike | None = None, validate_stages: bool = True) -> Catalog:
    """Load and validate a data catalog (default: :func:`default_catalog_path`)."""
    path = Path(path) if path is not None else default_catalog_path()
    if not path.is_file():
        raise FileNotFoundError(f"data catalog {path} does not exist")
    with open(path, encoding="utf-8") as f:
        try:
            raw = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from e
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the catalog must be a mapping at the top level")
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown top-level key(s) {unknown}; allowed: {sorted(_TOP_KEYS)}")
    for req in ("storage_root", "image_size", "layers", "shard_size", "runs", "categories", "fitting_presets"):
        if req not in raw:
            raise ConfigError(f"{path}: {req}: required key is missing")
    if raw.get("version", 1) != 1:
        raise ConfigError(f"{path}: version: only version 1 is supported, got {raw['version']!r}")

    runs_raw = raw["runs"]
    if not isinstance(runs_raw, dict) or not runs_raw:
        raise ConfigError(f"runs: expected a non-empty mapping of run presets, got {runs_raw!r}")
    runs = {name: dataclasses.replace(from_mapping(RunPreset, spec, f"runs.{name}"), name=name)
            for name, spec in runs_raw.items()}
    cats_raw = raw["categories"]
    if not isinstance(cats_raw, dict) or not cats_raw:
        raise ConfigError(f"categories: expected a non-empty mapping of categories, got {cats_raw!r}")
    cats = {}
    for name, spec in cats_raw.items():
        if not isinstance(spec, dict):
            raise ConfigError(f"categories.{name}: expected a mapping, got {type(spec).__name__}")
        if "name" in spec or "catalog_dir" in spec:
            raise ConfigError(f"categories.{name}: unknown key(s) ['name'/'catalog_dir'] (set by the loader)")
        cats[name] = from_mapping(Category, {**spec, "name": name, "catalog_dir": str(path.parent)},
                                  f"categories.{name}")
        for split in ("collection", "test_split"):
            cspec = getattr(cats[name], split)
            if cspec is not None and cspec.pose_sampler is not None and cspec.kind != "generated":
                raise ConfigError(f"categories.{name}.{split}.pose_sampler: only a generated collection samples "
                                  f"poses (kind is {cspec.kind!r}); remove the key or set kind: generated")
            if cspec is not None and cspec.pose_families is not None:
                _check_pose_families(cats[name], split, cspec)
    presets = raw["fitting_presets"]
    if not isinstance(presets, dict) or sorted(presets) != ["real", "synthetic"]:
        raise ConfigError(f"fitting_presets: expected exactly the presets 'synthetic' and 'real', got "
                          f"{sorted(presets) if isinstance(presets, dict) else presets!r}")
    catalog = Catalog(
        path=str(path),
        storage_root=_check("storage_root", raw["storage_root"], str),
        image_size=_check("image_size", raw["image_size"], int),
        layers=_check("layers", raw["layers"], int),
        shard_size=_check("shard_size", raw["shard_size"], int),
        camera_prior=_check("camera_prior", raw.get("camera_prior", {}) or {}, dict),
        fitting_presets=presets,
        runs=runs,
        categories=cats,
        features=_check("features", raw.get("features", {}) or {}, dict),
    )
    for key in ("image_size", "layers", "shard_size"):
        if getattr(catalog, key) <= 0:
            raise ConfigError(f"{key}: must be positive, got {getattr(catalog, key)}")
    if validate_stages:
        catalog.validate_stage_sections()
    return catalog


def fitting_preset(name: str, overrides: Mapping[str, Any] | None = None,
                   catalog: str | os.PathLike | None = None):
    """:meth:`Catalog.fitting_preset` of the catalog file ``catalog`` (default: :func:`default_catalog_path`)."""
    return load_catalog(catalog, validate_stages=False).fitting_preset(name, overrides)


def _check_pose_families(cat: Category, split: str, spec: CollectionSpec) -> None:
    """A collection's ``pose_families``: a generated collection of the ``toy_natural`` sampler, known families,
    non-negative frequencies with a positive sum."""
    from bat3r_core.poses import pose_family_weights

    key = f"categories.{cat.name}.{split}.pose_families"
    sampler = spec.pose_sampler or ("toy_natural" if cat.is_generated else "random")
    if spec.kind != "generated" or sampler != "toy_natural":
        raise ConfigError(f"{key}: only a generated collection with pose_sampler 'toy_natural' has pose families "
                          f"(kind {spec.kind!r}, pose_sampler {sampler!r})")
    try:
        pose_family_weights(spec.pose_families)
    except ValueError as e:
        raise ConfigError(f"{key}: {e}") from None


def _check(key: str, value: Any, tp: type) -> Any:
    if tp is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise ConfigError(f"{key}: expected an integer, got {type(value).__name__} {value!r}")
    if tp is not int and not isinstance(value, tp):
        raise ConfigError(f"{key}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
    return value


def replace_category(catalog: Catalog, name: str, **changes: Any) -> Catalog:
    """A copy of ``catalog`` with fields of category ``name`` replaced (used by tests and flows)."""
    cats = dict(catalog.categories)
    cats[name] = dataclasses.replace(catalog.category(name), **changes)
    return dataclasses.replace(catalog, categories=cats)
