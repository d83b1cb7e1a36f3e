"""Rendering: render jobs, the Blender worker (run in subprocesses) and the shard runner. No bpy here."""
