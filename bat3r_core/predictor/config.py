"""Configuration of the dual point map predictor: network sizes and the training schedule.

Both dataclasses are frozen and hold plain-typed fields only, so the data catalog builds them with
``config_utils.from_mapping`` and checkpoints store them as plain dicts (``config_utils.to_mapping``).
Named run presets (``tiny``, ``demo``, ``paper``) are data in the data catalog (``runs.<name>.model`` and
``runs.<name>.train``); ``bat3r_core.catalog.Catalog.model_config`` / ``train_config`` build them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from bat3r_core.config_utils import ConfigError

#: Values stored per (pixel, layer) by the network, in this channel order.
CHANNELS_PER_LAYER = 9  # canonical xyz, posed xyz, occupancy logit, canonical confidence, posed confidence


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of the two-stage UNet (see ``network.DualPointMapNet``)."""

    resolution: int = 64
    """Square input/output size H = W in pixels; must be divisible by ``2 ** depth``."""
    layers: int = 4
    """K, the number of point-map layers, front to back (reference: 4)."""
    in_channels: int = 3
    """C, channels of the feature tensor (``rgb``: 3; PCA-reduced DINOv2: 64 in the reference)."""
    base_channels: int = 16
    """Channels of the first UNet level; level i has ``base_channels * 2 ** min(i, 3)``."""
    depth: int = 3
    """Number of down-sampling steps of each UNet."""
    two_stage: bool = True
    """Stage 1 predicts the visible (layer-0) canonical map; stage 2 predicts the rest conditioned on it."""
    pixel_coordinates: bool = True
    """Append the pixel coordinates (u, v), scaled to [-1, 1], to the network input (CoordConv)."""
    feature: str = "rgb"
    """Name of the feature extractor the model was trained with (recorded so inference uses the same)."""

    def __post_init__(self) -> None:
        for name in ("resolution", "layers", "in_channels", "base_channels", "depth"):
            if getattr(self, name) < 1:
                raise ConfigError(f"ModelConfig.{name}: expected >= 1, got {getattr(self, name)}")
        if self.resolution % (2 ** self.depth):
            raise ConfigError(f"ModelConfig.resolution: expected a multiple of 2**depth = {2 ** self.depth}, "
                              f"got {self.resolution}")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation schedule of ``train.Trainer``. A step is one optimiser update of ``grad_accum`` micro-batches."""

    steps: int = 200
    """Number of optimiser steps (reference: 60K per bootstrap iteration)."""
    batch_size: int = 8
    """Samples per micro-batch and per process (reference: 12)."""
    grad_accum: int = 1
    """Micro-batches whose gradients are summed before each step (reference: 2)."""
    lr: float = 6e-4
    """Peak learning rate reached after warm-up (reference: 6e-4)."""
    weight_decay: float = 0.01
    """AdamW decoupled weight decay (reference: 0.01)."""
    betas: tuple[float, float] = (0.95, 0.9995)
    """AdamW (beta1, beta2). The paper "slightly increases the Adam momentum" without numbers; we take
    0.95 / 0.9995 instead of Adam's 0.9 / 0.999, i.e. moment averages over ~20 and ~2000 steps."""
    warmup_steps: int = 20
    """Linear warm-up from 0 to ``lr`` over this many steps, then cosine decay to 0 at ``steps``."""
    checkpoint_every: int = 50
    """Write ``checkpoint.pt`` every this many steps (and at the last step)."""
    loss: Literal["dualpm", "robust"] = "dualpm"
    """``dualpm``: squared errors; ``robust``: annealed Huber for noisy bootstrapped targets."""
    huber_delta_start: float = 0.1
    """Huber threshold (metres) at step 0 of the robust loss."""
    huber_delta_end: float = 100.0
    """Huber threshold at the last step; the schedule is log-linear in between."""
    grad_clip: float = 0.0
    """Clip the global gradient norm to this value; 0 disables clipping."""
    occupancy_weight: float = 1.0
    """Weight of the occupancy BCE term relative to the regression term."""
    mirror_probability: float = 0.0
    """Probability that a training sample is mirrored left-right (``predictor.mirror``: image and maps flipped,
    posed x negated, canonical points reflected through the rig's sagittal plane); > 0 needs a symmetric rest mesh
    (checked) and doubles the poses and views a set of renders holds. 0 (the paper): off."""
    seed: int = 0
    """Seeds the model initialisation and the data order (order of epoch e depends on (seed, e) only)."""
    amp_dtype: Literal["bfloat16", "float16", "none"] = "bfloat16"
    """Autocast dtype on CUDA; ignored on CPU, which always trains in float32."""
    deterministic: bool = False
    """Train under ``torch.use_deterministic_algorithms(True)`` (restored afterwards): bit-exact reruns on GPU
    too (set ``CUBLAS_WORKSPACE_CONFIG=:4096:8``), slower there. CPU training is reproducible without it."""
    shuffle_shards: int = 4
    """The data order shuffles samples within groups of this many shards (bounds the shard cache)."""
    log_every: int = 10
    """Append a line to ``train_log.jsonl`` every this many steps."""
    warm_start: bool = False
    """Refinement iterations: initialise Φ_i with Φ_{i-1}'s weights (fresh optimiser and schedule) instead of a
    random initialisation. The training data of earlier iterations is still discarded; only the weights carry
    over. The paper does not say how Φ_i is initialised; small runs (the ``demo`` preset) need the carried-over
    training to end up better than Φ_0 (see the README, "The two commands")."""
    canonical_replay: float = 0.0
    """Refinement iterations: also train on iteration 0's canonical (rest-pose) renders, this many per pseudo-label
    render and epoch (at most all of them; each epoch draws its share afresh, ``data.MixedDataset``). 0 (the
    paper): each iteration trains on its own renders alone. A regulariser against wrong fits: the canonical renders
    keep teaching the rest pose's correct labels while the fitted poses teach the collection's poses."""

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "grad_accum", "checkpoint_every", "shuffle_shards", "log_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"TrainConfig.{name}: expected >= 1, got {getattr(self, name)}")
        if not (self.canonical_replay >= 0):
            raise ConfigError(f"TrainConfig.canonical_replay: expected >= 0, got {self.canonical_replay}")
        if self.warmup_steps < 0:
            raise ConfigError(f"TrainConfig.warmup_steps: expected >= 0, got {self.warmup_steps}")
        if not (self.lr > 0):
            raise ConfigError(f"TrainConfig.lr: expected > 0, got {self.lr}")
        if not (0 < self.huber_delta_start and 0 < self.huber_delta_end):
            raise ConfigError("TrainConfig.huber_delta_start/end: expected > 0, got "
                              f"{self.huber_delta_start}, {self.huber_delta_end}")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ConfigError(f"TrainConfig.betas: expected two values in [0, 1), got {self.betas}")
        if not 0.0 <= self.mirror_probability <= 1.0:
            raise ConfigError("TrainConfig.mirror_probability: expected a value in [0, 1], got "
                              f"{self.mirror_probability}")
        if self.grad_clip < 0:
            raise ConfigError(f"TrainConfig.grad_clip: expected >= 0, got {self.grad_clip}")
