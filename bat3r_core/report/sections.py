"""The report's sections, one function per section id (``markup.SECTION_IDS``): matplotlib (Agg) figures and
tables of a loaded run (``run_data._RunData``)."""
from __future__ import annotations

import html
import math
from typing import Callable

import numpy as np
import pyarrow as pa
from matplotlib import colormaps
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from bat3r_core import analysis, evaluation, evaluation_masks, shards
from bat3r_core.report.inputs import QualitativeInputs, read_report_inputs
from bat3r_core.report.markup import _fmt, _note, _png, _table
from bat3r_core.report.run_data import _RunData, _col, _iter_label, _main_split

_MAX_QUALITATIVE = 4
_COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"]


# ---------------------------------------------------------------------------------------------- sections

def _section_summary(d: _RunData) -> str:
    items = [(k, v) for k, v in d.manifest.items() if isinstance(v, (str, int, float, bool))]
    iters = [it for it, _ in evaluation.iteration_dirs(d.run_dir)]
    parts = [f"<p>Run folder <code>{html.escape(str(d.run_dir))}</code>; iteration folders: "
             f"{', '.join(map(str, iters)) if iters else 'none yet'}.</p>"]
    parts.append(_table(["manifest entry", "value"], items) if items else _note("manifest.json: not available yet."))
    parts.extend(f'<p class="error">Could not read {html.escape(e)}</p>' for e in d.load_errors)
    if d.metrics.num_rows:
        last = d.metrics.to_pylist()
        split = _main_split([r["split"] for r in last if r["split"] != evaluation_masks.COLLECTION_SPLIT])
        if split is not None:
            row = [r for r in last if r["split"] == split][-1]
            parts.append(f'<p class="headline">Latest ({split}, iteration {row["iteration"]}): mCD '
                         f'<b>{_fmt(row["mcd_cm"])} cm</b>, {_fmt(row["pct_mcd_over_5cm"], 1)} % over 5 cm, '
                         f'ΔR {_fmt(row["rot_err_deg"])}°, n = {row["n"]}.</p>')
        coll = _collection_rows(d)
        if coll:
            row = coll[-1]
            parts.append(f'<p class="headline">Latest (collection, iteration {row["iteration"]}): '
                         f'predictor mask IoU <b>{_fmt(row.get("pred_mask_iou"), 3)}</b> (n = {row["n"]}), '
                         f'reprojected-fit mask IoU <b>{_fmt(row.get("fit_mask_iou"), 3)}</b> '
                         f'({row.get("n_fits") or 0} fits).</p>')
    return "".join(parts)


_METRIC_PLOTS = [("mcd_cm", "mCD (cm)"), ("pct_mcd_over_5cm", "% samples with CD > 5 cm"),
                 ("rot_err_deg", "ΔR (°)"), ("rms_cd_cm", "RMS CD (cm)"), ("mv_rms_cd_cm", "model-view RMS CD (cm)")]


def _section_metrics(d: _RunData) -> str:
    rows = [r for r in d.metrics.to_pylist() if r["split"] != evaluation_masks.COLLECTION_SPLIT]
    if not rows:
        return _note("No metrics yet: they appear once an iteration has been evaluated.")
    splits = sorted({r["split"] for r in rows})
    fig = Figure(figsize=(3.2 * len(_METRIC_PLOTS), 3.0))
    for k, (col, label) in enumerate(_METRIC_PLOTS):
        ax = fig.add_subplot(1, len(_METRIC_PLOTS), k + 1)
        for c, split in enumerate(splits):
            pts = sorted((r["iteration"], r.get(col)) for r in rows if r["split"] == split)
            x = [p[0] for p in pts]
            y = [np.nan if p[1] is None else p[1] for p in pts]
            ax.plot(x, y, marker="o", color=_COLORS[c % len(_COLORS)], label=split)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)
    fig.axes[0].legend(fontsize=8)
    fig.tight_layout()
    out = _png(fig, "metrics across iterations")
    return (_note(d.metrics_note) if d.metrics_note else "") + out


def _section_ablation(d: _RunData) -> str:
    rows = [r for r in d.metrics.to_pylist() if r["split"] != evaluation_masks.COLLECTION_SPLIT]
    if not rows:
        return _note("No metrics yet.")
    has_variant = "variant" in d.metrics.column_names
    header = (["variant"] if has_variant else []) + ["iteration", "split", "n", "failed", "mCD (cm)",
                                                     "% mCD > 5 cm", "ΔR (°)", "RMS CD (cm)", "MV RMS CD (cm)"]
    body = [([r.get("variant") or ""] if has_variant else []) +
            [_iter_label(r["iteration"]), r["split"], r["n"], r.get("n_failed"), r["mcd_cm"],
             r["pct_mcd_over_5cm"], r["rot_err_deg"], r["rms_cd_cm"], r["mv_rms_cd_cm"]] for r in rows]
    return _table(header, body, "num") + (
        "<p class=\"caption\">mCD: mean over samples of the per-sample RMS Chamfer distance after ICP with scale; "
        "RMS CD: root mean square of the same; MV: model-view alignment (scale and translation only).</p>")


def _collection_rows(d: _RunData) -> list[dict]:
    rows = [r for r in d.metrics.to_pylist() if r["split"] == evaluation_masks.COLLECTION_SPLIT]
    return sorted(rows, key=lambda r: r["iteration"])


def _section_collection_masks(d: _RunData) -> str:
    rows = _collection_rows(d)
    if not rows:
        return _note("No collection mask IoUs yet: they appear once an iteration's predictor has predicted the "
                     "collection.")
    body = [[_iter_label(r["iteration"]), r["n"], r.get("n_failed"), _fmt(r.get("pred_mask_iou"), 3),
             r.get("n_fits") or 0, _fmt(r.get("fit_mask_iou"), 3)] for r in rows]
    table = _table(["iteration", "images", "failed", "Φ mask IoU", "fits", "fit mask IoU"], body, "num")
    fig = Figure(figsize=(5.0, 3.0))
    ax = fig.add_subplot(1, 1, 1)
    x = [r["iteration"] for r in rows]
    for c, (col, label) in enumerate((("pred_mask_iou", "predictor Φ_i (occupancy > 0.5)"),
                                      ("fit_mask_iou", "reprojected fits"))):
        y = [np.nan if r.get(col) is None else r[col] for r in rows]
        ax.plot(x, y, marker="o", color=_COLORS[c], label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean mask IoU")
    ax.set_ylim(0.0, 1.02)
    ax.grid(alpha=0.3)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return table + _png(fig, "collection mask IoU across iterations") + (
        "<p class=\"caption\">Mean over the collection images (at the model's crop) of the IoU with their masks: "
        "Φ_i's layer-0 occupancy, and the silhouette of iteration i's fitted meshes (the pseudo-labels Φ_i was "
        "trained on; none at iteration 0) seen through their recovered cameras.</p>")


def _cluster_samples(samples: pa.Table) -> tuple[pa.Table, str]:
    """Per-sample rows without cluster ids: cluster the samples' ground-truth pose features (K-Means, K = 10 or
    fewer for small test sets; one id per sample id across iterations). Returns the rows and a note."""
    ids = samples.column("sample_id").to_pylist()
    feats = np.stack([np.asarray(samples.column(c).to_pylist(), dtype=np.float64) for c in ("f_ang", "f_sq", "f_dist")],
                     1)
    first = {}
    for i, sid in enumerate(ids):
        if sid not in first and np.isfinite(feats[i]).all():
            first[sid] = i
    k = min(analysis.DEFAULT_K, len(first))
    if k < 2:
        return samples, ""
    keys = sorted(first)
    labels = analysis.cluster_poses(feats[[first[s] for s in keys]], k=k, seed=0).labels
    by_id = dict(zip(keys, labels.tolist()))
    cluster = pa.array([by_id.get(sid, -1) for sid in ids], pa.int64())
    out = samples.set_column(samples.column_names.index("cluster"), "cluster", cluster)
    return out, (f"Clusters computed here from the samples' ground-truth pose features (K-Means, K = {k}), "
                 "as the per-sample rows carry none.")


def _section_clusters(d: _RunData) -> str:
    if d.samples.num_rows == 0:
        return _note("No per-sample evaluation rows yet.")
    split = _main_split(d.samples.column("split").to_pylist())
    samples, note = d.samples, ""
    if all(c < 0 for c in samples.column("cluster").to_pylist()):
        samples, note = _cluster_samples(samples)
    rows = [r for r in evaluation.cluster_breakdown(samples) if r["split"] == split]
    if not rows:
        return _note("No cluster ids in the per-sample rows, and too few samples with pose features to cluster.")
    iters = sorted({r["iteration"] for r in rows})
    clusters = sorted({r["cluster"] for r in rows})
    fig = Figure(figsize=(max(6.0, 0.7 * len(clusters) * max(1, len(iters)) ** 0.5 + 3), 3.4))
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / len(iters)
    for j, it in enumerate(iters):
        vals = {r["cluster"]: r["mcd_cm"] for r in rows if r["iteration"] == it}
        x = np.arange(len(clusters)) + (j - (len(iters) - 1) / 2) * width
        ax.bar(x, [vals.get(c, np.nan) for c in clusters], width, label=f"iteration {_iter_label(it)}",
               color=_COLORS[j % len(_COLORS)])
    ax.axhline(evaluation.FAILURE_THRESHOLD_CM, color="grey", ls="--", lw=0.8)
    ax.set_xticks(np.arange(len(clusters)), [str(c) for c in clusters])
    ax.set_xlabel("pose cluster (ordered by mean f_dist)")
    ax.set_ylabel("mCD (cm)")
    ax.set_title(f"mCD per cluster, split '{split}'", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    last = [r for r in rows if r["iteration"] == iters[-1]]
    table = _table(["cluster", "n", "mCD (cm)", "% > 5 cm", "MV mCD (cm)", "ΔR (°)"],
                   [[r["cluster"], r["n"], r["mcd_cm"], r["pct_mcd_over_5cm"], r["mv_mcd_cm"], r["rot_err_deg"]]
                    for r in last], "num")
    caption = f"<p class=\"caption\">{html.escape(note)}</p>" if note else ""
    return (_png(fig, "per-cluster mCD") + caption + f"<p class=\"caption\">Latest iteration ({iters[-1]}):</p>"
            + table)


def _section_failures(d: _RunData) -> str:
    if d.samples.num_rows == 0:
        return _note("No per-sample evaluation rows yet.")
    t = d.samples.filter(pa.array(shards.ok_mask(d.samples)))
    split = _main_split(t.column("split").to_pylist()) if t.num_rows else None
    if split is None:
        return _note("No successfully evaluated samples yet.")
    t = t.filter(pa.array([s == split for s in t.column("split").to_pylist()]))
    fd_all = _col(t, "f_dist")
    if not np.isfinite(fd_all).any() or not np.isfinite(_col(t, "azimuth_deg")).any():
        return _note("Azimuth or f_dist not recorded in the per-sample rows yet.")
    # shared f_dist bins (quartiles over all iterations) so the heat maps are comparable
    edges = np.unique(np.quantile(fd_all[np.isfinite(fd_all)], np.linspace(0, 1, 5)))
    if len(edges) < 2:
        edges = np.array([edges[0], edges[0] + 1e-9])
    its = sorted(set(t.column("iteration").to_pylist()))
    fig = Figure(figsize=(4.6 * len(its) + 1.0, 3.4), layout="constrained")
    cmap = colormaps["RdYlGn_r"].with_extremes(bad="#d9d9d9")
    image = None
    for k, it in enumerate(its):
        sub = t.filter(pa.array([i == it for i in t.column("iteration").to_pylist()]))
        fr = evaluation.failure_rates(_col(sub, "azimuth_deg"), _col(sub, "f_dist"), _col(sub, "cd_cm"),
                                      f_dist_edges=edges)
        ax = fig.add_subplot(1, len(its), k + 1)
        image = ax.imshow(100 * fr.rate, origin="lower", aspect="auto", cmap=cmap, vmin=0, vmax=100,
                          extent=(fr.azimuth_edges[0], fr.azimuth_edges[-1], 0, len(edges) - 1))
        ax.set_xticks([-180, -90, 0, 90, 180])
        ax.set_yticks(np.arange(len(edges) - 1) + 0.5, [f"{edges[i]:.2f}–{edges[i + 1]:.2f}"
                                                         for i in range(len(edges) - 1)], fontsize=7)
        ax.set_xlabel("azimuth (°; 0 front, ±90 side)")
        if k == 0:
            ax.set_ylabel("f_dist bin (m)")
        ax.set_title(f"iteration {_iter_label(it)}", fontsize=10)
    fig.colorbar(image, ax=fig.axes, label="% CD > 5 cm", fraction=0.03)
    return _png(fig, "failure rates") + (f'<p class="caption">Split \'{html.escape(split)}\': percentage of '
                                         "samples with CD > 5 cm per azimuth bin (30°) and f_dist quartile; grey "
                                         "cells hold no samples.</p>")


def _camera_sources(d: _RunData) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """[(label, azimuth, elevation, roll, cluster)] of the datasets with camera angles."""
    out = []
    if d.samples.num_rows:
        its = d.samples.column("iteration").to_pylist()
        last = max(its)
        t = d.samples.filter(pa.array([i == last for i in its]))
        az = _col(t, "azimuth_deg")
        if np.isfinite(az).any():
            out.append(("test set (ground-truth cameras)", az, _col(t, "elevation_deg"), _col(t, "roll_deg"),
                        _col(t, "cluster")))
    if d.fits:
        it = max(d.fits)
        t = d.fits[it]
        az = _col(t, "azimuth_deg")
        if np.isfinite(az).any():
            out.append((f"collection (estimated cameras, iteration {it})", az, _col(t, "elevation_deg"),
                        _col(t, "roll_deg"), _col(t, "cluster")))
    return out


def _heat(ax, counts: np.ndarray, xe: np.ndarray, ye: np.ndarray, xlabel: str, ylabel: str, title: str,
          vmax: float | None = None):
    im = ax.imshow(analysis.CameraHistograms.log_counts(counts), origin="lower", aspect="auto", cmap="viridis",
                   extent=(xe[0], xe[-1], ye[0], ye[-1]), vmin=0.0, vmax=vmax)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=9)
    return im


def _section_cameras(d: _RunData) -> str:
    sources = _camera_sources(d)
    if not sources:
        return _note("No camera angles recorded yet (azimuth_deg/elevation_deg/roll_deg in the evaluation or fit "
                     "rows).")
    parts = []
    for label, az, el, ro, cl in sources:
        h = analysis.camera_histograms(az, el, ro)
        fig = Figure(figsize=(13, 3.4), layout="constrained")
        ims = [
            _heat(fig.add_subplot(1, 3, 1), h.az_el, h.az_edges, h.el_edges, "azimuth (°)", "elevation (°)", ""),
            _heat(fig.add_subplot(1, 3, 2), h.az_roll, h.az_edges, h.roll_edges, "azimuth (°)", "roll (°)", ""),
            _heat(fig.add_subplot(1, 3, 3), h.el_roll, h.el_edges, h.roll_edges, "elevation (°)", "roll (°)", ""),
        ]
        fig.colorbar(ims[-1], ax=fig.axes, label="log10(1 + count)", fraction=0.02)
        fig.suptitle(f"{label}: {h.n} samples ({h.n_outside} outside the plotted range or missing)", fontsize=10)
        parts.append(_png(fig, f"camera heat maps, {label}"))
        finite = np.isfinite(cl) & (cl >= 0)
        if finite.any():
            per = analysis.camera_histograms_by_cluster(az[finite], el[finite], ro[finite], cl[finite].astype(int))
            n = len(per)
            cols = min(5, n)
            rows = int(math.ceil(n / cols))
            fig = Figure(figsize=(2.6 * cols + 0.8, 2.2 * rows + 0.5))
            fig.subplots_adjust(left=0.06, right=0.9, bottom=0.1, top=0.86, wspace=0.12, hspace=0.35)
            vmax = max(float(analysis.CameraHistograms.log_counts(hc.az_el).max()) for hc in per.values()) or 1.0
            axes = []
            for k, (c, hc) in enumerate(per.items()):
                ax = fig.add_subplot(rows, cols, k + 1)
                outer_x, outer_y = k >= n - cols, k % cols == 0
                im = _heat(ax, hc.az_el, hc.az_edges, hc.el_edges, "azimuth (°)" if outer_x else "",
                           "elevation (°)" if outer_y else "", f"cluster {c} (n={hc.n})", vmax=vmax)
                ax.tick_params(labelbottom=outer_x, labelleft=outer_y, labelsize=7)
                axes.append(ax)
            fig.colorbar(im, ax=axes, label="log10(1 + count)", fraction=0.02, pad=0.02)
            fig.suptitle(f"{label}: azimuth × elevation per pose cluster (log scale)", fontsize=10)
            parts.append(_png(fig, f"camera heat maps per cluster, {label}"))
    return "".join(parts)


def _section_angle_fits(d: _RunData) -> str:
    sources = _camera_sources(d)
    if not sources:
        return _note("No camera angles recorded yet.")
    label, _, el, ro, _ = sources[-1]  # prefer the collection's estimated cameras when present
    try:
        fits = analysis.fit_camera_angles(el, ro)
    except ImportError:
        return _note("bat3r_core.viewpoints.fit_angle_distribution is not available yet.")
    except ValueError as exc:
        return _note(f"Too few camera angles to fit yet ({exc}).")
    fig = Figure(figsize=(11, 3.4))
    for k, (name, values) in enumerate((("elevation", el), ("roll", ro))):
        fit = fits[name]
        v = values[np.isfinite(values)]
        ax = fig.add_subplot(1, 2, k + 1)
        lo, hi = np.percentile(v, [0.5, 99.5])
        pad = 0.1 * (hi - lo) + 1.0
        grid = np.linspace(lo - pad, hi + pad, 400)
        ax.hist(v, bins=60, range=(grid[0], grid[-1]), density=True, color="#bbbbbb", label="samples")
        pdf_t, pdf_n = analysis.angle_fit_densities(fit, grid)
        df, loc, scale = fit.student_t
        ax.plot(grid, pdf_t, color=_COLORS[0], lw=2,
                label=f"Student's t (df={df:.2f}, loc={loc:.2f}, scale={scale:.2f}); LL={fit.loglik_t:.1f}")
        ax.plot(grid, pdf_n, color=_COLORS[1], lw=2, ls="--",
                label=f"Normal (loc={fit.normal[0]:.2f}, σ={fit.normal[1]:.2f}); LL={fit.loglik_normal:.1f}")
        ax.set_xlabel(f"{name} (°)")
        ax.set_ylabel("density")
        ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{label}", fontsize=10)
    fig.tight_layout()
    rows = [[name, *fits[name].student_t, *fits[name].normal, fits[name].loglik_t, fits[name].loglik_normal]
            for name in ("elevation", "roll")]
    return _png(fig, "angle fits") + _table(["angle", "t df", "t loc", "t scale", "normal loc", "normal σ",
                                             "log-lik t", "log-lik normal"], rows, "num")


def _section_pseudo_labels(d: _RunData) -> str:
    if not d.fits:
        return _note("No fits yet: iteration 0 trains on canonical renders; fits appear from iteration 1 on.")
    summaries = {it: analysis.summarize_pseudo_labels(t) for it, t in sorted(d.fits.items())}
    statuses = sorted({s for m in summaries.values() for s in m.status_counts})
    rows = [[it, m.n, m.n_ok, *[m.status_counts.get(s, 0) for s in statuses if s != "ok"], m.mean_joint_err_cm,
             m.mean_vertex_err_cm, m.mean_angle_err_deg, m.mean_bone_err_deg] for it, m in summaries.items()]
    header = ["iteration", "fits", "kept (ok)", *[f"{s}" for s in statuses if s != "ok"],
              "joint err (cm)", "vertex err (cm)", "angle err (°)", "bone direction err (°)"]
    parts = [_table(header, rows, "num")]
    loss_names = sorted({k for m in summaries.values() for k in m.losses})
    if loss_names:
        main = "loss_total" if "loss_total" in loss_names else loss_names[0]
        fig = Figure(figsize=(11, 3.2))
        ax = fig.add_subplot(1, 2, 1)
        for j, (it, m) in enumerate(summaries.items()):
            v = m.losses.get(main, np.array([]))
            if len(v):
                ax.hist(v, bins=30, histtype="step", lw=1.5, color=_COLORS[j % len(_COLORS)],
                        label=f"iteration {it}")
        ax.set_xlabel(main)
        ax.set_ylabel("fits")
        ax.set_title("final fitting loss (kept fits)", fontsize=10)
        ax.legend(fontsize=8)
        ax = fig.add_subplot(1, 2, 2)
        its = list(summaries)
        for j, name in enumerate(loss_names):
            med = [float(np.median(summaries[i].losses[name])) if len(summaries[i].losses.get(name, [])) else np.nan
                   for i in its]
            ax.plot(its, med, marker="o", color=_COLORS[j % len(_COLORS)], label=name)
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        ax.set_title("median of each loss term", fontsize=10)
        ax.legend(fontsize=7)
        ax.xaxis.get_major_locator().set_params(integer=True)
        fig.tight_layout()
        parts.append(_png(fig, "fitting losses"))
    else:
        parts.append(_note("No loss_* columns in the fit rows yet."))
    reasons = [[it, r, c] for it, m in summaries.items() for r, c in list(m.reason_counts.items())[:8]]
    parts.append(_table(["iteration", "why filtered / failed", "samples"], reasons) if reasons
                 else "<p>No fit was filtered or failed.</p>")
    return "".join(parts)


def _project(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    z = np.where(np.abs(points[:, 2]) < 1e-9, 1e-9, points[:, 2])
    return np.stack([k[0, 0] * points[:, 0] / z + k[0, 2], k[1, 1] * points[:, 1] / z + k[1, 2]], 1)


def _point_size(n: int) -> float:
    return float(np.clip(4000.0 / max(n, 1), 1.0, 14.0))


def _qualitative_figure(q: QualitativeInputs) -> Figure:
    s = min(len(q.sample_id), _MAX_QUALITATIVE)
    fig = Figure(figsize=(11, 2.8 * s), layout="constrained")
    titles = ["input image", "prediction, input view", "prediction, novel view (90° about up)",
              "fitted mesh overlay"]
    for i in range(s):
        img = q.image[i]
        h, w = img.shape[:2]
        extent = (0, w, h, 0)  # pixel centres at (j + 0.5, i + 0.5)
        pts = q.pred_points[i].astype(np.float64)
        pts = pts[np.isfinite(pts).all(1)]
        axes = [fig.add_subplot(s, 4, 4 * i + c + 1) for c in range(4)]
        axes[0].imshow(img, extent=extent)
        cd = "" if q.cd_cm is None or not np.isfinite(q.cd_cm[i]) else f"\nCD {q.cd_cm[i]:.2f} cm"
        axes[0].set_ylabel(f"{q.sample_id[i]}{cd}", fontsize=8)
        axes[1].imshow(img, extent=extent, alpha=0.35)
        for ax in axes[1:3]:
            ax.set_facecolor("#15171c")
        if len(pts):
            size = _point_size(len(pts))
            norm = Normalize(float(pts[:, 2].min()), float(pts[:, 2].max()) + 1e-9)
            uv = _project(pts, q.intrinsics[i])
            axes[1].scatter(uv[:, 0], uv[:, 1], c=pts[:, 2], s=size, cmap="turbo", norm=norm, linewidths=0)
            # novel view: rotate 90° about the camera's vertical (y) axis around the centroid, orthographic
            rot = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
            nv = (pts - pts.mean(0)) @ rot.T
            axes[2].scatter(nv[:, 0], -nv[:, 1], c=nv[:, 2], s=size, cmap="turbo", linewidths=0)
            half = 0.55 * float(np.ptp(nv[:, :2], axis=0).max() + 1e-6)
            axes[2].set_xlim(-half, half)
            axes[2].set_ylim(-half, half)
            axes[2].set_aspect("equal")
        else:
            axes[2].text(0.5, 0.5, "no points", ha="center", va="center", color="white",
                         transform=axes[2].transAxes)
        axes[1].set_xlim(0, w)
        axes[1].set_ylim(h, 0)
        axes[3].imshow(img, extent=extent)
        fv = None if q.fitted_verts is None else q.fitted_verts[i]
        if fv is not None and np.isfinite(fv).all() and len(q.faces):
            uv = _project(fv.astype(np.float64), q.intrinsics[i])
            axes[3].add_collection(PolyCollection(uv[q.faces], facecolors=(0.2, 0.8, 1.0, 0.18),
                                                  edgecolors=(0.2, 0.9, 1.0, 0.7), linewidths=0.4))
            axes[3].set_xlim(0, w)
            axes[3].set_ylim(h, 0)
        else:
            axes[3].text(0.5, 0.5, "no fit", ha="center", va="center", transform=axes[3].transAxes,
                         color="white", fontsize=12, bbox={"facecolor": "black", "alpha": 0.5})
        for c, ax in enumerate(axes):
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(titles[c], fontsize=9)
    return fig


def _section_qualitative(d: _RunData) -> str:
    if not d.qualitative:
        return _note("No qualitative samples yet (iter-NN/evaluate/qualitative.npz).")
    parts = []
    for it, path in sorted(d.qualitative.items(), reverse=True):
        try:
            q = read_report_inputs(path)
        except (OSError, ValueError) as exc:
            parts.append(_note(f"iteration {it}: {path.name} unreadable ({exc})."))
            continue
        parts.append(f"<h3>Iteration {_iter_label(it)}</h3>" + _png(_qualitative_figure(q), f"qualitative {it}"))
    return "".join(parts)


_SECTIONS: dict[str, Callable[[_RunData], str]] = {
    "summary": _section_summary,
    "metrics-over-iterations": _section_metrics,
    "ablation-table": _section_ablation,
    "collection-masks": _section_collection_masks,
    "per-cluster": _section_clusters,
    "failure-rates": _section_failures,
    "camera-distribution": _section_cameras,
    "angle-fits": _section_angle_fits,
    "pseudo-labels": _section_pseudo_labels,
    "qualitative": _section_qualitative,
}
