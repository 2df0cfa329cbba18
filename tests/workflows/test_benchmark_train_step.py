"""``pixloc benchmark train-step`` on a tiny config: a row per variant with its steps per CPU hour
and ratio, and the cost of drawing a pair of each source (the whole run: docs/model_card.md)."""

import re

import pytest
import yaml

from workflows.cli import main
from tests.workflows.test_train import CONFIG


# benchmark tooling: slow tier, the default suite's 15 minutes
@pytest.mark.slow
def test_the_table_has_every_variant_and_the_costs_that_are_not_the_model(tmp_path, capsys):
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(dict(CONFIG, validation=[])))
    assert main(["benchmark", "train-step", "--config", str(path), "--work", str(tmp_path / "w"),
                 "--steps", "2", "--rounds", "1", "--data-root", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\| (today|freed memory reused|channels-last|encoder frozen) \| ([\d.]+) \| ([\d,]+) \| "
                      r"([\d.]+)x \|$", out, re.M)
    assert [r[0] for r in rows] == ["today", "freed memory reused", "channels-last", "encoder frozen"]
    for _, seconds, per_hour, ratio in rows:
        assert float(seconds) > 0 and abs(3600 / float(seconds) / float(per_hour.replace(",", "")) - 1) < 0.01
    assert rows[0][3] == "1.00"
    assert re.search(r"^\| draw a pair: synthetic-11 \| [\d.]+ ms \|$", out, re.M)
    assert re.search(r"^\| validation pair \(s\) \| [\d.]+ s \|$", out, re.M)
