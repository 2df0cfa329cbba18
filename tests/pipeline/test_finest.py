"""The finest level decoded where it is sampled (pipeline.localization.finest)."""

import pytest
import torch

from pipeline.localization.finest import WHOLE_ABOVE, FinestFill, write_level
from pixloc.geometry import Camera, Pose
from pixloc.interpolation import Interpolator
from pixloc.nets.registry import load_refiner
from pixloc.nets.unet import TILE, prepare_for_inference
from pixloc.optim import FeaturemetricProblem, linearize
from pixloc.optim.cost import new_query_maps
from pixloc.optim.evidence import alignment_evidence
from pixloc.losses import get_loss


@pytest.fixture(scope="module")
def net():
    return prepare_for_inference(load_refiner("pixloc-lite0").extractor.eval())


def _passes(net):
    """Two queries' passes, whole and deferred (a query keeps what it decoded: each its own)."""
    images = torch.rand(2, 1, 3, 192, 256, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return [(net(x), net(x, defer_finest=True)) for x in images]


@pytest.fixture
def passes(net):
    return _passes(net)


def _problem(passes, deferred: bool, n=40):
    """Two queries' finest level as one batch, with n points each in front of an identity camera."""
    g = torch.Generator().manual_seed(1)
    full = torch.stack([exact["features"][0][0] for exact, _ in passes])
    maps = new_query_maps(full.shape, passes[0][1]["finest"].source)
    finest = {}
    for b, (exact, lazy) in enumerate(passes):
        if deferred:
            finest[b] = lazy["finest"]
        else:
            write_level(maps[b], exact["features"][0][0], exact["confidences"][0][0])
    H, W = full.shape[-2:]
    p2d = torch.rand(2, n, 2, generator=g) * torch.tensor([W * 0.4, H * 0.4]) + torch.tensor([W * 0.3, H * 0.3])
    depth = 1 + torch.rand(2, n, 1, generator=g)
    camera = Camera.stack([Camera.from_colmap("PINHOLE", W, H, [200.0, 200.0, W / 2, H / 2])] * 2)
    p3d = torch.cat([(p2d - camera.c[:, None]) / camera.f[:, None] * depth, depth], -1)
    F_ref = torch.nn.functional.normalize(torch.randn(2, n, full.shape[1], generator=g), dim=-1)
    return FeaturemetricProblem(p3d, F_ref, maps[:, :-1], camera, torch.rand(2, n, generator=g), maps[:, -1],
                                maps=maps, fill=FinestFill(maps, finest) if deferred else None)


def test_the_lm_and_evidence_read_the_same_values_from_tiles_decoded_where_they_sample(passes):
    eager, lazy = _problem(passes, False), _problem(passes, True)
    interpolator = Interpolator(gradient_maps=True)
    assert bool(torch.isnan(lazy.maps).all())  # nothing decoded yet: a read that bypassed the fill is NaN
    pose = Pose.from_aa(torch.tensor([[0.01, -0.02, 0.005]] * 2), torch.tensor([[0.02, 0.0, -0.01]] * 2))
    for a, b in ((linearize(pose, eager, interpolator), linearize(pose, lazy, interpolator)),):
        for x, y in zip(a, b):
            if x is not None:
                torch.testing.assert_close(y, x, atol=1e-5, rtol=1e-5)
    for sub in (slice(1, 2), 0):  # a sub-batch fills its own rows of the batch's maps
        ev_a = alignment_evidence(eager.index(sub), pose[sub if isinstance(sub, slice) else slice(0, 1)],
                                  get_loss("scaled_barron(0, 0.1)"), interpolator)
        ev_b = alignment_evidence(lazy.index(sub), pose[sub if isinstance(sub, slice) else slice(0, 1)],
                                  get_loss("scaled_barron(0, 0.1)"), interpolator)
        for key in ev_a:
            torch.testing.assert_close(ev_b[key], ev_a[key], atol=1e-6, rtol=1e-6)
    fill = lazy.fill
    for b in (0, 1):
        total = fill.done[b].numel()
        assert 0 < fill.decoded[b].tiles < WHOLE_ABOVE * total  # 40 points: a few tiles, not the map
        assert len(fill.decoded[b].data) <= 2 * fill.decoded[b].tiles  # and the query holds only those
        decoded = fill.done[b].repeat_interleave(TILE, 0).repeat_interleave(TILE, 1)
        assert bool(torch.isnan(lazy.maps[b][:, ~decoded]).all())
        assert not bool(torch.isnan(lazy.maps[b][:, decoded]).any())
        torch.testing.assert_close(lazy.maps[b][:, decoded], eager.maps[b][:, decoded], atol=1e-5, rtol=0)


def test_values_alone_decode_only_the_cells_they_read(passes):
    """Verification's costs read values only (x0 .. x0 + 1): their fill decodes the tiles of those cells,
    not of the LM's central differences (x0 - 1 .. x0 + 2), with the same evidence as the whole pass."""
    eager, values, taps = _problem(passes, False, n=400), _problem(passes, True, n=400), _problem(passes, True, n=400)
    interpolator, loss = Interpolator(gradient_maps=True), get_loss("scaled_barron(0, 0.1)")
    pose = Pose.from_aa(torch.tensor([[0.01, -0.02, 0.005]] * 2), torch.tensor([[0.02, 0.0, -0.01]] * 2))
    ev_a = alignment_evidence(eager, pose, loss, interpolator)
    ev_b = alignment_evidence(values, pose, loss, interpolator)
    for key in ev_a:  # a read of a cell not decoded would be NaN
        torch.testing.assert_close(ev_b[key], ev_a[key], atol=1e-6, rtol=1e-6)
    linearize(pose, taps, interpolator)
    for b in (0, 1):
        assert 0 < values.fill.done[b].sum() < taps.fill.done[b].sum()  # the tiles each batch's maps got
        assert not bool((values.fill.done[b] & ~taps.fill.done[b]).any())


def test_a_first_request_for_most_of_the_map_decodes_it_whole_and_rows_share_a_querys_tiles(net, passes):
    lazy, eager = _problem(passes, True, n=4000), _problem(passes, False, n=4000)
    again = _problem(passes, True, n=4000)  # another batch with the same queries (a rival's, a start's)
    again.maps_at(again.p3d_world[..., :2] / again.p3d_world[..., 2:] * 200 + again.camera.c[:, None])
    decoded = {b: again.fill.decoded[b].tiles for b in (0, 1)}
    assert 0 < decoded[0] < WHOLE_ABOVE * again.fill.done[0].numel()
    grid = torch.stack(torch.meshgrid(torch.arange(0, 256, 4.0), torch.arange(0, 192, 4.0), indexing="xy"), -1)
    lazy.maps_at(grid.reshape(1, -1, 2).expand(2, -1, -1) + 0.5)  # a point in every tile
    assert all(bool(done.all()) for done in lazy.fill.done.values())
    # the tiles decoded before are kept, the rest decoded as tiles: the pass's maps to float rounding
    assert [lazy.fill.decoded[b].tiles for b in (0, 1)] == [lazy.fill.done[b].numel() for b in (0, 1)]
    torch.testing.assert_close(lazy.maps, eager.maps, atol=1e-5, rtol=0)
    fresh = _problem(_passes(net), True, n=4000)
    fresh.maps_at(grid.reshape(1, -1, 2).expand(2, -1, -1) + 0.5)
    assert torch.equal(fresh.maps, eager.maps)  # a first request for most of it: the whole pass, bit for bit


def test_a_problem_decoded_on_demand_is_not_copied_by_a_list_index(passes):
    with pytest.raises(ValueError, match="decoded on demand"):
        _problem(passes, True).index([0, 1])
