import numpy as np
import pytest
import torch

from pixloc.nets import lite0_unet, load_official_checkpoint


@pytest.fixture(scope="module")
def official(official_checkpoint):
    return load_official_checkpoint(official_checkpoint)


@pytest.mark.parametrize("name", ["a", "b"])
def test_official_unet_outputs(official, oracle, name, device):
    d = np.load(oracle / "unet_forward.npz")
    net = official.extractor.to(device)
    with torch.no_grad():
        out = net(torch.from_numpy(d[f"{name}/image"])[None].to(device))
    for level in range(3):
        np.testing.assert_allclose(out["features"][level][0].cpu().numpy(), d[f"{name}/features_{level}"],
                                   atol=1e-4, rtol=0)
        np.testing.assert_allclose(out["confidences"][level][0, 0].cpu().numpy(),
                                   d[f"{name}/confidences_{level}"], atol=1e-4, rtol=0)


def test_lite0_unet_levels():
    torch.manual_seed(1)
    net = lite0_unet().eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 130, 200))
    # Official layout: strides 1, 4, 16 with 32, 128, 128 channels, cropped to multiples of 16.
    assert [tuple(f.shape) for f in out["features"]] == [(2, 32, 128, 192), (2, 128, 32, 48), (2, 128, 8, 12)]
    assert [tuple(c.shape) for c in out["confidences"]] == [(2, 1, 128, 192), (2, 1, 32, 48), (2, 1, 8, 12)]
    # a sigmoid: in (0, 1), though float32 rounds the random decoder's largest logits to 1.0
    assert all(((c >= 0) & (c <= 1)).all() for c in out["confidences"])
    assert all(((c > 0) & (c < 1)).float().mean() > 0.9 for c in out["confidences"])
    assert net.strides == (1, 4, 16)
    assert sum(p.numel() for p in net.parameters()) < 2_000_000


def test_lite0_encoder_is_imagenet_initialised():
    a, b = lite0_unet(pretrained=True), lite0_unet(pretrained=False)
    wa, wb = a.encoder[1][0][0].weight, b.encoder[1][0][0].weight
    assert not torch.equal(wa, wb)
    assert lite0_unet(pretrained=True).encoder[1][0][0].weight.equal(wa)  # deterministic, from disk


def test_bad_images_are_named():
    net = lite0_unet(pretrained=False)
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        net(torch.rand(3, 64, 64))
    with pytest.raises(ValueError, match="at least 16 px"):
        net(torch.rand(1, 3, 8, 64))


@pytest.mark.parametrize("encoder,skips", [("vgg16", [64, 128, 256, 512, 512]), ("vgg19", [64, 128, 256, 512, 512])])
def test_vgg_unet_has_the_official_layout(encoder, skips):
    from pixloc.nets.unet import vgg_blocks, vgg_unet
    _, skip_dims = vgg_blocks(encoder)
    assert skip_dims == skips
    keys = set(vgg_unet(encoder).state_dict())
    last_conv = 5 if encoder == "vgg16" else 7  # torchvision indices inside the last block
    assert f"encoder.4.{last_conv}.weight" in keys and f"encoder.4.{last_conv + 2}.weight" not in keys
    assert {"adaptation.2.0.weight", "uncertainty.0.0.bias", "decoder.3.layers.1.running_var"} <= keys


def _prepared_matches(net, image, atol):
    from pixloc.nets.unet import prepare_for_inference
    with torch.no_grad():
        before = net(image)
        prepared = prepare_for_inference(net)
        after = prepared(image)
    assert prepared is net and not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    for key in ("features", "confidences"):
        for a, b in zip(after[key], before[key]):
            assert a.is_contiguous(memory_format=torch.channels_last)
            torch.testing.assert_close(a, b, atol=atol, rtol=0)


def test_the_shipped_network_prepared_for_inference_gives_the_same_maps():
    # BatchNorm folded into its convs, channels-last activations and 1x1 convs through oneDNN:
    # the same features and confidences to float rounding, for the shipped model on a random image
    from pipeline.images import to_tensor
    from pixloc.nets.registry import load_refiner
    rgb = np.asarray(np.random.default_rng(0).integers(0, 256, (200, 300, 3)), np.uint8)
    _prepared_matches(load_refiner("pixloc-lite0").extractor.eval(), to_tensor(rgb)[None], atol=1e-4)


def test_an_official_network_prepared_for_inference_matches_the_oracle(official, oracle):
    import copy
    d = np.load(oracle / "unet_forward.npz")
    _prepared_matches(copy.deepcopy(official.extractor).eval(), torch.from_numpy(d["a/image"])[None], atol=1e-4)


def test_the_pipeline_loads_the_prepared_network_with_the_weights_digest():
    from pipeline.models import localization_model
    from pixloc.nets.registry import load_refiner
    refiner, digest = localization_model("pixloc-lite0")
    assert digest == load_refiner("pixloc-lite0").feature_digest()  # stores built before still match
    assert refiner.extractor.memory_format == torch.channels_last


def test_the_finest_blocks_in_bfloat16_leave_the_coarser_levels_exact():
    # --network-precision bfloat16-fine: the two decoder blocks that only the finest level reads run in
    # bfloat16; the coarser levels are the float32 pass's bit for bit, the finest level float32 and close
    from pipeline.images import to_tensor
    from pixloc.nets.registry import load_refiner
    from pixloc.nets.unet import prepare_for_inference
    net = prepare_for_inference(load_refiner("pixloc-lite0").extractor.eval())
    assert net.fine_blocks == 2  # the blocks at strides 2 and 1
    rgb = np.asarray(np.random.default_rng(0).integers(0, 256, (200, 300, 3)), np.uint8)
    with torch.no_grad():
        exact, fine = net(to_tensor(rgb)[None]), net(to_tensor(rgb)[None], fine_dtype=torch.bfloat16)
    for key in ("features", "confidences"):
        for level, (a, b) in enumerate(zip(exact[key], fine[key])):
            assert b.dtype == torch.float32 and b.is_contiguous(memory_format=torch.channels_last)
            if level > 0:
                assert torch.equal(a, b), (key, level)
    a, b = (torch.nn.functional.normalize(x[0][0], dim=0) for x in (exact["features"], fine["features"]))
    cosine = (a * b).sum(0)
    assert float(cosine.min()) > 0.9995 and float(cosine.mean()) > 0.99995  # what the LM compares (0.99998, 0.999995)
    assert not torch.equal(exact["features"][0], fine["features"][0])  # it did run in bfloat16
    torch.testing.assert_close(fine["confidences"][0], exact["confidences"][0], atol=0.01, rtol=0)


def test_every_precision_returns_float32_maps_and_a_network_without_finest_blocks_runs_exact():
    from pixloc.nets.photometric import PhotometricExtractor
    from pixloc.nets.registry import load_refiner
    from pixloc.nets.unet import NETWORK_PRECISIONS, predict_in_precision
    image = torch.rand(1, 3, 64, 96)
    net = load_refiner("pixloc-lite0").extractor.eval()
    with torch.no_grad():
        exact = predict_in_precision(net, image)
        for precision in NETWORK_PRECISIONS:
            maps = predict_in_precision(net, image, precision)
            assert all(x.dtype == torch.float32 for v in maps.values() for x in v), precision
            coarse_exact = all(torch.equal(a, b) for a, b in zip(exact["features"][1:], maps["features"][1:]))
            assert coarse_exact == (precision != "bfloat16"), precision  # whole-pass bfloat16 changes them too
        photometric = PhotometricExtractor()
        assert torch.equal(predict_in_precision(photometric, image, "bfloat16-fine")["features"][0], image)
    with pytest.raises(ValueError, match="precision must be one of"):
        predict_in_precision(net, image, "float16")


def test_the_prepared_network_runs_in_every_precision_on_any_cpu():
    # its 1x1 convs go through oneDNN (PointwiseConv), whose bfloat16 path needs AVX-512 (or AVX-NE-CONVERT):
    # on other CPUs a whole-network bfloat16 pass failed every query ("bf16 path needs the cpu support ...")
    import copy
    from pixloc.nets.registry import load_refiner
    from pixloc.nets.unet import NETWORK_PRECISIONS, prepare_for_inference, predict_in_precision
    image = torch.rand(1, 3, 64, 96)
    net = prepare_for_inference(copy.deepcopy(load_refiner("pixloc-lite0").extractor).eval())
    with torch.no_grad():
        exact = predict_in_precision(net, image)
        for precision in NETWORK_PRECISIONS:
            maps = predict_in_precision(net, image, precision)
            for a, b in zip(exact["features"], maps["features"]):
                assert b.dtype == torch.float32, precision
                a, b = (torch.nn.functional.normalize(x[0], dim=0) for x in (a, b))
                cosine = (a * b).sum(0)
                assert float(cosine.mean()) > 0.99, precision  # reduced precision, the same maps nearly


@pytest.mark.parametrize("network", ["lite0", "lite0 prepared", "vgg16"])
@pytest.mark.parametrize("fine_dtype", [None, torch.bfloat16])
def test_the_deferred_finest_level_decodes_whole_or_in_tiles_to_the_same_maps(network, fine_dtype):
    # UNet.forward(defer_finest=True) stops before the fine blocks; FinestMaps decodes the finest
    # level whole (bit for bit the pass's) or in TILE x TILE tiles with their context (the same to float
    # rounding), at the map's edges too (zero padding); coarser levels unchanged
    from pixloc.nets.registry import load_refiner
    from pixloc.nets.unet import TILE, prepare_for_inference, vgg_unet
    torch.manual_seed(0)
    net = (vgg_unet("vgg16") if network == "vgg16" else load_refiner("pixloc-lite0").extractor).eval()
    if network.endswith("prepared"):
        prepare_for_inference(net)
    image = torch.rand(1, 3, 75, 122, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        exact = net(image, fine_dtype=fine_dtype)
        deferred = net(image, fine_dtype=fine_dtype, defer_finest=True)
        finest = deferred["finest"]
        assert deferred["features"][0] is None and deferred["confidences"][0] is None
        for key in ("features", "confidences"):
            assert all(torch.equal(a, b) for a, b in zip(exact[key][1:], deferred[key][1:]))
        features, confidences = finest.full()
        assert torch.equal(features, exact["features"][0]) and torch.equal(confidences, exact["confidences"][0])
        H, W = features.shape[-2:]
        assert finest.shape == tuple(features.shape)
        gy, gx = finest.grid
        ty, tx = (t.reshape(-1) for t in torch.meshgrid(torch.arange(gy), torch.arange(gx), indexing="ij"))
        order = torch.randperm(len(ty), generator=torch.Generator().manual_seed(1))  # any order, any subset
        f, c = finest.tiles(ty[order], tx[order])
        for maps, whole in ((f, features), (c, confidences)):
            tiled = torch.empty_like(maps)
            tiled[order] = maps
            tiled = tiled.reshape(gy, gx, -1, TILE, TILE).permute(2, 0, 3, 1, 4).reshape(-1, gy * TILE, gx * TILE)
            torch.testing.assert_close(tiled[:, :H, :W], whole[0], atol=1e-5, rtol=0)


def test_a_few_finest_tiles_decode_only_the_tiles_of_the_maps_before_them_that_they_read():
    # the deferred block at stride 2 is decoded in tiles too, where a finest tile reads it: a few finest
    # tiles decode a few of them, and read no cell left undecoded (NaN in the tests: FinestMaps.poison)
    from pixloc.nets.registry import load_refiner
    from pixloc.nets.unet import TILE, FinestMaps, prepare_for_inference
    assert FinestMaps.poison
    net = prepare_for_inference(load_refiner("pixloc-lite0").extractor.eval())
    image = torch.rand(1, 3, 130, 203, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        deferred = net(image, defer_finest=True)
        finest = deferred["finest"]
        features, confidences = finest.full()
        gy, gx = finest.grid
        assert len(finest.stages) == 1 and finest.stages[0] is None
        for ty, tx in (([0, 0], [0, 1]), ([gy - 1], [gx - 1]), ([gy // 2, gy // 2 + 1], [gx // 2, gx // 2])):
            ty, tx = torch.tensor(ty), torch.tensor(tx)
            f, c = finest.tiles(ty, tx)
            for t, (y, x) in enumerate(zip(ty.tolist(), tx.tolist())):
                h, w = min(TILE, features.shape[-2] - y * TILE), min(TILE, features.shape[-1] - x * TILE)
                at = (slice(None), slice(y * TILE, y * TILE + h), slice(x * TILE, x * TILE + w))
                torch.testing.assert_close(f[t, :, :h, :w], features[0][at], atol=1e-5, rtol=0)
                torch.testing.assert_close(c[t, :, :h, :w], confidences[0][at], atol=1e-5, rtol=0)
        maps, done = finest.stages[0]
        assert 0 < int(done.sum()) <= 4 * 5 < done.numel() // 4  # at most 2 x 2 for each of the 5 finest tiles
        assert bool(torch.isnan(maps).any())  # the rest is left undecoded


def test_the_finest_level_is_computed_where_it_cannot_be_deferred():
    # in training (gradients on) and in a network whose finest level has no block of its own
    torch.manual_seed(0)
    net = lite0_unet().eval()
    assert net.can_defer_finest
    out = net(torch.rand(1, 3, 64, 96), defer_finest=True)
    assert "finest" not in out and out["features"][0].requires_grad
    coarse_only = lite0_unet(output_scales=(2, 4), output_dims=(128, 128)).eval()
    assert not coarse_only.can_defer_finest
    with torch.no_grad():
        out = coarse_only(torch.rand(1, 3, 64, 96), defer_finest=True)
    assert "finest" not in out and all(x is not None for x in out["features"])
