"""The benchmark targets of the Makefile, read through ``make -n`` (the commands make would run, without running
them): each step of a two-step target reads the run the step before it wrote, and each records under a name of its
own, so refreshing one benchmark never overwrites another's record."""
from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from bat3r_core.catalog import load_catalog

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs make")


def _commands(target: str) -> list[dict]:
    """The benchmark scripts ``make <target>`` runs, each as {"script": ..., option: value}, without its ``install``
    prerequisite (``-o install``)."""
    out = subprocess.run(["make", "-n", "-o", "install", target], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout
    commands = []
    for line in out.splitlines():
        words = [w for w in shlex.split(line) if "=" not in w or w.startswith("--")]
        scripts = [w for w in words if w.startswith("benchmarks/") and w.endswith(".py")]
        if not scripts:
            continue
        args = words[words.index(scripts[0]) + 1:]
        options: dict = {"script": Path(scripts[0]).stem}
        for i, word in enumerate(args):
            if word.startswith("--"):
                value = args[i + 1] if i + 1 < len(args) and not args[i + 1].startswith("--") else True
                options[word[2:]] = value
        commands.append(options)
    return commands


def test_bench_fidelity_runs_the_bench_preset_on_a_generated_category_and_diagnoses_the_same_run():
    fidelity, fit_oracle = _commands("bench-fidelity")
    assert fidelity["script"] == "bench_fidelity" and fit_oracle["script"] == "bench_fit_oracle"
    catalog = load_catalog(ROOT / "data_catalog.yaml")
    assert fidelity["preset"] == "bench" and "bench" in catalog.runs
    # the fit diagnosis reads the run the benchmark wrote: same category, same run name
    assert fit_oracle["category"] == fidelity["category"] and fit_oracle["run-name"] == fidelity["run-name"]
    # a category with hidden truth (the oracle and the fit diagnosis need it): the widened toy
    category = catalog.categories[fidelity["category"]]
    assert category.collection.ground_truth and category.test_split.ground_truth
    assert fidelity["category"] == "toy_wide"
    assert fit_oracle["record-as"] == "fit_oracle_bench"


def test_bench_demo_records_under_names_of_its_own():
    control, fit_oracle = _commands("bench-demo")
    assert (control["script"], control["record-as"]) == ("bench_demo_control", "demo_control")
    # not fit_oracle.json, the paper-recipe record the README cites, nor make bench-fidelity's
    assert (fit_oracle["script"], fit_oracle["record-as"]) == ("bench_fit_oracle", "fit_oracle_demo")


def test_the_bench_preset_carries_what_the_benchmark_measured():
    """The preset make bench-fidelity runs: the silhouette term and canonical replay (the variant whose loop
    recovered half the control → oracle gap, README), for three iterations."""
    bench = load_catalog(ROOT / "data_catalog.yaml").runs["bench"]
    assert bench.iterations == 3
    assert bench.fitting["weight_silhouette"] == 16.0 and bench.train["canonical_replay"] == 1.0
