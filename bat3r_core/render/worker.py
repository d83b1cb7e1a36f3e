"""The Blender render worker: the only bat3r module that imports ``bpy``.

Run in its own process, one per shard (or per ``recycle_every`` images), by :mod:`bat3r_core.render.runner`::

    python -m bat3r_core.render.worker --spec SPEC.json --results RESULTS.jsonl --out WORKDIR < JOBS.jsonl

``SPEC.json`` holds the :class:`~bat3r_core.render.config.SceneAssets` (``asset``, ``textures``, ``envmaps``), the
:class:`~bat3r_core.render.config.RenderConfig` (``config``) and ``debug_vertices``. Jobs arrive on stdin, one JSON
object per line (the columns of :mod:`bat3r_core.render.jobs` plus ``index``). For each job the worker writes
``WORKDIR/ready-<pid>`` once the scene is set up, then ``WORKDIR/job-<index>.npz`` (``rgb (H, W, 3) uint8``, ``mask (H, W) bool`` from the Object Index pass, and with
``debug_vertices`` the depsgraph-evaluated ``posed_vertices (V, 3)`` in bat3r's world frame and rig vertex order),
then appends one JSON line ``{"index", "sample_id", "status", "reason", "seconds", "cpu_seconds"}`` to
``RESULTS.jsonl`` (wall and process CPU time of the job). A job
that cannot render (bad texture or environment file, NaN pose or camera) gets a non-``ok`` status and the worker
goes on with the next one.

Geometry. The worker never poses an armature: it builds the mesh from the rig's own arrays (the file's vertices,
triangles and UVs, as :func:`bat3r_core.rig_io.load_rig` reads them) and, for each job, writes into it the posed
vertices that the runner computed with :mod:`bat3r_core.skinning` for that job (``vertices_file``, an ``.npy`` of
``(V, 3)`` float32 in bat3r's world frame). Blender therefore renders exactly the mesh that is ray-cast for the
labels, whatever the asset's animations, node pose, bone orientations or morph targets: agreement by construction.
The mesh object carries ``W = GLTF_TO_BLENDER_WORLD`` (``(x, y, z) -> (x, -z, y)``), bat3r's Y-up world in
Blender's Z-up one; cameras come from :func:`bat3r_core.cameras.to_blender` with ``world_rotation = W``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

try:
    import bpy
    from mathutils import Matrix
except ImportError as e:  # pragma: no cover - depends on the environment
    raise ImportError("the render worker needs Blender's Python module: pip install bpy==5.0.1 "
                      "(Python 3.11, numpy<2)") from e

from bat3r_core.cameras import GLTF_TO_BLENDER_WORLD, PinholeCamera, to_blender
from bat3r_core.render.config import RenderConfig, SceneAssets
from bat3r_core.render.jobs import job_from_dict

MESH_PASS_INDEX = 1
_COLOUR_ATTRIBUTE = "bat3r_vertex_colour"
_W4 = np.eye(4)
_W4[:3, :3] = GLTF_TO_BLENDER_WORLD


def _log(msg: str) -> None:
    print(f"[bat3r-worker {os.getpid()}] {msg}", file=sys.stderr, flush=True)


class JobError(Exception):
    """A job that cannot be rendered: ``status`` is the short code recorded in its row."""

    def __init__(self, status: str, reason: str):
        super().__init__(reason)
        self.status = status
        self.reason = reason


class BlenderRenderer:
    """A Blender scene with one rigged asset, set up once and re-posed, re-textured and re-lit per job."""

    def __init__(self, assets: SceneAssets, config: RenderConfig, workdir: Path, debug_vertices: bool = False):
        from bat3r_core.rig_io import read_any_asset

        self.assets = assets
        self.config = config
        self.workdir = Path(workdir)
        self.debug_vertices = debug_vertices
        self.rig, info = read_any_asset(assets.asset)
        # the asset's own look, read once: its base colour, which its COLOR_0 multiplies (glTF); a category's own
        # textures replace both
        own_look = not assets.textures
        self.own_texture = info.texture if own_look else None
        self.vertex_colors = info.vertex_colors if own_look else None
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self._build_mesh()
        self._setup_render()
        self._setup_material()
        self._setup_worlds()
        self._setup_compositor()
        self._images: dict[int, object] = {}
        self._envmaps: dict[int, object] = {}

    # ------------------------------------------------------------------------------------------------ setup
    def _build_mesh(self) -> None:
        """The rig's mesh as a Blender object (file vertices, triangles and UVs; no armature)."""
        rig = self.rig
        me = bpy.data.meshes.new("bat3r_mesh")
        me.from_pydata(rig.rest_vertices.tolist(), [], rig.faces.tolist())
        if rig.uvs is not None:
            layer = me.uv_layers.new(name="UVMap")
            loop_vertices = np.empty(len(me.loops), dtype=np.int64)
            me.loops.foreach_get("vertex_index", loop_vertices)
            layer.data.foreach_set("uv", rig.uvs[loop_vertices].astype(np.float32).ravel())
        if self.vertex_colors is not None:
            colour = me.color_attributes.new(name=_COLOUR_ATTRIBUTE, type="FLOAT_COLOR", domain="POINT")
            rgba = np.c_[self.vertex_colors, np.ones(len(self.vertex_colors))].astype(np.float32)
            colour.data.foreach_set("color", rgba.ravel())  # linear, as COLOR_0 is
        me.polygons.foreach_set("use_smooth", np.ones(len(me.polygons), dtype=bool))
        me.update()
        self.mesh = bpy.data.objects.new("bat3r_mesh", me)
        self.scene.collection.objects.link(self.mesh)
        self.mesh.matrix_world = Matrix(_W4.tolist())
        self.mesh.pass_index = MESH_PASS_INDEX
        if len(me.vertices) != rig.num_vertices:
            raise RuntimeError(f"{self.assets.asset}: Blender's mesh has {len(me.vertices)} vertices, the rig "
                               f"{rig.num_vertices}")

    def _set_vertices(self, vertices: np.ndarray) -> None:
        """Write posed vertices (V, 3), bat3r world frame, into the mesh."""
        me = self.mesh.data
        me.vertices.foreach_set("co", np.ascontiguousarray(vertices, dtype=np.float32).ravel())
        me.update()

    @staticmethod
    def _to_bat3r(local: np.ndarray, matrix_world: np.ndarray) -> np.ndarray:
        """(V, 3) object-local coordinates -> bat3r world frame (undo the Y-up -> Z-up change)."""
        m = np.linalg.inv(_W4) @ matrix_world
        return local @ m[:3, :3].T + m[:3, 3]

    def _setup_render(self) -> None:
        cfg, s = self.config, self.scene
        s.render.engine = "CYCLES"
        s.render.use_persistent_data = True
        s.render.film_transparent = False
        s.render.resolution_percentage = 100
        s.render.image_settings.file_format = "PNG"
        s.cycles.samples = cfg.samples
        s.cycles.use_denoising = cfg.denoise
        s.cycles.use_adaptive_sampling = False
        s.cycles.filter_width = cfg.filter_width
        s.cycles.max_bounces = cfg.max_bounces
        s.cycles.diffuse_bounces = min(cfg.max_bounces, 2)
        s.cycles.glossy_bounces = min(cfg.max_bounces, 2)
        s.cycles.transmission_bounces = 0
        s.cycles.volume_bounces = 0
        s.cycles.transparent_max_bounces = 2
        s.view_settings.view_transform = cfg.view_transform
        s.view_settings.exposure = cfg.exposure
        if cfg.threads > 0:
            s.render.threads_mode = "FIXED"
            s.render.threads = cfg.threads
        s.cycles.device = "CPU"
        if cfg.device != "CPU":
            self._enable_gpu(cfg.device)
        s.view_layers[0].use_pass_object_index = True
        cam_data = bpy.data.cameras.new("bat3r_camera")
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.clip_start = 0.01
        cam_data.clip_end = 10000.0
        self.camera = bpy.data.objects.new("bat3r_camera", cam_data)
        s.collection.objects.link(self.camera)
        s.camera = self.camera

    def _enable_gpu(self, backend: str) -> None:
        prefs = bpy.context.preferences.addons["cycles"].preferences
        prefs.compute_device_type = backend
        prefs.get_devices()
        gpus = [d for d in prefs.devices if d.type == backend]
        if not gpus:
            raise RuntimeError(f"RenderConfig.device={backend} but Blender sees no {backend} device "
                               f"(CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES')!r})")
        for d in prefs.devices:
            d.use = False
        gpus[0].use = True  # the first visible device: the runner pins one GPU per process
        self.scene.cycles.device = "GPU"
        _log(f"rendering on {backend} device {gpus[0].name}")

    def _setup_material(self) -> None:
        mat = bpy.data.materials.new("bat3r_coat")
        nt = mat.node_tree
        bsdf = next(n for n in nt.nodes if n.type == "BSDF_PRINCIPLED")
        bsdf.inputs["Roughness"].default_value = 0.75
        self.tex_node = nt.nodes.new("ShaderNodeTexImage")
        self.tex_node.interpolation = "Linear"
        if not self.mesh.data.uv_layers:  # no UVs: project the texture with the generated coordinates
            coords = nt.nodes.new("ShaderNodeTexCoord")
            nt.links.new(coords.outputs["Generated"], self.tex_node.inputs["Vector"])
        base = self.tex_node.outputs["Color"]
        if self.vertex_colors is not None:
            attribute = nt.nodes.new("ShaderNodeVertexColor")
            attribute.layer_name = _COLOUR_ATTRIBUTE
            mix = nt.nodes.new("ShaderNodeMix")
            mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
            mix.inputs["Factor"].default_value = 1.0
            nt.links.new(base, mix.inputs["A"])
            nt.links.new(attribute.outputs["Color"], mix.inputs["B"])
            base = mix.outputs["Result"]
        nt.links.new(base, bsdf.inputs["Base Color"])
        self.mesh.data.materials.clear()
        self.mesh.data.materials.append(mat)
        for poly in self.mesh.data.polygons:
            poly.use_smooth = True

    def _setup_worlds(self) -> None:
        # procedural sky: an analytic (Hosek-Wilkie) sky above the horizon, a seeded grass-and-earth ground below
        # it, and a sun lamp; all three are cheap to change per image (a physical multiple-scattering sky would
        # recompute its table and the world's importance map every image, ~1 s)
        sky = bpy.data.worlds.new("bat3r_sky")
        sky.cycles.sample_map_resolution = 256
        nt = sky.node_tree
        nt.nodes.clear()
        coord = nt.nodes.new("ShaderNodeTexCoord")
        self.sky_tex = nt.nodes.new("ShaderNodeTexSky")
        self.sky_tex.sky_type = "HOSEK_WILKIE"
        sep = nt.nodes.new("ShaderNodeSeparateXYZ")
        noise = nt.nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 6.0
        noise.inputs["Detail"].default_value = 8.0
        self.ground_ramp = nt.nodes.new("ShaderNodeValToRGB")
        horizon = nt.nodes.new("ShaderNodeMapRange")  # 1 above the horizon, 0 below, soft blend
        horizon.inputs["From Min"].default_value = -0.02
        horizon.inputs["From Max"].default_value = 0.02
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        self.sky_bg = nt.nodes.new("ShaderNodeBackground")
        out = nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(coord.outputs["Generated"], sep.inputs["Vector"])
        nt.links.new(coord.outputs["Generated"], noise.inputs["Vector"])
        nt.links.new(noise.outputs["Fac"], self.ground_ramp.inputs["Fac"])
        nt.links.new(sep.outputs["Z"], horizon.inputs["Value"])
        nt.links.new(horizon.outputs["Result"], mix.inputs["Factor"])
        # aerial perspective: the ground fades into a haze colour towards the horizon
        distance = nt.nodes.new("ShaderNodeMapRange")  # 0 looking straight down, 1 at the horizon
        distance.inputs["From Min"].default_value = -0.15
        distance.inputs["From Max"].default_value = 0.0
        distance.inputs["To Max"].default_value = 0.8
        self.haze_mix = nt.nodes.new("ShaderNodeMix")
        self.haze_mix.data_type = "RGBA"
        nt.links.new(sep.outputs["Z"], distance.inputs["Value"])
        nt.links.new(distance.outputs["Result"], self.haze_mix.inputs["Factor"])
        nt.links.new(self.ground_ramp.outputs["Color"], self.haze_mix.inputs["A"])
        nt.links.new(self.haze_mix.outputs["Result"], mix.inputs["A"])
        nt.links.new(self.sky_tex.outputs["Color"], mix.inputs["B"])
        nt.links.new(mix.outputs["Result"], self.sky_bg.inputs["Color"])
        nt.links.new(self.sky_bg.outputs["Background"], out.inputs["Surface"])
        self.sky_world = sky
        sun_data = bpy.data.lights.new("bat3r_sun", "SUN")
        sun_data.angle = math.radians(2.0)
        self.sun = bpy.data.objects.new("bat3r_sun", sun_data)
        self.scene.collection.objects.link(self.sun)
        # environment map world: an equirectangular image, rotated about the up axis
        env = bpy.data.worlds.new("bat3r_envmap")
        nt = env.node_tree
        nt.nodes.clear()
        coord = nt.nodes.new("ShaderNodeTexCoord")
        self.env_mapping = nt.nodes.new("ShaderNodeMapping")
        self.env_tex = nt.nodes.new("ShaderNodeTexEnvironment")
        bg = nt.nodes.new("ShaderNodeBackground")
        out = nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(coord.outputs["Generated"], self.env_mapping.inputs["Vector"])
        nt.links.new(self.env_mapping.outputs["Vector"], self.env_tex.inputs["Vector"])
        nt.links.new(self.env_tex.outputs["Color"], bg.inputs["Color"])
        nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
        self.env_world = env
        self.scene.world = sky

    def _setup_compositor(self) -> None:
        tree = bpy.data.node_groups.new("bat3r_compositor", "CompositorNodeTree")
        self.scene.compositing_node_group = tree
        rl = tree.nodes.new("CompositorNodeRLayers")
        idmask = tree.nodes.new("CompositorNodeIDMask")
        idmask.inputs["Index"].default_value = MESH_PASS_INDEX
        idmask.inputs["Anti-Alias"].default_value = False
        self.rgb_out = tree.nodes.new("CompositorNodeOutputFile")
        self.rgb_out.format.media_type = "IMAGE"  # bpy 5.0: the media type comes before the file format
        self.rgb_out.format.file_format = "PNG"
        self.rgb_out.format.color_mode = "RGB"
        self.rgb_out.format.compression = 0  # written and read back at once: speed over size
        self.rgb_out.save_as_render = True
        self.rgb_out.file_output_items.new("RGBA", "rgb")
        self.mask_out = tree.nodes.new("CompositorNodeOutputFile")
        self.mask_out.format.media_type = "IMAGE"
        self.mask_out.format.file_format = "PNG"
        self.mask_out.format.color_mode = "BW"
        self.mask_out.format.compression = 0
        self.mask_out.save_as_render = False
        self.mask_out.file_output_items.new("FLOAT", "mask")
        tree.links.new(rl.outputs["Image"], self.rgb_out.inputs[0])
        tree.links.new(rl.outputs["Object Index"], idmask.inputs["ID value"])
        tree.links.new(idmask.outputs[0], self.mask_out.inputs[0])
        for node in (self.rgb_out, self.mask_out):
            node.directory = str(self.workdir / "_frame")
            node.file_name = ""

    # ------------------------------------------------------------------------------------------------ per job
    def _posed_vertices(self, row: dict) -> np.ndarray:
        """The job's posed vertices (V, 3) as bat3r's skinning computed them (the runner's ``vertices_file``)."""
        path = row.get("vertices_file")
        if not path:
            raise JobError("bad_job", "the job has no vertices_file (the runner writes the posed vertices)")
        v = np.load(path, allow_pickle=False)
        if v.shape != (self.rig.num_vertices, 3) or not np.isfinite(v).all():
            raise JobError("bad_job", f"{path}: expected finite posed vertices of shape ({self.rig.num_vertices}, 3), "
                                      f"got {v.shape}")
        return v

    @staticmethod
    def _image_from_array(name: str, rgb: np.ndarray):
        img = bpy.data.images.new(name, rgb.shape[1], rgb.shape[0])
        rgba = np.ones((rgb.shape[0], rgb.shape[1], 4), dtype=np.float32)
        rgba[..., :3] = rgb[::-1] / 255.0  # Blender stores rows bottom-up
        img.pixels.foreach_set(rgba.ravel())
        img.pack()
        return img

    def _texture(self, texture_id: int):
        if texture_id in self._images:
            return self._images[texture_id]
        if texture_id >= self.assets.num_textures:
            raise JobError("bad_texture", f"texture_id {texture_id} is out of range: the category has "
                                          f"{self.assets.num_textures} textures")
        if not self.assets.textures:  # the asset's own base-colour texture (grey when it has none)
            own = self.own_texture if self.own_texture is not None else np.full((4, 4, 3), 160, np.uint8)
            self._images[texture_id] = self._image_from_array("asset_base_colour", own)
            return self._images[texture_id]
        entry = self.assets.textures[texture_id]
        if entry.startswith("toy:"):
            from bat3r_core.toy import toy_coat_texture

            img = self._image_from_array(f"coat_{texture_id}", toy_coat_texture(entry[4:], size=512, seed=0))
        else:
            img = self._load_image(entry, "bad_texture", "texture")
        self._images[texture_id] = img
        return img

    @staticmethod
    def _load_image(path: str, status: str, what: str):
        if not Path(path).is_file():
            raise JobError(status, f"{what} file {path} does not exist")
        try:
            img = bpy.data.images.load(str(path), check_existing=True)
            ok = img.size[0] > 0 and img.size[1] > 0 and len(img.pixels) > 0
        except RuntimeError as e:
            raise JobError(status, f"{what} file {path} cannot be read: {e}") from None
        if not ok:
            bpy.data.images.remove(img)
            raise JobError(status, f"{what} file {path} cannot be read (not a valid image)")
        return img

    def _set_world(self, envmap_id: int, rotation: float, seed: int) -> None:
        if envmap_id < 0:
            rng = np.random.default_rng([seed, 1])
            elevation = math.radians(rng.uniform(15.0, 65.0))
            azimuth = rotation + rng.uniform(0.0, 2 * math.pi)
            sun_dir = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                       math.sin(elevation))
            self.sky_tex.sun_direction = sun_dir
            self.sky_tex.turbidity = float(rng.uniform(2.0, 6.0))
            self.sky_tex.ground_albedo = 0.3
            self.sky_bg.inputs["Strength"].default_value = float(rng.uniform(0.8, 1.3))
            self.sun.data.energy = float(rng.uniform(2.5, 4.5))
            self.sun.rotation_euler = (0.0, math.pi / 2 - elevation, azimuth)  # the lamp shines along its -z
            self.sun.hide_render = False
            gain = rng.uniform(0.9, 1.4)  # ground radiance ~ albedo x irradiance / pi
            grass = gain * np.array([rng.uniform(0.06, 0.12), rng.uniform(0.12, 0.22), rng.uniform(0.02, 0.06)])
            earth = gain * np.array([rng.uniform(0.16, 0.26), rng.uniform(0.12, 0.18), rng.uniform(0.07, 0.11)])
            haze = gain * np.array([0.20, 0.23, 0.26]) * rng.uniform(0.8, 1.1)
            self.haze_mix.inputs["B"].default_value = (*haze, 1.0)
            ramp = self.ground_ramp.color_ramp.elements
            ramp[0].color = (*earth, 1.0)
            ramp[1].color = (*grass, 1.0)
            ramp[0].position = float(rng.uniform(0.3, 0.45))
            ramp[1].position = float(rng.uniform(0.5, 0.7))
            self.scene.world = self.sky_world
            return
        self.sun.hide_render = True
        if envmap_id >= len(self.assets.envmaps):
            raise JobError("bad_envmap", f"envmap_id {envmap_id} is out of range: the category has "
                                         f"{len(self.assets.envmaps)} environment maps")
        if envmap_id not in self._envmaps:
            self._envmaps[envmap_id] = self._load_image(self.assets.envmaps[envmap_id], "bad_envmap",
                                                        "environment map")
        self.env_tex.image = self._envmaps[envmap_id]
        self.env_mapping.inputs["Rotation"].default_value = (0.0, 0.0, rotation)
        self.scene.world = self.env_world

    def _set_camera(self, camera: PinholeCamera) -> None:
        b = to_blender(camera, world_rotation=GLTF_TO_BLENDER_WORLD)
        cam = self.camera.data
        cam.lens = b["lens_mm"]
        cam.sensor_width = b["sensor_width_mm"]
        cam.shift_x = b["shift_x"]
        cam.shift_y = b["shift_y"]
        self.camera.matrix_world = Matrix(b["matrix_world"].tolist())
        self.scene.render.resolution_x = b["resolution_x"]
        self.scene.render.resolution_y = b["resolution_y"]

    def evaluated_vertices(self) -> np.ndarray:
        """(V, 3) depsgraph-evaluated (posed) vertices in bat3r's world frame, rig vertex order."""
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        ob = self.mesh.evaluated_get(dg)
        me = ob.to_mesh()
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        mw = np.array(ob.matrix_world)
        ob.to_mesh_clear()
        return self._to_bat3r(co.reshape(-1, 3), mw)

    def render(self, row: dict) -> dict:
        """Render one job row (dict of the job columns + ``index``); returns its result record."""
        import cv2

        t0, c0 = time.perf_counter(), time.process_time()
        index = int(row["index"])
        job = job_from_dict(row)
        problems = job.problems(self.rig.num_joints)
        if problems:
            raise JobError("bad_job", "; ".join(problems))
        img = self._texture(job.texture_id)
        self._set_world(job.envmap_id, job.envmap_rotation, job.seed)
        self.tex_node.image = img
        self._set_vertices(self._posed_vertices(row))
        self._set_camera(job.camera)
        self.scene.cycles.seed = int(job.seed) % (2 ** 31)
        frame_dir = self.workdir / "_frame"
        for p in frame_dir.glob("*.png"):
            p.unlink()
        bpy.ops.render.render(write_still=False)
        rgb_files = sorted(frame_dir.glob("rgb*.png"))
        mask_files = sorted(frame_dir.glob("mask*.png"))
        if not rgb_files or not mask_files:
            raise JobError("failed", f"Blender wrote no image (found {[p.name for p in frame_dir.iterdir()]})")
        rgb = cv2.imread(str(rgb_files[0]), cv2.IMREAD_COLOR)[..., ::-1]
        mask = cv2.imread(str(mask_files[0]), cv2.IMREAD_GRAYSCALE) > 127
        arrays = {"rgb": np.ascontiguousarray(rgb), "mask": mask}
        if self.debug_vertices:
            arrays["posed_vertices"] = self.evaluated_vertices()
        out = self.workdir / f"job-{index:06d}.npz"
        tmp = self.workdir / f".job-{index:06d}.npz.tmp"
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, out)
        return {"status": "ok", "reason": "", "seconds": time.perf_counter() - t0,
                "cpu_seconds": time.process_time() - c0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="bat3r Blender render worker (jobs as JSON lines on stdin)")
    ap.add_argument("--spec", required=True, help="JSON with asset, textures, envmaps, config, debug_vertices")
    ap.add_argument("--results", required=True, help="JSON-lines file the per-job results are appended to")
    ap.add_argument("--out", required=True, help="folder for job-<index>.npz outputs")
    args = ap.parse_args(argv)
    from bat3r_core.config_utils import from_mapping

    spec = json.loads(Path(args.spec).read_text())
    assets = SceneAssets(asset=spec["asset"], textures=tuple(spec["textures"]), envmaps=tuple(spec["envmaps"]))
    config = from_mapping(RenderConfig, spec["config"], "config")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    renderer = BlenderRenderer(assets, config, out, debug_vertices=bool(spec.get("debug_vertices", False)))
    _log(f"scene ready in {time.perf_counter() - t0:.2f} s ({renderer.rig.num_vertices} vertices)")
    (out / f"ready-{os.getpid()}").touch()  # tells the runner that start-up succeeded
    with open(args.results, "a", encoding="utf-8") as results:
        for line in sys.stdin:
            if not line.strip():
                continue
            row = json.loads(line)
            try:
                rec = renderer.render(row)
            except JobError as e:
                rec = {"status": e.status, "reason": e.reason, "seconds": 0.0}
            except Exception as e:  # noqa: BLE001 - any per-job failure is recorded, the shard goes on
                _log(traceback.format_exc())
                rec = {"status": "failed", "reason": f"{type(e).__name__}: {e}", "seconds": 0.0}
            rec.update(index=int(row["index"]), sample_id=str(row.get("sample_id", "")))
            results.write(json.dumps(rec) + "\n")
            results.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
