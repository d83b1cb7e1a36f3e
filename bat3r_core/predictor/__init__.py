"""Dual point map predictor: network, loss, training and inference (features/collections live beside it)."""
from bat3r_core.predictor.config import ModelConfig, TrainConfig
from bat3r_core.predictor.data import DeviceDataset, ShardDataset, TrainingBatch, TrainingTargets, rgb_features
from bat3r_core.predictor.infer import (DualClouds, PredictedMaps, PredictorConfigs, load_clouds, load_predictor,
                                        maps_to_clouds, predict_collection, predict_maps, save_clouds)
from bat3r_core.predictor.loss import LossTerms, dual_pointmap_loss, huber_delta
from bat3r_core.predictor.network import DualPointMapNet, PointMapPrediction, confidence
from bat3r_core.predictor.train import Trainer, train_predictor

__all__ = [
    "ModelConfig", "TrainConfig",
    "DeviceDataset", "ShardDataset", "TrainingBatch", "TrainingTargets", "rgb_features",
    "LossTerms", "dual_pointmap_loss", "huber_delta",
    "DualPointMapNet", "PointMapPrediction", "confidence",
    "Trainer", "train_predictor",
    "DualClouds", "PredictedMaps", "PredictorConfigs", "load_clouds", "load_predictor", "maps_to_clouds",
    "predict_collection", "predict_maps", "save_clouds",
]
