"""One model per process: map building and localization share the loaded refiner (before: the
network was loaded twice, once as a whole refiner whose solvers were thrown away)."""

from pipeline.models import localization_model, network
from pixloc.nets.registry import available_models


def test_building_and_localization_share_one_model():
    refiner, digest = localization_model("photometric")
    net, net_digest = network("photometric")
    assert net is refiner.extractor and net_digest == digest == refiner.feature_digest()
    assert not refiner.training and localization_model("photometric")[0] is refiner


def test_every_named_model_is_listed_once():
    assert list(available_models()) == ["pixloc-lite0", "lite0-imagenet", "photometric"]
