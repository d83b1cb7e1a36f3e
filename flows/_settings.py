"""Resolve a run's settings from the data catalog, a run preset, dotted overrides and the paper's ablation switches.

The result (``RunSettings``) holds one typed config per stage plus the run-level numbers; ``to_mapping()`` is the
JSON written to ``manifest.json``. ``stage_specs`` cuts it into the typed spec of each stage task
(``bat3r_core.specs``), which the tasks receive and hash into their cache keys, so a changed setting recomputes
exactly the stages it reaches.

Overrides are ``{"<section>.<key>[.<key>...]": value}`` with sections ``render``, ``model``, ``train``,
``features``, ``fitting``, ``camera_prior``, ``pseudo_label_filter`` (stage configs), ``random_poses`` (the
random-poses baseline's sampler, ``bat3r_core.poses.RandomPoseConfig``; the supplement's by default) and ``run``
(fields of the run preset, e.g. ``run.canonical_samples``), plus the top-level ``shard_size`` and
``max_failed_fraction``.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from bat3r_core.catalog import Catalog, default_catalog_path, load_catalog
from bat3r_core.config_utils import ConfigError, replace_path, to_mapping
from bat3r_core.fitting.augment import AugmentConfig
from bat3r_core.fitting.config import FittingConfig
from bat3r_core.poses import RandomPoseConfig
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.features import FeatureConfig
from bat3r_core.predictor.mirror import CanonicalMirror, canonical_mirror_for_rig
from bat3r_core.pseudo_labels import PseudoLabelFilterConfig
from bat3r_core.render.config import RenderConfig, SceneAssets
from bat3r_core.runs import RunLayout, read_manifest
from bat3r_core.specs import (CollectionEvaluationSpec, CropCamera, EvaluateSpec, FitSpec, InferSpec, PlanViewsSpec,
                              RawImagesSpec, RenderSpec, SampledPlanSpec, TrainSpec, TruthSpec)
from bat3r_core.viewpoints import AnglePrior, CameraPriorConfig, ViewTypePrior

__all__ = ["Ablations", "RunSettings", "StageSpecs", "resolve_run", "stage_specs", "recorded_run"]

_SECTIONS = ("render", "model", "train", "features", "fitting", "camera_prior", "pseudo_label_filter", "random_poses",
             "run")


@dataclass(frozen=True)
class Ablations:
    """The paper's ablation switches (all off = the method).

    Attributes:
        gaussian_cameras: sample viewpoints from Normal priors instead of Student's t (same loc and scale per
            view type, no df).
        no_fitting_regularisation: zero the angle, edge, volume, repulsion and scale weights of the mesh fit.
        no_view_augmentation: render only the estimated view of each fit (no augmented views).
        no_pseudo_label_filter: plan views for every ok fit (no filter stage between fit and plan views).
        random_poses: the random-poses baseline (training images of random poses instead of fitted ones).
        raw_images: the raw-image baseline (train on the collection images with the fitted pseudo-labels,
            without re-rendering).
    """

    gaussian_cameras: bool = False
    no_fitting_regularisation: bool = False
    no_view_augmentation: bool = False
    no_pseudo_label_filter: bool = False
    random_poses: bool = False
    raw_images: bool = False


@dataclass(frozen=True)
class RunSettings:
    """Everything a bootstrap run needs, resolved (see the module docstring). ``catalog_file``: the data catalog
    it was resolved from; ``source_asset``: the category's asset file as the catalog names it (``assets.asset`` is
    the normalised GLB the stages load; ``generated:toy`` for the toy)."""

    layout: RunLayout
    category: str
    preset: str
    iterations: int
    image_size: int
    layers: int
    shard_size: int
    canonical_samples: int
    collection_size: int
    test_size: int
    views_per_fit_max: int
    infer_batch_size: int
    max_failed_fraction: float
    render: RenderConfig
    model: ModelConfig
    train: TrainConfig
    features: FeatureConfig
    fitting: FittingConfig
    camera_prior: CameraPriorConfig
    pseudo_label_filter: PseudoLabelFilterConfig
    assets: SceneAssets
    body_frame: dict[str, Any]
    collection: dict[str, Any]
    test_split: dict[str, Any] | None
    ablations: Ablations
    catalog_file: str = ""
    source_asset: str = ""
    mirror: CanonicalMirror | None = None
    """The rig's sagittal plane when ``train.mirror_probability > 0`` (checked symmetric at resolve time)."""
    random_poses: RandomPoseConfig = RandomPoseConfig()
    """The random-poses baseline's pose sampler (``--random-poses``; ``--set random_poses.sigma1=…``)."""

    def hint_context(self) -> dict[str, str]:
        """What ``bat3r_core.runs.require_samples`` fills into its hint: the category, its asset file (none for the
        generated toy) and the catalog file when it is not the default one."""
        default = str(default_catalog_path().resolve())
        return {"category": self.category,
                "asset": "" if self.source_asset.startswith("generated:") else self.source_asset,
                "catalog": "" if not self.catalog_file or self.catalog_file == default else self.catalog_file}

    def to_mapping(self) -> dict[str, Any]:
        """JSON-serialisable form (for ``manifest.json``)."""
        out = {f.name: to_mapping(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "layout"}
        out["run_dir"] = str(self.layout.root)
        return out


def _gaussian(prior: CameraPriorConfig) -> CameraPriorConfig:
    def normal(p: AnglePrior | None) -> AnglePrior | None:
        return None if p is None else AnglePrior(loc=p.loc, scale=p.scale)

    table = {k: ViewTypePrior(normal(v.elevation), normal(v.roll)) for k, v in (prior.per_view_type or {}).items()}
    return dataclasses.replace(prior, distribution="normal", elevation=normal(prior.elevation),
                               roll=normal(prior.roll), per_view_type=table or None)


def _texture(catalog_dir: Path, t: str) -> str:
    if t.startswith("procedural:"):
        return "toy:" + t.split(":", 1)[1]
    p = Path(os.path.expanduser(t))
    return str(p if p.is_absolute() else catalog_dir / p)


def _collection(cat, spec, size: int, resolution: int, assets: SceneAssets, body_frame: dict[str, Any],
                generated_seed_offset: int = 0) -> dict[str, Any] | None:
    """The resolved collection (or test split) of a category; a ``generated`` one also carries what
    ``bat3r_core.generated_collections.make_collection`` renders it from: the asset (None: the embedded toy, built
    in-process), the body frame, the category's textures (``()``: the asset's own embedded texture), environment maps, the
    pose sampler (``toy_natural`` for the toy, ``random`` otherwise, unless the spec names one), its pose-family
    frequencies when the spec sets them and the sample-id prefix (the category name)."""
    if spec is None:
        return None
    path = cat.resolve(spec.path)
    if spec.kind != "generated":
        return {"kind": spec.kind, "path": str(path)}
    n = spec.n or size
    tag = f"n{n}-r{resolution}"  # one cached collection per size, so presets do not overwrite each other
    gt = cat.resolve(spec.ground_truth) if spec.ground_truth else path.parent / f"{path.name}_ground_truth"
    out = {"kind": "generated", "path": str(path / tag), "ground_truth": str(gt / tag), "n": n,
           "seed": spec.seed + generated_seed_offset,
           "pose_sampler": spec.pose_sampler or ("toy_natural" if cat.is_generated else "random")}
    if spec.pose_families is not None:
        out["pose_families"] = dict(spec.pose_families)
    if not cat.is_generated:
        out.update(asset=assets.asset, body_frame=body_frame, textures=list(assets.textures),
                   envmaps=list(assets.envmaps), prefix=cat.name)
    return out


def _split_overrides(overrides: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {s: {} for s in _SECTIONS}
    out["top"] = {}
    for key, value in overrides.items():
        if key in ("shard_size", "max_failed_fraction"):
            out["top"][key] = value
            continue
        section, _, rest = str(key).partition(".")
        if section not in _SECTIONS or not rest:
            raise ConfigError(f"override '{key}': expected '<section>.<key>' with section one of "
                              f"{list(_SECTIONS)}, or 'shard_size' / 'max_failed_fraction'")
        out[section][rest] = value
    return out


def _catalog(catalog: Catalog | str | os.PathLike | None) -> Catalog:
    """A loaded catalog: ``catalog`` itself, the file it names, or the default (``$BAT3R_CATALOG``, else
    ``./data_catalog.yaml``)."""
    return catalog if isinstance(catalog, Catalog) else load_catalog(catalog)


def resolve_run(category: str, preset: str, run_name: str, overrides: Mapping[str, Any] | None = None,
                ablations: Ablations | Mapping[str, bool] | None = None,
                catalog: Catalog | str | os.PathLike | None = None, max_failed_fraction: float = 0.1) -> RunSettings:
    """The settings of run ``run_name`` of ``category`` at run preset ``preset`` (see the module docstring).
    catalog: a loaded catalog, its file, or None for the default file."""
    catalog = _catalog(catalog)
    cat = catalog.category(category)
    if isinstance(ablations, Mapping):
        from bat3r_core.config_utils import from_mapping

        ablations = from_mapping(Ablations, ablations, "ablations")
    ablations = ablations or Ablations()
    ov = _split_overrides(dict(overrides or {}))
    run = catalog.run_preset(preset)
    for key, value in ov["run"].items():
        run = replace_path(run, key, value)
    # stage configs from the run preset with its overrides applied (run.image_size reaches render and model)
    render = catalog.render_config(run)
    model = catalog.model_config(run)
    train = catalog.train_config(run)
    fitting = catalog.fitting_config(category, run)
    prior = catalog.camera_prior_config(category)
    # the catalog's features section (DINOv2 model, input size, channels, cache folder) with the preset's extractor;
    # one cache folder per category, so a PCA fitted on one category's renders is never reused for another's
    features = catalog.feature_config(run)
    features = dataclasses.replace(features, cache_dir=str(
        Path(features.cache_dir or catalog.storage() / "_cache" / "features") / category))
    configs = {"render": render, "model": model, "train": train, "features": features, "fitting": fitting,
               "camera_prior": prior, "pseudo_label_filter": catalog.pseudo_label_filter_config(run),
               "random_poses": RandomPoseConfig()}
    for section in configs:
        for key, value in ov[section].items():
            configs[section] = replace_path(configs[section], key, value)
    if ablations.gaussian_cameras:
        configs["camera_prior"] = _gaussian(configs["camera_prior"])
    if ablations.no_fitting_regularisation:
        configs["fitting"] = dataclasses.replace(configs["fitting"], weight_angle=0.0, weight_edge=0.0,
                                                 weight_volume=0.0, weight_repulsion=0.0, weight_scale=0.0)
    shard_size = int(ov["top"].get("shard_size", catalog.shard_size))
    mff = float(ov["top"].get("max_failed_fraction", max_failed_fraction))
    if shard_size < 1:
        raise ConfigError(f"shard_size: must be >= 1, got {shard_size}")
    if not 0.0 <= mff <= 1.0:
        raise ConfigError(f"max_failed_fraction: must be in [0, 1], got {mff}")
    asset = catalog.asset_path(category)
    # no textures: the toy renders its procedural coats, any other asset its own base-colour texture (empty list)
    textures = tuple(_texture(catalog.root, t) for t in cat.textures)
    assets = SceneAssets(asset=str(asset), textures=textures or (SceneAssets("").textures if cat.is_generated else ()),
                         envmaps=tuple(str(cat.resolve(e)) for e in cat.environment_maps))
    bf = catalog.body_frame(category)
    body_frame = {"origin": bf.origin, "forward": list(bf.forward), "horizontal": list(bf.horizontal)}
    mirror = None
    if configs["train"].mirror_probability > 0:
        from bat3r_core.rig_io import load_rig

        mirror = canonical_mirror_for_rig(load_rig(asset), body_frame,
                                          source=f"categories.{category} (asset {cat.asset})")
    return RunSettings(
        layout=RunLayout(catalog.storage(), category, run_name), category=category, preset=preset,
        iterations=run.iterations, image_size=run.image_size, layers=catalog.layers, shard_size=shard_size,
        canonical_samples=run.canonical_samples, collection_size=run.collection_size, test_size=run.test_size,
        views_per_fit_max=run.views_per_fit_max, infer_batch_size=run.infer_batch_size, max_failed_fraction=mff, assets=assets,
        body_frame=body_frame,
        collection=_collection(cat, cat.collection, run.collection_size, run.image_size, assets, body_frame),
        test_split=_collection(cat, cat.test_split, run.test_size, run.image_size, assets, body_frame),
        ablations=ablations, catalog_file=str(Path(catalog.path).resolve()),
        source_asset=cat.asset if cat.is_generated else str(cat.resolve(cat.asset)), mirror=mirror, **configs)


@dataclass(frozen=True)
class StageSpecs:
    """The typed spec of every stage task of one iteration (``bat3r_core.specs``), cut from a run's settings by
    :func:`stage_specs`: the one place settings become what the tasks receive. ``pseudo_label_truth`` is the
    collection's hidden truth (None without one: no ``pseudo_labels`` / ``filter_check`` stage); ``evaluate`` the
    test split's (None: no per-sample evaluation). The evaluation specs take the iteration from
    :meth:`evaluate_at` / :meth:`collection_evaluation_at`."""

    plan: SampledPlanSpec
    render: RenderSpec
    features: FeatureConfig
    train: TrainSpec
    infer: InferSpec
    fit: FitSpec
    filter: PseudoLabelFilterConfig
    plan_views: PlanViewsSpec
    raw_images: RawImagesSpec
    pseudo_label_truth: TruthSpec | None
    evaluate: EvaluateSpec | None
    asset: str

    def evaluate_at(self, iteration: int) -> EvaluateSpec:
        if self.evaluate is None:
            raise ValueError("the test split has no ground truth: there is no evaluate spec")
        return dataclasses.replace(self.evaluate, iteration=int(iteration))

    def collection_evaluation_at(self, iteration: int) -> CollectionEvaluationSpec:
        return CollectionEvaluationSpec(asset=self.asset, iteration=int(iteration))

    def train_from(self, init_from: str | None) -> TrainSpec:
        """The train spec warm-started from ``init_from`` (None: from scratch)."""
        return dataclasses.replace(self.train, init_from=init_from)


def stage_specs(settings: RunSettings, seed: int) -> StageSpecs:
    """The stage specs of one iteration of the run ``settings`` describe; ``seed``: the iteration's seed (the run
    seed plus the iteration)."""
    asset = settings.assets.asset
    truth = _truth_file(settings.collection)
    gt = _truth_file(settings.test_split, must_exist=False)
    prior = settings.camera_prior
    return StageSpecs(
        plan=SampledPlanSpec(kind="random_pose" if settings.ablations.random_poses else "canonical",
                             n=settings.canonical_samples, seed=seed, resolution=settings.image_size,
                             shard_size=settings.shard_size, body_frame=dict(settings.body_frame), prior=prior,
                             num_textures=settings.assets.num_textures, num_envmaps=len(settings.assets.envmaps),
                             random_poses=settings.random_poses),
        render=RenderSpec(render=settings.render, assets=settings.assets),
        features=settings.features,
        train=TrainSpec(model=settings.model, train=settings.train, features=settings.features,
                        mirror=settings.mirror),
        infer=InferSpec(features=settings.features, batch_size=settings.infer_batch_size),
        fit=FitSpec(fitting=settings.fitting,
                    camera=CropCamera(fov_deg=prior.fov_deg, resolution=settings.image_size),
                    geodesic_cache=str(settings.layout.storage_root / "_cache" / "geodesics")),
        filter=settings.pseudo_label_filter,
        plan_views=PlanViewsSpec(
            augment=AugmentConfig(camera_prior=prior, width=settings.image_size, height=settings.image_size,
                                  num_textures=settings.assets.num_textures, num_envmaps=len(settings.assets.envmaps),
                                  augment=not settings.ablations.no_view_augmentation),
            body_frame=dict(settings.body_frame), seed=seed),
        raw_images=RawImagesSpec(layers=settings.layers),
        pseudo_label_truth=None if truth is None else TruthSpec(asset=asset, ground_truth=truth),
        evaluate=None if gt is None else EvaluateSpec(asset=asset, ground_truth=gt,
                                                      body_frame=dict(settings.body_frame), split="test",
                                                      iteration=0, seed=seed),
        asset=asset)


def _truth_file(split: Mapping[str, Any] | None, must_exist: bool = True) -> str | None:
    """The ``ground_truth.npz`` of a split with a hidden truth (a generated collection): None without one, or,
    with ``must_exist``, while the file is not on disk yet."""
    gt = (split or {}).get("ground_truth")
    if not gt:
        return None
    path = Path(gt) / "ground_truth.npz"
    return str(path) if path.is_file() or not must_exist else None


def recorded_run(category: str, run_name: str, catalog: Catalog | str | os.PathLike | None = None
                 ) -> tuple[RunSettings, dict[str, Any]]:
    """The settings an existing run was made with, re-resolved from its ``manifest.json`` (preset, overrides,
    ablation switches, failed-fraction limit), and the run parameters the manifest records (``iterations,
    task_runner, seed, overrides``) — for tools that analyse a finished run (e.g. the demo benchmarks).

    catalog: the catalog whose storage root holds the run (a loaded catalog, its file, or None for the default).
    Raises FileNotFoundError when the run has no manifest.
    """
    catalog = _catalog(catalog)
    layout = RunLayout(catalog.storage(), category, run_name)
    config = read_manifest(layout).get("config")
    if not config:
        raise FileNotFoundError(f"{layout.manifest}: no such run (run the bootstrap flow with --run-name "
                                f"{run_name} first)")
    parameters = config["parameters"]
    settings = resolve_run(category, config["preset"], run_name, parameters["overrides"], config["ablations"],
                           catalog=catalog, max_failed_fraction=config["max_failed_fraction"])
    return settings, parameters
