"""A misspelt key of a dataset preset or a training config is refused with the nearest valid
name, instead of passing unnoticed while its setting keeps the default."""

import dataclasses
from pathlib import Path

import pytest

from workflows import presets
from workflows.train import load_config, train

ROOT = Path(__file__).resolve().parents[2]


def test_every_packaged_preset_and_training_config_loads():
    for name in presets.available():
        presets.load(name)
    for path in (presets.resources.files(presets.__package__) / "training").iterdir():
        if path.name.endswith(".yaml"):
            load_config(str(path))
    experiments = sorted((ROOT / "docs" / "experiments").glob("*.yaml"))  # the unshipped candidates' configs
    assert len(experiments) >= 4
    for path in experiments:
        load_config(str(path))


def test_an_unknown_preset_key_is_refused_with_the_nearest_name(tmp_path, monkeypatch):
    (tmp_path / "mine.yaml").write_text("localizer: {num_dbs: 3, num_iter: 50}\nprior: top1\n")
    monkeypatch.setattr(presets.resources, "files", lambda package: tmp_path)
    with pytest.raises(ValueError, match=r"preset mine.yaml: unknown key 'localizer.num_iter' "
                                         r"\(did you mean 'localizer.num_iters'\?\)"):
        presets.load("mine")


def test_a_misspelt_training_key_is_refused_with_the_nearest_name(tmp_path):
    """Before: train() read ~30 keys with config.get(key, default): 'val_evry' trained with the default."""
    (tmp_path / "run.yaml").write_text("steps: 10\nval_evry: 5\n")
    with pytest.raises(ValueError, match=r"unknown key 'val_evry' \(did you mean 'val_every'\?\)"):
        load_config(str(tmp_path / "run.yaml"))
    with pytest.raises(ValueError, match="did you mean 'damping_lr_scale'"):
        train({"damping_lr_scal": 0.0}, tmp_path / "out", tmp_path)


def test_a_training_config_takes_each_default_from_its_dataclass_and_reads_back(tmp_path):
    """Before: train() read ~30 keys with config.get(key, default), and its defaults disagreed with
    TrainConfig's (lr 1e-4 against 1e-5)."""
    import yaml

    from pipeline.data.training_data import PairConfig
    from pixloc.training import TrainConfig
    from workflows.train import TrainingRun
    run = TrainingRun.from_dict({"steps": 40, "ema": 0.9, "max_size": 256})
    assert run.trainer.lr == TrainConfig().lr and run.trainer.ema == 0.9 and run.trainer.total_steps == 40
    assert run.pairs == PairConfig(max_size=256)
    assert TrainingRun.from_dict({"steps": 40, "decay_steps": 30}).trainer.total_steps == 30
    packaged = load_config("lite0", {"steps": 7, "lr": 3e-5})
    assert (packaged.steps, packaged.trainer.lr, packaged.trainer.total_steps) == (7, 3e-5, 7)
    (tmp_path / "resolved.yaml").write_text(yaml.safe_dump(packaged.to_dict()))  # as train writes config.yaml
    assert load_config(str(tmp_path / "resolved.yaml")) == packaged


def test_a_job_recorded_before_a_setting_existed_reads_as_the_same_job():
    """Runs recorded before an option existed have no such key: they read back with its default, so a
    rerun of one is the same run (no hand-written deletion per new field); schema 1, the flat job of
    earlier versions, reads back too."""
    from pipeline.localization.priors import Hloc, Sift
    from pipeline.localization.refine import LocalizerConfig
    from pipeline.localization.retrieval import GlobalDescriptors, PairsFile
    from pipeline.localization.shard import LocalizationJob
    from pipeline.mapping.features import FeatureConfig
    job = LocalizationJob("map.zarr", FeatureConfig(), "pixloc-lite0", LocalizerConfig(), GlobalDescriptors())
    recorded = job.to_dict()
    assert recorded["schema"] == 3 and recorded["prior"] == {"name": "top1"}
    del recorded["localizer"]["network_precision"], recorded["localizer"]["verification"]["rivals"]
    assert LocalizationJob.from_dict(recorded) == job
    half = LocalizationJob("map.zarr", FeatureConfig(), "pixloc-lite0", LocalizerConfig(network_precision="bfloat16"),
                           GlobalDescriptors())
    assert LocalizationJob.from_dict(half.to_dict()) == half != job
    with pytest.raises(ValueError, match="network_precision must be one of"):
        LocalizerConfig(network_precision="float16")
    # schema 1: every prior's settings flat beside the prior's name, every method's in retrieval
    flat = {"store": "map.zarr", "features": dataclasses.asdict(FeatureConfig()), "model": "pixloc-lite0",
            "localizer": dataclasses.asdict(LocalizerConfig()), "prior": "hloc", "num_hypotheses": 3,
            "device": "cpu", "prior_poses": None, "levels": [0, 1], "hloc_logs": "/x/logs.pkl",
            "point_selection": "inliers", "min_matches_db": 10, "min_inliers": 10, "scales": None,
            "retrieval": {"method": "pairs", "pairs": "/x/pairs.txt", "k": 10, "same_tag": None, "descriptors": None}}
    old = LocalizationJob.from_dict(flat)
    assert old.prior == Hloc(hloc_logs="/x/logs.pkl", point_selection="inliers") and old.levels == (0, 1)
    assert old.retrieval == PairsFile(pairs="/x/pairs.txt")
    sift = LocalizationJob.from_dict({**flat, "prior": "sift", "sift": {"min_inliers": 20},
                                      "search": {"keep": 2}})
    assert sift.prior.sift.min_inliers == 20 and sift.prior.search.keep == 2 and isinstance(sift.prior, Sift)
    with pytest.raises(ValueError, match="unknown key 'localizer.num_iter'"):
        LocalizationJob.from_dict({**job.to_dict(), "localizer": {"num_iter": 3}})


def test_a_value_of_another_type_is_refused_naming_its_key(tmp_path):
    """Before: the config's values reached the dataclasses as YAML gave them: ``steps: x`` failed its
    range check with a TypeError traceback, ``synthetic_camera: [PINHOLE, 320, x]`` one deeper, and
    ``clip_grad: .nan`` trained."""
    from workflows.options import build
    from workflows.train import TrainingRun
    for config, said in (({"steps": "x"}, "steps is 'x', not a whole number"),
                         ({"lr": [1]}, r"lr is \[1\], not a number"),
                         ({"clip_grad": float("nan")}, "clip_grad is nan, not a number"),
                         ({"lr_schedule": 3}, "lr_schedule is 3, not a string"),
                         ({"data": "synthetic"}, "data is 'synthetic', not a list of Dicts"),
                         ({"synthetic_camera": ["PINHOLE", 320, "x", [1.0]]}, "synthetic_camera is"),
                         ({"synthetic_camera": ["PINHOLE", 320, 0, [250.0, 250.0, 160.0, 120.0]]},
                          "synthetic_camera: camera PINHOLE has an invalid size 320x0")):
        with pytest.raises(ValueError, match=rf"^run.yaml: {said}"):
            TrainingRun.from_dict(config, "run.yaml")
    run = TrainingRun.from_dict({"steps": 40.0, "lr": 1})  # a whole number is both
    assert run.steps == 40 and isinstance(run.steps, int) and run.trainer.lr == 1
    from pipeline.localization.shard import LocalizationJob
    for layer, said in (({"localizer.num_iters": "50"}, "localizer.num_iters is '50', not a whole number"),
                        ({"localizer.average_observations": 1},
                         "localizer.average_observations is 1, not true or false"),
                        ({"retrieval.k": None}, "retrieval.k is None, not a whole number")):
        with pytest.raises(ValueError, match=f"^job.json: {said}"):
            build(LocalizationJob, {"store": "m.zarr", "model": "pixloc-lite0"}, layer, where="job.json")


def test_a_damaged_training_config_is_refused_naming_its_file(tmp_path):
    """Text that is not YAML or not UTF-8, or YAML that is not a mapping: an error naming the file
    (and line), not yaml's ParserError or a UnicodeDecodeError."""
    for text, said in (("steps: [1, 2\n", r":\d+: training config is not valid YAML"),
                       (b"steps: 1\n\xff\n", "training config is not UTF-8"),
                       ("- 1\n- 2\n", "training config should hold a YAML mapping, not a list")):
        path = tmp_path / "bad.yaml"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(ValueError, match=f"^{path}{said}" if said.startswith(":") else f"^{path}: {said}"):
            load_config(str(path))
