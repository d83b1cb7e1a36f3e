"""``bat3r stages``: the stage table a newcomer reads first, printed from ``bat3r_core.stages.STAGES``."""
from __future__ import annotations

import json

from bat3r_core import stages
from bat3r_core.cli import main


def test_bat3r_stages_prints_every_stage_in_data_flow_order(capsys):
    assert main(["stages"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["stage", "inputs", "folder", "task", "function"]
    assert [line.split()[0] for line in lines[1:]] == [s.name for s in stages.STAGES]
    fit = next(line for line in lines if line.startswith("fit "))
    assert "iter-NN/fit" in fit and "tasks.fit:fit_shard" in fit and "bat3r_core.fitting.io:fit_prediction_shard" in fit


def test_bat3r_stages_json_rows_name_inputs_that_are_stages(capsys):
    assert main(["stages", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    names = [r["stage"] for r in rows]
    assert names == [s.name for s in stages.STAGES]
    for position, row in enumerate(rows):
        for name in row["inputs"]:  # produced earlier in the table, or (previous:) by the iteration before
            if name.startswith("previous:"):
                assert name.removeprefix("previous:") in names, (row, name)
            else:
                assert name in names[:position], (row, name)
    assert {r["scope"] for r in rows} == {"external", "run", "iteration"}
