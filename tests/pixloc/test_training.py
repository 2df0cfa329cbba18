import pytest
import torch

from pipeline.scene import CameraRecord
from pipeline.training_data import PairConfig, PairDataset, synthetic_scene
from pixloc.nets.registry import load_refiner
from pixloc.training import TrainConfig, Trainer

CAMERA = CameraRecord("PINHOLE", 160, 128, (125.0, 125.0, 80.0, 64.0))


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    scene = synthetic_scene(tmp_path_factory.mktemp("syn"), 4, CAMERA, num_references=12, queries_per_condition=2)
    return PairDataset([("syn", scene)], PairConfig(max_size=160, num_points=128)).fixed(3, seed=1)


def fresh_trainer(lr=1e-3):
    torch.manual_seed(0)
    return Trainer(load_refiner("lite0-imagenet"), TrainConfig(lr=lr, num_iters=5))


def test_loss_falls_on_a_tiny_synthetic_set(pairs):
    trainer = fresh_trainer(lr=3e-4)
    first = [trainer.step(p)["total"] for p in pairs]
    for _ in range(9):
        for p in pairs:
            trainer.step(p)
    last = [trainer.step(p)["total"] for p in pairs]
    assert sum(last) < 0.8 * sum(first), (first, last)


def test_resume_reaches_the_same_state(pairs, tmp_path):
    a = fresh_trainer()
    for p in pairs[:2]:
        a.step(p)
    torch.save(a.state_dict(), tmp_path / "ckpt.pt")
    a.step(pairs[2])
    b = fresh_trainer()
    b.load_state_dict(torch.load(tmp_path / "ckpt.pt", weights_only=True))
    assert b.step_count == 2
    b.step(pairs[2])
    for (name, x), (_, y) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
        assert torch.equal(x, y), name


def test_damping_learns_at_100x():
    trainer = fresh_trainer(lr=1e-4)
    lrs = [g["lr"] for g in trainer.optimizer.param_groups]
    assert lrs == [pytest.approx(1e-4), pytest.approx(1e-2)]
    assert all(p.requires_grad for p in trainer.optimizer.param_groups[1]["params"])


def test_gradient_checkpointing_gives_the_same_gradients(pairs):
    grads = []
    for checkpointing in (False, True):
        trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(num_iters=3, grad_checkpointing=checkpointing))
        trainer.train_mode()
        losses = trainer.model.loss(trainer.model(pairs[0]), pairs[0])
        trainer.model.zero_grad()
        losses["total"].mean().backward()
        grads.append({n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 50
    for name, g in grads[0].items():
        assert torch.allclose(g, grads[1][name], rtol=1e-4, atol=1e-6), name
