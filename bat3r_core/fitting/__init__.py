"""Mesh fitting of the rigged canonical mesh to predicted dual point clouds, camera recovery and viewpoint
augmentation (see docs/fitting.md)."""
from .config import FittingConfig
from .fit import FitResult, FittingAsset, PointCloudInstance, fit_batch
from .io import fit_points_file, read_points_npz, write_points_npz

__all__ = ["FittingConfig", "FittingAsset", "PointCloudInstance", "FitResult", "fit_batch",
           "fit_points_file", "read_points_npz", "write_points_npz"]
