"""Render settings (:class:`RenderConfig`; named ones live in the data catalog) and the scene assets a worker
renders with.

Pure data, no bpy: the runner, the data catalog and the job builders import this; the worker receives it as JSON.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, Mapping

from bat3r_core.config_utils import ConfigError, from_mapping

__all__ = ["RenderConfig", "render_config", "SceneAssets", "DEVICES"]

DEVICES = ("CPU", "CUDA", "OPTIX", "HIP", "METAL")


@dataclass(frozen=True)
class RenderConfig:
    """How images are rendered (Cycles) and labelled (ray casting).

    Attributes:
        resolution: square image side in pixels used by the job builders (the worker renders each job's own
            ``width`` x ``height``).
        samples: Cycles samples per pixel.
        denoise: run OpenImageDenoise on the image.
        device: ``CPU`` or a GPU backend (``CUDA``/``OPTIX``/``HIP``/``METAL``); the GPU index comes from
            ``CUDA_VISIBLE_DEVICES`` (one device per worker process).
        threads: Cycles CPU threads (0 = all cores).
        filter_width: Cycles pixel filter width in pixels (Blackman-Harris). Smaller keeps the Object Index mask
            closer to the ray-cast pixel-centre occupancy; 1.5 is Blender's default.
        view_transform: colour view transform (``Standard``, ``AgX``, ``Filmic``...).
        exposure: film exposure in stops.
        recycle_every: a worker process renders at most this many images, then a fresh one takes over
            (bpy memory grows over many renders).
        retries: how many times the remaining jobs of a shard are retried after the worker process crashed.
        timeout_s: a worker whose scene is ready and that finishes no image for this many seconds is killed (its
            unfinished jobs are retried).
        startup_timeout_s: seconds allowed for a worker process to start and set up its scene.
        num_layers: K, layers of the ray-cast dual point maps.
        max_bounces: Cycles light bounces.
    """

    resolution: int = 128
    samples: int = 16
    denoise: bool = False
    device: Literal["CPU", "CUDA", "OPTIX", "HIP", "METAL"] = "CPU"
    threads: int = 0
    filter_width: float = 1.0
    view_transform: str = "Standard"
    exposure: float = 0.0
    recycle_every: int = 256
    retries: int = 2
    timeout_s: float = 60.0
    startup_timeout_s: float = 120.0
    num_layers: int = 4
    max_bounces: int = 4

    def __post_init__(self) -> None:
        checks = [("resolution", self.resolution >= 8, ">= 8"), ("samples", self.samples >= 1, ">= 1"),
                  ("threads", self.threads >= 0, ">= 0"),
                  ("filter_width", 0.01 <= self.filter_width <= 10, "in [0.01, 10]"),
                  ("recycle_every", self.recycle_every >= 1, ">= 1"), ("retries", self.retries >= 0, ">= 0"),
                  ("timeout_s", self.timeout_s > 0, "> 0"), ("startup_timeout_s", self.startup_timeout_s > 0, "> 0"),
                  ("num_layers", self.num_layers >= 1, ">= 1"), ("max_bounces", self.max_bounces >= 0, ">= 0"),
                  ("exposure", math.isfinite(self.exposure), "finite")]
        for name, ok, expected in checks:
            if not ok:
                raise ValueError(f"RenderConfig.{name} must be {expected}, got {getattr(self, name)!r}")
        if self.device not in DEVICES:
            raise ValueError(f"RenderConfig.device must be one of {DEVICES}, got {self.device!r}")


def render_config(value: Mapping[str, Any] | RenderConfig | None, path: str = "render") -> RenderConfig:
    """A :class:`RenderConfig` from a mapping (strict, via ``config_utils.from_mapping``), an existing config, or
    None (the class defaults). Named render settings live in the data catalog only, as each run preset's
    ``render:`` section (``Catalog.render_config(run)``); a name here is refused with that pointer."""
    if value is None:
        return RenderConfig()
    if isinstance(value, RenderConfig):
        return value
    if isinstance(value, str):
        raise ConfigError(f"{path}: render settings are not named in code; got {value!r}. Give a mapping of "
                          "RenderConfig fields, or a run preset's render config: "
                          f"bat3r_core.catalog.load_catalog().render_config({value!r})")
    if not isinstance(value, Mapping):
        raise ConfigError(f"{path}: expected a mapping of RenderConfig fields, got {type(value).__name__} {value!r}")
    return from_mapping(RenderConfig, dict(value), path)


@dataclass(frozen=True)
class SceneAssets:
    """The files a worker renders one category with.

    Attributes:
        asset: the rigged canonical mesh (GLB/glTF; FBX/.blend are converted first by the runner).
        textures: one entry per ``texture_id``: an image file path, or ``"toy:<coat>"`` for a procedural toy coat
            (:data:`bat3r_core.toy.TOY_COATS`). Empty: the asset's own base-colour texture (the one embedded in the
            GLB) is the only texture, ``texture_id`` 0.
        envmaps: one HDR/EXR (or LDR) file per ``envmap_id``; ``envmap_id = -1`` uses a procedural sky.
    """

    asset: str
    textures: tuple[str, ...] = ("toy:bay", "toy:chestnut", "toy:grey", "toy:pinto")
    envmaps: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.textures, str):
            raise TypeError("SceneAssets.textures must be a sequence of texture entries, not one string")

    @property
    def num_textures(self) -> int:
        """Texture ids a job may use: the listed textures, or 1 (the asset's own) when none are listed."""
        return max(len(self.textures), 1)
