"""bat3r_core: the method of BAT3R as a library (rigs and skinning, cameras, dual point maps, rendering worker,
predictor, mesh fitting, view augmentation, metrics, analysis, shard I/O, data catalog).

Every stage is callable without Prefect; the ``tasks/`` and ``flows/`` packages only orchestrate these functions.
Heavy submodules (torch, open3d, bpy) are imported by the modules that need them, not here.
"""
__version__ = "0.1.0"

from .rig import Rig, RigError  # noqa: F401  (pure numpy, cheap)
