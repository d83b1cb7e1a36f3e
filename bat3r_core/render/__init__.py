"""Rendering: render jobs, render settings and the shard runner.

No bpy here: the Blender worker (:mod:`bat3r_core.render.worker`) and the FBX/.blend converter
(:mod:`bat3r_core.render.blender_convert`) import bpy and run in their own processes.
"""
from .config import RenderConfig, SceneAssets, render_config  # noqa: F401
from .jobs import JobSchemaError, RenderJob, read_jobs, write_jobs  # noqa: F401
from .runner import ShardResult, render_command, render_jobs, render_shard  # noqa: F401
