"""Configuration of the mesh-fitting stage: one frozen dataclass. Its presets are data: ``fitting_presets`` of the
data catalog (the paper's supplement and REFERENCE.md values), loaded by
``bat3r_core.catalog.fitting_preset(name, overrides)`` (this module does not read the catalog).
"""
from __future__ import annotations

from dataclasses import dataclass

from bat3r_core.config_utils import ConfigError

__all__ = ["FittingConfig", "HORSE_LENGTH_M"]

HORSE_LENGTH_M = 2.7
"""Length (longest rest-pose bounding-box side, metres) of the horse the reference thresholds were set for."""


@dataclass(frozen=True)
class FittingConfig:
    """Mesh fitting of the rigged canonical mesh to one predicted dual point cloud per image.

    Attributes:
        steps: Adam steps (200 synthetic, 300 real).
        lr_rotations: learning rate of the excess rotations θ (2e-2).
        lr_bone_scales: learning rate of the log bone scales (2e-2).
        lr_global: learning rate of the global similarity (axis-angle delta, translation, log scale) (1e-3).
        rotation_lr_halving_steps: θ's and the bone scales' learning rates are halved every this many steps (100;
            the reference halves both). θ is wrapped to |θ_j| <= π after every step (the same rotations).
        huber_delta: δ of the Huber data term, metres (0.1).
        weight_angle, weight_edge, weight_volume, weight_repulsion, weight_scale: λ of Eq. 4, acting on the terms
            normalised as the reference normalises them (mean data term, absolute volume change; ``losses``).
        weight_silhouette: weight of the silhouette term (not in the paper; 0 = off, the paper's objective): the
            fitted mesh's projection against the image's mask (:mod:`.silhouette`), on the data term's scale.
            Whatever the weight, fits report its final value (``loss_silhouette``).
        data_depth_weight: weight of the camera-depth (z) component of the data term's residual (1 = the paper's
            isotropic term). Single-image depth is what Φ predicts worst (on the toy bench Φ₀'s posed maps are off
            ~4–5 cm RMS across the image and ~20 cm in depth), so below 1 the fit trusts the maps' x, y — where
            each pixel's point lies across the image — more than their depth. The initial similarity is solved
            under the same weighting.
        correspondence_refresh_steps: every this many steps, each control point is re-assigned the fitting-mesh
            vertex nearest to it in the current fit, in the joint posed + canonical space
            (``correspondences.reassign_vertices``: posed distance weighted like the data term, canonical distance
            by ``correspondence_canonical_weight``). 0 = never: the paper's fixed nearest-canonical-vertex
            correspondences. Predicted canonical maps are least right on limbs posed away from rest (a raised leg
            labelled where it would hang); re-assignment lets the posed map correct those labels.
        correspondence_canonical_weight: β of the re-assignment's canonical distance (1: a centimetre off in the
            canonical map costs as much as a centimetre off in the posed map; large: the fixed correspondences).
        silhouette_vertices: fitting-mesh vertices (farthest point sample) whose projections the term checks.
        silhouette_mask_samples: mask pixels (at most; a seeded sample) that must be covered by a projection.
        silhouette_refresh_steps: each mask pixel's nearest projected vertex (the coverage's assignment, most of
            the term's cost) is searched every this many steps and reused in between (1: every step, exact; 5 is
            2x faster and fitted as well on the 64x64 predictions, docs/fitting.md).
        warmup: start the angle, edge and volume weights at ``warmup_factor`` times and decay them linearly to
            1x over ``warmup_steps`` steps (the reference warm-up).
        warmup_factor: initial multiplier of the warm-up (10).
        warmup_steps: length of the warm-up in steps (25).
        inlier_distance: a predicted canonical point is an inlier only if its nearest canonical vertex is closer
            than this, metres (reference: 0.1 horse, 0.05 other categories).
        min_confidence: and its confidence ``C`` is at least this (2). Points without confidence pass.
        num_control_points: control points kept by farthest point sampling (200; 300 elephant).
        repulsion_geodesic_threshold: vertex pairs further apart than this on the canonical surface may repel,
            metres, for an asset of length ``repulsion_reference_length`` (reference: 0.5 m for the 2.7 m horse).
        repulsion_reference_length: the threshold is scaled by (asset length / this), the asset length being the
            longest side of its rest bounding box; 0 uses the threshold as an absolute distance. For the 2.36 m
            toy the default gives 0.5 · 2.36 / 2.7 = 0.44 m.
        repulsion_k: nearest neighbours per vertex considered for repulsion (100).
        repulsion_radius: r of ``relu(r² − d²)²``, metres for an asset of length ``objective_reference_length``
            (0.05 for the 2.7 m horse), scaled with the asset's length.
        objective_reference_length: the fitting objective is evaluated in units of (asset length / this): the
            data term's distances and Huber δ, the edge (∝ length⁴), volume (∝ length⁶) and repulsion terms are
            those of the asset scaled to this length, so the paper's λ (tuned on a 2.7 m horse) weigh the terms of a
            0.5 m dog as they weigh a horse's. 0 evaluates everything in metres.
        repulsion_refresh_steps: the repulsion candidate pairs (k-NN in the posed state) are recomputed every this
            many steps; pairs are searched within ``2 r`` so motion between refreshes is covered.
        bone_scale_bounds: bone scales are clamped to this range ([0.5, 2]).
        enable_bone_scales: optimise per-bone scales S (False for synthetic images).
        fit_root_rotation: optimise the root joint's excess rotation too (it overlaps the global rotation; the
            angle penalty keeps it small).
        regulariser_max_vertices: the edge, volume and repulsion terms run on a quadric-decimated proxy of the
            mesh with about this many vertices when the rig has more (0: always the full mesh). Exact full-mesh
            terms cost about 3x more per step for the 4.8K-vertex toy (docs/fitting.md). Only the full mesh
            reproduces the reference's weighting exactly; the proxy's edge and volume gradients are within a factor
            ~1.5-2 of it (docs/fitting.md, "Weighting as the reference weights it").
        min_valid_points: instances with fewer inlier points are recorded with status ``too_few_points``.
        seed: seed of the random FPS start points.
        weld_relative_tolerance: fitting runs on the rig's welded mesh: file vertices closer than this fraction
            of the mesh extent (longest rest bounding-box side) are one vertex (``bat3r_core.topology``; 1e-6;
            0 merges exact duplicates only). Outputs stay on the file's vertices.
        geodesic_landmarks: landmarks of the geodesic estimates that farthest point sampling reads (512;
            ``fitting.geodesics.LandmarkGeodesics``: memory ``2 L V`` float32, exact when the welded mesh has at
            most this many vertices).
        densify_max_edge_fraction: fitting refines the welded mesh by midpoint subdivision (interpolated skin
            weights) while its median edge is longer than this fraction of the asset's longest rest extent (0.02;
            0: never), so that every surface point has a vertex near it for the nearest-vertex data term. Dense
            meshes (toy 1.5 %, horse-like scans) are untouched; the 290-vertex Khronos Fox (5.3 %) gets 2 levels.
        geodesic_exact_max_vertices: the repulsion term reads exact geodesics among the regulariser mesh's
            vertices (an ``S × S`` block from Dijkstra rows of those vertices) when it has at most this many
            (5000), else the landmark estimates.
    """

    steps: int = 200
    lr_rotations: float = 2e-2
    lr_bone_scales: float = 2e-2
    lr_global: float = 1e-3
    rotation_lr_halving_steps: int = 100
    huber_delta: float = 0.1
    weight_angle: float = 1e-5
    weight_edge: float = 100.0
    weight_volume: float = 20.0
    weight_repulsion: float = 1.0
    weight_scale: float = 0.0
    weight_silhouette: float = 0.0
    data_depth_weight: float = 1.0
    correspondence_refresh_steps: int = 0
    correspondence_canonical_weight: float = 1.0
    silhouette_vertices: int = 600
    silhouette_mask_samples: int = 400
    silhouette_refresh_steps: int = 5
    warmup: bool = True
    warmup_factor: float = 10.0
    warmup_steps: int = 25
    inlier_distance: float = 0.1
    min_confidence: float = 2.0
    num_control_points: int = 200
    repulsion_geodesic_threshold: float = 0.5
    repulsion_reference_length: float = HORSE_LENGTH_M
    objective_reference_length: float = HORSE_LENGTH_M
    repulsion_k: int = 100
    repulsion_radius: float = 0.05
    repulsion_refresh_steps: int = 20
    bone_scale_bounds: tuple[float, float] = (0.5, 2.0)
    enable_bone_scales: bool = False
    fit_root_rotation: bool = True
    regulariser_max_vertices: int = 1500
    min_valid_points: int = 30
    seed: int = 0
    weld_relative_tolerance: float = 1e-6
    densify_max_edge_fraction: float = 0.02
    geodesic_landmarks: int = 512
    geodesic_exact_max_vertices: int = 5000

    def __post_init__(self) -> None:
        positive_ints = ("steps", "rotation_lr_halving_steps", "num_control_points", "repulsion_k",
                         "silhouette_vertices", "silhouette_mask_samples", "silhouette_refresh_steps",
                         "repulsion_refresh_steps", "min_valid_points", "geodesic_landmarks")
        for name in positive_ints:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"FittingConfig.{name} must be an int >= 1, got {v!r}")
        rmv = self.regulariser_max_vertices
        if isinstance(rmv, bool) or not isinstance(rmv, int) or rmv < 0 or 0 < rmv < 4:
            raise ConfigError(f"FittingConfig.regulariser_max_vertices must be 0 or an int >= 4, got {rmv!r}")
        gem = self.geodesic_exact_max_vertices
        if isinstance(gem, bool) or not isinstance(gem, int) or gem < 0:
            raise ConfigError(f"FittingConfig.geodesic_exact_max_vertices must be an int >= 0, got {gem!r}")
        crs = self.correspondence_refresh_steps
        if isinstance(crs, bool) or not isinstance(crs, int) or crs < 0:
            raise ConfigError(f"FittingConfig.correspondence_refresh_steps must be an int >= 0, got {crs!r}")
        if isinstance(self.warmup_steps, bool) or not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            raise ConfigError(f"FittingConfig.warmup_steps must be an int >= 0, got {self.warmup_steps!r}")
        for name in ("lr_rotations", "lr_bone_scales", "lr_global", "huber_delta", "inlier_distance",
                     "repulsion_radius", "repulsion_geodesic_threshold"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"FittingConfig.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("weight_angle", "weight_edge", "weight_volume", "weight_repulsion", "weight_scale",
                     "weight_silhouette", "data_depth_weight", "correspondence_canonical_weight", "min_confidence",
                     "repulsion_reference_length",
                     "objective_reference_length", "weld_relative_tolerance", "densify_max_edge_fraction"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"FittingConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.warmup_factor >= 1:
            raise ConfigError(f"FittingConfig.warmup_factor must be >= 1, got {self.warmup_factor!r}")
        lo, hi = self.bone_scale_bounds
        if not 0 < lo <= 1 <= hi:
            raise ConfigError(f"FittingConfig.bone_scale_bounds must satisfy 0 < lo <= 1 <= hi, got "
                              f"{self.bone_scale_bounds}")

    def geodesic_threshold_for(self, asset_length: float) -> float:
        """The repulsion geodesic threshold in metres for an asset whose longest rest extent is ``asset_length``."""
        if self.repulsion_reference_length == 0:
            return self.repulsion_geodesic_threshold
        return self.repulsion_geodesic_threshold * float(asset_length) / self.repulsion_reference_length
