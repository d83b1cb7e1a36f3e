"""The typed stage specs (``bat3r_core.specs``) and the one place a run's settings become them
(``flows._settings.stage_specs``)."""
from __future__ import annotations

import dataclasses

import pytest

from bat3r_core.config_utils import ConfigError, to_mapping
from bat3r_core.fitting.augment import AugmentConfig
from bat3r_core.specs import CropCamera, FitSpec, InferSpec, PlanViewsSpec, SampledPlanSpec, TrainSpec, as_spec


@pytest.mark.parametrize("preset", ["tiny", "demo", "bench", "paper"])
def test_every_preset_cuts_into_specs_that_round_trip_through_their_mapping(catalog, preset):
    """A deployment passes a spec's mapping form: it must rebuild the same spec (and so the same cache key)."""
    from flows._settings import resolve_run, stage_specs

    settings = resolve_run("toy", preset, f"specs-{preset}", catalog=catalog / "data_catalog.yaml")
    specs = stage_specs(settings, seed=3)
    for field in dataclasses.fields(specs):
        spec = getattr(specs, field.name)
        if not dataclasses.is_dataclass(spec):
            continue
        assert as_spec(type(spec), to_mapping(spec), field.name) == spec, field.name
    # what each spec carries comes from the settings, not from constants in the flow or the tasks
    assert specs.infer.batch_size == settings.infer_batch_size and specs.infer.features == settings.features
    assert specs.fit.camera == CropCamera(settings.camera_prior.fov_deg, settings.image_size)
    assert specs.fit.camera.pinhole().width == settings.image_size
    assert specs.plan.n == settings.canonical_samples and specs.plan.seed == 3 == specs.plan_views.seed
    assert specs.render.render == settings.render and specs.render.render.num_layers == settings.layers
    assert specs.raw_images.layers == settings.layers and specs.train.init_from is None
    assert specs.train_from("/x/predictor.pt").init_from == "/x/predictor.pt"
    assert specs.evaluate_at(2).iteration == 2 and specs.collection_evaluation_at(1).iteration == 1


def test_run_overrides_reach_the_specs(catalog):
    from flows._settings import resolve_run, stage_specs

    settings = resolve_run("toy", "tiny", "specs-over", {"run.infer_batch_size": 3, "camera_prior.fov_deg": 40.0},
                           catalog=catalog / "data_catalog.yaml")
    specs = stage_specs(settings, seed=0)
    assert specs.infer.batch_size == 3 and specs.fit.camera.fov_deg == 40.0
    assert specs.plan_views.augment.camera_prior.fov_deg == 40.0


def test_a_bad_mapping_names_the_stage_and_the_key():
    with pytest.raises(ConfigError, match=r"fit config: unknown key\(s\) \['fov_deg'\]"):
        as_spec(FitSpec, {"fitting": {}, "camera": {"fov_deg": 50.0, "resolution": 32}, "fov_deg": 50.0},
                "fit config")
    with pytest.raises(ConfigError, match=r"fit config.camera.resolution: required key is missing"):
        as_spec(FitSpec, {"fitting": {}, "camera": {"fov_deg": 50.0}}, "fit config")
    with pytest.raises(ConfigError, match=r"infer config: expected a InferSpec \(or its mapping\), got TrainSpec"):
        as_spec(InferSpec, TrainSpec.__new__(TrainSpec), "infer config")
    with pytest.raises(ConfigError, match=r"infer.batch_size: must be >= 1, got 0"):
        as_spec(InferSpec, {"features": {"extractor": "rgb"}, "batch_size": 0}, "infer config")
    with pytest.raises(ConfigError, match=r"plan.kind: expected one of \['canonical', 'random_pose'\]"):
        as_spec(SampledPlanSpec, {"kind": "posed", "n": 4, "seed": 0, "resolution": 32, "shard_size": 4,
                                  "body_frame": {}}, "plan")
    with pytest.raises(ConfigError, match=r"plan_views.body_frame: missing key\(s\) \['horizontal'\]"):
        PlanViewsSpec(augment=AugmentConfig(), body_frame={"origin": "spine", "forward": ["a", "b"]})


def test_a_task_given_a_bad_config_fails_with_the_key_in_its_error(tmp_path):
    """The task parses nothing itself: a wrong key reaches the user as the spec's error, naming the stage."""
    from tasks.predict import infer_shard

    with pytest.raises(ConfigError, match=r"infer config: unknown key\(s\) \['batchsize'\]"):
        infer_shard.fn(str(tmp_path / "predictor.pt"), str(tmp_path), 0, str(tmp_path / "out"),
                       {"features": {"extractor": "rgb"}, "batchsize": 4})
