"""A misspelt key of a dataset preset or a training config is refused with the nearest valid
name, instead of passing unnoticed while its setting keeps the default."""

import pytest

from workflows import presets
from workflows.train import load_config, train


def test_every_packaged_preset_and_training_config_loads():
    for name in presets.available():
        presets.load(name)
    for path in (presets.resources.files(presets.__package__) / "training").iterdir():
        if path.name.endswith(".yaml"):
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
