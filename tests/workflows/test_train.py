import csv
import json
import math

import pytest
import torch
import yaml

from pixloc.nets.registry import load_refiner
from workflows.cli import main

CONFIG = {
    "model": "lite0-imagenet", "lr": 1e-3, "num_iters": 4, "max_size": 128, "num_points": 96,
    "val_every": 2, "val_pairs": 2, "checkpoint_every": 2,
    "lr_schedule": "cosine", "decay_steps": 4, "lr_min_factor": 0.1, "far_init_prob": 0.5,
    "synthetic_camera": ["PINHOLE", 128, 96, [100.0, 100.0, 64.0, 48.0]],
    "data": [{"kind": "synthetic", "seed": 11}],
    "validation": [{"kind": "synthetic", "seed": 12}],
}


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "tiny.yaml"
    path.write_text(yaml.safe_dump(CONFIG))
    return path


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_interrupted_training_resumes_to_the_same_state(config, tmp_path):
    """4 steps in one go, and 2 steps then a resume to 4: the same weights and the same metrics."""
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "a"), "--steps", "4"]) == 0
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "b"), "--steps", "2"]) == 0
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "b"), "--steps", "4"]) == 0
    ca, cb = (torch.load(tmp_path / k / "checkpoint.pt", weights_only=True)["trainer"] for k in "ab")
    assert ca["step"] == cb["step"] == 4
    for name, x in ca["model"].items():
        assert torch.equal(x, cb["model"][name]), name
    for x, y in zip(ca["optimizer"]["state"].values(), cb["optimizer"]["state"].values()):
        assert torch.equal(x["exp_avg"], y["exp_avg"])
    b = load_refiner(str(tmp_path / "b" / "model.pt"))
    ra, rb = rows(tmp_path / "a" / "metrics.csv"), rows(tmp_path / "b" / "metrics.csv")
    assert [r["step"] for r in rb] == ["1", "2", "3", "4"]
    assert [r["total"] for r in ra] == [r["total"] for r in rb]
    val = rows(tmp_path / "b" / "validation.csv")
    assert [r["step"] for r in val] == ["0", "2", "4"]
    lrs = [float(r["lr"]) for r in rb]
    assert lrs[0] == pytest.approx(1e-3)
    assert lrs[-1] == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5 * (1 + math.cos(0.75 * math.pi))))
    assert [float(r["lr"]) for r in ra] == lrs  # the resumed run followed the same schedule
    best = json.loads((tmp_path / "b" / "best.json").read_text())
    errors = [float(r["error_px_median"]) for r in val]
    assert best["step"] == int(val[errors.index(min(errors))]["step"])
    assert torch.load(tmp_path / "b" / "model_best.pt", weights_only=True)["info"]["steps"] == best["step"]
    assert (tmp_path / "b" / "curves.png").stat().st_size > 10_000
    trained = torch.load(tmp_path / "b" / "model.pt", weights_only=True)
    assert trained["info"]["steps"] == 4 and trained["info"]["data"] == ["synthetic-11"]
    untrained = load_refiner("lite0-imagenet")
    changed = [n for n, p in untrained.named_parameters() if not torch.allclose(p, b.state_dict()[n], atol=1e-3)]
    assert any(n.startswith("extractor.") for n in changed) and any(n.startswith("solvers.") for n in changed)


def test_missing_training_data_is_reported(tmp_path, capsys):
    cfg = dict(CONFIG, data=[{"kind": "colmap", "path": "nowhere/sparse"}], validation=[])
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["train", "--config", str(path), "--output", str(tmp_path / "o"), "--data-root",
                 str(tmp_path)]) == 2
    assert "No training data" in capsys.readouterr().err


def test_numbers_out_of_range_are_refused_before_the_data(tmp_path, capsys):
    """Before: steps -5 or lr 0 prepared the training data (minutes of SIFT on real sources) first."""
    for key, value, said in (("steps", -5, "steps -5 (at least 1)"), ("lr", 0, "lr 0 (positive)"),
                             ("workers", -1, "workers -1 (not negative)")):
        path = tmp_path / f"{key}.yaml"
        path.write_text(yaml.safe_dump(dict(CONFIG, **{key: value})))
        assert main(["train", "--config", str(path), "--output", str(tmp_path / key)]) == 2
        assert f"pixloc: error: training config {path}: {said}." in capsys.readouterr().err
        assert not (tmp_path / key).exists()


def test_worker_processes_load_the_same_pairs(config, tmp_path):
    """Batches of 2 pairs read in 2 worker processes: the same steps as read in-process."""
    for workers in ("0", "2"):
        assert main(["train", "--config", str(config), "--output", str(tmp_path / workers), "--steps", "2",
                     "--batch-size", "2", "--workers", workers]) == 0
    a, b = rows(tmp_path / "0" / "metrics.csv"), rows(tmp_path / "2" / "metrics.csv")
    assert [r["total"] for r in a] == [r["total"] for r in b] and len(a) == 2


def test_a_second_run_into_the_same_folder_is_refused(config, tmp_path, capsys):
    """Before: two runs at once into one --output wrote over each other's checkpoint, and one died with
    '[Errno 2] No such file or directory: .../checkpoint.tmp -> .../checkpoint.pt'."""
    import os
    import socket
    out = tmp_path / "o"
    out.mkdir()
    (out / ".pixloc.lock").write_text(f"{socket.gethostname()} {os.getppid()}")  # a live run holds it
    assert main(["train", "--config", str(config), "--output", str(out), "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert f"pixloc: error: {out} is in use by another pixloc run" in err and not (out / "checkpoint.pt").exists()
    (out / ".pixloc.lock").write_text(f"{socket.gethostname()} 999999999")  # a killed run's: taken over
    assert main(["train", "--config", str(config), "--output", str(out), "--steps", "1"]) == 0
    assert not (out / ".pixloc.lock").exists()


def test_training_on_cuda_without_a_gpu_is_refused(config, tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("a GPU is available")
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "o"), "--device", "cuda"]) == 2
    assert "no CUDA device" in capsys.readouterr().err


@pytest.mark.gpu
def test_pixloc_train_on_the_gpu(config, tmp_path, device):
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "g"), "--steps", "4",
                 "--device", "cuda", "--amp", "--batch-size", "2", "--workers", "2"]) == 0
    assert "cuda" in torch.load(tmp_path / "g" / "model.pt", weights_only=True)["info"]["hardware"]
    assert [r["step"] for r in rows(tmp_path / "g" / "validation.csv")] == ["0", "2", "4"]


def test_contact_sheet_shows_pairs_of_every_source(config, tmp_path):
    import cv2
    assert main(["train", "--config", str(config), "--output", str(tmp_path / "s"), "--contact-sheet"]) == 0
    sheet = cv2.imread(str(tmp_path / "s" / "contact_sheet.jpg"))[..., ::-1]
    # 2 sources (training, validation) x 2 pairs, two pairs (4 tiles of 128 px) per row
    assert sheet.shape == (2 * 128, 4 * 128, 3)
    green = (sheet[..., 1] > 150) & (sheet[..., 0] < 90) & (sheet[..., 2] < 90)
    red = (sheet[..., 0] > 170) & (sheet[..., 1] < 90) & (sheet[..., 2] < 90)
    assert green.sum() > 50 and red.sum() > 20  # points at the truth, and at the initial pose
    assert not (tmp_path / "s" / "checkpoint.pt").exists()  # nothing trained


def test_photos_train_as_self_supervised_pairs(tmp_path, caplog):
    import cv2
    import numpy as np
    rng = np.random.default_rng(0)
    (tmp_path / "data" / "pics").mkdir(parents=True)
    for k in range(2):  # textured photos: smoothed noise
        image = cv2.GaussianBlur(rng.uniform(0, 255, (96, 128, 3)).astype(np.uint8), (0, 0), 2)
        cv2.imwrite(str(tmp_path / "data" / "pics" / f"p{k}.jpg"), image)
    (tmp_path / "data" / "pics" / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not a jpeg")  # left out, named
    config = dict(CONFIG, steps=2, val_every=2, checkpoint_every=2,
                  data=[{"kind": "photos", "paths": ["pics/*.jpg"], "exclude": ["pics/p1.jpg"]},
                        {"kind": "photos", "name": "nothing", "paths": ["none/*.jpg"]}],
                  validation=[{"kind": "photos", "name": "held", "paths": ["pics/p1.jpg"]}])
    path = tmp_path / "photos.yaml"
    path.write_text(yaml.safe_dump(config))
    out = tmp_path / "run"
    assert main(["train", "--config", str(path), "--output", str(out), "--data-root", str(tmp_path / "data")]) == 0
    assert [r["source"] for r in rows(out / "metrics.csv")] == ["photos", "photos"]
    val = rows(out / "validation.csv")
    assert len(val) == 2 and float(val[0]["error_px_init_median"]) > 0.5
    assert torch.load(out / "model.pt", weights_only=False)["info"]["skipped_data"] == ["nothing"]
    assert "photos left out" in caplog.text and "broken.jpg" in caplog.text
