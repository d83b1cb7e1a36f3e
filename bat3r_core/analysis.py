"""Dataset analyses: pose clusters and splits, camera distributions, pseudo-label quality.

* **Pose clusters**: features ``[f_ang, f_sq, f_dist]`` per sample (``bat3r_core.poses.pose_features``) are
  standardised (zero mean, unit variance per column) and clustered with K-Means (K = 10, seeded). Cluster ids are
  renumbered by increasing mean ``f_dist`` of their members, so cluster 0 holds the poses closest to the rest pose
  and the ids do not depend on K-Means' internal order.
* **Splits**: ``stratified_split`` draws train/test sets whose per-cluster counts follow the overall cluster
  proportions (largest-remainder rounding: each cluster's share is within ``1 / n`` of its overall share);
  ``alternative_split`` drops chosen clusters from a base train set and refills from the allowed clusters to the
  base size, as in the paper's supplement.
* **Cameras**: 2-D histograms of body-centric azimuth/elevation/roll (counts; log scale is for display) per dataset
  and per cluster; Student's t vs Normal fits via ``bat3r_core.viewpoints.fit_angle_distribution``.
* **Pseudo-labels**: fitted vs ground-truth pose errors, fitting-loss distributions, filter counts.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import pyarrow as pa
from scipy import stats
from scipy.spatial.transform import Rotation
from sklearn.cluster import KMeans

from bat3r_core.metrics import M_TO_CM, rotation_error_deg

__all__ = [
    "PoseClusters",
    "SplitIndices",
    "CameraHistograms",
    "PoseErrors",
    "bone_direction_error_deg",
    "PseudoLabelSummary",
    "standardize",
    "cluster_poses",
    "assign_clusters",
    "stratified_split",
    "alternative_split",
    "camera_histograms",
    "camera_histograms_by_cluster",
    "fit_camera_angles",
    "angle_fit_densities",
    "pose_errors",
    "summarize_pseudo_labels",
]

DEFAULT_K = 10


def _features(features) -> np.ndarray:
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"features must have shape (N, 3) [f_ang, f_sq, f_dist], got {f.shape}")
    if not np.isfinite(f).all():
        raise ValueError("features contains non-finite values")
    return f


def standardize(features: np.ndarray, mean: np.ndarray | None = None, std: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Standardise (N, 3) pose features column-wise: ``(f - mean) / std``.

    mean, std: (3,) to reuse the statistics of another set; computed from ``features`` when None (a constant column
    gets std 1). Returns ``(z (N, 3), mean (3,), std (3,))``.
    """
    f = _features(features)
    if mean is None:
        mean = f.mean(axis=0)
    if std is None:
        std = f.std(axis=0)
        std = np.where(std > 1e-12, std, 1.0)
    return (f - mean) / std, np.asarray(mean, float), np.asarray(std, float)


@dataclass(frozen=True)
class PoseClusters:
    """K-Means pose clusters.

    labels: (N,) int cluster id per sample, 0 … K-1, ordered by increasing mean f_dist of the cluster.
    centers: (K, 3) cluster centres in standardised feature units, in id order.
    mean, std: (3,) standardisation statistics of the features the clusters were fitted on.
    inertia: K-Means sum of squared distances (standardised units).
    """

    labels: np.ndarray
    centers: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    inertia: float

    @property
    def k(self) -> int:
        return len(self.centers)

    def proportions(self) -> np.ndarray:
        """(K,) fraction of the fitted samples in each cluster."""
        return np.bincount(self.labels, minlength=self.k) / len(self.labels)


def cluster_poses(features: np.ndarray, k: int = DEFAULT_K, seed: int = 0, n_init: int = 10) -> PoseClusters:
    """Standardise (N, 3) pose features ``[f_ang, f_sq, f_dist]`` and cluster them with K-Means (scikit-learn,
    ``random_state=seed``, ``n_init`` restarts). Reproducible for a given seed. N must be ≥ k."""
    f = _features(features)
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    if len(f) < k:
        raise ValueError(f"features must have at least k={k} rows, got {len(f)}")
    z, mean, std = standardize(f)
    km = KMeans(n_clusters=int(k), random_state=seed, n_init=n_init).fit(z)
    raw = km.labels_
    mean_fdist = np.array([f[raw == c, 2].mean() if np.any(raw == c) else np.inf for c in range(k)])
    order = np.argsort(mean_fdist, kind="stable")      # new id → old id
    relabel = np.empty(k, dtype=np.int64)
    relabel[order] = np.arange(k)                        # old id → new id
    return PoseClusters(relabel[raw].astype(np.int64), km.cluster_centers_[order], mean, std, float(km.inertia_))


def assign_clusters(clusters: PoseClusters, features: np.ndarray) -> np.ndarray:
    """(N,) id of the nearest cluster centre for new (N, 3) features, standardised with the fitted statistics."""
    z, _, _ = standardize(features, clusters.mean, clusters.std)
    d2 = ((z[:, None, :] - clusters.centers[None, :, :]) ** 2).sum(-1)  # (N, K)
    return np.argmin(d2, axis=1).astype(np.int64)


@dataclass(frozen=True)
class SplitIndices:
    """Sorted sample indices of a split: train (N_train,), test (N_test,), disjoint."""

    train: np.ndarray
    test: np.ndarray


def _labels(cluster_ids) -> np.ndarray:
    c = np.asarray(cluster_ids)
    if c.ndim != 1 or not np.issubdtype(c.dtype, np.integer) or (len(c) and c.min() < 0):
        raise ValueError(f"cluster_ids must be a 1-D array of non-negative integers, got shape {c.shape} "
                         f"dtype {c.dtype}")
    return c.astype(np.int64)


def _quotas(counts: np.ndarray, total: int) -> np.ndarray:
    """Split ``total`` over clusters proportionally to ``counts`` (largest remainder, capped by the counts)."""
    exact = counts * total / counts.sum()
    q = np.floor(exact).astype(np.int64)
    order = np.argsort(-(exact - q), kind="stable")
    for c in order[: total - q.sum()]:
        q[c] += 1
    return np.minimum(q, counts)


def stratified_split(cluster_ids: np.ndarray, n_test: int, n_train: int | None = None, seed: int = 0
                     ) -> SplitIndices:
    """Draw disjoint test and train sets stratified by cluster.

    cluster_ids: (N,) non-negative ints. The test set takes ``n_test`` samples, each cluster contributing its
    overall proportion (largest-remainder rounding, so every cluster's share is within ``1 / n_test`` of its overall
    share); the train set takes ``n_train`` of the rest the same way (default: all the rest). Sampling within a
    cluster is uniform without replacement with ``numpy.random.default_rng(seed)``.
    """
    c = _labels(cluster_ids)
    n = len(c)
    if not 0 < n_test < n:
        raise ValueError(f"n_test must be in [1, {n - 1}] for {n} samples, got {n_test}")
    rest = n - n_test
    if n_train is None:
        n_train = rest
    if not 0 < n_train <= rest:
        raise ValueError(f"n_train must be in [1, {rest}] (samples left after the test set), got {n_train}")
    rng = np.random.default_rng(seed)
    ids = np.unique(c)
    counts = np.array([np.sum(c == k) for k in ids])
    test_q = _quotas(counts, n_test)
    train_q = _quotas(counts, n_train)
    train_q = np.minimum(train_q, counts - test_q)
    # rounding caps can leave a few places unfilled: give them to the clusters with spare samples, largest first
    short = n_train - train_q.sum()
    for i in np.argsort(-(counts - test_q - train_q), kind="stable"):
        take = min(short, counts[i] - test_q[i] - train_q[i])
        train_q[i] += take
        short -= take
    test, train = [], []
    for k, tq, rq in zip(ids, test_q, train_q):
        members = rng.permutation(np.flatnonzero(c == k))
        test.append(members[:tq])
        train.append(members[tq:tq + rq])
    return SplitIndices(np.sort(np.concatenate(train)), np.sort(np.concatenate(test)))


def alternative_split(cluster_ids: np.ndarray, base_train: np.ndarray, excluded_clusters: Sequence[int], *,
                      exclude_indices: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """The "alternative" train set: the base train set without the excluded clusters, refilled to its size.

    Keeps every base-train sample whose cluster is allowed, then adds samples drawn uniformly without replacement
    (``default_rng(seed)``) from the allowed clusters that are neither in the base train set nor in
    ``exclude_indices`` (e.g. the test set), until the size of ``base_train`` is reached.
    Returns sorted indices (len(base_train),). Raises ValueError when the allowed pool is too small.
    """
    c = _labels(cluster_ids)
    base = np.unique(np.asarray(base_train, dtype=np.int64))
    if len(base) != len(np.asarray(base_train)) or (len(base) and (base.min() < 0 or base.max() >= len(c))):
        raise ValueError(f"base_train must hold distinct indices in [0, {len(c)}), got {len(base_train)} entries")
    excluded = np.asarray(list(excluded_clusters), dtype=np.int64)
    allowed = ~np.isin(c, excluded)
    kept = base[allowed[base]]
    blocked = np.zeros(len(c), bool)
    blocked[base] = True
    if exclude_indices is not None:
        blocked[np.asarray(exclude_indices, dtype=np.int64)] = True
    pool = np.flatnonzero(allowed & ~blocked)
    need = len(base) - len(kept)
    if need > len(pool):
        raise ValueError(f"alternative split needs {need} more samples from the allowed clusters but only "
                         f"{len(pool)} are available")
    extra = np.random.default_rng(seed).choice(pool, size=need, replace=False)
    return np.sort(np.concatenate([kept, extra]))


@dataclass(frozen=True)
class CameraHistograms:
    """2-D histograms of body-centric camera angles (degrees).

    az_el: (n_el, n_az) counts, rows = elevation bins, columns = azimuth bins; az_roll: (n_roll, n_az);
    el_roll: (n_roll, n_el). *_edges: bin edges in degrees. n: samples given; n_outside: samples outside the
    edges of at least one histogram (dropped there). ``log_counts`` gives log10(1 + counts) for display.
    """

    az_el: np.ndarray
    az_roll: np.ndarray
    el_roll: np.ndarray
    az_edges: np.ndarray
    el_edges: np.ndarray
    roll_edges: np.ndarray
    n: int
    n_outside: int

    @staticmethod
    def log_counts(counts: np.ndarray) -> np.ndarray:
        return np.log10(1.0 + np.asarray(counts, dtype=np.float64))


def _angles(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D (N,), got shape {a.shape}")
    return a


def camera_histograms(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, roll_deg: np.ndarray, *,
                      az_edges: np.ndarray | None = None, el_edges: np.ndarray | None = None,
                      roll_edges: np.ndarray | None = None) -> CameraHistograms:
    """Histograms of (N,) azimuth, elevation and roll in degrees. Azimuth is wrapped to [-180, 180).
    Default edges: azimuth 36 bins over [-180, 180], elevation and roll 36 bins over [-90, 90]."""
    az = _angles("azimuth_deg", azimuth_deg)
    el = _angles("elevation_deg", elevation_deg)
    ro = _angles("roll_deg", roll_deg)
    if not len(az) == len(el) == len(ro):
        raise ValueError(f"azimuth_deg, elevation_deg and roll_deg must have equal lengths, got "
                         f"{len(az)}, {len(el)}, {len(ro)}")
    finite = np.isfinite(az) & np.isfinite(el) & np.isfinite(ro)
    az, el, ro = np.mod(az[finite] + 180.0, 360.0) - 180.0, el[finite], ro[finite]
    ae = np.linspace(-180, 180, 37) if az_edges is None else np.asarray(az_edges, float)
    ee = np.linspace(-90, 90, 37) if el_edges is None else np.asarray(el_edges, float)
    re_ = np.linspace(-90, 90, 37) if roll_edges is None else np.asarray(roll_edges, float)
    inside = ((az >= ae[0]) & (az <= ae[-1]) & (el >= ee[0]) & (el <= ee[-1]) & (ro >= re_[0]) & (ro <= re_[-1]))
    az_el, _, _ = np.histogram2d(el, az, bins=[ee, ae])
    az_roll, _, _ = np.histogram2d(ro, az, bins=[re_, ae])
    el_roll, _, _ = np.histogram2d(ro, el, bins=[re_, ee])
    return CameraHistograms(az_el.astype(np.int64), az_roll.astype(np.int64), el_roll.astype(np.int64),
                            ae, ee, re_, int(len(np.asarray(azimuth_deg))),
                            int((~finite).sum() + (~inside).sum()))


def camera_histograms_by_cluster(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, roll_deg: np.ndarray,
                                 cluster_ids: np.ndarray, **edges) -> dict[int, CameraHistograms]:
    """``camera_histograms`` of each cluster's samples (same edges for all), keyed by cluster id."""
    c = _labels(cluster_ids)
    az, el, ro = (_angles(n, a) for n, a in (("azimuth_deg", azimuth_deg), ("elevation_deg", elevation_deg),
                                            ("roll_deg", roll_deg)))
    if len(c) != len(az):
        raise ValueError(f"cluster_ids must have {len(az)} entries, got {len(c)}")
    return {int(k): camera_histograms(az[c == k], el[c == k], ro[c == k], **edges) for k in np.unique(c)}


def fit_camera_angles(elevation_deg: np.ndarray, roll_deg: np.ndarray) -> dict[str, Any]:
    """Student's t and Normal fits of elevation and roll: ``{"elevation": AngleFit, "roll": AngleFit}``, from
    ``bat3r_core.viewpoints.fit_angle_distribution`` (non-finite samples dropped)."""
    from bat3r_core.viewpoints import fit_angle_distribution

    out = {}
    for name, a in (("elevation", elevation_deg), ("roll", roll_deg)):
        a = _angles(f"{name}_deg", a)
        out[name] = fit_angle_distribution(a[np.isfinite(a)])
    return out


def angle_fit_densities(fit: Any, grid_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Densities (per degree) of an ``AngleFit``'s Student's t ``(df, loc, scale)`` and Normal ``(loc, scale)``
    on ``grid_deg`` (G,). Returns ``(pdf_t (G,), pdf_normal (G,))``."""
    df, loc, scale = fit.student_t
    n_loc, n_scale = fit.normal
    g = np.asarray(grid_deg, dtype=np.float64)
    return stats.t.pdf(g, df, loc=loc, scale=scale), stats.norm.pdf(g, loc=n_loc, scale=n_scale)


@dataclass(frozen=True)
class PoseErrors:
    """Per-sample errors of fitted poses against ground truth (same frame for both).

    joint_err_cm: (N,) mean joint-position error, cm. vertex_err_cm: (N,) mean vertex error, cm.
    angle_err_deg: (N,) mean over joints of the geodesic angle between fitted and true excess rotations, degrees.
    """

    joint_err_cm: np.ndarray
    vertex_err_cm: np.ndarray
    angle_err_deg: np.ndarray


def pose_errors(fitted_joints: np.ndarray, gt_joints: np.ndarray, fitted_verts: np.ndarray, gt_verts: np.ndarray,
                fitted_rotations: np.ndarray, gt_rotations: np.ndarray) -> PoseErrors:
    """Fitted-pose vs ground-truth pose errors of N samples.

    fitted_joints, gt_joints: (N, J, 3) joint positions, metres, one common frame (e.g. camera frame).
    fitted_verts, gt_verts: (N, V, 3) posed mesh vertices, metres, same frame and vertex order.
    fitted_rotations, gt_rotations: (N, J, 3) excess rotations θ, axis-angle radians.
    """
    fj, gj = _joint_like("joints", fitted_joints, gt_joints)
    fv, gv = _joint_like("verts", fitted_verts, gt_verts)
    fr, gr = _joint_like("rotations", fitted_rotations, gt_rotations)
    if not (len(fj) == len(fv) == len(fr)) or fj.shape[1] != fr.shape[1]:
        raise ValueError(f"joints {fj.shape}, verts {fv.shape} and rotations {fr.shape} must agree on N (and J)")
    joint = np.linalg.norm(fj - gj, axis=-1).mean(-1) * M_TO_CM
    vert = np.linalg.norm(fv - gv, axis=-1).mean(-1) * M_TO_CM
    n, j = fr.shape[:2]
    ra = Rotation.from_rotvec(fr.reshape(-1, 3)).as_matrix()
    rb = Rotation.from_rotvec(gr.reshape(-1, 3)).as_matrix()
    ang = np.asarray(rotation_error_deg(ra, rb)).reshape(n, j).mean(-1) if n * j else np.zeros(n)
    return PoseErrors(joint, vert, ang)


def bone_direction_error_deg(fitted_joints: np.ndarray, gt_joints: np.ndarray, parents: np.ndarray,
                             rest_joints: np.ndarray) -> np.ndarray:
    """Mean angle (degrees) between the fitted and the true bones of N samples.

    A bone is the vector from a joint's parent to the joint; bones shorter than 1e-3 of the longest in the rest
    pose (``rest_joints`` (J, 3)) have no direction and are left out. Twist about a bone leaves its direction, and
    almost the whole surface, unchanged: this error counts the swing of the joints, which point maps show, where
    the excess-rotation error (:func:`pose_errors`) also counts twist, which they do not.

    fitted_joints, gt_joints: (N, J, 3) joint positions, metres, one common frame. parents: (J,), -1 for the root.
    """
    fj, gj = _joint_like("joints", fitted_joints, gt_joints)
    parents = np.asarray(parents, dtype=np.int64)
    child = np.flatnonzero(parents >= 0)
    rest = np.asarray(rest_joints, dtype=np.float64)
    length = np.linalg.norm(rest[child] - rest[parents[child]], axis=-1)
    child = child[length > 1e-3 * length.max()] if len(child) else child
    if not len(child):
        return np.full(len(fj), math.nan)
    a, b = fj[:, child] - fj[:, parents[child]], gj[:, child] - gj[:, parents[child]]
    cos = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).mean(-1)


def _joint_like(name: str, a, b) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 3 or a.shape[-1] != 3 or a.shape != b.shape:
        raise ValueError(f"fitted and ground-truth {name} must both have shape (N, *, 3), got {a.shape} and {b.shape}")
    return a, b


@dataclass(frozen=True)
class PseudoLabelSummary:
    """Pseudo-label quality of one iteration's fits.

    n: fit rows; n_ok: rows with status "ok". status_counts: {status: count} over all rows; reason_counts:
    {reason: count} over non-ok rows (most frequent first). losses: {loss column: (n_ok,) finite values of the ok
    rows}. mean_joint_err_cm, mean_vertex_err_cm, mean_angle_err_deg, mean_bone_err_deg: means over ok rows with
    finite values of the ``joint_err_cm``, ``vertex_err_cm``, ``angle_err_deg`` and ``bone_err_deg`` columns (NaN
    when absent: no ground truth, or a run written before the column existed).
    """

    n: int
    n_ok: int
    status_counts: dict[str, int]
    reason_counts: dict[str, int]
    losses: dict[str, np.ndarray] = field(default_factory=dict)
    mean_joint_err_cm: float = math.nan
    mean_vertex_err_cm: float = math.nan
    mean_angle_err_deg: float = math.nan
    mean_bone_err_deg: float = math.nan


POSE_ERROR_COLUMNS = ("joint_err_cm", "vertex_err_cm", "angle_err_deg", "bone_err_deg")


def summarize_pseudo_labels(fits: pa.Table | Sequence[Mapping[str, Any]]) -> PseudoLabelSummary:
    """Summarise fit rows (``iter-NN/fit`` shards): ``sample_id``, ``status``, ``reason``, any ``loss_*`` float
    columns (final fitting losses), and optionally ``joint_err_cm``, ``vertex_err_cm``, ``angle_err_deg``,
    ``bone_err_deg``."""
    table = fits if isinstance(fits, pa.Table) else pa.Table.from_pylist(list(fits))
    if table.num_rows and "status" not in table.column_names:
        raise ValueError(f"fit rows need a 'status' column; got {table.column_names}")
    status = [str(s) for s in table.column("status").to_pylist()] if table.num_rows else []
    reasons = table.column("reason").to_pylist() if "reason" in table.column_names else [""] * len(status)
    ok = np.array([s == "ok" for s in status], dtype=bool)
    status_counts: dict[str, int] = {}
    for s in status:
        status_counts[s] = status_counts.get(s, 0) + 1
    reason_counts: dict[str, int] = {}
    for s, r in zip(status, reasons):
        if s != "ok":
            key = str(r) if r else s
            reason_counts[key] = reason_counts.get(key, 0) + 1
    reason_counts = dict(sorted(reason_counts.items(), key=lambda kv: (-kv[1], kv[0])))

    def finite(name: str) -> np.ndarray:
        v = np.array([math.nan if x is None else x for x in table.column(name).to_pylist()], dtype=np.float64)[ok]
        return v[np.isfinite(v)]

    losses = {c: finite(c) for c in table.column_names if c.startswith("loss_")}
    means = {}
    for c in POSE_ERROR_COLUMNS:
        v = finite(c) if c in table.column_names else np.array([])
        means[c] = float(v.mean()) if len(v) else math.nan
    return PseudoLabelSummary(len(status), int(ok.sum()), status_counts, reason_counts, losses,
                              means["joint_err_cm"], means["vertex_err_cm"], means["angle_err_deg"],
                              means["bone_err_deg"])
