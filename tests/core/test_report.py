"""The run report: built from a synthetic run folder, checked structurally and in a real headless Chromium."""
from __future__ import annotations

import base64
import json
import math
import re
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from bat3r_core import evaluation as E
from bat3r_core import report as R
from bat3r_core import shards
from bat3r_core.metrics import SampleMetrics

CHROMIUM = Path("/usr/bin/chromium")


class _Page(HTMLParser):
    """Collects section ids, <img> attributes, and the classes used on the page."""

    def __init__(self):
        super().__init__()
        self.sections: list[str] = []
        self.imgs: list[dict[str, str]] = []
        self.classes: list[str] = []
        self.body: dict[str, str] = {}

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if tag == "section":
            self.sections.append(a.get("id", ""))
        if tag == "img":
            self.imgs.append(a)
        if tag == "body":
            self.body = a
        if "class" in a:
            self.classes.extend(a["class"].split())


def _parse(text: str) -> _Page:
    p = _Page()
    p.feed(text)
    return p


def _sphere(n_lat: int = 8, n_lon: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 1: vertices (V, 3) and faces (F, 3)."""
    verts = [[0.0, 1.0, 0.0]]
    for i in range(1, n_lat):
        th = math.pi * i / n_lat
        for j in range(n_lon):
            ph = 2 * math.pi * j / n_lon
            verts.append([math.sin(th) * math.cos(ph), math.cos(th), math.sin(th) * math.sin(ph)])
    verts.append([0.0, -1.0, 0.0])
    faces = []
    ring = lambda i, j: 1 + (i - 1) * n_lon + j % n_lon  # noqa: E731
    for j in range(n_lon):
        faces.append([0, ring(1, j), ring(1, j + 1)])
        faces.append([len(verts) - 1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)])
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            faces.append([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)])
            faces.append([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)])
    return np.array(verts), np.array(faces)


def _qualitative(stage_dir: Path, iteration: int, rng: np.random.Generator) -> None:
    s, h, w = 3, 64, 80
    k = np.array([[70.0, 0, w / 2], [0, 70.0, h / 2], [0, 0, 1]])
    verts, faces = _sphere(24, 36)
    images, masks, clouds, fitted = [], [], [], []
    for i in range(s):
        body = verts * [0.9, 0.5, 0.5] + [0.1 * i, 0.0, 3.0]  # an ellipsoid 3 m in front of the camera
        uv = np.stack([k[0, 0] * body[:, 0] / body[:, 2] + k[0, 2], k[1, 1] * body[:, 1] / body[:, 2] + k[1, 2]], 1)
        yy, xx = np.mgrid[0:h, 0:w] + 0.5
        cu, cv = uv.mean(0)
        ru, rv = np.ptp(uv[:, 0]) / 2, np.ptp(uv[:, 1]) / 2
        mask = ((xx - cu) / ru) ** 2 + ((yy - cv) / rv) ** 2 <= 1
        img = np.full((h, w, 3), 40, np.uint8)
        img[mask] = [200, 150, 90]
        images.append(img)
        masks.append(mask)
        front = body[body[:, 2] < 3.0]
        clouds.append(front + rng.normal(0, 0.02 * (3 - iteration), size=front.shape))
        fitted.append(body if i < 2 else np.full_like(body, np.nan))
    R.write_report_inputs(stage_dir, sample_ids=[f"img-{i}" for i in range(s)], images=np.stack(images),
                          intrinsics=np.repeat(k[None], s, 0), pred_points=clouds, masks=np.stack(masks),
                          fitted_verts=np.stack(fitted), faces=faces, cd_cm=[1.5, 4.0, 7.5])


def _make_run(root: Path, iterations: int = 3, n: int = 120) -> Path:
    run = root / "toy" / "report-test"
    run.mkdir(parents=True)
    (run / "manifest.json").write_text(json.dumps({"category": "toy", "run_name": "report-test",
                                                   "code_version": "abc123", "config": {"nested": True}}))
    rng = np.random.default_rng(0)
    az = rng.uniform(-180, 180, n)
    el = 3 + 6 * rng.standard_t(2.0, n)
    ro = 4 * rng.standard_t(1.7, n)
    cluster = rng.integers(0, 10, n)
    f_dist = 0.2 + 0.15 * cluster + rng.uniform(0, 0.1, n)
    for it in range(iterations):
        base = 8.0 / (1 + it)
        rows = []
        for i in range(n):
            lateral = abs(abs(az[i]) - 90) < 45
            cd = base * (0.6 if lateral else 1.2) * (1 + 0.1 * cluster[i]) * rng.uniform(0.6, 1.4)
            m = SampleMetrics(cd, cd * 1.25, 10.0 / (1 + it) * rng.uniform(0.5, 1.5), 1.0, 0.0, 1.0, 500, 800)
            split = "test" if i < 100 else "val"
            rows.append(E.sample_row(f"s{i:04d}", split, it, m, azimuth_deg=az[i], elevation_deg=el[i],
                                     roll_deg=ro[i], pose_features=(0.1, 0.02, f_dist[i]), cluster=int(cluster[i])))
        rows.append(E.sample_row("bad", "test", it, None, status="empty", reason="no confident points"))
        E.write_sample_rows(run / f"iter-{it:02d}" / "evaluate", 0, rows)
        _qualitative(run / f"iter-{it:02d}" / "evaluate", it, rng)
        if it >= 1:
            status = np.where(rng.uniform(size=n) < 0.15, "filtered", "ok")
            fit_rows = [{"sample_id": f"c{i:04d}", "status": str(st),
                         "reason": "" if st == "ok" else "final loss above threshold",
                         "loss_total": float(rng.gamma(2, 0.05 / it)), "loss_data": float(rng.gamma(2, 0.03 / it)),
                         "loss_edge": float(rng.gamma(2, 0.01)), "joint_err_cm": float(rng.gamma(2, 3.0 / it)),
                         "vertex_err_cm": float(rng.gamma(2, 2.5 / it)), "angle_err_deg": float(rng.gamma(2, 4 / it)),
                         "bone_err_deg": 12.0 / it,  # not drawn: the draws after it stay as they were
                         "azimuth_deg": float(rng.uniform(-180, 180)), "elevation_deg": float(5 * rng.standard_t(2)),
                         "roll_deg": float(4 * rng.standard_t(1.5)), "cluster": int(rng.integers(0, 10))}
                        for i, st in enumerate(status)]
            shards.write_shard(run / f"iter-{it:02d}" / "fit", 0, fit_rows)
        _collection_rows(run, it, rng)
    E.evaluate_run(run)
    return run


def _collection_rows(run: Path, it: int, rng: np.random.Generator, n: int = 20) -> None:
    """Per-image mask IoU rows of the collection (``bat3r_core.evaluation_masks``), improving with iterations."""
    from bat3r_core import evaluation_masks as M

    rows = [{"sample_id": f"c{i:04d}", "split": "collection", "iteration": it, "status": "ok", "reason": "",
             "pred_mask_iou": float(min(1.0, 0.5 + 0.15 * it + rng.uniform(-0.05, 0.05))), "mask_pixels": 500,
             "pred_pixels": 400, "fit_status": "ok" if it else "no_fit",
             "fit_mask_iou": float(0.4 + 0.2 * it) if it else math.nan, "fit_pixels": 450 if it else 0}
            for i in range(n)]
    shards.write_shard(run / f"iter-{it:02d}" / "evaluate" / M.COLLECTION_ROWS_DIR, 0, rows)


@pytest.fixture(scope="module")
def full_run(tmp_path_factory) -> Path:
    run = _make_run(tmp_path_factory.mktemp("runs"))
    R.build_report(run)
    return run


def test_full_report_has_every_section_and_valid_images(full_run):
    page = _parse((full_run / "report.html").read_text())
    assert page.sections == list(R.SECTION_IDS)
    assert "error" not in page.classes, "a section failed to draw"
    assert "na" not in page.classes, "a section of a complete run says 'not available'"
    assert len(page.imgs) >= 12
    for img in page.imgs:
        m = re.fullmatch(r"data:image/png;base64,(.+)", img["src"])
        assert m, "images must be embedded PNGs"
        assert base64.b64decode(m.group(1))[:8] == b"\x89PNG\r\n\x1a\n"
    text = (full_run / "report.html").read_text()
    assert "src=\"http" not in text and "<link" not in text  # self-contained
    assert "report-test" in text and "0 (canonical)" in text


def test_report_of_an_empty_or_partial_run_shows_notes(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    page = _parse(R.build_report(run).read_text())
    assert page.sections == list(R.SECTION_IDS)
    assert page.classes.count("na") >= len(R.SECTION_IDS) - 1 and "error" not in page.classes
    # iteration 0 evaluated, no fits, metrics.parquet not written yet, qualitative file corrupt
    rows = [E.sample_row(f"s{i}", "test", 0, SampleMetrics(3.0 + i, 4.0 + i, 5.0, 1, 0, 1, 10, 10))
            for i in range(5)]
    E.write_sample_rows(run / "iter-00" / "evaluate", 0, rows)
    (run / "iter-00" / "evaluate" / R.QUALITATIVE_FILE).write_bytes(b"not an npz")
    text = R.build_report(run).read_text()
    page = _parse(text)
    assert page.sections == list(R.SECTION_IDS) and "error" not in page.classes
    assert "computed from the per-sample rows" in text
    assert "No fits yet" in text and "unreadable" in text
    assert not (run / "metrics.parquet").exists()  # the report reads, never writes metrics
    # an unreadable shard is reported on the page instead of failing the report
    (run / "iter-00" / "evaluate" / "part-00001.parquet").write_bytes(b"garbage")
    text = R.build_report(run).read_text()
    assert _parse(text).sections == list(R.SECTION_IDS)
    assert "Could not read per-sample evaluation rows" in text
    with pytest.raises(FileNotFoundError, match="does not exist"):
        R.build_report(tmp_path / "missing")


def test_report_inputs_round_trip_and_checks(tmp_path):
    rng = np.random.default_rng(1)
    clouds = [rng.normal(size=(50, 3)), rng.normal(size=(5000, 3))]
    path = R.write_report_inputs(tmp_path, sample_ids=["a", "b"], images=np.zeros((2, 8, 9, 3), np.uint8),
                                 intrinsics=np.repeat(np.eye(3)[None], 2, 0), pred_points=clouds, max_points=100)
    q = R.read_report_inputs(path)
    assert q.sample_id.tolist() == ["a", "b"] and q.pred_points.shape == (2, 100, 3)
    np.testing.assert_allclose(q.pred_points[0, :50], clouds[0].astype(np.float32))
    assert np.isnan(q.pred_points[0, 50:]).all() and np.isfinite(q.pred_points[1]).all()
    assert q.fitted_verts is None and q.mask is None
    with pytest.raises(ValueError, match=r"images must be \(S=2, H, W, 3\) uint8"):
        R.write_report_inputs(tmp_path, sample_ids=["a", "b"], images=np.zeros((2, 8, 9)),
                              intrinsics=np.zeros((2, 3, 3)), pred_points=clouds)
    with pytest.raises(ValueError, match="fitted_verts and faces must be given together"):
        R.write_report_inputs(tmp_path, sample_ids=["a", "b"], images=np.zeros((2, 8, 9, 3), np.uint8),
                              intrinsics=np.zeros((2, 3, 3)), pred_points=clouds, fitted_verts=np.zeros((2, 4, 3)))


_CHECK_SCRIPT = """<script>
window.addEventListener('load', function () {
  // after 'load' every <img> has finished loading; drawing one into a canvas forces its pixels to be decoded
  var canvas = document.createElement('canvas');
  canvas.width = 16; canvas.height = 16;
  var ctx = canvas.getContext('2d');
  Array.prototype.forEach.call(document.images, function (im) {
    var painted = 0;
    try {
      ctx.clearRect(0, 0, 16, 16);
      ctx.drawImage(im, 0, 0, 16, 16);
      var px = ctx.getImageData(0, 0, 16, 16).data;
      for (var i = 3; i < px.length; i += 4) { painted += px[i] > 0 ? 1 : 0; }
    } catch (e) { painted = -1; }
    im.setAttribute('data-complete', im.complete ? '1' : '0');
    im.setAttribute('data-natural-width', String(im.naturalWidth));
    im.setAttribute('data-painted', String(painted));
  });
  var ids = Array.prototype.map.call(document.querySelectorAll('section'), function (s) { return s.id; });
  document.body.setAttribute('data-sections', ids.join(','));
  document.body.setAttribute('data-check', 'done');
});
</script>"""


def _chromium(args: list[str], profile: Path) -> subprocess.CompletedProcess:
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--disable-dev-shm-usage", f"--user-data-dir={profile}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.mark.browser
@pytest.mark.skipif(not CHROMIUM.exists(), reason="needs /usr/bin/chromium (apt-get install chromium)")
def test_report_loads_in_headless_chromium(full_run, tmp_path):
    checked = tmp_path / "checked.html"
    checked.write_text((full_run / "report.html").read_text().replace("</body>", _CHECK_SCRIPT + "</body>"))
    res = _chromium(["--virtual-time-budget=15000", "--dump-dom", checked.as_uri()], tmp_path / "profile")
    assert res.returncode == 0, res.stderr[-2000:]
    page = _parse(res.stdout)
    assert page.body.get("data-check") == "done", "the page's load handler did not finish"
    assert page.body["data-sections"].split(",") == list(R.SECTION_IDS)
    assert len(page.imgs) >= 12
    for img in page.imgs:
        assert img.get("data-complete") == "1", f"image {img.get('alt')!r} did not load"
        assert int(img.get("data-natural-width", "0")) > 100, f"image {img.get('alt')!r} did not decode"
        assert int(img.get("data-painted", "0")) > 0, f"image {img.get('alt')!r} painted no pixels"
    shot = tmp_path / "report.png"
    res = _chromium(["--window-size=1400,2400", "--hide-scrollbars", f"--screenshot={shot}",
                     (full_run / "report.html").as_uri()], tmp_path / "profile2")
    assert res.returncode == 0 and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_clusters_are_computed_from_pose_features_when_rows_carry_none(tmp_path):
    from bat3r_core import evaluation as E
    from bat3r_core.metrics import SampleMetrics

    rng = np.random.default_rng(5)
    run = tmp_path / "toy" / "r"
    for it in (0, 1):
        rows = [E.sample_row(f"s{i}", "test", it, SampleMetrics(float(2 + i % 7), 3.0, 4.0, 1.0, 0.0, 1.0, 10, 10),
                             pose_features=rng.random(3) + [0, 0, i % 4]) for i in range(14)]
        E.write_sample_rows(run / f"iter-{it:02d}" / "evaluate", 0, rows)
    page = (R.build_report(run)).read_text()
    section = page[page.index('id="per-cluster"'):]
    section = section[:section.index("</section>")]
    assert "Clusters computed here from the samples" in section and "<img" in section


def test_report_shows_the_fits_bone_direction_errors(full_run):
    """The pseudo-label table's bone direction column: the mean over each iteration's ok fits (12° and 6° here)."""
    text = (full_run / "report.html").read_text()
    section = re.search(r'<section id="pseudo-labels">(.*?)</section>', text, re.S).group(1)
    assert "bone direction err (°)" in section
    rows = re.findall(r"<tr>(<td>.*?)</tr>", section)
    assert rows[0].endswith("<td>12.00</td>") and rows[1].endswith("<td>6.00</td>"), rows[:2]


def test_report_shows_the_collection_mask_ious_per_iteration(full_run, tmp_path):
    text = (full_run / "report.html").read_text()
    section = re.search(r'<section id="collection-masks">(.*?)</section>', text, re.S).group(1)
    cells = re.findall(r"<tr>(<td>.*?)</tr>", section)
    assert len(cells) == 3                                   # one table row per iteration
    assert "0 (canonical)" in cells[0] and "–" in cells[0]   # iteration 0: no fits of its own
    assert "<td>0.800</td>" in cells[2] and "<td>20</td>" in cells[2]  # iteration 2's mean fit IoU, 20 fits
    assert "<img" in section and "Latest (collection, iteration 2)" in text
    metrics = {(r["iteration"], r["split"]): r for r in E.read_metrics(full_run).to_pylist()}
    pred = [metrics[i, "collection"]["pred_mask_iou"] for i in range(3)]
    assert pred[0] < pred[1] < pred[2]
    for it in range(3):
        assert f"<td>{pred[it]:.3f}</td>" in cells[it]
    # a run with collection rows only (real photos, no test ground truth), metrics.parquet not written yet
    run = tmp_path / "photos"
    _collection_rows(run, 0, np.random.default_rng(1))
    _collection_rows(run, 1, np.random.default_rng(2))
    text = R.build_report(run).read_text()
    page = _parse(text)
    assert page.sections == list(R.SECTION_IDS) and "error" not in page.classes
    assert "Latest (collection, iteration 1)" in text and "<td>0.600</td>" in text  # iteration 1's fit IoU


@pytest.mark.parametrize("without_metrics", [False, True])
def test_report_reads_only_its_declared_inputs(full_run, tmp_path, without_metrics):
    """The report task is cached by ``report_inputs``: a file the report opens that is not listed there could change
    without the report being rebuilt. Every read is watched (inotify, ``tests/file_reads.py``); without
    ``metrics.parquet`` the report aggregates the per-sample and collection rows itself."""
    import shutil

    from file_reads import FileReads

    run = tmp_path / "run"
    shutil.copytree(full_run, run)
    (run / "report.html").unlink()
    if without_metrics:
        (run / "metrics.parquet").unlink()
    declared = set(R.report_inputs(run))
    with FileReads(run) as reads:
        R.build_report(run)
    # an atomic write fsyncs its temporary file through a read-only open (shards.atomic_write): gone by now
    opened = {p for p in reads.counts if p.exists()}
    assert opened, "the watch saw no read"
    assert opened <= declared, sorted(str(p.relative_to(run)) for p in opened - declared)
    assert {p.name for p in opened} >= {"qualitative.npz", "part-00000.parquet"}
