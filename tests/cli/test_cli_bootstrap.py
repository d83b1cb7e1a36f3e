"""`bat3r bootstrap` and `python flows/bootstrap.py` share one option definition; `--catalog` on the subcommands
that read the catalog (a catalog file written in tmp_path). The real runs of `bat3r bootstrap --catalog` are in
tests/flows/test_sample_drops.py (a run that stops) and tests/flows/test_bootstrap.py (`flows/bootstrap.py
--catalog`, killed and resumed)."""
from __future__ import annotations

import dataclasses
import inspect
import shutil
from pathlib import Path

import pytest
import yaml

from bat3r_core.cli import ABLATION_SWITCHES, build_parser, main, parse_overrides

ROOT = Path(__file__).resolve().parents[2]


def _options(parser) -> set[str]:
    return {s for a in parser._actions for s in a.option_strings} - {"-h", "--help"}


def _subparser(name: str):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices[name]


def test_bat3r_bootstrap_has_exactly_the_options_of_the_flow_script():
    from flows._settings import Ablations
    from flows.bootstrap import bootstrap, build_parser as flow_parser

    assert _options(_subparser("bootstrap")) == _options(flow_parser())
    assert {"--category", "--preset", "--catalog", "--iterations", "--run-name", "--set", "--task-runner",
            "--max-failed-fraction", "--seed", "--init-predictor", "--gaussian-cameras", "--no-fitting-regularisation",
            "--no-view-augmentation", "--no-pseudo-label-filter", "--random-poses", "--raw-images"} == _options(flow_parser())
    assert set(ABLATION_SWITCHES) == {f.name for f in dataclasses.fields(Ablations)}
    # the parsed options are exactly the flow's keyword arguments
    args = build_parser().parse_args(["bootstrap", "--category", "horse", "--preset", "paper", "--catalog",
                                      "cat.yaml", "--iterations", "1", "--set", "train.steps=7", "--set",
                                      "run.fitting={\"steps\": 9}", "--set", "render.device=CPU",
                                      "--no-view-augmentation"])
    from bat3r_core.cli import bootstrap_parameters

    params = bootstrap_parameters(args)
    assert set(params) == set(inspect.signature(bootstrap.fn).parameters)
    assert params["overrides"] == {"train.steps": 7, "run.fitting": {"steps": 9}, "render.device": "CPU"}
    assert params["catalog"] == str(Path("cat.yaml").resolve()) and params["iterations"] == 1
    assert params["no_view_augmentation"] and not params["raw_images"] and not params["no_pseudo_label_filter"]
    assert bootstrap_parameters(flow_parser().parse_args(["--no-pseudo-label-filter"]))["no_pseudo_label_filter"]
    assert (params["category"], params["preset"]) == ("horse", "paper")
    assert bootstrap_parameters(flow_parser().parse_args([]))["catalog"] is None


def test_set_values_parse_as_json_and_bad_items_are_named():
    assert parse_overrides(["a.b=1.5", "c.d=[1, 2]", "e.f=true", "g.h=word"]) == \
        {"a.b": 1.5, "c.d": [1, 2], "e.f": True, "g.h": "word"}
    with pytest.raises(ValueError, match=r"--set expects KEY=VALUE, got 'train.steps'"):
        parse_overrides(["train.steps"])
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bootstrap", "--iterations", "two"])


@pytest.fixture()
def own_catalog(tmp_path, monkeypatch):
    """The project's catalog with the toy renamed `critter`, written in tmp_path (storage root beside it)."""
    monkeypatch.delenv("BAT3R_STORAGE_ROOT", raising=False)
    monkeypatch.setenv("BAT3R_CATALOG", str(ROOT / "data_catalog.yaml"))  # must not be what the commands read
    data = yaml.safe_load((ROOT / "data_catalog.yaml").read_text())
    data["categories"] = {"critter": data["categories"]["toy"]}
    path = tmp_path / "my_catalog.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_catalog_validate_reads_the_catalog_it_is_given(own_catalog, capsys):
    assert main(["catalog", "validate", "--catalog", str(own_catalog)]) == 0
    out = capsys.readouterr().out
    assert f"catalog {own_catalog}" in out and "critter" in out and "horse" not in out
    assert "1/1 categories ready" in out
    assert main(["catalog", "validate", str(own_catalog)]) == 0
    assert "critter" in capsys.readouterr().out
    assert main(["catalog", "validate", str(ROOT / "data_catalog.yaml"), "--catalog", str(own_catalog)]) == 2
    assert "give the catalog once" in capsys.readouterr().err


def test_bootstrap_checks_the_catalog_it_is_given_before_starting(own_catalog, tmp_path, capsys):
    assert main(["bootstrap", "--catalog", str(own_catalog), "--category", "toy"]) == 2
    assert f"unknown category 'toy' in {own_catalog}; available: ['critter']" in capsys.readouterr().err
    assert main(["bootstrap", "--catalog", str(own_catalog), "--category", "critter", "--preset", "huge"]) == 2
    assert "unknown run preset 'huge'" in capsys.readouterr().err
    assert main(["bootstrap", "--catalog", str(tmp_path / "none.yaml")]) == 2
    assert f"data catalog {tmp_path / 'none.yaml'} does not exist" in capsys.readouterr().err


def test_bootstrap_without_a_checkout_says_what_is_missing(tmp_path, capsys, monkeypatch):
    """An installed bat3r_core without the checkout's flows/ (copied package) refuses with the path it looked
    for."""
    package = tmp_path / "site" / "bat3r_core"
    shutil.copytree(ROOT / "bat3r_core", package, ignore=shutil.ignore_patterns("__pycache__"))
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", "import sys; from bat3r_core.cli import main; "
                           "sys.exit(main(['bootstrap']))"], cwd=tmp_path, capture_output=True, text=True,
                          env={"PYTHONPATH": str(tmp_path / "site"), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert f"{tmp_path / 'site' / 'flows' / 'bootstrap.py'} is missing" in proc.stderr


def test_local_runs_give_the_temporary_server_time_to_start_and_keep_a_users_setting():
    """Prefect reads its settings once, at import: the entry points set the defaults before importing it (a
    subprocess, so this test's own Prefect import does not count); a value the user exported wins."""
    import os
    import subprocess
    import sys

    code = ("import sys; from bat3r_core.cli import local_server_environment; assert 'prefect' not in sys.modules; "
            "local_server_environment(); from prefect.settings import get_current_settings as g; "
            "s = g().server; print(s.ephemeral.startup_timeout_seconds, s.analytics_enabled)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_SERVER_")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["180", "False"]
    env["PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"] = "45"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["45", "False"]
