import pickle

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pixloc.nets import CheckpointError, load_official_checkpoint


def test_loads_strictly_with_its_damping(oracle, official_checkpoint):
    model = load_official_checkpoint(official_checkpoint)
    assert not model.training
    for k in range(5):
        d = np.load(oracle / f"lm_case_{k}.npz")
        lam = model.solvers[int(d["level"])].damping().detach().numpy()
        np.testing.assert_allclose(lam, d["damping_lambda"], rtol=1e-6)
    assert [s.num_iters for s in model.solvers] == [15, 15, 15]
    assert [s.interpolator.pad for s in model.solvers] == [2, 2, 2]
    assert model.extractor.strides == (1, 4, 16)


class Evil:
    def __reduce__(self):
        return (print, ("this would run arbitrary code",))


def test_refuses_arbitrary_code(tmp_path):
    path = tmp_path / "evil.tar"
    torch.save({"model": {}, "conf": {}, "payload": Evil()}, path)
    with pytest.raises(CheckpointError, match="arbitrary pickled code"):
        load_official_checkpoint(path)


def test_refuses_corrupt_and_foreign_files(tmp_path, official_checkpoint):
    corrupt = tmp_path / "corrupt.tar"
    corrupt.write_bytes(official_checkpoint.read_bytes()[:5000])
    with pytest.raises(CheckpointError, match="corrupt or not a PyTorch checkpoint"):
        load_official_checkpoint(corrupt)
    plain = tmp_path / "plain.pkl"
    plain.write_bytes(pickle.dumps({"a": 1}, protocol=2))
    with pytest.raises(CheckpointError):
        load_official_checkpoint(plain)
    foreign = tmp_path / "foreign.pth"
    torch.save({"state_dict": {"w": torch.zeros(1)}}, foreign)
    with pytest.raises(CheckpointError, match="expected the keys 'model' and 'conf'"):
        load_official_checkpoint(foreign)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_official_checkpoint(tmp_path / "missing.tar")


def test_refuses_a_state_dict_that_does_not_match_its_conf(tmp_path, official_checkpoint):
    ckpt = torch.load(official_checkpoint, weights_only=False)  # trusted fixture
    ckpt["conf"]["model"]["extractor"]["encoder"] = "vgg16"
    path = tmp_path / "mismatch.tar"
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="does not match its configuration"):
        load_official_checkpoint(path)
    ckpt["conf"]["model"]["extractor"]["encoder"] = "resnet50"
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="Unsupported extractor"):
        load_official_checkpoint(path)


SHIPPED = None


def _shipped_refiner():
    global SHIPPED_REFINER
    if SHIPPED_REFINER is None:
        from pixloc.nets.registry import DEFAULT_MODEL, load_refiner
        SHIPPED_REFINER = load_refiner(DEFAULT_MODEL)
    return SHIPPED_REFINER


SHIPPED_REFINER = None


def _shipped_bytes() -> bytes:
    global SHIPPED
    if SHIPPED is None:
        from pixloc.nets.registry import DEFAULT_MODEL, shipped_model_path
        SHIPPED = shipped_model_path(DEFAULT_MODEL).read_bytes()
    return SHIPPED


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.one_of(st.none(), st.floats(0, 0.999)),
       flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), min_size=0, max_size=8))
def test_a_damaged_model_file_is_refused(tmp_path, cut, flips):
    """Random truncation or byte flips of the shipped model's file: refused, naming the file, or
    loaded as the very same weights, never as other weights (torch.load does not check the zip format's
    CRC-32s; before the check, 33 of 40 flipped files loaded, one with non-finite weights)."""
    from pixloc.nets.registry import load_refiner
    raw = bytearray(_shipped_bytes())
    for at, xor in flips:
        raw[int(at * (len(raw) - 1))] ^= xor
    if cut is not None:
        raw = raw[:int(cut * len(raw))]
    path = tmp_path / f"m{abs(hash((cut, tuple(flips))))}.pt"
    path.write_bytes(bytes(raw))
    if bytes(raw) == _shipped_bytes():  # flips that undo each other
        load_refiner(str(path))
        return
    try:
        loaded = load_refiner(str(path))
    except CheckpointError as e:
        assert str(path) in str(e)
        return
    # loaded: the damage hit bytes that no weight is read from (the zip's alignment padding between
    # records, which no CRC covers; found by this test on 2026-12-07): the weights are the shipped ones
    shipped = _shipped_refiner().state_dict()
    assert all(torch.equal(v, shipped[k]) for k, v in loaded.state_dict().items())


def test_a_model_with_non_finite_weights_is_refused(tmp_path):
    from pixloc.nets.registry import DEFAULT_MODEL, load_refiner, save_model
    refiner = load_refiner(DEFAULT_MODEL)
    with torch.no_grad():
        next(refiner.extractor.parameters()).view(-1)[7] = float("nan")
    path = save_model(refiner, "lite0", tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match="not finite numbers"):
        load_refiner(str(path))
