"""Progress for long stages and the task size that keeps it moving."""

import io
import re

from workflows.localize import auto_shard_size
from pipeline.progress import Progress


def test_progress_off_a_terminal_is_a_few_status_lines_with_rate_and_eta():
    out = io.StringIO()
    with Progress(10, "localize", "query", "queries", stream=out, every=0.0) as p:
        for _ in range(10):
            p.update(1)
    lines = out.getvalue().splitlines()
    assert lines[0] == "localize: 10 queries to do"
    assert re.fullmatch(r"localize: 5/10 queries \(50 %\), [\d.]+ queries/s, elapsed \d+ s, ETA \d+ s", lines[5])
    assert lines[-1].startswith("localize: 10/10 queries (100 %)") and "ETA" not in lines[-1]
    assert "\r" not in out.getvalue() and len(lines) == 11  # start, 9 statuses (every=0), end


def test_progress_is_quiet_between_periods_and_says_where_it_stopped():
    out = io.StringIO()
    try:
        with Progress(100, "features", "image", stream=out, every=3600) as p:
            p.update(40)
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        pass
    assert out.getvalue().splitlines() == ["features: 100 images to do", "features: stopped at 40/100"]


def test_shards_give_every_worker_several_tasks():
    """Before: 6 queries in one shard of 8 left one of two workers idle and the bar at 0 % until the end."""
    assert auto_shard_size(6, 2) == 1
    assert auto_shard_size(20, 2) == 3
    assert auto_shard_size(75_000, 64) == 8  # one LM batch of 8 per task at scale
    assert auto_shard_size(1, 1) == 1


def test_counts_read_as_english():
    """Before: 'localize 1 queries in 1 shards', '1 failures retried'."""
    from pipeline.progress import count
    assert [count(1, "query"), count(2, "query"), count(0, "failure"), count(3, "finished shard"), count(2, "day")] \
        == ["1 query", "2 queries", "0 failures", "3 finished shards", "2 days"]
