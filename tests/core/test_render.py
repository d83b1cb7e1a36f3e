"""Render jobs, the Blender worker and the shard runner: tiny shards rendered for real with Cycles."""
from __future__ import annotations

import dataclasses
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch
from scipy.spatial.transform import Rotation

from bat3r_core.config_utils import ConfigError
from bat3r_core.render.config import RenderConfig, SceneAssets, render_config
from bat3r_core.render.jobs import (JobSchemaError, RenderJob, job_from_dict, job_to_dict, jobs_from_table,
                                    jobs_to_table, read_jobs, write_jobs)
from bat3r_core.shards import read_shard, shard_paths
from bat3r_core.skinning import skin
from bat3r_core.viewpoints import frame_camera, identity_frame

TINY = RenderConfig(resolution=32, samples=2, timeout_s=60.0)


# ------------------------------------------------------------------------------------------------ helpers
def _posed(rig, theta, scale=1.0, rotation=None, translation=None) -> np.ndarray:
    """bat3r_core skinning of one pose, (V, 3) float64 world frame."""
    r = np.eye(3) if rotation is None else rotation
    t = np.zeros(3) if translation is None else translation
    out = skin(rig.tensors(torch.float64), torch.as_tensor(theta, dtype=torch.float64)[None],
               global_scale=torch.tensor([scale], dtype=torch.float64),
               global_rotation=torch.as_tensor(r, dtype=torch.float64)[None],
               global_translation=torch.as_tensor(t, dtype=torch.float64)[None])
    return out.vertices[0].numpy()


def _job(rig, sample_id, theta, size, azimuth=-60.0, scale=1.0, rotation=None, translation=None, **kw) -> RenderJob:
    """A job whose camera frames the posed mesh (world up = canonical +Y after the similarity's rotation)."""
    verts = _posed(rig, theta, scale, rotation, translation)
    frame = identity_frame(verts.mean(0))
    if rotation is not None:
        frame = type(frame)(origin=verts.mean(0), rotation=np.asarray(rotation))
    view = frame_camera(verts, frame, azimuth, 12.0, 4.0, 40.0, size, size, 0.12)
    return RenderJob(sample_id=sample_id, excess_rotations=theta, camera=view.camera, global_scale=scale,
                     global_rotation=np.eye(3) if rotation is None else rotation,
                     global_translation=np.zeros(3) if translation is None else translation, **kw)


def _nontrivial_theta(rig, seed=0) -> np.ndarray:
    from bat3r_core.poses import sample_toy_natural_poses

    theta, _ = sample_toy_natural_poses(1, seed, families=("gallop",))
    rng = np.random.default_rng(seed)
    return theta[0] + rng.normal(0.0, 0.15, size=theta[0].shape)  # every joint rotated, about all three axes


@pytest.fixture(scope="module")
def toy_glb(tmp_path_factory, toy_rig) -> Path:
    from bat3r_core.rig_io import save_rig_glb

    return save_rig_glb(toy_rig, tmp_path_factory.mktemp("asset") / "toy.glb")


# ------------------------------------------------------------------------------------------------ jobs schema
def test_job_table_round_trip(tmp_path, toy_rig):
    theta = _nontrivial_theta(toy_rig)
    jobs = [_job(toy_rig, f"s{i}", theta, 16, texture_id=i, envmap_id=i - 1, envmap_rotation=0.5 * i, seed=10 + i)
            for i in range(3)]
    path = write_jobs(jobs, tmp_path / "jobs.parquet")
    back = read_jobs(path)
    assert [j.sample_id for j in back] == ["s0", "s1", "s2"]
    for a, b in zip(jobs, back):
        assert job_to_dict(a) == job_to_dict(b)
        assert b.camera.allclose(a.camera)
    table = jobs_to_table(jobs)
    assert table.column_names[:4] == ["sample_id", "source_id", "view_kind", "view_type"]
    assert table.schema.field("excess_rotations").type == pa.list_(pa.float64())
    assert table.schema.field("width").type == pa.int32() and table.schema.field("seed").type == pa.int64()


def test_job_table_errors_name_the_column(toy_rig):
    job = _job(toy_rig, "a", np.zeros((toy_rig.num_joints, 3)), 16)
    table = jobs_to_table([job])
    with pytest.raises(JobSchemaError, match="lacks column.*'envmap_id'"):
        jobs_from_table(table.drop_columns(["envmap_id"]))
    with pytest.raises(JobSchemaError, match="column 'seed' must have type int64, got string"):
        jobs_from_table(table.set_column(table.schema.get_field_index("seed"), "seed", pa.array(["x"])))
    row = job_to_dict(job)
    row["camera_rotation"] = [1.0, 0.0]
    with pytest.raises(JobSchemaError, match="row 0 \\('a'\\): column 'camera_rotation' must hold 9 numbers, got 2"):
        jobs_from_table(pa.Table.from_pylist([row]))
    with pytest.raises(JobSchemaError, match="column 'sample_id' must be unique"):
        jobs_to_table([job, job])
    row = job_to_dict(job)
    row["view_kind"] = "sideways"
    with pytest.raises(JobSchemaError, match="column 'view_kind' must be one of"):
        job_from_dict(row)
    row = job_to_dict(job)
    row["excess_rotations"] = [0.0] * 7
    with pytest.raises(JobSchemaError, match="'excess_rotations' must hold J\\*3 numbers, got 7"):
        job_from_dict(row)


def test_job_problems_are_reported_not_raised(toy_rig):
    job = _job(toy_rig, "a", np.zeros((toy_rig.num_joints, 3)), 16)
    assert job.problems(toy_rig.num_joints) == []
    row = job_to_dict(job)
    row["fx"] = float("nan")
    row["excess_rotations"][5] = float("nan")
    bad = job_from_dict(row)
    problems = bad.problems(toy_rig.num_joints)
    assert bad.camera is None
    assert any("NaN" in p for p in problems) and any("invalid camera" in p and "fx" in p for p in problems)
    assert "excess_rotations has 27 joints, the rig has 26" in job.problems(26)[0]


def test_render_config_from_mappings_and_the_catalog_only():
    assert render_config(None) == RenderConfig() and (RenderConfig().resolution, RenderConfig().samples) == (128, 16)
    cfg = render_config({"samples": 3, "denoise": True})
    assert (cfg.resolution, cfg.samples, cfg.denoise) == (128, 3, True)
    assert render_config({"resolution": 48}).resolution == 48
    with pytest.raises(ConfigError, match="render: unknown key\\(s\\) \\['sampels'\\]"):
        render_config({"sampels": 3})
    with pytest.raises(ConfigError, match=r"not named in code; got 'paper'.*render_config\('paper'\)"):
        render_config("paper")
    # named settings are the catalog's run presets, with the run's image size and the catalog's K
    from bat3r_core.catalog import load_catalog

    catalog = load_catalog(Path(__file__).resolve().parents[2] / "data_catalog.yaml")
    paper = catalog.render_config("paper")
    assert (paper.resolution, paper.samples, paper.denoise, paper.num_layers) == (160, 64, True, catalog.layers)
    with pytest.raises(ValueError, match="RenderConfig.device must be one of"):
        RenderConfig(device="TPU")
    with pytest.raises(ValueError, match="RenderConfig.samples must be >= 1, got 0"):
        RenderConfig(samples=0)


def test_render_shard_rejects_bad_inputs(tmp_path, toy_rig, toy_glb):
    job16 = _job(toy_rig, "a", np.zeros((toy_rig.num_joints, 3)), 16)
    job32 = _job(toy_rig, "b", np.zeros((toy_rig.num_joints, 3)), 32)
    from bat3r_core.render.runner import render_shard

    with pytest.raises(ValueError, match="share one image size"):
        render_shard([job16, job32], SceneAssets(str(toy_glb)), tmp_path)
    with pytest.raises(ValueError, match="jobs must not be empty"):
        render_shard([], SceneAssets(str(toy_glb)), tmp_path)
    with pytest.raises(TypeError, match="jobs must be RenderJob objects, got dict"):
        render_shard([job_to_dict(job16)], SceneAssets(str(toy_glb)), tmp_path)


# ------------------------------------------------------------------------------------------------ rendering
@pytest.fixture(scope="module")
def mixed_shard(tmp_path_factory, toy_rig, toy_glb):
    """One 32x32 shard mixing good jobs (articulated, with a similarity, image texture, HDR env map) and bad ones."""
    import cv2

    from bat3r_core.render.runner import render_shard

    d = tmp_path_factory.mktemp("mixed")
    good_png = d / "coat.png"
    cv2.imwrite(str(good_png), np.full((16, 16, 3), (40, 200, 230), np.uint8))  # BGR: a yellow coat
    corrupt = d / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\nthis is not an image")
    red_env = d / "red.hdr"
    env = np.full((16, 32, 3), 0.45, np.float32)
    env[..., 2] = 0.9  # BGR: a reddish light everywhere
    cv2.imwrite(str(red_env), env)
    assets = SceneAssets(asset=str(toy_glb), textures=("toy:bay", str(good_png), str(corrupt)),
                         envmaps=(str(red_env),))
    theta = _nontrivial_theta(toy_rig)
    rot = Rotation.from_rotvec([0.4, -0.9, 0.3]).as_matrix()
    sim = dict(scale=0.7, rotation=rot, translation=np.array([0.3, -0.2, 1.5]))
    nan_theta = theta.copy()
    nan_theta[3, 1] = np.nan
    nan_camera = job_to_dict(_job(toy_rig, "nan_camera", theta, 32, **sim))
    nan_camera["cx"] = float("nan")
    jobs = [
        _job(toy_rig, "good_sky", theta, 32, **sim, seed=1),
        dataclasses.replace(_job(toy_rig, "nan_pose", theta, 32, **sim), excess_rotations=nan_theta),
        _job(toy_rig, "bad_texture", theta, 32, texture_id=2),
        job_from_dict(nan_camera),
        _job(toy_rig, "good_envmap", theta, 32, azimuth=100.0, texture_id=1, envmap_id=0, envmap_rotation=1.0),
        _job(toy_rig, "missing_envmap", theta, 32, envmap_id=3),
    ]
    result = render_shard(jobs, assets, d / "out", 0, TINY, rig=toy_rig, debug_vertices=True,
                          progress=_PROGRESS.append, progress_interval_s=0.0)
    table, arrays = read_shard(d / "out", 0)
    return jobs, result, table, arrays


_PROGRESS: list[dict] = []  # the mixed shard's progress reports


@pytest.mark.blender
def test_a_shard_reports_images_done_as_they_finish(mixed_shard):
    jobs = mixed_shard[0]
    done = [p["done"] for p in _PROGRESS]
    assert done and done == sorted(set(done)) and done[-1] == len(jobs)  # every job answered, good or bad
    assert all(p["total"] == len(jobs) and p["images_per_s"] > 0 for p in _PROGRESS)
    assert _PROGRESS[-1]["shard"].endswith("part-00000")


@pytest.mark.blender
def test_blender_pose_matches_skinning(mixed_shard, toy_rig):
    jobs, _, table, arrays = mixed_shard
    status = table.column("status").to_pylist()
    for i in (0, 4):
        assert status[i] == "ok"
        j = jobs[i]
        expected = _posed(toy_rig, j.excess_rotations, j.global_scale, j.global_rotation, j.global_translation)
        err = np.linalg.norm(arrays["blender_vertices"][i] - expected, axis=1)
        assert err.max() < 1e-3, f"job {j.sample_id}: Blender's posed mesh differs by up to {err.max() * 1e3:.3f} mm"
        # the pose is far from the rest pose, so agreement is not trivial
        assert np.linalg.norm(expected - toy_rig.rest_vertices, axis=1).max() > 0.5


@pytest.mark.blender
def test_bad_jobs_recorded_while_the_shard_completes(mixed_shard):
    jobs, result, table, arrays = mixed_shard
    status = dict(zip(table.column("sample_id").to_pylist(), table.column("status").to_pylist()))
    reason = dict(zip(table.column("sample_id").to_pylist(), table.column("reason").to_pylist()))
    assert status == {"good_sky": "ok", "nan_pose": "bad_job", "bad_texture": "bad_texture",
                      "nan_camera": "bad_job", "good_envmap": "ok", "missing_envmap": "bad_envmap"}
    assert "NaN" in reason["nan_pose"] and "cx" in reason["nan_camera"]
    assert "corrupt.png" in reason["bad_texture"] and "out of range" in reason["missing_envmap"]
    assert result.num_ok == 2 and result.num_failed == 4 and result.crashes == 0
    assert arrays["rgb"].shape == (6, 32, 32, 3) and arrays["P"].shape == (6, 32, 32, 4, 3)
    for i, sid in enumerate(table.column("sample_id").to_pylist()):
        if status[sid] != "ok":
            assert not arrays["rgb"][i].any() and not arrays["occupancy"][i].any()
        else:
            assert arrays["mask"][i].sum() > 30 and arrays["rgb"][i].std() > 5
            np.testing.assert_allclose(arrays["K_intrinsics"][i], jobs[i].camera.K, rtol=1e-6)


@pytest.mark.blender
def test_envmap_and_image_texture_are_used(mixed_shard):
    _, _, table, arrays = mixed_shard
    i = table.column("sample_id").to_pylist().index("good_envmap")
    rgb = arrays["rgb"][i].astype(float)
    bg = rgb[~arrays["mask"][i]].mean(0)
    assert bg[0] > bg[1] + 40 and abs(bg[1] - bg[2]) < 10, f"background should be the reddish env map, got {bg}"
    fg = rgb[arrays["mask"][i]].mean(0)
    assert fg[1] > fg[2] + 30, f"the yellow coat (green > blue) should show, got {fg}"


@pytest.mark.blender
def test_blender_mask_matches_ray_cast_occupancy_at_128(tmp_path, toy_rig, toy_glb):
    from bat3r_core.pointmaps import dual_point_maps
    from bat3r_core.render.runner import render_shard

    theta = _nontrivial_theta(toy_rig, seed=3)
    rot = Rotation.from_rotvec([0.0, 2.2, 0.0]).as_matrix()
    jobs = [_job(toy_rig, "a", theta, 128, azimuth=-75.0, rotation=rot, seed=3),
            _job(toy_rig, "b", theta, 128, azimuth=160.0, scale=1.3, translation=np.array([2.0, 0.0, -1.0]))]
    render_shard(jobs, SceneAssets(str(toy_glb)), tmp_path, 0, RenderConfig(resolution=128, samples=2), rig=toy_rig)
    table, arrays = read_shard(tmp_path, 0)
    assert table.column("status").to_pylist() == ["ok", "ok"]
    for i, job in enumerate(jobs):
        # an independent ray cast of the same skinned mesh
        maps = dual_point_maps(_posed(toy_rig, job.excess_rotations, job.global_scale, job.global_rotation,
                                      job.global_translation), toy_rig.rest_vertices, toy_rig.faces, job.camera)
        blender, occ = arrays["mask"][i], maps.mask
        iou = (blender & occ).sum() / (blender | occ).sum()
        assert occ.sum() > 1500, "the animal should fill a good part of the image"
        assert iou >= 0.98, f"job {job.sample_id}: IoU {iou:.4f}"
        np.testing.assert_array_equal(arrays["occupancy"][i], maps.occupancy)
        assert table.column("mask_iou").to_pylist()[i] == pytest.approx(iou)


@pytest.mark.blender
def test_same_seed_same_image(tmp_path, toy_rig, toy_glb):
    from bat3r_core.render.runner import render_shard

    theta = _nontrivial_theta(toy_rig, seed=5)
    a = _job(toy_rig, "a", theta, 32, seed=7)
    b = _job(toy_rig, "b", theta, 32, seed=7)
    c = _job(toy_rig, "c", theta, 32, seed=8)
    cfg = RenderConfig(resolution=32, samples=4)
    render_shard([a, c, b], SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig)
    render_shard([a], SceneAssets(str(toy_glb)), tmp_path, 1, cfg, rig=toy_rig)  # another process
    _, one = read_shard(tmp_path, 0)
    _, two = read_shard(tmp_path, 1)
    np.testing.assert_array_equal(one["rgb"][0], one["rgb"][2])
    np.testing.assert_array_equal(one["rgb"][0], two["rgb"][0])
    assert np.abs(one["rgb"][0].astype(int) - one["rgb"][1].astype(int)).max() > 10, "another seed, other noise"
    # the same shard rendered again, seconds later, is the same bytes: the cache keys downstream of it hold
    render_shard([a, c, b], SceneAssets(str(toy_glb)), tmp_path / "again", 0, cfg, rig=toy_rig)
    first, again = shard_paths(tmp_path, 0), shard_paths(tmp_path / "again", 0)
    assert first.npz.read_bytes() == again.npz.read_bytes()
    assert first.parquet.read_bytes() == again.parquet.read_bytes()


@pytest.mark.blender
def test_killed_worker_is_retried_and_processes_recycled(tmp_path, toy_rig, toy_glb):
    from bat3r_core.render.runner import render_shard

    theta = np.zeros((toy_rig.num_joints, 3))
    jobs = [_job(toy_rig, f"s{i}", theta, 32, azimuth=-170.0 + 50 * i, seed=i) for i in range(6)]
    started: list[subprocess.Popen] = []
    killed = threading.Event()

    def kill_after_two(proc: subprocess.Popen) -> None:
        started.append(proc)
        if len(started) != 1:
            return
        results = tmp_path / ".work-part-00000" / "results.jsonl"

        def watch():
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and proc.poll() is None:
                if results.is_file() and len(results.read_text().splitlines()) >= 2:
                    os.kill(proc.pid, signal.SIGKILL)
                    killed.set()
                    return
                time.sleep(0.01)

        threading.Thread(target=watch, daemon=True).start()

    cfg = RenderConfig(resolution=32, samples=1, recycle_every=4, retries=2)
    result = render_shard(jobs, SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig,
                          on_worker_start=kill_after_two)
    assert killed.is_set()
    table, arrays = read_shard(tmp_path, 0)
    assert table.column("status").to_pylist() == ["ok"] * 6
    assert result.crashes == 1
    # killed after 2 of its 4 jobs; the retry takes the next 4 (2 left of the batch + 2 more) in one process
    assert result.processes == 2 and len(started) == 2
    assert all(arrays["mask"][i].sum() > 20 for i in range(6))
    assert not (tmp_path / ".work-part-00000").exists()


@pytest.mark.blender
def test_a_stop_request_kills_the_blender_worker_and_writes_no_shard(tmp_path, toy_rig, toy_glb):
    """A stopped run (``bat3r_core.stopping``) does not wait for the shard's remaining images: the worker is killed
    within its poll interval, no shard (and no failed row) is written, and the same shard renders on a rerun."""
    from bat3r_core.render.runner import render_shard
    from bat3r_core.stopping import StopRequested, clear_stop_request, request_stop

    theta = np.zeros((toy_rig.num_joints, 3))
    jobs = [_job(toy_rig, f"s{i}", theta, 32, azimuth=-170.0 + 40 * i, seed=i) for i in range(8)]
    started: list[subprocess.Popen] = []

    def stop_after_the_first_image(report: dict) -> None:
        if report["done"] >= 1:
            request_stop("the test")

    cfg = RenderConfig(resolution=32, samples=1)
    try:
        with pytest.raises(StopRequested, match=r"rendering .* images done\): stopped \(the test\)") as stop:
            render_shard(jobs, SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig,
                         on_worker_start=started.append, progress=stop_after_the_first_image, progress_interval_s=0)
    finally:
        clear_stop_request()
    done = int(re.search(r"\((\d+) of 8 images done\)", str(stop.value)).group(1))
    assert 1 <= done < 8
    assert len(started) == 1 and started[0].poll() is not None  # killed, not left running
    assert not list(tmp_path.glob("part-*"))
    render_shard(jobs, SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig)
    table, _ = read_shard(tmp_path, 0)
    assert table.column("status").to_pylist() == ["ok"] * 8


@pytest.mark.blender
def test_worker_that_cannot_start_fails_the_shard_after_retries(tmp_path, toy_rig, toy_glb):
    from bat3r_core.render.runner import render_shard

    job = _job(toy_rig, "a", np.zeros((toy_rig.num_joints, 3)), 16)
    if sys.platform == "darwin":
        pytest.skip("Metal devices exist on macOS")
    cfg = RenderConfig(resolution=16, samples=1, device="METAL", retries=1)  # never available on Linux/Windows
    result = render_shard([job], SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig)
    table, _ = read_shard(tmp_path, 0)
    assert table.column("status").to_pylist() == ["failed"]
    reason = table.column("reason")[0].as_py()
    assert "METAL" in reason and "before its scene was ready" in reason
    assert result.processes == 2 and result.crashes == 2


@pytest.mark.blender
def test_render_command_renders_a_job_file(tmp_path, toy_rig, toy_glb):
    from bat3r_core.render.runner import render_command

    theta = _nontrivial_theta(toy_rig, 4)
    jobs = [_job(toy_rig, f"s{i}", theta, 24, azimuth=30.0 + 90 * i, texture_id=i, seed=i) for i in range(2)]
    write_jobs(jobs, tmp_path / "jobs.parquet")
    # without textures only texture_id 0 (the asset's own) exists: job s1 is refused
    own = render_command(tmp_path / "jobs.parquet", toy_glb, tmp_path / "own", config=TINY)
    assert own.num_ok == 1 and read_shard(tmp_path / "own", 0)[0].column("status").to_pylist() == ["ok", "bad_texture"]
    result = render_command(tmp_path / "jobs.parquet", toy_glb, tmp_path / "out", config=TINY,
                            textures=["toy:bay", "toy:grey"])
    assert result.parquet == tmp_path / "out" / "part-00000.parquet" and result.num_ok == 2
    table, arrays = read_shard(tmp_path / "out", 0)
    assert table.column("sample_id").to_pylist() == ["s0", "s1"]
    assert arrays["rgb"].shape == (2, 24, 24, 3) and arrays["mask"].any(axis=(1, 2)).all()
    with pytest.raises(FileNotFoundError, match="render-job file .*missing.parquet does not exist"):
        render_command(tmp_path / "missing.parquet", toy_glb, tmp_path / "out")


@pytest.mark.blender
def test_hanging_worker_is_killed_and_its_job_failed(tmp_path, toy_rig, toy_glb):
    from bat3r_core.render.runner import render_shard

    jobs = [_job(toy_rig, f"s{i}", np.zeros((toy_rig.num_joints, 3)), 96, seed=i) for i in range(2)]
    # one image takes far longer than the timeout: each worker is killed during its first job
    cfg = RenderConfig(resolution=96, samples=256, timeout_s=0.2, retries=3)
    result = render_shard(jobs, SceneAssets(str(toy_glb)), tmp_path, 0, cfg, rig=toy_rig)
    table, _ = read_shard(tmp_path, 0)
    assert table.column("status").to_pylist() == ["failed", "failed"]
    reasons = table.column("reason").to_pylist()
    assert "crashed twice on this job (killed after no progress" in reasons[0]
    assert "crashed twice on this job" in reasons[1]
    assert result.crashes == 4 and result.processes == 4


@pytest.mark.blender
@pytest.mark.parametrize("fmt", [".blend", ".fbx"])
def test_blend_and_fbx_convert_round_trip(tmp_path, toy_rig, toy_glb, fmt):
    from bat3r_core.rig_io import load_rig
    from scipy.spatial import cKDTree

    export = {".blend": "bpy.ops.wm.save_as_mainfile(filepath=sys.argv[2])",
              ".fbx": "bpy.ops.export_scene.fbx(filepath=sys.argv[2], add_leaf_bones=False)"}[fmt]
    script = textwrap.dedent(f"""
        import sys, bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.import_scene.gltf(filepath=sys.argv[1])
        {export}
    """)
    target = tmp_path / f"toy{fmt}"
    proc = subprocess.run([sys.executable, "-c", script, str(toy_glb), str(target)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rig = load_rig(target)  # converted by `python -m bat3r_core.render.blender_convert`
    assert sorted(rig.joint_names) == sorted(toy_rig.joint_names)
    perm = [rig.joint_names.index(n) for n in toy_rig.joint_names]
    np.testing.assert_allclose(rig.rest_joint_positions[perm], toy_rig.rest_joint_positions, atol=1e-5)
    parent_names = [rig.joint_names[rig.parents[k]] if rig.parents[k] >= 0 else None for k in perm]
    assert parent_names == [toy_rig.joint_names[p] if p >= 0 else None for p in toy_rig.parents]
    assert rig.num_vertices == toy_rig.num_vertices and len(rig.faces) == len(toy_rig.faces)
    dist, idx = cKDTree(rig.rest_vertices).query(toy_rig.rest_vertices)
    assert dist.max() < 1e-5
    np.testing.assert_allclose(rig.skin_weights[idx][:, perm], toy_rig.skin_weights, atol=1e-4)
    # the converted rig poses like the original (the toy's joint frames are axis-aligned in both)
    np.testing.assert_allclose(rig.rest_transforms[perm], toy_rig.rest_transforms, atol=1e-5)
    theta = _nontrivial_theta(toy_rig, 2)
    a = _posed(toy_rig, theta)
    theta_b = np.zeros((rig.num_joints, 3))
    theta_b[perm] = theta
    b = _posed(rig, theta_b)
    assert np.abs(b[idx] - a).max() < 1e-4


@pytest.mark.blender
def test_blender_convert_rejects_a_mesh_without_armature(tmp_path):
    script = "import sys, bpy; bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])"  # the default cube scene
    target = tmp_path / "cube.blend"
    subprocess.run([sys.executable, "-c", script, str(target)], check=True, capture_output=True, timeout=300)
    proc = subprocess.run([sys.executable, "-m", "bat3r_core.render.blender_convert", str(target),
                           str(tmp_path / "cube.glb")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert "no armature" in proc.stderr
