"""Image collections: crop transform, preprocessing, listing, bad-file records and sharding."""
from __future__ import annotations

import re

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bat3r_core.predictor.collection import (
    BadSample, CollectionConfig, CollectionSample, CropTransform, apply_exif_orientation, crop_box_for_mask,
    crop_to_square, crop_transform_from_row, exif_orientation, list_collection, list_parquet_collection, load_sample,
    write_collection_shards,
)
from bat3r_core.shards import list_shards, read_shard, read_table


# ------------------------------------------------------------------------------------------------- crop transform
def test_crop_transform_round_trip_pixels():
    rng = np.random.default_rng(0)
    for _ in range(20):
        tf = CropTransform(rng.uniform(-50, 300), rng.uniform(-50, 300), rng.uniform(5, 900), int(rng.integers(8, 300)))
        uv = rng.uniform(-100, 1200, size=(7, 5, 2))
        back = tf.invert(tf.apply(uv))
        assert np.abs(back - uv).max() < 1e-6
        # the homogeneous matrix agrees with apply
        h = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], -1) @ tf.matrix.T
        np.testing.assert_allclose(h[..., :2], tf.apply(uv), atol=1e-9)
    # the crop box corners map to the crop image's corners
    tf = CropTransform(10.0, 20.0, 80.0, 160)
    np.testing.assert_allclose(tf.apply([[10.0, 20.0], [90.0, 100.0]]), [[0, 0], [160, 160]])
    assert tf.scale == 2.0 and tf.box == (10.0, 20.0, 90.0, 100.0)


def test_crop_intrinsics_match_projection():
    rng = np.random.default_rng(1)
    K = np.array([[612.0, 0.0, 301.5], [0.0, 598.0, 233.25], [0.0, 0.0, 1.0]])
    X = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(2, 6, 50)])  # metres, camera
    uv = (X @ K.T)[:, :2] / X[:, 2:]
    tf = CropTransform(137.0, 61.0, 243.0, 160)
    K2 = tf.intrinsics(K)
    uv2 = (X @ K2.T)[:, :2] / X[:, 2:]
    assert np.abs(tf.apply(uv) - uv2).max() < 1e-6
    # pixel-centre convention: crop pixel j' has centre j' + 0.5, an original pixel centre maps on the same ray
    with pytest.raises(ValueError, match=r"K must have shape \(3, 3\), got \(2, 3\)"):
        tf.intrinsics(K[:2])
    with pytest.raises(ValueError, match=r"uv must have shape \(\.\.\., 2\), got \(4, 3\)"):
        tf.apply(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="crop size must be > 0, got 0"):
        CropTransform(0.0, 0.0, 0.0, 10)


def _ramp_image(h: int, w: int) -> np.ndarray:
    """Channel 0 = 2 x column index, channel 1 = 2 x row index, channel 2 = 7 (slope 2 halves uint8 rounding)."""
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    return np.stack([2 * jj, 2 * ii, np.full_like(jj, 7)], -1).astype(np.uint8)


@pytest.mark.parametrize("resolution", [40, 64, 97, 150])  # downscale (area) and upscale (linear)
def test_crop_pixels_follow_the_transform(resolution):
    img = _ramp_image(120, 120)
    mask = np.zeros((120, 120), bool)
    mask[30:101, 40:91] = True  # 71 rows x 51 columns
    rgb, m, tf = crop_to_square(img, mask, resolution, margin=0.15)
    assert rgb.shape == (resolution, resolution, 3) and rgb.dtype == np.uint8 and m.shape == (resolution,) * 2
    # slow reference: the original location of every foreground crop pixel centre, read off the ramp whose
    # pixel j (centre j + 0.5) holds 2 j; a linear ramp survives area and bilinear resampling up to rounding
    ii, jj = np.nonzero(m)
    orig = tf.invert(np.column_stack([jj + 0.5, ii + 0.5]))
    inner = (orig[:, 0] > 42) & (orig[:, 0] < 88) & (orig[:, 1] > 32) & (orig[:, 1] < 98)
    assert inner.sum() > 50
    for c in (0, 1):
        err = rgb[ii[inner], jj[inner], c] / 2.0 - (orig[inner, c] - 0.5)
        # a half crop-pixel offset would bias the error by 0.5 / scale >= 0.34 original pixels
        assert np.abs(err).max() < 0.4 and abs(err.mean()) < 0.1
    # the mask follows the same transform: crop pixel centres inside the original box are foreground
    centres = tf.invert(np.stack(np.meshgrid(np.arange(resolution) + 0.5, np.arange(resolution) + 0.5), -1))
    u, v = centres[..., 0], centres[..., 1]
    inside = (u > 40.5) & (u < 90.5) & (v > 30.5) & (v < 100.5)
    outside = (u < 39.5) | (u > 91.5) | (v < 29.5) | (v > 101.5)
    assert m[inside].all() and not m[outside].any()
    assert (rgb[~m] == 0).all()


def test_crop_box_margin_and_centre():
    mask = np.zeros((300, 400), bool)
    mask[100:160, 50:250] = True  # extent 200 (columns)
    x0, y0, size = crop_box_for_mask(mask, 0.175)
    assert size == int(np.ceil(200 / 0.65))
    assert abs((x0 + size / 2) - 150) <= 0.5 and abs((y0 + size / 2) - 130) <= 0.5
    assert 50 - x0 >= 0.175 * size - 1 and (x0 + size) - 250 >= 0.175 * size - 1
    assert crop_box_for_mask(mask, 0.0)[2] == 200
    with pytest.raises(ValueError, match=r"margin must be in \[0, 0.5\), got 0.5"):
        crop_box_for_mask(mask, 0.5)
    with pytest.raises(ValueError, match="mask has no foreground pixel"):
        crop_box_for_mask(np.zeros((4, 4), bool))


def test_crop_pads_outside_the_image_with_zeros():
    img = np.full((50, 80, 3), 200, np.uint8)
    mask = np.ones((50, 80), bool)  # the box is the whole image, so the crop leaves it on every side
    rgb, m, tf = crop_to_square(img, mask, 64, margin=0.2)
    centres = tf.invert(np.stack(np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5), -1))
    in_img = (centres[..., 0] > 1) & (centres[..., 0] < 79) & (centres[..., 1] > 1) & (centres[..., 1] < 49)
    out_img = (centres[..., 0] < -1) | (centres[..., 0] > 81) | (centres[..., 1] < -1) | (centres[..., 1] > 51)
    assert out_img.sum() > 100
    assert (rgb[out_img] == 0).all() and not m[out_img].any()
    assert (rgb[in_img] == 200).all() and m[in_img].all()
    with pytest.raises(ValueError, match=r"image must be \(H, W, 3\) uint8"):
        crop_to_square(img[..., 0], mask, 64)
    with pytest.raises(ValueError, match=r"mask must have shape \(50, 80\)"):
        crop_to_square(img, mask[:10], 64)


def test_config_checks():
    with pytest.raises(ValueError, match=r"margin must be in \[0, 0.5\), got 0.6"):
        CollectionConfig(margin=0.6)
    with pytest.raises(ValueError, match="shard_size must be >= 1, got 0"):
        CollectionConfig(shard_size=0)


# ------------------------------------------------------------------------------------------------ collections
def _write(path, arr, ext=None):
    ok, buf = cv2.imencode(ext or path.suffix, arr)
    assert ok
    path.write_bytes(buf.tobytes())
    return buf.tobytes()


def _blob_mask(h, w, r0=8, c0=10):
    m = np.zeros((h, w), np.uint8)
    m[r0:h - 6, c0:w - 9] = 255
    return m


def test_a_sideways_phone_photo_is_turned_upright_to_match_its_mask(tmp_path):
    from PIL import Image, ImageOps

    stored = np.random.default_rng(5).integers(0, 256, (48, 64, 3), np.uint8)  # landscape as the sensor wrote it
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    for name, orientation in (("turned", 6), ("upside_down", 3)):
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(stored).save(tmp_path / "images" / f"{name}.png", exif=exif)
        _write(tmp_path / "masks" / f"{name}.png", _blob_mask(64, 48))  # drawn on the photo as displayed (portrait)
    samples = {s.sample_id: s for s in list_collection(tmp_path)}
    image, mask = load_sample(samples["turned"])
    with Image.open(tmp_path / "images" / "turned.png") as im:
        upright = np.asarray(ImageOps.exif_transpose(im))
    assert image.shape == (64, 48, 3) and np.array_equal(image, upright) and mask.shape == (64, 48)
    with pytest.raises(BadSample, match=r"is 48x64 \(WxH\) but image .*upside_down\.png is 64x48"):
        load_sample(samples["upside_down"])  # turning by 180 degrees keeps the size: a real mismatch
    for orientation in range(1, 9):  # every EXIF orientation as Pillow's viewer-side transpose shows it
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(stored[:5, :7]).save(tmp_path / "o.png", exif=exif)
        assert exif_orientation(tmp_path / "o.png") == orientation
        with Image.open(tmp_path / "o.png") as im:
            assert np.array_equal(apply_exif_orientation(stored[:5, :7], orientation),
                                  np.asarray(ImageOps.exif_transpose(im))), orientation


@pytest.fixture()
def bad_collection(tmp_path):
    """A folder collection with two good samples and one sample for every bad-file case."""
    rng = np.random.default_rng(3)
    root = tmp_path / "coll"
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    img = rng.integers(0, 256, (48, 64, 3), np.uint8)
    img = cv2.GaussianBlur(img, (5, 5), 2)
    mask = _blob_mask(48, 64)
    images, masks = root / "images", root / "masks"
    # good ones
    _write(images / "good_jpg.jpg", img)
    _write(masks / "good_jpg.png", mask)
    _write(images / "good_png.png", img)
    _write(masks / "good_png.png", np.repeat(mask[..., None], 3, -1))  # grey mask saved as RGB is fine
    # a JPEG with bytes after its end-of-image marker is complete
    (images / "trailing.jpg").write_bytes(_write(images / "trailing.jpg", img) + b"\x00" * 16)
    _write(masks / "trailing.png", mask)
    # truncated files: cut bytes off the end
    data = _write(images / "trunc_jpg.jpg", img)
    (images / "trunc_jpg.jpg").write_bytes(data[: len(data) * 2 // 3])
    _write(masks / "trunc_jpg.png", mask)
    data = _write(images / "trunc_png.png", img)
    (images / "trunc_png.png").write_bytes(data[:-20])
    _write(masks / "trunc_png.png", mask)
    data = _write(images / "trunc_webp.webp", img)
    (images / "trunc_webp.webp").write_bytes(data[: len(data) * 2 // 3])
    _write(masks / "trunc_webp.png", mask)
    data = _write(images / "trunc_mask.jpg", img)
    data = _write(masks / "trunc_mask.png", mask)
    (masks / "trunc_mask.png").write_bytes(data[: len(data) // 2])
    # missing, empty, wrong size masks
    _write(images / "no_mask.jpg", img)
    _write(images / "empty_mask.jpg", img)
    _write(masks / "empty_mask.png", np.zeros((48, 64), np.uint8))
    _write(images / "size_mismatch.jpg", img)
    _write(masks / "size_mismatch.png", _blob_mask(40, 64))
    # grey-scale, RGBA, garbage, 16-bit
    _write(images / "grey.png", img[..., 0])
    _write(masks / "grey.png", mask)
    _write(images / "rgba.png", np.concatenate([img, np.full((48, 64, 1), 255, np.uint8)], -1))
    _write(masks / "rgba.png", mask)
    (images / "garbage.jpg").write_bytes(rng.integers(0, 256, 3000, np.uint8).tobytes())
    _write(masks / "garbage.png", mask)
    _write(images / "deep.png", img.astype(np.uint16) * 257)
    _write(masks / "deep.png", mask)
    colour_mask = np.zeros((48, 64, 3), np.uint8)
    colour_mask[10:30, 10:30, 2] = 255
    _write(images / "colour_mask.jpg", img)
    _write(masks / "colour_mask.png", colour_mask)
    (images / "phone.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic" + bytes(64))  # listed, recorded, not decoded
    _write(masks / "phone.png", mask)
    (images / "notes.txt").write_text("not an image")
    return root


EXPECTED = {
    "good_jpg": ("ok", r"^$"),
    "good_png": ("ok", r"^$"),
    "trailing": ("ok", r"^$"),
    "trunc_jpg": ("bad_image", r"image .*trunc_jpg\.jpg is truncated or corrupt: JPEG ends before its end-of-image"),
    "trunc_png": ("bad_image", r"image .*trunc_png\.png is truncated or corrupt: PNG ends before its IEND chunk"),
    "trunc_webp": ("bad_image", r"image .*trunc_webp\.webp is truncated or corrupt: decoding failed"),
    "trunc_mask": ("bad_mask", r"mask .*trunc_mask\.png is truncated or corrupt: PNG ends before its IEND"),
    "no_mask": ("missing_mask", r"no mask file was found for the image"),
    "empty_mask": ("empty_mask", r"mask .*empty_mask\.png has no foreground pixel"),
    "size_mismatch": ("size_mismatch", r"mask .*size_mismatch\.png is 64x40 \(WxH\) but image .*size_mismatch\.jpg "
                                       r"is 64x48; expected equal sizes"),
    "grey": ("bad_image", r"image .*grey\.png is grey-scale \(1 channel\); expected 3-channel RGB"),
    "rgba": ("bad_image", r"image .*rgba\.png has an alpha channel \(RGBA, 4 channels\); expected 3-channel RGB"),
    "garbage": ("bad_image", r"image .*garbage\.jpg is not a readable image"),
    "deep": ("bad_image", r"image .*deep\.png has dtype uint16; expected 8-bit RGB"),
    "colour_mask": ("bad_mask", r"mask .*colour_mask\.png has 3 differing channels; expected a single-channel"),
    "phone": ("bad_image", r"image .*phone\.HEIC is HEIC/HEIF, which bat3r does not decode; expected \.jpg, .* "
                           r"\(convert it to JPEG or PNG\)"),
}


def test_every_bad_file_case_is_recorded(bad_collection, tmp_path):
    samples = list_collection(bad_collection)
    assert [s.sample_id for s in samples] == sorted(EXPECTED)  # sorted by file name, .txt ignored
    out = tmp_path / "shards"
    paths = write_collection_shards(bad_collection, out, CollectionConfig(resolution=32, shard_size=4))
    assert list_shards(out) == [0, 1, 2, 3] and all(p.complete for p in paths)
    table = read_table(out)
    rows = {r["sample_id"]: r for r in table.to_pylist()}
    assert list(rows) == sorted(EXPECTED)
    for sid, (status, reason) in EXPECTED.items():
        assert rows[sid]["status"] == status, (sid, rows[sid]["reason"])
        assert re.search(reason, rows[sid]["reason"]), (sid, rows[sid]["reason"])
    # arrays follow the rows; bad rows are zero, good rows hold the masked crop
    for index in list_shards(out):
        t, arrays = read_shard(out, index)
        assert arrays["rgb"].shape == (t.num_rows, 32, 32, 3) and arrays["rgb"].dtype == np.uint8
        assert arrays["mask"].shape == (t.num_rows, 32, 32) and arrays["mask"].dtype == bool
        assert arrays["crop_box"].shape == (t.num_rows, 4) and arrays["crop_matrix"].shape == (t.num_rows, 3, 3)
        for k, r in enumerate(t.to_pylist()):
            if r["status"] == "ok":
                assert arrays["mask"][k].sum() > 100 and (arrays["rgb"][k][~arrays["mask"][k]] == 0).all()
                tf = crop_transform_from_row(r)
                np.testing.assert_allclose(arrays["crop_matrix"][k], tf.matrix)
                np.testing.assert_allclose(arrays["crop_box"][k], tf.box)
                assert (r["image_width"], r["image_height"]) == (64, 48)
            else:
                assert not arrays["mask"][k].any() and not arrays["rgb"][k].any()
    with pytest.raises(ValueError, match="row 'grey' has status 'bad_image'; only 'ok' rows"):
        crop_transform_from_row(rows["grey"])


def test_sharding_is_deterministic_and_resumable(bad_collection, tmp_path):
    cfg = CollectionConfig(resolution=24, shard_size=5)
    a, b = tmp_path / "a", tmp_path / "b"
    write_collection_shards(bad_collection, a, cfg)
    write_collection_shards(bad_collection, b, cfg)
    for index in list_shards(a):
        ta, xa = read_shard(a, index)
        tb, xb = read_shard(b, index)
        assert ta.equals(tb)
        for k in xa:
            np.testing.assert_array_equal(xa[k], xb[k])
    # a rerun keeps complete shards and writes only the missing one
    (a / "part-00001.parquet").unlink()
    before = (a / "part-00000.parquet").stat().st_mtime_ns
    write_collection_shards(bad_collection, a, cfg)
    assert list_shards(a) == [0, 1, 2, 3] and (a / "part-00000.parquet").stat().st_mtime_ns == before


def test_parquet_index(bad_collection, tmp_path):
    index = bad_collection / "index.parquet"
    pq.write_table(pa.table({"image_path": ["images/good_png.png", str(bad_collection / "images/good_jpg.jpg"),
                                            "images/no_mask.jpg"],
                             "mask_path": ["masks/good_png.png", "masks/good_jpg.png", None]}), index)
    samples = list_parquet_collection(index)
    assert [s.sample_id for s in samples] == ["good_png", "good_jpg", "no_mask"]  # row order
    assert samples[0].image_path == bad_collection / "images/good_png.png" and samples[2].mask_path is None
    image, mask = load_sample(samples[0])
    assert image.shape == (48, 64, 3) and mask.sum() == (48 - 6 - 8) * (64 - 9 - 10)
    # the PNG holds BGR on disk; samples come back as RGB
    bgr = cv2.imread(str(samples[0].image_path))
    np.testing.assert_array_equal(image, bgr[..., ::-1])
    out = tmp_path / "idx_shards"
    write_collection_shards(index, out, CollectionConfig(resolution=16, shard_size=8))
    assert read_table(out).column("status").to_pylist() == ["ok", "ok", "missing_mask"]

    pq.write_table(pa.table({"sample_id": ["x", "x"], "image_path": ["a.jpg", "b.jpg"],
                             "mask_path": ["a.png", "b.png"]}), tmp_path / "dup.parquet")
    with pytest.raises(ValueError, match=r"sample ids must be unique; duplicated: \['x'\]"):
        list_parquet_collection(tmp_path / "dup.parquet")
    pq.write_table(pa.table({"image": ["a.jpg"], "mask_path": ["a.png"]}), tmp_path / "nocol.parquet")
    with pytest.raises(ValueError, match="must have a 'image_path' column"):
        list_parquet_collection(tmp_path / "nocol.parquet")
    pq.write_table(pa.table({"image_path": ["a/s.jpg", "b/s.jpg"], "mask_path": ["1.png", "2.png"]}),
                   tmp_path / "stems.parquet")
    assert [s.sample_id for s in list_parquet_collection(tmp_path / "stems.parquet")] == ["a/s.jpg", "b/s.jpg"]
    with pytest.raises(ValueError, match="collection must be a folder with images/ and masks/ or a .parquet"):
        list_collection(tmp_path / "nothing.csv")


def test_shared_stems_and_missing_image(tmp_path):
    root = tmp_path / "c"
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    img = np.full((20, 20, 3), 90, np.uint8)
    _write(root / "images/a.jpg", img)
    _write(root / "images/a.png", img)
    _write(root / "masks/a.png", _blob_mask(20, 20, 4, 4))
    assert [s.sample_id for s in list_collection(root)] == ["a.jpg", "a.png"]
    out = tmp_path / "s"
    missing = CollectionSample("ghost", root / "images/ghost.jpg", root / "masks/a.png")
    write_collection_shards(list_collection(root) + [missing], out, CollectionConfig(resolution=8))
    rows = read_table(out).to_pylist()
    assert [r["status"] for r in rows] == ["ok", "ok", "bad_image"]
    assert re.search(r"image .*ghost\.jpg does not exist", rows[2]["reason"])


def test_masks_as_annotation_tools_write_them(tmp_path):
    """Soft and JPEG masks are cut at half brightness, label masks (0/1, instance ids) are nonzero, coloured palette
    PNGs (DAVIS, VOC) are read by palette index with VOC's void border left out, grey palettes by their grey levels,
    and a flat-coloured RGBA mask by its alpha; a folder's masks are found by stem in any image format and case."""
    from PIL import Image

    from bat3r_core.predictor.collection import mask_foreground, read_mask

    truth = _blob_mask(48, 64) > 0
    yy, xx = np.mgrid[:48, :64]
    ring = (np.abs(yy - 8) <= 2) | (np.abs(yy - 41) <= 2) | (np.abs(xx - 10) <= 2) | (np.abs(xx - 54) <= 2)
    soft = np.where(truth, 255, 0).astype(np.uint8)
    soft[ring & ~truth] = 60  # a dim antialiased fringe outside the object
    soft[ring & truth] = 200  # a bright one inside it
    _write(tmp_path / "soft.png", soft)
    assert np.array_equal(read_mask(tmp_path / "soft.png"), truth)
    _write(tmp_path / "lossy.jpg", np.where(truth, 255, 0).astype(np.uint8))  # JPEG ringing around the edges
    noisy = cv2.imread(str(tmp_path / "lossy.jpg"), cv2.IMREAD_UNCHANGED)
    assert ((noisy != 0) & ~truth).sum() > 20  # nonzero would widen this mask
    assert (read_mask(tmp_path / "lossy.jpg") != truth).sum() <= 4
    ids = np.zeros((48, 64), np.uint8)
    ids[truth] = 1
    ids[10:20, 12:30] = 2  # two instance ids: both are the object
    _write(tmp_path / "ids.png", ids)
    assert np.array_equal(read_mask(tmp_path / "ids.png"), truth)
    deep = np.where(truth, 65535, 0).astype(np.uint16)
    deep[ring & ~truth] = 9000
    _write(tmp_path / "deep.png", deep)
    assert np.array_equal(read_mask(tmp_path / "deep.png"), truth)
    assert np.array_equal(mask_foreground(np.where(truth, 0.9, 0.2).astype(np.float32)), truth)

    # indexed PNGs: a DAVIS-like coloured palette, a VOC one with its void border (255), a grey one (white = 0)
    davis = Image.fromarray(ids, mode="P")
    davis.putpalette([0, 0, 0, 128, 0, 0, 0, 128, 0] + [0] * 759)
    davis.save(tmp_path / "davis.png")
    assert np.array_equal(read_mask(tmp_path / "davis.png"), truth)
    voc = np.where(truth, 13, 0).astype(np.uint8)
    voc[ring & ~truth] = 255
    im = Image.fromarray(voc, mode="P")
    im.putpalette([0, 0, 0] * 13 + [192, 128, 128] + [0, 0, 0] * 241 + [224, 224, 192])
    im.save(tmp_path / "voc.png")
    assert np.array_equal(read_mask(tmp_path / "voc.png"), truth)
    inverted = Image.fromarray(np.where(truth, 1, 0).astype(np.uint8), mode="P")
    inverted.putpalette([255, 255, 255, 0, 0, 0] + [0] * 762)  # index 0 white: a black object on white
    inverted.save(tmp_path / "grey_palette.png")
    assert np.array_equal(read_mask(tmp_path / "grey_palette.png"), ~truth)  # grey levels, as before: no guess
    data = (tmp_path / "davis.png").read_bytes()
    (tmp_path / "torn.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(BadSample, match=r"mask .*torn\.png is truncated or corrupt"):
        read_mask(tmp_path / "torn.png")

    rgba = np.zeros((48, 64, 4), np.uint8)  # black everywhere, the object in the alpha channel
    rgba[..., 3] = np.where(truth, 255, 0)
    _write(tmp_path / "cutout.png", rgba)
    assert np.array_equal(read_mask(tmp_path / "cutout.png"), truth)
    rgba[..., :3] = np.where(truth, 255, 0)[..., None]  # a grey mask with an opaque alpha: the grey levels
    rgba[..., 3] = 255
    _write(tmp_path / "opaque.png", rgba)
    assert np.array_equal(read_mask(tmp_path / "opaque.png"), truth)

    root = tmp_path / "c"
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    img = np.full((48, 64, 3), 90, np.uint8)
    for stem in ("a", "b", "c", "d"):
        _write(root / "images" / f"{stem}.jpg", img)
    _write(root / "masks" / "a.jpg", soft)  # JPEG only
    _write(root / "masks" / "b.PNG", soft)  # upper-case suffix
    _write(root / "masks" / "b.jpg", np.zeros_like(soft))  # the lossless one wins
    _write(root / "masks" / "c.tif", soft)
    samples = {s.sample_id: s for s in list_collection(root)}
    assert {k: s.mask_path.name if s.mask_path else None for k, s in samples.items()} == {
        "a": "a.jpg", "b": "b.PNG", "c": "c.tif", "d": None}
    for stem in ("a", "b", "c"):
        assert (load_sample(samples[stem])[1] != truth).sum() <= 4, stem
