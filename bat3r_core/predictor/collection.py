"""Image collections: listing, validating, object-centred cropping and sharding of photos with masks.

A collection is given explicitly, either as

* a folder with ``images/`` and ``masks/`` subfolders whose files are matched by stem
  (``images/a01.jpg`` ↔ ``masks/a01.png``), or
* a Parquet index with columns ``image_path`` and ``mask_path`` (relative paths resolve against the index
  file's folder) and an optional ``sample_id`` column.

Each sample is read with its mask, checked (see ``STATUS_*`` below), cropped to a square around the mask's
bounding box with a relative margin, resized to the model resolution and masked. The ``CropTransform`` kept with
every sample maps original pixel coordinates to crop pixel coordinates and back, and original intrinsics to the
crop's intrinsics, in the pixel convention of ``docs/CONVENTIONS.md`` (the image spans ``[0, W] x [0, H]``,
pixel ``[i, j]`` has its centre at ``(j + 0.5, i + 0.5)``).

Images are decoded in their stored pixel orientation (EXIF orientation tags are not applied), the same way the
masks are. A photo whose mask has the size of the photo as displayed (its EXIF orientation turns it by 90 degrees,
and the mask was drawn on the turned photo) is turned the same way (:func:`apply_exif_orientation`); any other size
difference is a size mismatch.
"""
from __future__ import annotations

import io
import math
import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import pyarrow.parquet as pq

from bat3r_core.shards import STATUS_OK, ShardPaths, shard_paths, write_shard

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff")
# Photo formats bat3r does not decode: listed anyway, so each is recorded as a bad image that says how to convert it
# instead of vanishing from the collection.
UNREADABLE_IMAGE_FORMATS = {".heic": "HEIC/HEIF", ".heif": "HEIC/HEIF", ".avif": "AVIF", ".gif": "GIF",
                            ".jxl": "JPEG XL", ".dng": "camera raw (DNG)", ".cr2": "camera raw (CR2)",
                            ".cr3": "camera raw (CR3)", ".nef": "camera raw (NEF)", ".arw": "camera raw (ARW)",
                            ".orf": "camera raw (ORF)", ".rw2": "camera raw (RW2)", ".raf": "camera raw (RAF)"}
MASK_SUFFIX = ".png"  # the preferred mask format (lossless)
MASK_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".webp", ".jpg", ".jpeg")  # looked up in this order

# Statuses of a collection row besides "ok"; the row's ``reason`` names the file and what was expected.
STATUS_BAD_IMAGE = "bad_image"          # missing, unreadable, truncated, grey-scale, RGBA or not 8-bit
STATUS_MISSING_MASK = "missing_mask"    # no mask file for the image
STATUS_BAD_MASK = "bad_mask"            # mask unreadable, truncated or with differing colour channels
STATUS_EMPTY_MASK = "empty_mask"        # mask has no foreground pixel
STATUS_SIZE_MISMATCH = "size_mismatch"  # mask and image sizes differ

DEFAULT_MARGIN = 0.175  # the middle of the U(0.1, 0.25) margin the training renders leave around the object


@dataclass(frozen=True)
class CollectionConfig:
    """Preprocessing of a collection for the predictor.

    Attributes:
        resolution: side of the square crops fed to the predictor, pixels (reference 160).
        margin: fraction of the crop side left free on each side of the mask's bounding box (along its longer
            side): ``side = extent / (1 - 2 margin)``. The default matches the training renders.
        shard_size: samples per output shard.
    """

    resolution: int = 160
    margin: float = DEFAULT_MARGIN
    shard_size: int = 256

    def __post_init__(self) -> None:
        if self.resolution < 1:
            raise ValueError(f"resolution must be >= 1, got {self.resolution}")
        if not 0.0 <= self.margin < 0.5:
            raise ValueError(f"margin must be in [0, 0.5), got {self.margin}")
        if self.shard_size < 1:
            raise ValueError(f"shard_size must be >= 1, got {self.shard_size}")


@dataclass(frozen=True)
class CollectionSample:
    """One entry of a collection before it is read: ``mask_path`` is None when no mask was found."""

    sample_id: str
    image_path: Path
    mask_path: Path | None


# --------------------------------------------------------------------------------------------------- crop transform
@dataclass(frozen=True)
class CropTransform:
    """A square crop of an image, resized to ``resolution`` pixels.

    The crop box is ``[x0, x0 + size] x [y0, y0 + size]`` in continuous original pixel coordinates (it may
    extend beyond the image, where the crop is padded with zeros); ``scale = resolution / size`` crop pixels
    per original pixel. A point ``(u, v)`` of the original image maps to ``((u - x0) scale, (v - y0) scale)``.
    """

    x0: float
    y0: float
    size: float
    resolution: int

    def __post_init__(self) -> None:
        if not self.size > 0:
            raise ValueError(f"crop size must be > 0, got {self.size}")
        if self.resolution < 1:
            raise ValueError(f"crop resolution must be >= 1, got {self.resolution}")

    @property
    def scale(self) -> float:
        """Crop pixels per original pixel."""
        return self.resolution / self.size

    @property
    def box(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)`` in original pixels."""
        return (self.x0, self.y0, self.x0 + self.size, self.y0 + self.size)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float64 ``S`` with ``[u', v', 1] = S @ [u, v, 1]`` (original → crop pixels)."""
        s = self.scale
        return np.array([[s, 0.0, -s * self.x0], [0.0, s, -s * self.y0], [0.0, 0.0, 1.0]])

    def apply(self, uv: np.ndarray) -> np.ndarray:
        """Original pixel coordinates → crop pixel coordinates.

        Args:
            uv: (..., 2) float, original image pixels ``(u, v)``.
        Returns:
            (..., 2) float64, crop pixels.
        """
        uv = _check_uv(uv)
        return (uv - np.array([self.x0, self.y0])) * self.scale

    def invert(self, uv_crop: np.ndarray) -> np.ndarray:
        """Crop pixel coordinates → original pixel coordinates; (..., 2) → (..., 2) float64."""
        uv_crop = _check_uv(uv_crop, "uv_crop")
        return uv_crop / self.scale + np.array([self.x0, self.y0])

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """Intrinsics of the crop from intrinsics ``K`` (3, 3) of the original image: ``K' = S @ K``."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape (3, 3), got {K.shape}")
        return self.matrix @ K


def _check_uv(uv: np.ndarray, name: str = "uv") -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim == 0 or uv.shape[-1] != 2:
        raise ValueError(f"{name} must have shape (..., 2), got {uv.shape}")
    return uv


def crop_box_for_mask(mask: np.ndarray, margin: float = DEFAULT_MARGIN) -> tuple[int, int, int]:
    """Integer square crop ``(x0, y0, size)`` around the foreground of ``mask`` (H, W) bool, original pixels.

    The box is centred on the mask's bounding box and its side is ``ceil(extent / (1 - 2 margin))`` where
    ``extent`` is the bounding box's longer side, so the object keeps at least ``margin`` of the side free on
    each side. Integer corners make the crop a pixel-exact slice before resizing.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must have shape (H, W), got {mask.shape}")
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        raise ValueError("mask has no foreground pixel")
    # continuous box: pixel j covers [j, j + 1]
    u0, u1 = cols[0], cols[-1] + 1
    v0, v1 = rows[0], rows[-1] + 1
    extent = max(u1 - u0, v1 - v0)
    size = max(1, math.ceil(extent / (1.0 - 2.0 * margin) - 1e-9))
    x0 = math.floor((u0 + u1 - size) / 2.0 + 0.5)
    y0 = math.floor((v0 + v1 - size) / 2.0 + 0.5)
    return int(x0), int(y0), int(size)


def crop_to_square(image: np.ndarray, mask: np.ndarray, resolution: int, margin: float = DEFAULT_MARGIN
                   ) -> tuple[np.ndarray, np.ndarray, CropTransform]:
    """Object-centred square crop of an image, resized to ``resolution`` and masked.

    Args:
        image: (H, W, 3) uint8 RGB.
        mask: (H, W) bool, foreground.
        resolution: output side R, pixels.
        margin: relative margin, see ``crop_box_for_mask``.
    Returns:
        rgb (R, R, 3) uint8 with background 0, mask (R, R) bool and the ``CropTransform``. Parts of the box
        outside the image are zero. Images are resized with area averaging when shrunk and bilinearly when
        enlarged; masks by nearest neighbour with pixel-centre sampling (``INTER_NEAREST_EXACT``).
    """
    image = np.asarray(image)
    mask = np.asarray(mask)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask must have shape {image.shape[:2]} (the image's), got {mask.shape}")
    if resolution < 1:
        raise ValueError(f"resolution must be >= 1, got {resolution}")
    mask = mask.astype(bool)
    x0, y0, size = crop_box_for_mask(mask, margin)
    img_crop = _padded_slice(image, x0, y0, size)
    mask_crop = _padded_slice(mask.astype(np.uint8), x0, y0, size)
    interp = cv2.INTER_AREA if size > resolution else cv2.INTER_LINEAR
    rgb = cv2.resize(img_crop, (resolution, resolution), interpolation=interp)
    out_mask = cv2.resize(mask_crop, (resolution, resolution), interpolation=cv2.INTER_NEAREST_EXACT) > 0
    rgb[~out_mask] = 0
    return rgb, out_mask, CropTransform(float(x0), float(y0), float(size), int(resolution))


def _padded_slice(a: np.ndarray, x0: int, y0: int, size: int) -> np.ndarray:
    """``a[y0:y0+size, x0:x0+size]`` with zeros where the window leaves the array."""
    h, w = a.shape[:2]
    out = np.zeros((size, size) + a.shape[2:], dtype=a.dtype)
    sx0, sy0 = max(x0, 0), max(y0, 0)
    sx1, sy1 = min(x0 + size, w), min(y0 + size, h)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = a[sy0:sy1, sx0:sx1]
    return out


# ---------------------------------------------------------------------------------------------------------- listing
def list_folder_collection(folder: str | os.PathLike) -> list[CollectionSample]:
    """Samples of a folder collection (``images/`` + ``masks/``), sorted by image file name.

    The sample id is the image's stem; where two images share a stem (``a.jpg``, ``a.png``) both use their
    file name instead. The mask is ``masks/<stem>`` with an image suffix in any letter case, a lossless one first
    (``.png``, then ``.bmp``, ``.tif``, ``.tiff``, ``.webp``, ``.jpg``, ``.jpeg``: ``MASK_SUFFIXES``); none gives
    ``mask_path=None``.
    """
    folder = Path(folder)
    images_dir, masks_dir = folder / "images", folder / "masks"
    if not images_dir.is_dir():
        raise FileNotFoundError(f"collection folder {folder} has no 'images/' subfolder")
    listed = set(IMAGE_SUFFIXES) | set(UNREADABLE_IMAGE_FORMATS)
    images = sorted((p for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in listed),
                    key=lambda p: p.name)
    masks = _masks_by_stem(masks_dir)
    stem_count = Counter(p.stem for p in images)
    samples = []
    for p in images:
        sample_id = p.stem if stem_count[p.stem] == 1 else p.name
        samples.append(CollectionSample(sample_id, p, masks.get(p.stem)))
    return samples


def _masks_by_stem(masks_dir: Path) -> dict[str, Path]:
    """The mask file of each stem in ``masks_dir``: where several files share a stem (``a.png``, ``a.jpg``), the
    one whose suffix comes first in ``MASK_SUFFIXES`` (lossless before JPEG), then by file name."""
    if not masks_dir.is_dir():
        return {}
    rank = {suffix: k for k, suffix in enumerate(MASK_SUFFIXES)}
    files = sorted((p for p in masks_dir.iterdir() if p.is_file() and p.suffix.lower() in rank),
                   key=lambda p: (rank[p.suffix.lower()], p.name))
    found: dict[str, Path] = {}
    for p in files:
        found.setdefault(p.stem, p)
    return found


def list_parquet_collection(index_path: str | os.PathLike) -> list[CollectionSample]:
    """Samples of a Parquet index (``image_path``, ``mask_path``, optional ``sample_id``), in row order.

    Relative paths resolve against the index file's folder; an empty or null ``mask_path`` means no mask.
    Without a ``sample_id`` column the id is the image's stem, or its path as written where stems collide.
    """
    index_path = Path(index_path)
    table = pq.read_table(index_path)
    for col in ("image_path", "mask_path"):
        if col not in table.column_names:
            raise ValueError(f"collection index {index_path} must have a '{col}' column; "
                             f"got columns {table.column_names}")
    base = index_path.parent
    images = table.column("image_path").to_pylist()
    masks = table.column("mask_path").to_pylist()
    for i, p in enumerate(images):
        if not isinstance(p, str) or not p:
            raise ValueError(f"collection index {index_path}: row {i} has image_path {p!r}, expected a path")
    if "sample_id" in table.column_names:
        ids = [str(s) for s in table.column("sample_id").to_pylist()]
    else:
        stems = [Path(p).stem for p in images]
        counts = Counter(stems)
        ids = [s if counts[s] == 1 else p for s, p in zip(stems, images)]
    if len(set(ids)) != len(ids):
        dup = sorted(s for s, c in Counter(ids).items() if c > 1)[:5]
        raise ValueError(f"collection index {index_path}: sample ids must be unique; duplicated: {dup}")

    def resolve(p: str) -> Path:
        q = Path(p)
        return q if q.is_absolute() else base / q

    return [CollectionSample(sid, resolve(img), resolve(m) if isinstance(m, str) and m else None)
            for sid, img, m in zip(ids, images, masks)]


def list_collection(path: str | os.PathLike) -> list[CollectionSample]:
    """A folder collection (a directory) or a Parquet index (a ``.parquet`` file)."""
    path = Path(path)
    if path.is_dir():
        return list_folder_collection(path)
    if path.is_file() and path.suffix == ".parquet":
        return list_parquet_collection(path)
    raise ValueError(f"collection must be a folder with images/ and masks/ or a .parquet index, got {path}")


# ---------------------------------------------------------------------------------------------------------- reading
class BadSample(Exception):
    """A sample that cannot be used: ``status`` is one of the ``STATUS_*`` codes, ``reason`` says why."""

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(f"{status}: {reason}")
        self.status = status
        self.reason = reason


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"


def _truncation_problem(data: bytes) -> str | None:
    """Why an encoded image looks cut short, or None. PNG must hold its IEND chunk; a JPEG must have an EOI
    marker after its last start-of-scan (entropy-coded data stuffs 0xFF bytes, so 0xFFD9 cannot occur there).
    Other formats are fully decoded by Pillow, which raises on a truncated file."""
    if data.startswith(_PNG_MAGIC):
        return None if _PNG_IEND in data[-64:] or _PNG_IEND in data else "PNG ends before its IEND chunk"
    if data.startswith(b"\xff\xd8"):
        sos = data.rfind(b"\xff\xda")
        if sos < 0:
            return "JPEG has no start-of-scan marker"
        return None if data.find(b"\xff\xd9", sos) >= 0 else "JPEG ends before its end-of-image marker"
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:  # without Pillow only the decoder's own checks apply
        return None
    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()
    except UnidentifiedImageError:
        return None  # not an image format Pillow knows: the OpenCV decoder decides
    except Exception as e:  # Pillow raises OSError, SyntaxError, ValueError... for broken files
        return f"decoding failed ({type(e).__name__})"
    return None


def _decode(path: Path, status: str, what: str) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as e:
        raise BadSample(status, f"{what} {path} cannot be read ({e.strerror or e})") from None
    problem = _truncation_problem(data)
    if problem:
        raise BadSample(status, f"{what} {path} is truncated or corrupt: {problem}")
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise BadSample(status, f"{what} {path} is not a readable image")
    return arr


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit colour image as (H, W, 3) uint8 RGB; raise ``BadSample`` (status ``bad_image``) for a
    missing, unreadable, truncated, grey-scale, RGBA or higher-bit-depth file."""
    path = Path(path)
    if not path.is_file():
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} does not exist")
    unreadable = UNREADABLE_IMAGE_FORMATS.get(path.suffix.lower())
    if unreadable:
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} is {unreadable}, which bat3r does not decode; expected "
                                          f"{', '.join(IMAGE_SUFFIXES)} (convert it to JPEG or PNG)")
    arr = _decode(path, STATUS_BAD_IMAGE, "image")
    if arr.dtype != np.uint8:
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} has dtype {arr.dtype}; expected 8-bit RGB")
    channels = 1 if arr.ndim == 2 else arr.shape[2]
    if channels == 1:
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} is grey-scale (1 channel); expected 3-channel RGB")
    if channels == 4:
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} has an alpha channel (RGBA, 4 channels); "
                                          f"expected 3-channel RGB with the mask in masks/")
    if channels != 3:
        raise BadSample(STATUS_BAD_IMAGE, f"image {path} has {channels} channels; expected 3-channel RGB")
    return cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)


def read_mask(path: str | os.PathLike | None) -> np.ndarray:
    """Read a mask as (H, W) bool; ``BadSample`` when it is missing, unreadable or ambiguous.

    What counts as foreground (``mask_foreground``):

    * a grey-scale mask whose brightest pixel lies in the upper half of its range (above 127 for 8 bits) is an
      intensity mask: foreground where it is at least half bright (>= 128), so antialiased edges and JPEG noise
      around a black background do not widen the mask;
    * any other grey-scale mask is a label mask (0/1 masks, instance ids): nonzero = foreground;
    * a colour mask is accepted when its colour channels are equal (a grey mask saved as RGB); an RGBA mask whose
      colour is one flat value everywhere carries the mask in its alpha channel;
    * an indexed (palette) PNG with a coloured palette (DAVIS, PASCAL VOC annotations) is a label mask: nonzero
      palette index = foreground, except index 255 (VOC's "void" border) when other labels are present. An indexed
      PNG whose palette is grey reads as its grey levels.
    """
    if path is None or not Path(path).is_file():
        raise BadSample(STATUS_MISSING_MASK, f"mask {path} does not exist" if path is not None
                        else "no mask file was found for the image")
    path = Path(path)
    labels = _palette_labels(path)
    if labels is not None:
        return labels
    arr = _decode(path, STATUS_BAD_MASK, "mask")
    if arr.ndim == 3:
        colour = arr[..., :3]
        if colour.shape[2] > 1 and not (colour == colour[..., :1]).all():
            raise BadSample(STATUS_BAD_MASK, f"mask {path} has {arr.shape[2]} differing channels; "
                                             f"expected a single-channel mask (nonzero = foreground)")
        flat_colour = arr.shape[2] == 4 and (colour == colour.flat[0]).all()
        arr = arr[..., 3] if flat_colour and not (arr[..., 3] == arr[0, 0, 3]).all() else colour[..., 0]
    return mask_foreground(arr)


def mask_foreground(values: np.ndarray) -> np.ndarray:
    """Foreground of a single-channel mask (see ``read_mask``): an intensity mask (brightest value above half the
    range: 127 for uint8, 32767 for uint16, 0.5 for floats) thresholded at half the range, a label mask nonzero."""
    values = np.asarray(values)
    if values.dtype == bool:
        return values.copy()
    half = 0.5 if values.dtype.kind == "f" else np.iinfo(values.dtype).max / 2
    if values.size and values.max() > half:
        return values >= half
    return values != 0


def _palette_labels(path: Path) -> np.ndarray | None:
    """The label mask of an indexed PNG with a coloured palette (see ``read_mask``); None for any other file
    (grey palettes included), which ``_decode`` then reads."""
    with path.open("rb") as f:
        head = f.read(26)
    if not (head.startswith(_PNG_MAGIC) and head[12:16] == b"IHDR" and head[25] == 3):  # colour type 3: indexed
        return None
    data = path.read_bytes()
    problem = _truncation_problem(data)
    if problem:
        raise BadSample(STATUS_BAD_MASK, f"mask {path} is truncated or corrupt: {problem}")
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            index = np.asarray(im)
            palette = np.asarray(im.getpalette() or [], np.int64).reshape(-1, 3)
    except Exception as e:  # noqa: BLE001 - Pillow raises several types for broken files
        raise BadSample(STATUS_BAD_MASK, f"mask {path} is not a readable image ({type(e).__name__})") from None
    used = np.unique(index)
    colours = palette[used[used < len(palette)]]
    if len(colours) and (colours == colours[:, :1]).all():
        return None  # a grey palette: the grey levels are the mask
    labels = index != 0
    if (used == 255).any() and (used[(used != 0) & (used != 255)]).size:
        labels &= index != 255
    return labels


EXIF_ORIENTATION_TAG = 0x0112


def exif_orientation(path: str | os.PathLike) -> int:
    """The EXIF orientation tag of an image file (1-8; 1, "as stored", when it has none or cannot be read)."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            value = int(im.getexif().get(EXIF_ORIENTATION_TAG, 1))
    except Exception:  # noqa: BLE001 - no EXIF, or a format Pillow does not read: the stored order
        return 1
    return value if 1 <= value <= 8 else 1


def apply_exif_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """``image`` (H, W[, C]) in stored pixel order, turned the way a viewer shows it under the EXIF ``orientation``
    (2: mirrored, 3: turned 180 degrees, 4: flipped, 5: transposed, 6: turned 90 degrees clockwise, 7: transversed,
    8: turned 90 degrees counter-clockwise)."""
    ops = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: np.rot90(a, -1)[::-1],
           8: lambda a: np.rot90(a, 1)}
    if orientation not in ops:
        raise ValueError(f"EXIF orientation must be 1-8, got {orientation!r}")
    return np.ascontiguousarray(ops[orientation](image))


def load_sample(sample: CollectionSample) -> tuple[np.ndarray, np.ndarray]:
    """Image (H, W, 3) uint8 RGB and mask (H, W) bool of a sample; ``BadSample`` when it cannot be used.

    A mask with the size of the image as displayed under its EXIF orientation (a phone photo stored sideways, its
    mask drawn on the upright photo) gets the image turned upright to match it."""
    image = read_image(sample.image_path)
    mask = read_mask(sample.mask_path)
    if mask.shape != image.shape[:2]:
        orientation = exif_orientation(sample.image_path)
        upright = apply_exif_orientation(image, orientation)
        if orientation in (5, 6, 7, 8) and upright.shape[:2] == mask.shape:
            image = upright
        else:
            raise BadSample(STATUS_SIZE_MISMATCH,
                            f"mask {sample.mask_path} is {mask.shape[1]}x{mask.shape[0]} (WxH) but image "
                            f"{sample.image_path} is {image.shape[1]}x{image.shape[0]}; expected equal sizes")
    if not mask.any():
        raise BadSample(STATUS_EMPTY_MASK, f"mask {sample.mask_path} has no foreground pixel; "
                                           f"expected a nonzero object region")
    return image, mask


# --------------------------------------------------------------------------------------------------------- sharding
def plan_shards(samples: Sequence[CollectionSample], shard_size: int) -> list[list[CollectionSample]]:
    """Consecutive chunks of ``shard_size`` samples (the last one may be shorter)."""
    if shard_size < 1:
        raise ValueError(f"shard_size must be >= 1, got {shard_size}")
    return [list(samples[i:i + shard_size]) for i in range(0, len(samples), shard_size)]


def write_collection_shard(samples: Sequence[CollectionSample], out_dir: str | os.PathLike, index: int,
                           cfg: CollectionConfig = CollectionConfig()) -> ShardPaths:
    """Preprocess ``samples`` and write them as shard ``index`` of ``out_dir``.

    Rows (one per sample, in order): ``sample_id, image_path, mask_path, status, reason, image_width,
    image_height, crop_x0, crop_y0, crop_size, crop_scale, resolution`` (pixels; crop values 0 for bad rows).
    npz: ``rgb (N, R, R, 3) uint8`` (background 0), ``mask (N, R, R) bool``, ``crop_box (N, 4) float64``
    ``(x0, y0, x1, y1)`` original pixels, ``crop_scale (N,) float64``, ``crop_matrix (N, 3, 3) float64``
    (``S`` of ``CropTransform.matrix``). Bad samples keep their row with a non-"ok" status and zero arrays.
    """
    R = cfg.resolution
    n = len(samples)
    rgb = np.zeros((n, R, R, 3), np.uint8)
    masks = np.zeros((n, R, R), bool)
    crop_box = np.zeros((n, 4), np.float64)
    crop_scale = np.zeros((n,), np.float64)
    crop_matrix = np.zeros((n, 3, 3), np.float64)
    rows = []
    for i, s in enumerate(samples):
        row = {"sample_id": s.sample_id, "image_path": str(s.image_path),
               "mask_path": "" if s.mask_path is None else str(s.mask_path), "status": STATUS_OK, "reason": "",
               "image_width": 0, "image_height": 0, "crop_x0": 0.0, "crop_y0": 0.0, "crop_size": 0.0,
               "crop_scale": 0.0, "resolution": R}
        try:
            image, mask = load_sample(s)
            rgb[i], masks[i], tf = crop_to_square(image, mask, R, cfg.margin)
        except BadSample as e:
            row["status"], row["reason"] = e.status, e.reason
        else:
            row.update(image_width=int(image.shape[1]), image_height=int(image.shape[0]), crop_x0=tf.x0,
                       crop_y0=tf.y0, crop_size=tf.size, crop_scale=tf.scale)
            crop_box[i], crop_scale[i], crop_matrix[i] = tf.box, tf.scale, tf.matrix
        rows.append(row)
    arrays = {"rgb": rgb, "mask": masks, "crop_box": crop_box, "crop_scale": crop_scale,
              "crop_matrix": crop_matrix}
    return write_shard(out_dir, index, rows, arrays if n else None)


def write_collection_shards(collection: str | os.PathLike | Sequence[CollectionSample],
                            out_dir: str | os.PathLike, cfg: CollectionConfig = CollectionConfig(),
                            skip_existing: bool = True) -> list[ShardPaths]:
    """List (if given a path), preprocess and shard a whole collection into ``out_dir``.

    ``skip_existing`` keeps complete shards already in ``out_dir`` (a rerun after a crash redoes only the rest).
    """
    samples = list_collection(collection) if isinstance(collection, (str, os.PathLike)) else list(collection)
    out = []
    for index, chunk in enumerate(plan_shards(samples, cfg.shard_size)):
        paths = shard_paths(out_dir, index)
        if skip_existing and paths.complete:
            out.append(paths)
            continue
        out.append(write_collection_shard(chunk, out_dir, index, cfg))
    return out


def crop_transform_from_row(row: dict) -> CropTransform:
    """The ``CropTransform`` of an ok collection row (a mapping with ``crop_x0, crop_y0, crop_size,
    resolution``); ValueError for a bad row."""
    if row.get("status") != STATUS_OK:
        raise ValueError(f"row {row.get('sample_id')!r} has status {row.get('status')!r}; "
                         f"only 'ok' rows have a crop transform")
    return CropTransform(float(row["crop_x0"]), float(row["crop_y0"]), float(row["crop_size"]),
                         int(row["resolution"]))
