"""COCO instance annotations as a collection: RLE and polygon masks against independent references (pycocotools'
encoder, a point-in-polygon test per pixel centre), and the conversion end to end through the collection reader."""
import json

import cv2
import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from pycocotools import mask as mask_utils

from bat3r_core.cli import main as cli_main
from bat3r_core.predictor.coco import (CONVERSION_FILE, coco_to_collection, decode_rle, polygons_to_mask,
                                       rle_counts, segmentation_to_mask)
from bat3r_core.predictor.collection import (CollectionConfig, list_collection, load_sample,
                                             write_collection_shards)
from bat3r_core.shards import read_shard


def _blobs(rng, h, w, k=4):
    """A random mask of a few overlapping ellipses (with holes between them)."""
    m = np.zeros((h, w), np.uint8)
    for _ in range(k):
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (int(rng.integers(1, max(w // 2, 2))), int(rng.integers(1, max(h // 2, 2))))
        cv2.ellipse(m, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    return m.astype(bool)


def _star(rng, cx, cy, r, n=9):
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    rad = r * rng.uniform(0.35, 1.0, n)
    return np.c_[cx + rad * np.cos(ang), cy + rad * np.sin(ang)].ravel().tolist()


def test_rle_decodes_as_pycocotools_encodes():
    rng = np.random.default_rng(0)
    for h, w in [(37, 53), (120, 80), (1, 9), (64, 64)]:
        for _ in range(5):
            m = _blobs(rng, h, w)
            rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
            assert np.array_equal(decode_rle({"size": rle["size"], "counts": rle["counts"].decode()}), m)
            # the uncompressed form COCO uses for crowd annotations: a list of run lengths
            runs = rle_counts(rle["counts"])
            assert sum(runs) == h * w
            assert np.array_equal(decode_rle({"size": [h, w], "counts": runs}), m)
            assert np.array_equal(mask_utils.decode(mask_utils.frPyObjects({"size": [h, w], "counts": runs}, h, w)),
                                  m.astype(np.uint8))
    with pytest.raises(ValueError, match="cover 10 pixels; its size 3x4 has 12"):
        decode_rle({"size": [3, 4], "counts": [4, 6]})


def test_polygons_rasterise_by_pixel_centres():
    rng = np.random.default_rng(1)
    h, w = 70, 90
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.c_[xx.ravel() + 0.5, yy.ravel() + 0.5]
    for _ in range(10):
        rings = [_star(rng, rng.uniform(10, 80), rng.uniform(10, 60), rng.uniform(5, 30)) for _ in range(2)]
        ours = polygons_to_mask(rings, h, w)
        # slow reference: each pixel centre tested against each ring (matplotlib's even-odd test), union
        ref = np.zeros(h * w, bool)
        for ring in rings:
            ref |= MplPath(np.reshape(ring, (-1, 2))).contains_points(centres)
        assert np.array_equal(ours, ref.reshape(h, w))
        # pycocotools rasterises its own way (upsampled edge walking): the same masks up to boundary pixels
        coco = mask_utils.decode(mask_utils.merge(mask_utils.frPyObjects(rings, h, w))).astype(bool)
        iou = (coco & ours).sum() / (coco | ours).sum()
        assert iou > 0.9, iou
    # an axis-aligned rectangle on pixel edges covers exactly its pixels
    rect = polygons_to_mask([[10, 5, 30, 5, 30, 25, 10, 25]], h, w)
    assert rect.sum() == 20 * 20 and rect[5:25, 10:30].all()
    with pytest.raises(ValueError, match="polygon 0 has 4 numbers"):
        polygons_to_mask([[0, 0, 1, 1]], h, w)
    with pytest.raises(ValueError, match="RLE size 5x5 differs from the image's 6x5"):
        segmentation_to_mask({"size": [5, 5], "counts": [25]}, 6, 5)
    with pytest.raises(ValueError, match="list of polygons or an RLE dict; got list \\(empty\\)"):
        segmentation_to_mask([], 6, 5)


def _photo(path, h, w, seed):
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))


@pytest.fixture()
def coco_set(tmp_path):
    """Three photos and their annotations: horses as polygons and as compressed RLE, two horses in one photo,
    a crowd, a tiny horse, a broken segmentation, a dog."""
    images = tmp_path / "photos" / "train"
    images.mkdir(parents=True)
    for name, (h, w) in {"a.jpg": (120, 160), "b.png": (100, 100), "c.jpg": (90, 140)}.items():
        _photo(images / name, h, w, len(name))
    rng = np.random.default_rng(3)
    big = _star(rng, 80, 60, 50)
    rle_mask = _blobs(rng, 100, 100, k=3)
    rle_mask[30:70, 30:70] = True
    rle = mask_utils.encode(np.asfortranarray(rle_mask.astype(np.uint8)))
    small_pair = [[100, 10, 130, 10, 130, 50, 100, 50]]  # 30 x 40 = 1200 px: a second horse in c.jpg
    data = {
        "images": [{"id": 1, "file_name": "a.jpg", "height": 120, "width": 160},
                   {"id": 2, "file_name": "b.png", "height": 100, "width": 100},
                   {"id": 3, "file_name": "c.jpg", "height": 90, "width": 140}],
        "categories": [{"id": 17, "name": "Horse"}, {"id": 18, "name": "dog"}],
        "annotations": [
            {"id": 101, "image_id": 1, "category_id": 17, "iscrowd": 0, "segmentation": [big]},
            {"id": 102, "image_id": 2, "category_id": 17, "iscrowd": 0,
             "segmentation": {"size": rle["size"], "counts": rle["counts"].decode()}},
            {"id": 103, "image_id": 3, "category_id": 17, "iscrowd": 0,
             "segmentation": [[10, 10, 90, 10, 90, 80, 10, 80]]},  # 80 x 70: the larger horse of c.jpg
            {"id": 104, "image_id": 3, "category_id": 17, "iscrowd": 0, "segmentation": small_pair},
            {"id": 105, "image_id": 1, "category_id": 17, "iscrowd": 1,
             "segmentation": {"size": [120, 160], "counts": [0, 120 * 160]}},
            {"id": 106, "image_id": 2, "category_id": 17, "iscrowd": 0, "segmentation": [[1, 1, 5, 1, 5, 5]]},
            {"id": 107, "image_id": 2, "category_id": 17, "iscrowd": 0,
             "segmentation": {"size": [50, 50], "counts": [2500]}},
            {"id": 108, "image_id": 1, "category_id": 18, "iscrowd": 0, "segmentation": [big]},
        ]}
    ann = tmp_path / "instances.json"
    ann.write_text(json.dumps(data))
    return {"annotations": ann, "images": images, "big": big, "rle_mask": rle_mask, "tmp": tmp_path}


def test_coco_converts_to_a_collection_every_stage_reads(coco_set):
    out = coco_set["tmp"] / "horses"
    conv = coco_to_collection(coco_set["annotations"], coco_set["images"], "horse", out)
    assert conv.samples == 4 and conv.images == 3
    assert conv.skipped == {"crowd annotation (iscrowd 1: several animals in one mask)": 1,
                            "smaller than min_area (1024 pixels)": 1,
                            "bad segmentation: RLE size 50x50 differs from the image's 100x100": 1}
    samples = {s.sample_id: s for s in list_collection(out / "index.parquet")}
    assert sorted(samples) == ["a-101", "b-102", "c-103", "c-104"]
    _, mask = load_sample(samples["b-102"])
    assert np.array_equal(mask, coco_set["rle_mask"])
    _, mask = load_sample(samples["a-101"])
    assert np.array_equal(mask, polygons_to_mask([coco_set["big"]], 120, 160))
    _, mask = load_sample(samples["c-104"])
    assert mask.sum() == 30 * 40 and mask[10:50, 100:130].all()
    assert samples["a-101"].image_path.resolve() == (coco_set["images"] / "a.jpg").resolve()
    report = json.loads((out / CONVERSION_FILE).read_text())
    assert report["category"] == "Horse" and report["category_id"] == 17 and report["samples"] == 4
    assert report["skipped_examples"]["crowd annotation (iscrowd 1: several animals in one mask)"] == [105]

    # the crops the pipeline makes are centred on each instance
    shards = write_collection_shards(out / "index.parquet", coco_set["tmp"] / "shards",
                                     CollectionConfig(resolution=32, shard_size=8))
    table, arrays = read_shard(coco_set["tmp"] / "shards", 0)
    rows = table.to_pylist()
    assert [r["status"] for r in rows] == ["ok"] * 4, [r["reason"] for r in rows]
    c104 = [i for i, r in enumerate(rows) if r["sample_id"] == "c-104"][0]
    x0, y0, x1, y1 = arrays["crop_box"][c104]
    assert abs((x0 + x1) / 2 - 115) < 1 and abs((y0 + y1) / 2 - 30) < 1
    assert len(shards) == 1

    # largest_only: one sample per photo; a rerun replaces the index
    conv = coco_to_collection(coco_set["annotations"], coco_set["images"], 17, out, largest_only=True)
    assert conv.samples == 3 and conv.skipped["not the image's largest instance (largest_only)"] == 1
    assert sorted(s.sample_id for s in list_collection(out / "index.parquet")) == ["a-101", "b-102", "c-103"]
    # moved together, the folders still resolve (image paths are relative to the index)
    moved = coco_set["tmp"].parent / (coco_set["tmp"].name + "-moved")
    coco_set["tmp"].rename(moved)
    assert all(s.image_path.is_file() and s.mask_path.is_file()
               for s in list_collection(moved / "horses" / "index.parquet"))


def test_coco_errors_name_the_file_and_what_was_expected(coco_set, tmp_path, capsys):
    ann = coco_set["annotations"]
    with pytest.raises(ValueError, match=r"no category named or numbered 'zebra'; it has 2: Horse \(17\), dog \(18\)"):
        coco_to_collection(ann, coco_set["images"], "zebra", tmp_path / "o1")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"images": [], "categories": []}))
    with pytest.raises(ValueError, match=r"bad\.json: expected a list under 'annotations'; it is missing"):
        coco_to_collection(bad, coco_set["images"], "horse", tmp_path / "o2")
    with pytest.raises(ValueError, match=r"no instance of category 'Horse' \(17\) makes a sample \(1 bad segmentation.*; 5 smaller than min_area"):
        coco_to_collection(ann, coco_set["images"], "horse", tmp_path / "o3", min_area=10 ** 6)
    assert not (tmp_path / "o3" / "index.parquet").exists()
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "index.parquet").write_bytes(b"user data")
    with pytest.raises(ValueError, match="was not written by a COCO conversion"):
        coco_to_collection(ann, coco_set["images"], "horse", foreign)
    assert (foreign / "index.parquet").read_bytes() == b"user data"

    out = tmp_path / "cli"
    assert cli_main(["collection", "coco", str(ann), "--images", str(coco_set["images"]), "--category", "horse",
                     "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 samples from 3 images" in printed and "skipped 1: crowd annotation" in printed
    assert cli_main(["collection", "coco", str(ann), "--images", str(coco_set["images"]), "--category", "cat",
                     "--out", str(out)]) == 2
    assert "no category named or numbered 'cat'" in capsys.readouterr().err


def test_exclude_truncated_skips_instances_cut_off_by_the_photo_edge(tmp_path, capsys):
    """A photo with three horses: the largest runs off the left edge, one touches the bottom row, one is whole.
    --exclude-truncated keeps the whole one (also as the photo's largest with --largest-only); without it all three
    are samples. A mask one pixel short of the edge is whole."""
    images = tmp_path / "photos"
    images.mkdir()
    _photo(images / "p.jpg", 60, 80, 1)
    off_left = [[0, 5, 40, 5, 40, 45, 0, 45]]         # columns 0..39: touches the first column
    on_bottom = [[50, 30, 78, 30, 78, 60, 50, 60]]    # rows 30..59: touches the last row
    whole = [[45, 2, 79, 2, 79, 25, 45, 25]]          # columns 45..78, rows 2..24: one pixel short of the edges
    data = {"images": [{"id": 1, "file_name": "p.jpg", "height": 60, "width": 80}],
            "categories": [{"id": 1, "name": "horse"}],
            "annotations": [{"id": i, "image_id": 1, "category_id": 1, "iscrowd": 0, "segmentation": seg}
                            for i, seg in ((1, off_left), (2, on_bottom), (3, whole))]}
    ann = tmp_path / "instances.json"
    ann.write_text(json.dumps(data))
    assert polygons_to_mask(whole, 60, 80)[:, -1].sum() == 0 and polygons_to_mask(off_left, 60, 80)[:, 0].any()

    conv = coco_to_collection(ann, images, "horse", tmp_path / "all", min_area=100)
    assert conv.samples == 3 and conv.skipped == {}
    conv = coco_to_collection(ann, images, "horse", tmp_path / "whole", min_area=100, exclude_truncated=True,
                              largest_only=True)
    assert conv.samples == 1 and conv.skipped == {"cut off by the image border (exclude_truncated)": 2}
    assert [s.sample_id for s in list_collection(tmp_path / "whole" / "index.parquet")] == ["p-3"]
    assert json.loads((tmp_path / "whole" / CONVERSION_FILE).read_text())["exclude_truncated"] is True

    assert cli_main(["collection", "coco", str(ann), "--images", str(images), "--category", "horse",
                     "--out", str(tmp_path / "cli"), "--min-area", "100", "--exclude-truncated"]) == 0
    assert "skipped 2: cut off by the image border (exclude_truncated)" in capsys.readouterr().out
    assert [s.sample_id for s in list_collection(tmp_path / "cli" / "index.parquet")] == ["p-3"]


def test_max_occlusion_skips_instances_along_other_objects(tmp_path, capsys):
    """A ridden horse and a free one: the rider (a person, another category) sits on the ridden horse's back, so
    60 of the 456 pixels of its 3-pixel outer ring lie in the rider's mask (0.132, by hand: the ring of a 40 x 30
    rectangle is 46 x 36 - 40 x 30 pixels, the rider covers 3 rows x 20 columns of it); the free horse touches
    nothing. --max-occlusion 0.1 drops the ridden horse, 0.2 keeps it."""
    from bat3r_core.predictor.coco import occlusion_fraction

    images = tmp_path / "photos"
    images.mkdir()
    _photo(images / "p.jpg", 80, 100, 2)
    ridden = [[10, 30, 50, 30, 50, 60, 10, 60]]   # columns 10..49, rows 30..59
    rider = [[20, 10, 40, 10, 40, 30, 20, 30]]    # columns 20..39, rows 10..29: on the ridden horse's back
    free = [[60, 40, 90, 40, 90, 70, 60, 70]]     # columns 60..89, rows 40..69: 11 columns from the ridden horse
    data = {"images": [{"id": 1, "file_name": "p.jpg", "height": 80, "width": 100}],
            "categories": [{"id": 1, "name": "horse"}, {"id": 2, "name": "person"}],
            "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "iscrowd": 0, "segmentation": ridden},
                            {"id": 2, "image_id": 1, "category_id": 2, "iscrowd": 0, "segmentation": rider},
                            {"id": 3, "image_id": 1, "category_id": 1, "iscrowd": 0, "segmentation": free}]}
    ann = tmp_path / "instances.json"
    ann.write_text(json.dumps(data))
    masks = {k: polygons_to_mask(seg, 80, 100) for k, seg in (("ridden", ridden), ("rider", rider), ("free", free))}
    assert occlusion_fraction(masks["ridden"], masks["rider"] | masks["free"]) == pytest.approx(60 / 456)
    assert occlusion_fraction(masks["free"], masks["rider"] | masks["ridden"]) == 0.0
    assert occlusion_fraction(np.ones((4, 4), bool), np.zeros((4, 4), bool)) == 0.0  # no ring: nothing touches

    conv = coco_to_collection(ann, images, "horse", tmp_path / "strict", min_area=100, max_occlusion=0.1)
    reason = "runs along another annotated object for more than 0.1 of its outline (max_occlusion)"
    assert conv.samples == 1 and conv.skipped == {reason: 1} and conv.examples == {reason: [1]}
    assert [s.sample_id for s in list_collection(tmp_path / "strict" / "index.parquet")] == ["p-3"]
    report = json.loads((tmp_path / "strict" / CONVERSION_FILE).read_text())
    assert report["max_occlusion"] == 0.1 and report["occlusion_ring_px"] == 3
    # applied before largest_only: the ridden horse is the larger, yet the photo keeps its free one
    conv = coco_to_collection(ann, images, "horse", tmp_path / "largest", min_area=100, max_occlusion=0.1,
                              largest_only=True)
    assert [s.sample_id for s in list_collection(tmp_path / "largest" / "index.parquet")] == ["p-3"]
    conv = coco_to_collection(ann, images, "horse", tmp_path / "loose", min_area=100, max_occlusion=0.2)
    assert conv.samples == 2 and conv.skipped == {}
    with pytest.raises(ValueError, match="max_occlusion must be a fraction in \\[0, 1\\], got 1.5"):
        coco_to_collection(ann, images, "horse", tmp_path / "bad", max_occlusion=1.5)

    assert cli_main(["collection", "coco", str(ann), "--images", str(images), "--category", "horse",
                     "--out", str(tmp_path / "cli"), "--min-area", "100", "--max-occlusion", "0.1"]) == 0
    assert f"skipped 1: {reason}" in capsys.readouterr().out
    assert [s.sample_id for s in list_collection(tmp_path / "cli" / "index.parquet")] == ["p-3"]
