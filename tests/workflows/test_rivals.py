"""Rival starts (``pipeline.localization.search.rival_starts``, ``check_rivals``): a pose refined from a
map pose is accepted only when the next reference's pose, refined the same way, does not end verified
elsewhere.

On the Middlebury temple ring (views 7.7 deg apart around the object), the top-1 refinement stays
at the neighbouring view's pose, and verification alone accepts it (17 of 19 queries of the
accuracy benchmark, before this check)."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.localization.refine import Candidate, LocalizerConfig, QueryCache, QueryResult
from pipeline.localization.retrieval import GlobalDescriptors
from pipeline.localization.search import check_rivals, rival_starts
from pipeline.localization.verify import VerificationConfig
from pipeline.evaluate import record_errors
from pipeline.descriptors import GeM
from pipeline.mapping.features import FeatureConfig
from workflows.benchmarks.accuracy import RELATIVE, SPLITS, scene_scale, split_parts
from workflows.benchmarks.search import localize_priors


def _pose(yaw_deg: float, x: float = 0.0) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return np.concatenate([R, np.array([[x], [0.0], [0.0]])], 1)


def _result(refined, prior, success=True, confidence=0.9, reason=""):
    return QueryResult("q.jpg", success, prior, refined, evidence={"depth": 1.0}, confidence=confidence, reason=reason)


def test_rival_starts_are_the_next_references_that_are_not_a_start():
    names = ["a", "b", "c", "d"]
    poses = [_pose(0), _pose(0.5), _pose(8), _pose(16)]
    reader = SimpleNamespace(cam_from_world=poses, names=names)
    top1 = Candidate(SimpleNamespace(name="q.jpg"), [0, 1, 2, 3], poses[0], rgb=np.zeros(1), cache=QueryCache(),
                     origin="top-1 reference")
    rivals = rival_starts(reader, [top1], VerificationConfig(rivals=2))
    assert [c.origin for c in rivals] == ["rival: reference b", "rival: reference c"]
    assert np.allclose(rivals[1].prior, poses[2]) and rivals[0].dbs == top1.dbs and rivals[0].cache is top1.cache
    # hypotheses from a and c: b is the rival; none without verification or with rivals 0
    second = dataclasses.replace(top1, prior=poses[2])
    assert [c.origin for c in rival_starts(reader, [top1, second], VerificationConfig())] == ["rival: reference b"]
    assert rival_starts(reader, [top1], VerificationConfig(rivals=0)) == []
    assert rival_starts(reader, [top1], VerificationConfig(enabled=False)) == []


def test_a_rival_verified_at_another_pose_rejects_the_result():
    conf = VerificationConfig()  # agree within 10 % of the depth and 5 deg
    here = _result(_pose(0), _pose(0))
    check_rivals(here, [("rival: reference c.png", _result(_pose(3), _pose(8)))], conf)
    assert here.success and "converged to the same pose" in here.notes[-1]
    check_rivals(here, [("rival: reference c.png", _result(_pose(8), _pose(8), success=False, reason="rejected: x"))],
                 conf)
    assert here.success and "rival start reference c.png: not verified (rejected: x)" in here.notes[-1]
    check_rivals(here, [("rival: reference c.png", _result(_pose(8), _pose(8), confidence=0.97))], conf)
    assert not here.success
    assert here.reason.startswith("rejected: ambiguous: the start from reference c.png is verified too "
                                  "(confidence 0.97) at a pose 8.0 deg")
    # a move of the camera centre alone, beyond agree_t x the depth, is another pose too
    moved = _result(_pose(0), _pose(0))
    check_rivals(moved, [("c.png: yaw +15 deg", _result(_pose(0, x=0.2), _pose(0)))], conf)
    assert not moved.success and "the start from c.png: yaw +15 deg" in moved.reason
    # a rejected result stays as it is
    rejected = _result(_pose(0), _pose(0), success=False, reason="rejected: y")
    check_rivals(rejected, [("rival: reference c.png", _result(_pose(8), _pose(8)))], conf)
    assert rejected.reason == "rejected: y" and rejected.notes == []


def test_on_the_temple_ring_no_neighbouring_view_is_accepted(shared, tmp_path, monkeypatch):
    """The first fold of the accuracy benchmark's temple ring, 5 queries, ``top1``: without the
    check, refinements that stayed at a neighbour's pose are accepted; with it, none is, and each
    is rejected as ambiguous, naming the rival's reference. A rival that stops where it joins the
    query's start (``join``, the default) gives the verdicts of one run through every level. The
    ``max_sigma`` gate is off here, to see the rival check alone (the gate alone leaves 1 of these wrong
    poses accepted; tests/workflows/test_pinned_down.py tests it). The rivals are solved in LM batches
    of their own (a batch's peak memory holds a copy of each problem's query maps), and the queries'
    own refinements are those of a run without rivals."""
    from pipeline.localization.refine import Localizer
    batches = []
    solve = Localizer._solve_level
    monkeypatch.setattr(Localizer, "_solve_level", lambda self, group, *a: batches.append(
        {st.own is not None for st in group}) or solve(self, group, *a))
    # the maps on which the faults were found: retrieval by gem (build-map's default then), whose top-1 starts these are
    fconf = FeatureConfig(resize=512, image_scales=(1,), descriptor=GeM.name)
    parts = list(split_parts("templeRing", SPLITS["templeRing"], shared, tmp_path, fconf, limit=5))[:1]
    scale = scene_scale(parts[0][1])
    (t_max, R_max), runs = RELATIVE[2], {}
    for rivals, join in ((0, 0.5), (1, 0.5), (1, 0.0)):
        lconf = LocalizerConfig(num_dbs=3, num_iters=50,
                                verification=VerificationConfig(rivals=rivals, join=join, max_sigma=0))
        per_prior, gt = localize_priors(parts, ["top1"], tmp_path / f"runs-{rivals}-{join}", lconf,
                                        GlobalDescriptors(k=5))
        records = {r["name"]: r for r in per_prior["top1"]["records"]}
        assert len(records) == 5
        far = [n for n, r in records.items()
               if (lambda t, R: t > t_max * scale or R > R_max)(*record_errors(r, gt[n])["refined"])]
        runs[rivals, join] = records, [n for n in far if records[n]["success"]]
    (_, wrong_before), (after, wrong_after), (full, _) = runs[0, 0.5], runs[1, 0.5], runs[1, 0.0]
    assert len(wrong_before) >= 3, wrong_before  # the fault the check removes
    assert wrong_after == []
    for name in wrong_before:
        assert after[name]["reason"].startswith("rejected: ambiguous: the start from reference templeR")
    assert {n: (r["success"], r["reason"][:40]) for n, r in after.items()} == \
        {n: (r["success"], r["reason"][:40]) for n, r in full.items()}
    for name, record in after.items():
        assert np.allclose(record["refined"], full[name]["refined"], atol=1e-6)
        assert np.allclose(record["refined"], runs[0, 0.5][0][name]["refined"], atol=1e-6)
    assert {True} in batches and all(len(b) == 1 for b in batches)  # rivals in batches of their own
    # rivals run only for a query with a verified start (an accepted one notes its rival's outcome; an
    # ambiguous one names it); a query rejected on its own was given no rival's verdict
    for name, record in after.items():
        rival = [n for n in record["notes"] if n.startswith("rival start")]
        ambiguous = record["reason"].startswith("rejected: ambiguous")
        assert bool(rival) == record["success"] and (record["success"] or ambiguous or "rival" not in record["reason"])


def test_a_pose_rejected_as_ambiguous_still_counts_as_a_verified_rival():
    """The search goes on where its top-1 start was rejected as ambiguous; a winner elsewhere is then
    contradicted by that top-1 refinement (verified, not unique) and rejected too."""
    conf = VerificationConfig()
    top1 = _result(_pose(0), _pose(0), success=False, reason="rejected: ambiguous: the start from reference b ...")
    winner = _result(_pose(8), _pose(0))
    check_rivals(winner, [("a.png: reference", top1)], conf)
    assert not winner.success and winner.reason.startswith("rejected: ambiguous: the start from a.png: reference")


def test_a_rival_stops_where_it_joins_its_querys_start():
    """``Localizer._join_rivals``: after a coarser level, a rival within ``join`` x (agree_t, agree_R) of
    one of its query's own starts at the end of that level stops (it would end at the same pose), one
    farther goes on, and one whose query's own starts had all stopped by then stops too;
    ``check_rivals`` notes it as agreeing."""
    import torch

    from pixloc.geometry import Pose
    from pipeline.localization.refine import JOINED, LevelState, Localizer

    xyz = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.1, 1.0]])  # median depth 1

    def state(T, own=None):
        st = LevelState(SimpleNamespace(name="q.jpg"), None, {}, _result(None, T, success=False), active=True,
                        T=Pose.from_matrix(T).float(), refs=(xyz, []))
        st.own = own
        return st

    start = {(1, 1): _pose(10), (1, 0): _pose(0)}  # the query's own start at the end of two levels
    near, far, mover = state(_pose(2), [start]), state(_pose(3), [start]), state(_pose(0, x=0.03), [start])
    localizer = SimpleNamespace(conf=LocalizerConfig())  # join 0.5: within 5 % of the depth and 2.5 deg
    Localizer._join_rivals(localizer, [near, far, mover], image_scale=1, level=0)
    assert far.active and not near.active and not mover.active
    assert near.result.reason.startswith(JOINED + "it reached the query's start at image scale 1, level 0 (2.00 deg")
    here = _result(_pose(0), _pose(0))
    check_rivals(here, [("rival: reference b.png", near.result)], VerificationConfig())
    assert here.success and here.notes[-1].startswith("rival start reference b.png: it reached the query's start")
    at_level_1 = state(_pose(2), [start])  # the same pose, compared with where the start was after level 1
    Localizer._join_rivals(localizer, [at_level_1], image_scale=1, level=1)
    assert at_level_1.active
    Localizer._join_rivals(localizer, [far], image_scale=4, level=1)  # the start had stopped before: no pose
    assert not far.active and far.result.reason == JOINED + "its query's own starts stopped before it"
    # join 0: every rival runs through every level
    alone = state(_pose(0), [{(1, 0): _pose(0)}])
    off = SimpleNamespace(conf=LocalizerConfig(verification=VerificationConfig(join=0.0)))
    Localizer._join_rivals(off, [alone], image_scale=1, level=0)
    assert alone.active


def test_a_rival_not_pinned_down_still_contradicts():
    """A rival rejected only by the ``max_sigma`` gate sits in a minimum that is sharp for image shifts:
    it is another answer all the same, and the result is ambiguous (without this, the gate turned
    ambiguous poses on beer_capture and dino into accepted wrong ones)."""
    here = _result(_pose(0), _pose(0))
    loose = _result(_pose(8), _pose(8), success=False, reason="rejected: the pose is not pinned down: sigma 0.09 ...")
    check_rivals(here, [("rival: reference c.png", loose)], VerificationConfig())
    assert not here.success and here.reason.startswith("rejected: ambiguous: the start from reference c.png")


def test_a_rival_much_less_sharp_than_the_result_does_not_reject_it():
    """Two verified poses are ambiguous when both are about as well supported; where the result's cost
    is ``sharper_by`` times sharper (its 3 px contrast) than the rival's, the rival's is the weaker pose.
    On the photo city, 5 of the 6 poses rejected as ambiguous were right (6 to 21 cm, 0.3 to 1 deg) with
    contrasts 2.8 to 7.5 times their rivals'; the one wrong (2 m, 10 deg) had 1.5 times its rival's."""
    def sharp(refined, contrast, **kw):
        r = _result(refined, refined, **kw)
        r.evidence["contrast_3px"] = contrast
        return r
    here = sharp(_pose(0), 0.30)
    check_rivals(here, [("rival: reference c.png", sharp(_pose(8), 0.10))], VerificationConfig())
    assert here.success and "3.0 times less sharp (contrast 0.100 against 0.300)" in here.notes[-1]
    close = sharp(_pose(0), 0.15)
    check_rivals(close, [("rival: reference c.png", sharp(_pose(8), 0.10))], VerificationConfig())
    assert not close.success and close.reason.startswith("rejected: ambiguous: the start from reference c.png")
    off = sharp(_pose(0), 0.30)
    check_rivals(off, [("rival: reference c.png", sharp(_pose(8), 0.10))], VerificationConfig(sharper_by=0))
    assert not off.success
    hypothesis = sharp(_pose(0), 0.30)  # another start of the search, not a rival start: it still rejects
    check_rivals(hypothesis, [("c.png: reference", sharp(_pose(8), 0.10))], VerificationConfig())
    assert not hypothesis.success
    with pytest.raises(ValueError, match="sharper_by"):
        VerificationConfig(sharper_by=0.5)
