"""COCO-style instance annotations as a bat3r collection: one mask PNG per kept instance and a Parquet index.

Photo collections of animals often come as one COCO ``instances`` JSON (COCO itself, LVIS, Animal-Pose, APT-36K,
exports of CVAT, Label Studio and Roboflow) rather than one mask file per image. :func:`coco_to_collection`
turns one category of such a file into the Parquet-index layout every bat3r stage reads
(``docs/collections.md``): ``<out>/masks/<sample_id>.png`` (0/255) and ``<out>/index.parquet`` with ``sample_id``,
``image_path`` (the original photo, not copied) and ``mask_path``. Point the catalog's collection at the index
(``kind: parquet``).

* Segmentations: polygons (a list of ``[x1, y1, x2, y2, ...]`` rings in pixel-edge coordinates, whose union is the
  instance), uncompressed RLE (``counts`` a list) and compressed RLE (``counts`` a string), both column-major as
  COCO stores them. Polygons are rasterised by pixel centres (a pixel is inside when its centre ``(j + 0.5,
  i + 0.5)`` is inside a ring, even-odd rule); RLE is decoded exactly.
* One sample per instance (the crop centres on it; the rest of the photo is background to the mask), id
  ``<image stem>-<annotation id>``; ``largest_only`` keeps only each image's largest instance of the category.
* Instances that cannot make a pseudo-label are not written and are counted by reason in ``coco_conversion.json``:
  crowd annotations (``iscrowd`` 1: several animals in one mask), instances below ``min_area`` mask pixels,
  annotations whose segmentation is missing, malformed or of another size than its image, and with
  ``exclude_truncated`` instances whose mask touches the image border (the animal continues outside the photo:
  its crop shows part of a body the fit would place as a whole), and with ``max_occlusion`` instances whose outline
  runs along another annotated object for more than that fraction of it (:func:`occlusion_fraction`: a rider on a
  horse, a foal in front of its mare), whose mask lacks the parts hidden behind it.
"""
from __future__ import annotations

import json
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

from bat3r_core.shards import atomic_write, atomic_write_bytes, atomic_write_text

__all__ = ["CocoConversion", "rle_counts", "decode_rle", "polygons_to_mask", "segmentation_to_mask",
           "occlusion_fraction", "coco_to_collection", "CONVERSION_FILE", "INDEX_FILE", "OCCLUSION_RING_PX"]

INDEX_FILE = "index.parquet"
CONVERSION_FILE = "coco_conversion.json"  # what was converted from which file, and what was skipped and why
OCCLUSION_RING_PX = 3
"""Width (pixels) of the ring just outside an instance's mask in which :func:`occlusion_fraction` looks for other
objects: annotators leave a pixel or two between touching objects, and polygon rasterisation another."""


def rle_counts(counts: str | bytes) -> list[int]:
    """The run lengths of a compressed COCO RLE string.

    Each count is a little-endian sequence of 5-bit groups, each group stored as one character ``48 + g`` whose
    bit 5 (0x20) says another group follows; the last group's bit 4 (0x10) is the sign. From the fourth count on,
    the stored value is the difference to the count two places before (runs of zeros and of ones alternate, and
    neighbouring runs of the same kind tend to be alike)."""
    data = counts.encode("ascii") if isinstance(counts, str) else bytes(counts)
    out: list[int] = []
    p = 0
    while p < len(data):
        value, shift, more = 0, 0, True
        while more:
            if p >= len(data):
                raise ValueError("compressed RLE ends inside a count")
            group = data[p] - 48
            if not 0 <= group < 64:
                raise ValueError(f"compressed RLE has a character {chr(data[p])!r} outside '0'..'o'")
            value |= (group & 0x1F) << shift
            more = bool(group & 0x20)
            p += 1
            shift += 5
            if not more and group & 0x10:
                value -= 1 << shift  # negative: sign-extend from the last group
        if len(out) > 2:
            value += out[-2]
        out.append(value)
    return out


def decode_rle(rle: Mapping[str, Any]) -> np.ndarray:
    """A COCO RLE (``{"size": [h, w], "counts": list or string}``) as a (h, w) bool mask."""
    try:
        h, w = (int(v) for v in rle["size"])
        counts = rle["counts"]
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"RLE must have 'size' [height, width] and 'counts'; got keys {sorted(rle)}") from None
    runs = rle_counts(counts) if isinstance(counts, (str, bytes)) else [int(c) for c in counts]
    runs_arr = np.asarray(runs, dtype=np.int64)
    if (runs_arr < 0).any():
        raise ValueError("RLE has a negative run length")
    if int(runs_arr.sum()) != h * w:
        raise ValueError(f"RLE runs cover {int(runs_arr.sum())} pixels; its size {h}x{w} has {h * w}")
    values = np.zeros(len(runs_arr), dtype=bool)
    values[1::2] = True  # runs alternate, starting with background
    flat = np.repeat(values, runs_arr)
    return flat.reshape(w, h).T  # column-major, as COCO stores it


def polygons_to_mask(polygons: Sequence[Sequence[float]], height: int, width: int) -> np.ndarray:
    """The union of polygon rings (``[x1, y1, x2, y2, ...]`` in pixel-edge coordinates: pixel ``(i, j)`` covers
    ``[j, j + 1] x [i, i + 1]``) rasterised by pixel centres, as a (height, width) bool mask."""
    from skimage.draw import polygon as fill_polygon

    mask = np.zeros((height, width), dtype=bool)
    for k, ring in enumerate(polygons):
        xy = np.asarray(ring, dtype=np.float64)
        if xy.ndim != 1 or len(xy) < 6 or len(xy) % 2:
            raise ValueError(f"polygon {k} has {len(xy)} numbers; expected x, y pairs of at least 3 points")
        if not np.isfinite(xy).all():
            raise ValueError(f"polygon {k} has a non-finite coordinate")
        # skimage tests integer pixel coordinates (the centres); COCO's centres sit at j + 0.5
        rr, cc = fill_polygon(xy[1::2] - 0.5, xy[0::2] - 0.5, shape=(height, width))
        mask[rr, cc] = True
    return mask


def segmentation_to_mask(segmentation: Any, height: int, width: int) -> np.ndarray:
    """A COCO ``segmentation`` (polygons, or RLE with list or string counts) as a (height, width) bool mask of an
    image of that size; ValueError says what is wrong (a malformed entry, an RLE of another size)."""
    if isinstance(segmentation, dict):
        mask = decode_rle(segmentation)
        if mask.shape != (height, width):
            raise ValueError(f"RLE size {mask.shape[0]}x{mask.shape[1]} differs from the image's "
                             f"{height}x{width}")
        return mask
    if isinstance(segmentation, list) and segmentation and all(isinstance(r, list) for r in segmentation):
        return polygons_to_mask(segmentation, height, width)
    raise ValueError(f"segmentation must be a list of polygons or an RLE dict; got {type(segmentation).__name__}"
                     f"{' (empty)' if not segmentation else ''}")


@dataclass
class CocoConversion:
    """What :func:`coco_to_collection` wrote: the index, the number of samples, and the skipped instances by
    reason (with up to three example annotation ids each)."""

    index: Path
    samples: int
    images: int
    skipped: dict[str, int] = field(default_factory=dict)
    examples: dict[str, list[Any]] = field(default_factory=dict)


def occlusion_fraction(mask: np.ndarray, others: np.ndarray, ring_px: int = OCCLUSION_RING_PX) -> float:
    """The share of an instance's outline that runs along other objects.

    The outline is the ring of pixels within ``ring_px`` (Chebyshev distance) outside ``mask`` and inside the
    image; the result is the fraction of it covered by ``others`` (the union of the image's other annotations'
    masks). Where another object touches the instance it may stand in front of it, hiding a part of the animal the
    mask then lacks (COCO does not say which is in front), so the fraction bounds how much of the outline may be
    an occlusion boundary rather than the animal's own. 0 for a mask without a ring (it fills the image).

    Args:
        mask, others: (H, W) bool.
    """
    mask, others = np.asarray(mask, dtype=bool), np.asarray(others, dtype=bool)
    if mask.shape != others.shape or mask.ndim != 2:
        raise ValueError(f"mask and others must be (H, W) of one shape, got {mask.shape} and {others.shape}")
    kernel = np.ones((2 * ring_px + 1, 2 * ring_px + 1), np.uint8)
    ring = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool) & ~mask
    n = int(ring.sum())
    return float((ring & others).sum() / n) if n else 0.0


def _load(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ValueError(f"COCO annotations {path} cannot be read ({e.strerror or e})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"COCO annotations {path} is not JSON: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"COCO annotations {path}: expected a JSON object with 'images', 'annotations' and "
                         f"'categories'; got a {type(data).__name__}")
    for key in ("images", "annotations", "categories"):
        if not isinstance(data.get(key), list):
            raise ValueError(f"COCO annotations {path}: expected a list under '{key}'; "
                             f"{'it is missing' if key not in data else 'got ' + type(data[key]).__name__} "
                             f"(keys: {sorted(data)})")
    return data


def _category_id(data: dict, category: str | int, path: Path) -> tuple[int, str]:
    cats = [c for c in data["categories"] if isinstance(c, dict) and "id" in c]
    for c in cats:
        if str(c.get("name", "")).lower() == str(category).lower() or str(c["id"]) == str(category):
            return int(c["id"]), str(c.get("name", c["id"]))
    names = ", ".join(f"{c.get('name', '?')} ({c['id']})" for c in cats[:40])
    raise ValueError(f"COCO annotations {path}: no category named or numbered {category!r}; it has "
                     f"{len(cats)}: {names}{', ...' if len(cats) > 40 else ''}")


def coco_to_collection(annotations: str | os.PathLike, images: str | os.PathLike, category: str | int,
                       out: str | os.PathLike, min_area: int = 1024, largest_only: bool = False,
                       exclude_truncated: bool = False, max_occlusion: float | None = None) -> CocoConversion:
    """Write one category of a COCO instances file as a bat3r Parquet-index collection in ``out``.

    Args:
        annotations: the COCO JSON (``images``, ``annotations``, ``categories``).
        images: the folder the images' ``file_name`` entries are relative to.
        category: the category's name (case-insensitive) or id.
        out: the collection folder: ``masks/``, ``index.parquet`` and ``coco_conversion.json`` are written there
            (rerunning replaces them; other files are left alone).
        min_area: instances with fewer mask pixels are skipped (default 32 x 32: smaller animals give crops
            with little more than a silhouette).
        largest_only: keep only the largest qualifying instance of each image.
        exclude_truncated: skip instances whose mask has a pixel in the image's first or last row or column
            (cut off by the photo's edge). Applied before ``largest_only``, so a photo whose largest animal is cut
            off keeps its largest whole one.
        max_occlusion: skip instances whose :func:`occlusion_fraction` against every other annotation of their
            image (any category, crowds included) exceeds this (None: keep them all). Applied before
            ``largest_only`` too.

    Images are not opened or copied: a missing or unreadable photo becomes a ``bad_image`` row when the
    collection is read, like any other. Raises ValueError naming the file and key for a file that is not COCO
    instances, or an unknown category.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    annotations, images, out = Path(annotations), Path(images), Path(out)
    if min_area < 0:
        raise ValueError(f"min_area must be >= 0, got {min_area}")
    if max_occlusion is not None and not 0.0 <= max_occlusion <= 1.0:
        raise ValueError(f"max_occlusion must be a fraction in [0, 1], got {max_occlusion}")
    data = _load(annotations)
    cat_id, cat_name = _category_id(data, category, annotations)
    index_path = out / INDEX_FILE
    if index_path.exists() and not (out / CONVERSION_FILE).exists():
        raise ValueError(f"{index_path} exists and was not written by a COCO conversion "
                         f"(no {CONVERSION_FILE} beside it); choose another --out")
    image_rows: dict[Any, dict] = {}
    for k, im in enumerate(data["images"]):
        if not isinstance(im, dict) or "id" not in im or not isinstance(im.get("file_name"), str):
            raise ValueError(f"COCO annotations {annotations}: images[{k}] must have 'id' and 'file_name'")
        image_rows[im["id"]] = im

    skipped: Counter[str] = Counter()
    examples: dict[str, list[Any]] = {}

    def skip(reason: str, ann_id: Any) -> None:
        skipped[reason] += 1
        examples.setdefault(reason, [])
        if len(examples[reason]) < 3:
            examples[reason].append(ann_id)

    # one pass over the annotations without decoding anything, then one image at a time, so memory holds the masks
    # of one photo, not of the whole category (COCO's horses alone would be ~2 GB of full-size masks)
    candidates: dict[Any, list[tuple[Any, Any]]] = {}  # image id -> [(annotation id, segmentation)]
    for k, ann in enumerate(data["annotations"]):
        if not isinstance(ann, dict) or ann.get("category_id") != cat_id:
            continue
        ann_id = ann.get("id", f"#{k}")
        im = image_rows.get(ann.get("image_id"))
        if im is None:
            skip("image_id not among the images", ann_id)
            continue
        if ann.get("iscrowd", 0):
            skip("crowd annotation (iscrowd 1: several animals in one mask)", ann_id)
            continue
        candidates.setdefault(im["id"], []).append((ann_id, ann.get("segmentation")))
    occluders: dict[Any, list[tuple[Any, Any]]] = {}  # image id -> every annotation of it, any category
    if max_occlusion is not None:
        for k, ann in enumerate(data["annotations"]):
            if isinstance(ann, dict) and ann.get("image_id") in candidates:
                occluders.setdefault(ann["image_id"], []).append((ann.get("id", f"#{k}"), ann.get("segmentation")))

    rows, written, images_with_samples = [], set(), 0
    for image_id, anns in candidates.items():
        im = image_rows[image_id]
        try:
            h, w = int(im["height"]), int(im["width"])
        except (KeyError, TypeError, ValueError):
            for ann_id, _ in anns:
                skip("its image has no integer width and height", ann_id)
            continue
        instances: list[tuple[int, Any, np.ndarray]] = []  # (area, annotation id, mask)
        for ann_id, segmentation in anns:
            try:
                mask = segmentation_to_mask(segmentation, h, w)
            except ValueError as e:
                skip(f"bad segmentation: {e}", ann_id)
                continue
            area = int(mask.sum())
            if area < max(min_area, 1):
                skip(f"smaller than min_area ({min_area} pixels)" if area else "empty mask", ann_id)
                continue
            if exclude_truncated and (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any()):
                skip("cut off by the image border (exclude_truncated)", ann_id)
                continue
            instances.append((area, ann_id, mask))
        if max_occlusion is not None and instances:
            instances = _drop_occluded(instances, occluders[image_id], h, w, max_occlusion, skip)
        if not instances:
            continue
        images_with_samples += 1
        instances.sort(key=lambda t: -t[0])
        if largest_only:
            for _, ann_id, _ in instances[1:]:
                skip("not the image's largest instance (largest_only)", ann_id)
            instances = instances[:1]
        stem = Path(im["file_name"]).stem
        for _, ann_id, mask in instances:
            sid = f"{stem}-{ann_id}"
            if sid in written:  # two images share a stem: qualify by the image id
                sid = f"{stem}-{image_id}-{ann_id}"
            written.add(sid)
            ok, png = cv2.imencode(".png", mask.astype(np.uint8) * 255)
            if not ok:
                raise RuntimeError(f"could not encode the mask of annotation {ann_id}")
            mask_rel = f"masks/{sid}.png"
            atomic_write_bytes(out / mask_rel, png.tobytes())
            image_path = images / im["file_name"]
            try:  # relative to the index when it can be, so the folders can move together
                image_ref = os.path.relpath(image_path.resolve(), out.resolve())
            except ValueError:  # another drive (Windows)
                image_ref = str(image_path.resolve())
            rows.append({"sample_id": sid, "image_path": image_ref, "mask_path": mask_rel})
    rows.sort(key=lambda r: r["sample_id"])
    if not rows:
        why = "; ".join(f"{n} {r}" for r, n in sorted(skipped.items())) or "it has no annotations"
        raise ValueError(f"COCO annotations {annotations}: no instance of category '{cat_name}' ({cat_id}) "
                         f"makes a sample ({why})")
    table = pa.table({k: pa.array([r[k] for r in rows], pa.string())
                      for k in ("sample_id", "image_path", "mask_path")})
    report = {"annotations": str(annotations.resolve()), "images": str(images.resolve()),
              "category": cat_name, "category_id": cat_id, "min_area": min_area, "largest_only": largest_only,
              "exclude_truncated": exclude_truncated, "max_occlusion": max_occlusion,
              "occlusion_ring_px": OCCLUSION_RING_PX,
              "samples": len(rows), "images_with_samples": images_with_samples,
              "skipped": dict(sorted(skipped.items())), "skipped_examples": examples}
    atomic_write_text(out / CONVERSION_FILE, json.dumps(report, indent=1, default=str))
    atomic_write(index_path, lambda tmp: pq.write_table(table, tmp))
    return CocoConversion(index_path, len(rows), images_with_samples, dict(skipped), examples)


def _drop_occluded(instances: list[tuple[int, Any, np.ndarray]], annotations: list[tuple[Any, Any]], height: int,
                   width: int, max_occlusion: float, skip) -> list[tuple[int, Any, np.ndarray]]:
    """``instances`` (area, annotation id, mask) of one image without those whose outline runs along the image's
    other ``annotations`` (annotation id, segmentation) for more than ``max_occlusion`` of it. Every annotation
    counts as an occluder, whatever its category or crowd flag; one whose segmentation does not decode is left
    out."""
    own = {ann_id: mask for _, ann_id, mask in instances}
    count = np.zeros((height, width), np.uint16)  # how many annotations cover each pixel
    for ann_id, segmentation in annotations:
        if ann_id in own:
            count += own[ann_id]
            continue
        try:
            count += segmentation_to_mask(segmentation, height, width)
        except ValueError:
            continue
    whole = []
    for area, ann_id, mask in instances:
        if occlusion_fraction(mask, (count - mask) > 0) > max_occlusion:
            skip(f"runs along another annotated object for more than {max_occlusion:g} of its outline "
                 "(max_occlusion)", ann_id)
        else:
            whole.append((area, ann_id, mask))
    return whole
