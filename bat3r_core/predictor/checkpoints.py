"""The predictor's checkpoint files: ``predictor.pt`` (weights and configs) and the training ``checkpoint.pt``
(plus optimiser, scheduler, RNG and data-order state). Training writes them (``bat3r_core.predictor.train``);
inference and warm starts read them here, so loading a model for prediction does not go through the training
module. Loaded with ``torch.load(weights_only=True)``: tensors and plain data only.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from bat3r_core.config_utils import from_mapping
from bat3r_core.predictor.config import ModelConfig, TrainConfig

__all__ = ["CHECKPOINT_FORMAT", "read_state", "load_configs"]

CHECKPOINT_FORMAT = "bat3r-predictor/1"
"""The ``format`` entry of every state bat3r writes."""


def read_state(path: str | os.PathLike, argument: str) -> dict[str, Any]:
    """The state dict of a ``predictor.pt`` or training ``checkpoint.pt`` (``torch.load(weights_only=True)``),
    checked to be one: a missing file or another kind of file is an error naming ``argument`` and the path."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{argument}: no such file {path}")
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{argument}: {path} is not a '{CHECKPOINT_FORMAT}' predictor checkpoint")
    return state


def load_configs(state: dict[str, Any]) -> tuple[ModelConfig, TrainConfig]:
    """Configs stored in a checkpoint/predictor state dict, rebuilt strictly."""
    return (from_mapping(ModelConfig, state["model_config"], "checkpoint.model_config"),
            from_mapping(TrainConfig, state["train_config"], "checkpoint.train_config"))
