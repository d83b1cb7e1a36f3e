"""The flow scripts read the catalog given by --catalog (`flows/evaluate.py` here; `flows/bootstrap.py` in
test_bootstrap.py, `flows/toy_collection.py` in test_generated_collection.py)."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import pyarrow.parquet as pq

from bat3r_core import evaluation as E
from bat3r_core.metrics import SampleMetrics

ROOT = Path(__file__).resolve().parents[2]


def test_evaluate_script_finds_the_run_in_its_catalogs_storage_root(prefect_harness, tmp_path, monkeypatch, capsys):
    from flows.evaluate import main

    monkeypatch.delenv("BAT3R_STORAGE_ROOT", raising=False)
    monkeypatch.setenv("BAT3R_CATALOG", str(ROOT / "data_catalog.yaml"))
    catalog = tmp_path / "elsewhere" / "data_catalog.yaml"
    catalog.parent.mkdir()
    shutil.copy(ROOT / "data_catalog.yaml", catalog)
    run = catalog.parent / "runs" / "toy" / "e1"
    rows = [E.sample_row(f"s{i}", "test", 0, SampleMetrics(cd_cm=cd, mv_cd_cm=cd, rot_err_deg=1.0, icp_scale=1.0,
                                                          icp_start_deg=0.0, mv_scale=1.0, n_pred=10, n_gt=10),
                         azimuth_deg=0.0) for i, cd in enumerate([1.0, 5.0])]
    E.write_sample_rows(run / "iter-00" / "evaluate", 0, rows)
    assert main(["--catalog", str(catalog), "--category", "toy", "--run-name", "e1"]) == 0
    assert f"report: {run / 'report.html'}" in capsys.readouterr().out
    assert math.isclose(pq.read_table(run / "metrics.parquet").to_pylist()[0]["mcd_cm"], 3.0)
