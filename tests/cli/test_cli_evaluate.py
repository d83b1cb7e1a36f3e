import math

import pyarrow.parquet as pq

from bat3r_core import evaluation as E
from bat3r_core.cli import main
from bat3r_core.metrics import SampleMetrics


def _row(i, it, cd):
    m = SampleMetrics(cd_cm=cd, mv_cd_cm=cd + 1.0, rot_err_deg=2.0, icp_scale=1.0, icp_start_deg=0.0, mv_scale=1.0,
                      n_pred=100,
                      n_gt=100)
    return E.sample_row(f"s{it}-{i}", "test", it, m, azimuth_deg=float(i))


def test_bat3r_evaluate_recomputes_metrics_and_report(tmp_path, capsys):
    run = tmp_path / "toy" / "run"
    for it, cds in ((0, [2.0, 6.0]), (1, [1.0, 3.0])):
        E.write_sample_rows(run / f"iter-{it:02d}" / "evaluate", 0, [_row(i, it, c) for i, c in enumerate(cds)])
    assert main(["evaluate", "--run", str(run)]) == 0
    out = capsys.readouterr().out
    table = pq.read_table(run / "metrics.parquet").to_pylist()
    by_it = {r["iteration"]: r for r in table}
    assert math.isclose(by_it[0]["mcd_cm"], 4.0) and math.isclose(by_it[1]["mcd_cm"], 2.0)
    assert math.isclose(by_it[0]["pct_mcd_over_5cm"], 50.0)
    assert (run / "report.html").is_file() and "mcd_cm" in out
    assert main(["evaluate", "--run", str(tmp_path / "nope")]) == 2


def test_bat3r_evaluate_finds_the_run_in_the_storage_root_of_its_catalog(tmp_path, capsys, monkeypatch):
    import shutil
    from pathlib import Path

    monkeypatch.delenv("BAT3R_STORAGE_ROOT", raising=False)
    catalog = tmp_path / "cat" / "data_catalog.yaml"
    catalog.parent.mkdir()
    shutil.copy(Path(__file__).resolve().parents[2] / "data_catalog.yaml", catalog)
    run = tmp_path / "cat" / "runs" / "toy" / "r1"  # storage_root: runs, relative to the catalog file
    E.write_sample_rows(run / "iter-00" / "evaluate", 0, [_row(i, 0, c) for i, c in enumerate([2.0, 4.0])])
    assert main(["evaluate", "--catalog", str(catalog), "--category", "toy", "--run-name", "r1"]) == 0
    assert math.isclose(pq.read_table(run / "metrics.parquet").to_pylist()[0]["mcd_cm"], 3.0)
    assert main(["evaluate", "--catalog", str(catalog), "--category", "toy", "--run-name", "r2"]) == 2
    assert f"run folder {run.parent / 'r2'} does not exist" in capsys.readouterr().err
    assert main(["evaluate", "--catalog", str(catalog), "--category", "toy"]) == 2
    assert "give either --run DIR or --category NAME --run-name NAME" in capsys.readouterr().err
