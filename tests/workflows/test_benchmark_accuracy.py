"""``pixloc benchmark accuracy`` on a small part of its scenes: the table's rows and columns, every
figure a real outcome, and no wrong pose reported as a success (the whole run: docs/benchmarks.md)."""

import json

import pytest

from workflows.benchmarks.accuracy import RECALLS
from workflows.cli import main


@pytest.fixture(scope="module")
def run(shared, tmp_path_factory):
    work = tmp_path_factory.mktemp("accuracy")
    rc = main(["benchmark", "accuracy", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
               "templeRing", "--priors", "top1", "sift", "--limit", "1"])  # templeRing: 2 folds, a query each
    return rc, json.loads((work / "rows.json").read_text()), work


def test_the_table_has_a_row_per_scene_and_prior_and_the_pooled_rows(run):
    rc, rows, _ = run
    assert rc == 0
    priors = ("top1", "sift", "sift-pnp", "reference")
    assert [(r["scene"], r["prior"]) for r in rows] == [
        (scene, prior) for scene in ("kermit", "templeRing", "all") for prior in priors]
    for r in rows:
        assert r["queries"] == {"kermit": 1, "templeRing": 2, "all": 3}[r["scene"]]  # a query per fold
        assert all(r[k] is None or 0 <= r[k] <= 1 for k in RECALLS)
        assert (r["accepted"] is None) == (r["prior"] in ("sift-pnp", "reference"))
    # neither scene is metric (Bundler and Middlebury units): no figure in metres
    assert all(r[k] is None for r in rows for k in RECALLS[3:])
    scales = {r["scene"]: r["scale"] for r in rows if r["scene"] != "all"}
    assert all(s > 0 for s in scales.values())


def test_sift_places_both_queries_and_no_wrong_pose_is_accepted(run):
    _, rows, _ = run
    get = {(r["scene"], r["prior"]): r for r in rows}
    for scene in ("kermit", "templeRing"):
        assert get[scene, "sift"][RECALLS[1]] == 1.0 and get[scene, "sift-pnp"][RECALLS[1]] == 1.0
        assert get[scene, "sift"]["median_t_pct"] < 1.0 and get[scene, "sift"]["median_R"] < 1.0
        assert get[scene, "reference"]["start_t_pct"] > 5.0  # the top-1 reference is far: a real prior to refine
        assert get[scene, "sift"]["s_per_query"] > get[scene, "sift-pnp"]["s_per_query"] > 0
    assert all(r["wrong"] == [] for r in rows if r["wrong"] is not None)


def test_a_rerun_reads_the_runs_back(run, shared):
    _, rows, work = run
    before = {(r["scene"], r["prior"]): r["s_per_query"] for r in rows}
    main(["benchmark", "accuracy", "--shared", str(shared), "--work", str(work), "--scenes", "kermit", "templeRing",
          "--priors", "top1", "sift", "--limit", "1"])
    again = json.loads((work / "rows.json").read_text())
    assert {(r["scene"], r["prior"]): r["s_per_query"] for r in again} == before  # the same runs, not new ones


def test_a_work_folder_of_other_feature_settings_is_refused(run, shared, capsys):
    _, _, work = run
    with pytest.raises(SystemExit, match="--resize, --sift"):
        main(["benchmark", "accuracy", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
              "--resize", "640", "--limit", "1"])


def test_paired_counts_closer_farther_gained_and_lost():
    from workflows.benchmarks.accuracy import paired
    base = [{"scene": "s", "prior": "sift", "errors": {"a": [0.02, 0.5], "b": [0.002, 0.2], "c": None, "d": [0.5, 9]}}]
    mine = [{"scene": "s", "prior": "sift", "errors": {"a": [0.005, 0.5], "b": [0.03, 0.2], "c": [0.004, 0.1],
                                                       "d": [0.5, 9]}}]
    s, pooled = paired(mine, base)
    assert (s["queries"], s["closer"], s["farther"]) == (4, 2, 1) and pooled["scene"] == "all"
    assert s["1 %, 1 deg"] == (2, 1) and s["5 %, 2 deg"] == (1, 0) and s["10 %, 5 deg"] == (1, 0)
    assert s["sign_test_p"] == 1.0


def test_a_run_paired_with_itself_has_no_difference(run, shared, capsys):
    _, _, work = run
    main(["benchmark", "accuracy", "--shared", str(shared), "--work", str(work), "--scenes", "kermit", "templeRing",
          "--priors", "top1", "sift", "--limit", "1", "--paired", str(work)])
    out = capsys.readouterr().out
    assert "| all | sift | 3 | 0 | 0 | 1.000 | 0 / 0 | 0 / 0 | 0 / 0 |" in out


def test_the_retrieval_benchmark_on_the_same_maps(run, shared):
    """``pixloc benchmark retrieval`` reuses the accuracy benchmark's maps: per scene, condition and
    method, recall against the co-visibility oracle; the relit queries are darker copies, written once."""
    import numpy as np
    from pipeline.images import read_image

    _, _, work = run
    rc = main(["benchmark", "retrieval", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
               "templeRing", "--limit", "1", "--rank-references", "500"])
    assert rc == 0
    rows = json.loads((work / "retrieval-rows.json").read_text())
    get = {(r["scene"], r["condition"], r["method"]): r for r in rows}
    # maps of build-map's descriptor, gem-lw: the row that whitens gem descriptors has nothing to do
    assert {r["method"] for r in rows} == {"global", "bow", "fusion", "oracle"}
    for scene in ("kermit", "templeRing", "all"):
        for condition in ("as-taken", "relit"):
            oracle = get[scene, condition, "oracle"]
            assert oracle["queries"] == {"kermit": 1, "templeRing": 2, "all": 3}[scene] and oracle["no_right"] == 0
            assert oracle["r@1"] == 1.0 and (scene == "all" or oracle["top1_rank"] == 1)
            for method in ("global", "bow", "fusion"):
                r = get[scene, condition, method]
                assert r["r@1"] <= r["r@5"] <= r["r@10"] <= 1.0 and r["ms"] > 0
                assert scene == "all" or r["top1_rank"] >= 1
    assert get["all", "as-taken", "bow"]["r@5"] == 1.0  # measured: every query has a right reference in its top 5
    assert get["kermit", "as-taken", "global"]["bytes"] == 128 * 4  # a float32 GeM of 128 channels
    assert get["kermit", "as-taken", "bow"]["bytes"] > 128 * 4
    relit = sorted((work / "relit").rglob("*.jpg"))
    assert len(relit) == 3  # a relit copy per query, written once
    for p in relit:
        folder = shared / "data" / ("middlebury/templeRing" if "temple" in p.name else "bundler_kermit")
        original = read_image(folder / p.name[:-4]).astype(float)
        assert read_image(p).shape == original.shape and np.abs(read_image(p) - original).mean() > 10


def test_check_store_names_each_feature_groups_global_descriptor(run, capsys):
    """A store keeps the descriptor it was built with; check-store says which (build-map's default: gem-lw)."""
    _, _, work = run
    assert main(["check-store", str(work / "kermit-1of2.zarr")]) == 0
    out = capsys.readouterr().out
    assert "all chunks verified" in out
    assert "at 512 px, image scales [1], int8 + PCA 48; global descriptor gem-lw" in out


def test_localize_with_fusion_retrieval(run, shared):
    """``--retrieval fusion`` through the localization jobs (the accuracy benchmark's runs, kept apart from
    global's): the query starts from fusion's top references, the ones fusion ranks first."""
    from pipeline.localization.refine import Localizer, LocalizerConfig, QueryCache
    from pipeline.localization.retrieval import Fusion, retrieve
    from pipeline.localization.shard import describer, fit_query
    from pipeline.models import localization_model
    from pipeline.store.info import feature_config
    from pipeline.store.reader import MapReader
    from workflows.benchmarks.accuracy import SPLITS, split_parts

    _, _, work = run
    assert main(["benchmark", "accuracy", "--shared", str(shared), "--work", str(work), "--scenes", "kermit",
                 "--priors", "top1", "--limit", "1", "--retrieval", "fusion"]) == 0
    (record,) = [json.loads(line) for line in (work / "runs-fusion-limit1" / "kermit-1of2" / "top1" /
                                                "records.jsonl").read_text().splitlines()]
    assert record["prior"] is not None and len(record["references"]) == 3  # a start from the top-1, 3 used
    store = work / "kermit-1of2.zarr"
    conf = feature_config(store)
    ((_, _, queries),) = split_parts("kermit", SPLITS["kermit"], shared, work, conf, limit=1)
    reader = MapReader(store, conf)
    refiner, _ = localization_model(conf.model, "cpu")
    query, rgb = fit_query(queries[0])
    localizer = Localizer(refiner.extractor, refiner.solvers, reader, LocalizerConfig(), "cpu")
    ranked = retrieve(Fusion(k=5), reader, query, describer(reader, localizer, rgb, QueryCache())).dbs
    assert record["references"] == [reader.names[i] for i in ranked[:len(record["references"])]]
