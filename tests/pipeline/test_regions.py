import numpy as np

from pipeline.regions import morton, region_order


def test_morton_keeps_quadrants_together():
    xy = np.array([[0, 0], [1, 1], [0.1, 0.9], [0.9, 0.1], [0.05, 0.05]])
    codes = morton(xy)
    order = np.argsort(codes)
    assert order[0] == 0 and order[1] == 4 and order[-1] == 1


def test_region_order_groups_queries_by_the_blocks_of_their_references():
    """4 blocks of a city, queries listed in a round-robin over them: region order puts each
    block's queries side by side; queries without a reference go last."""
    rng = np.random.default_rng(0)
    blocks = np.array([[0, 0], [100, 0], [0, 100], [100, 100]], float)
    centres = np.concatenate([b + rng.uniform(0, 10, (5, 2)) for b in blocks])
    centres = np.concatenate([centres, rng.normal(0, 0.1, (20, 1))], 1)  # a flat city
    refs = [f"db{i}" for i in range(20)]
    names = [f"q{k}" for k in range(40)]
    top1 = {f"q{k}": f"db{(k % 4) * 5 + (k // 4) % 5}" for k in range(38)}  # q38, q39: nothing retrieved
    order = region_order(names, top1, refs, centres)
    assert sorted(order) == list(range(40)) and order[-2:] == [38, 39]
    block = [int(top1[names[k]][2:]) // 5 for k in order[:-2]]
    assert sum(a != b for a, b in zip(block, block[1:])) == 3  # one run per block
