import pytest
import torch

from pipeline.scene import CameraRecord
from pipeline.data.training_data import PairConfig, PairDataset, synthetic_scene
from pixloc.nets.registry import load_refiner
from pixloc.training import TrainConfig, Trainer, reprojection_px

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
    for _ in range(4):  # the loss levels off at about 0.42 x the first after 5 passes over the pairs
        for p in pairs:
            trainer.step(p)
    last = [trainer.step(p)["total"] for p in pairs]
    assert sum(last) < 0.7 * sum(first), (first, last)


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


def test_damping_can_be_kept_while_the_features_learn(pairs):
    torch.manual_seed(0)
    trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(lr=1e-3, num_iters=3, damping_lr_scale=0.0))
    before = {n: p.detach().clone() for n, p in trainer.model.named_parameters()}
    trainer.step(pairs[0])
    after = dict(trainer.model.named_parameters())
    damping = [n for n in before if n.startswith("solvers.")]
    assert damping and all(torch.equal(before[n], after[n]) for n in damping)
    assert any(not torch.equal(before[n], after[n]) for n in before if not n.startswith("solvers."))


def test_the_weight_average_follows_the_steps_and_resumes(pairs, tmp_path):
    torch.manual_seed(0)
    init = load_refiner("lite0-imagenet")
    start = {n: p.detach().clone() for n, p in init.named_parameters()}
    conf = TrainConfig(lr=1e-3, num_iters=3, ema=0.5)
    a = Trainer(init, conf)
    a.step(pairs[0])
    a.step(pairs[1])
    trained = {n: p.detach().clone() for n, p in a.model.named_parameters()}
    name = next(n for n in trained if not torch.equal(trained[n], start[n]))  # a weight the steps moved
    with a.averaged() as model:  # two steps at 0.5 from the initial weights: between them and the trained ones
        avg = dict(model.named_parameters())[name].detach().clone()
    assert not torch.equal(avg, trained[name]) and not torch.equal(avg, start[name])
    d_avg, d_start = (avg - trained[name]).norm(), (start[name] - trained[name]).norm()
    assert 0 < d_avg < d_start
    for n, p in a.model.named_parameters():  # the trained weights are back after the block
        assert torch.equal(p, trained[n]), n
    torch.save(a.state_dict(), tmp_path / "ckpt.pt")
    torch.manual_seed(1)
    b = Trainer(load_refiner("lite0-imagenet"), conf)
    b.load_state_dict(torch.load(tmp_path / "ckpt.pt", weights_only=True))
    for n in a.ema:
        assert torch.equal(a.ema[n], b.ema[n]), n
    with pytest.raises(ValueError, match="no weight average"):
        Trainer(load_refiner("lite0-imagenet"), conf).load_state_dict(fresh_trainer().state_dict())


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


def test_cosine_schedule_decays_from_lr_to_the_floor():
    conf = TrainConfig(lr=1e-4, lr_schedule="cosine", total_steps=100, decay_start=20, lr_min_factor=0.1)
    factors = [conf.lr_factor(s) for s in range(0, 121, 10)]
    assert factors[:3] == [1.0, 1.0, 1.0]
    assert factors[6] == pytest.approx(0.55)  # half-way through the decay: half-way down
    assert factors[-3:] == [pytest.approx(0.1)] * 3
    assert all(a >= b for a, b in zip(factors, factors[1:]))
    with pytest.raises(ValueError, match="lr_schedule"):
        TrainConfig(lr_schedule="linear").lr_factor(0)


def test_the_schedule_sets_both_learning_rates(pairs):
    trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(lr=1e-4, num_iters=2, lr_schedule="cosine",
                                                                  total_steps=2, lr_min_factor=0.5))
    trainer.step_count = 1  # the last step of two: half-way down the cosine
    metrics = trainer.step(pairs[0])
    assert metrics["lr"] == pytest.approx(0.75e-4)
    assert [g["lr"] for g in trainer.optimizer.param_groups] == [pytest.approx(0.75e-4), pytest.approx(0.75e-2)]


def test_a_stacked_batch_is_the_mean_of_its_pairs(pairs):
    """Two pairs in one step: stacked when their sizes agree, and the same loss and gradient as
    the pairs accumulated one by one."""
    grads, metrics = [], []
    for stack in (True, False):
        trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(num_iters=3))
        if not stack:  # different shape keys: one forward per pair
            trainer_pairs = pairs[:2]
            trainer.optimizer.step = lambda: None
            keys = iter([("a",), ("b",)])
            for p in trainer_pairs:
                p.shape_key = (lambda k: (lambda: k))(next(keys))
        else:
            trainer.optimizer.step = lambda: None
        metrics.append(trainer.step(list(pairs[:2])))
        grads.append(torch.cat([p.grad.flatten() for p in trainer.model.parameters() if p.grad is not None]))
        for p in pairs[:2]:
            p.__dict__.pop("shape_key", None)
    assert metrics[0]["total"] == pytest.approx(metrics[1]["total"], rel=1e-4)
    assert metrics[0]["error_px"] == pytest.approx(metrics[1]["error_px"], rel=1e-4)
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-6)


@pytest.mark.gpu
def test_training_steps_on_the_gpu_in_mixed_precision(pairs, device):
    trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(lr=3e-4, num_iters=5, device=str(device), amp=True))
    assert next(trainer.model.parameters()).device.type == "cuda"
    first = [trainer.step(list(pairs))["total"]]
    for _ in range(9):
        trainer.step(list(pairs))
    last = trainer.step(list(pairs))
    assert last["total"] < 0.8 * first[0] and last["grad_norm"] > 0


def test_a_frozen_encoder_stays_put_then_trains_at_its_own_rate(pairs):
    torch.manual_seed(0)
    trainer = Trainer(load_refiner("lite0-imagenet"),
                      TrainConfig(lr=1e-3, num_iters=5, freeze_encoder_steps=2, encoder_lr_scale=0.25))
    encoder = {n: p.detach().clone() for n, p in trainer.model.named_parameters() if n.startswith("extractor.encoder.")}
    decoder = {n: p.detach().clone() for n, p in trainer.model.named_parameters() if n.startswith("extractor.decoder.")}
    now = lambda names: {n: p for n, p in trainer.model.named_parameters() if n in names}
    for p in pairs[:2]:
        trainer.step(p)
    assert all(torch.equal(v, encoder[n]) for n, v in now(encoder).items())
    assert any(not torch.equal(v, decoder[n]) for n, v in now(decoder).items())
    trainer.step(pairs[2])
    assert any(not torch.equal(v, encoder[n]) for n, v in now(encoder).items())
    assert [g["lr"] for g in trainer.optimizer.param_groups] == pytest.approx([1e-3, 1e-1, 2.5e-4])


def test_channels_last_training_steps_like_the_default_layout(pairs):
    losses = []
    for channels_last in (False, True):
        torch.manual_seed(0)
        trainer = Trainer(load_refiner("lite0-imagenet"), TrainConfig(lr=1e-3, num_iters=5),
                          channels_last=channels_last)
        losses.append([trainer.step(p)["total"] for p in pairs])
        conv = next(m for m in trainer.model.extractor.modules() if isinstance(m, torch.nn.Conv2d))
        assert conv.weight.is_contiguous(memory_format=torch.channels_last) == channels_last
    assert losses[1] == pytest.approx(losses[0], rel=1e-3)


def test_a_point_outside_a_radial_cameras_valid_radius_leaves_the_pair_finite():
    # opensfm_berlin's camera (k2 < 0): a point far off the axis distorts to inf; it is masked out
    # and must not make the pair's error NaN (27 training steps were lost to it)
    from pixloc.geometry import Camera, Pose
    from pixloc.refiner import PairBatch, masked_mean
    assert masked_mean(torch.tensor([[1.0, float("nan"), float("inf"), 3.0]]),
                       torch.tensor([[True, False, False, True]]), -1).item() == 2.0
    cam = Camera.from_colmap("RADIAL", 320, 240, [278.0, 160.0, 120.0, 0.0885, -0.2324]).reshape(1)
    p3d = torch.tensor([[[0.0, 0.0, 5.0], [0.2, 0.1, 4.0], [-0.3, 0.2, 6.0], [1e9, 1e9, 1.0]]])
    gt = Pose.from_Rt(torch.eye(3), torch.zeros(3)).reshape(1)
    init = Pose.from_Rt(torch.eye(3), torch.tensor([0.05, 0.0, 0.0])).reshape(1)
    image = torch.zeros(1, 3, 240, 320)
    batch = PairBatch(image, image, cam, cam, p3d, init, gt, torch.ones(1, 4, dtype=torch.bool))
    error = reprojection_px(init, batch)
    assert torch.isfinite(error).all() and error.item() > 0
