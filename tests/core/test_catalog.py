import shutil
from pathlib import Path

import pytest
import yaml

from bat3r_core.catalog import ConfigError, load_catalog
from bat3r_core.cli import main

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def catalog_copy(tmp_path):
    dst = tmp_path / "data_catalog.yaml"
    shutil.copy(ROOT / "data_catalog.yaml", dst)
    return dst


def _edit(path, fn):
    data = yaml.safe_load(path.read_text())
    fn(data)
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_shipped_catalog_loads_with_typed_stage_configs(catalog_copy):
    cat = load_catalog(catalog_copy)
    assert {"toy", "horse", "cow", "sheep"} <= set(cat.categories)
    assert {"tiny", "demo", "paper"} <= set(cat.runs)
    toy = cat.category("toy")
    assert toy.body_frame.origin == "spine.2" and toy.body_frame.horizontal == ("thigh.L", "thigh.R")
    assert toy.missing() == []
    # paths resolve relative to the catalog file, not the working directory
    assert cat.category("horse").resolve("assets/horse/horse.glb") == catalog_copy.parent / "assets/horse/horse.glb"
    assert cat.fitting_config("horse").weight_edge == 3000.0  # real preset
    assert cat.fitting_config("toy").weight_edge == 100.0  # synthetic preset
    assert cat.fitting_config("toy", run="tiny").steps == cat.runs["tiny"].fitting["steps"]
    assert cat.model_config("paper").resolution == 160 and cat.model_config("paper").layers == 4
    assert cat.camera_prior_config().distribution == "student_t"
    assert cat.train_config("paper").weight_decay == 0.01


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(colour="red"), r"unknown top-level key\(s\) \['colour'\]"),
    (lambda d: d["categories"]["toy"].update(pose="x"), r"categories\.toy: unknown key\(s\) \['pose'\]"),
    (lambda d: d["categories"]["horse"]["body_frame"].pop("origin"),
     r"categories\.horse\.body_frame\.origin: required key is missing"),
    (lambda d: d["categories"]["horse"]["body_frame"].update(forward="spine"),
     r"categories\.horse\.body_frame\.forward: expected a list"),
    (lambda d: d["runs"]["tiny"].update(iterations="two"), r"runs\.tiny\.iterations: expected an integer"),
    (lambda d: d.update(shard_size=1.5), r"shard_size: expected an integer"),
    (lambda d: d["runs"]["demo"]["train"].update(stepz=3), r"runs\.demo\.train: unknown key\(s\) \['stepz'\]"),
    (lambda d: d["fitting_presets"]["real"].update(weight_edge="big"),
     r"fitting_presets\.real\.weight_edge: expected a number"),
    (lambda d: d["categories"]["cow"]["collection"].update(kind="zip"),
     r"categories\.cow\.collection\.kind: expected one of \['folder', 'parquet', 'generated'\]"),
    (lambda d: d.pop("runs"), r"runs: required key is missing"),
    (lambda d: d["camera_prior"].update(distribution="cauchy"), r"camera_prior\.distribution"),
])
def test_bad_catalogs_name_the_key(catalog_copy, edit, message):
    _edit(catalog_copy, edit)
    with pytest.raises(ConfigError, match=message):
        load_catalog(catalog_copy)


def test_missing_asset_reported_on_use(catalog_copy):
    cat = load_catalog(catalog_copy)
    with pytest.raises(FileNotFoundError, match=r"category 'horse': rigged asset .*assets/horse/horse.glb does not "
                                                r"exist\. Provide a rigged, skinned canonical mesh"):
        cat.category("horse").require_asset()
    assert any("horse.glb" in m for m in cat.category("horse").missing())


def test_toy_asset_generated_on_first_use(catalog_copy, tmp_path, monkeypatch):
    monkeypatch.setenv("BAT3R_STORAGE_ROOT", str(tmp_path / "store"))
    cat = load_catalog(catalog_copy)
    path = cat.asset_path("toy")
    assert path.is_file() and path.parent == tmp_path / "store" / "_assets"
    rig = cat.load_rig("toy")
    assert rig.num_joints == 27 and rig.joint_index("spine.2") >= 0


def test_cli_catalog_validate(catalog_copy, capsys):
    assert main(["catalog", "validate", str(catalog_copy)]) == 0
    out = capsys.readouterr().out
    assert "toy      ready" in out
    assert "toy_wide ready" in out
    assert "horse" in out and "needs rigged asset" in out and "2/5 categories ready" in out
    _edit(catalog_copy, lambda d: d.update(layers="four"))
    assert main(["catalog", "validate", str(catalog_copy)]) == 2
    assert "layers: expected an integer" in capsys.readouterr().err


def test_cli_asset_toy(tmp_path, capsys):
    out = tmp_path / "toy.glb"
    assert main(["asset", "toy", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and "27 joints" in text


def test_asset_units_axes_and_auto_body_frame(catalog_copy, tmp_path, monkeypatch, toy_rig):
    """A user asset in centimetres, Z-up: refused without asset_scale, normalised once with it (metres, Y-up),
    and `body_frame: auto` resolved from the skeleton."""
    import numpy as np

    from bat3r_core.rig import Rig, RigError
    from bat3r_core.rig_io import save_rig_glb

    monkeypatch.delenv("BAT3R_STORAGE_ROOT", raising=False)
    z_up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the toy's +Y up becomes +Z up, in centimetres
    g = toy_rig.rest_transforms.copy()
    g[:, :3, :3] = z_up @ g[:, :3, :3]
    g[:, :3, 3] = 100.0 * g[:, :3, 3] @ z_up.T
    cm = Rig(name="cm", rest_vertices=100.0 * toy_rig.rest_vertices @ z_up.T, faces=toy_rig.faces,
             joint_names=toy_rig.joint_names, parents=toy_rig.parents, rest_transforms=g,
             skin_weights=toy_rig.skin_weights, uvs=toy_rig.uvs)
    save_rig_glb(cm, tmp_path / "cm.glb")

    def category(scale):
        def edit(d):
            d["storage_root"] = str(tmp_path / "runs")
            d["categories"]["cm"] = {**d["categories"]["horse"], "asset": str(tmp_path / "cm.glb"),
                                     "up_axis": "+Z", "body_frame": "auto", "textures": []}
            if scale is not None:
                d["categories"]["cm"]["asset_scale"] = scale
        return edit

    cat = load_catalog(_edit(catalog_copy, category(None)))
    with pytest.raises(RigError, match=r"236\.\d m long .*set `asset_scale: 0.01`"):
        cat.asset_path("cm")
    cat = load_catalog(_edit(catalog_copy, category(0.01)))
    path = cat.asset_path("cm")
    assert path.parent == tmp_path / "runs" / "_assets" and cat.asset_path("cm") == path  # normalised once
    rig = cat.load_rig("cm")
    np.testing.assert_allclose(np.sort(rig.rest_vertices, axis=0), np.sort(toy_rig.rest_vertices, axis=0),
                               atol=1e-5)
    frame = cat.body_frame("cm")
    assert (frame.origin, frame.forward, frame.horizontal) == ("spine.2", ("spine.1", "spine.2"),
                                                               ("thigh.L", "thigh.R"))
    with pytest.raises(ConfigError, match=r"categories.cm.asset_scale: expected a positive number"):
        load_catalog(_edit(catalog_copy, category(-1.0)))
    with pytest.raises(ConfigError, match=r"categories.cm.up_axis: expected one of"):
        load_catalog(_edit(catalog_copy, lambda d: d["categories"]["cm"].update(up_axis="up")))
