"""A self-contained HTML report of a localization run (one file, offline: plots are embedded PNGs).

Sections, in order:
- the run: outcomes, the job, the map, time per query;
- accuracy: ``all`` first, then one table and one plot of cumulative errors per tag family
  (``condition``, ``area``, ...), values sorted, prior and result side by side;
- failures grouped by reason;
- every query in one table (failures first, then by error; click a header to sort);
- a top view of the map with each query's prior, result and ground truth;
- examples chosen to inform: per condition the best, median and worst query, and failures,
  with the map points projected at the prior, refined and ground-truth poses, the feature and
  confidence maps, and the convergence over the levels.
"""

import html
import json
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from pipeline.evaluate import DEFAULT_THRESHOLDS, evaluate, fmt, shown_families
from pipeline.localization.shard import LocalizationJob
from pipeline.mapping.readers.sources import map_units
from pipeline.store.info import map_source
from pipeline.store.reader import MapReader
from pipeline.queries import QueryRecord
from pipeline.localization.results import outcome, read_records, reason_groups, stages_text
from pipeline.textfiles import write_atomic

from .report_figures import (error_curves, example_figure, natural_key, query_errors, refinement_confidence,
                             threshold_tradeoff, top_view, tradeoff_figure)

OUTCOME_ORDER = {"failed": 0, "rejected": 1, "refined": 2}
MAX_CONDITIONS = 8  # conditions of a family given examples

def tag_families(summary: Dict, group_by=None) -> List[Tuple[str, List[str]]]:
    """[('all', ['all']), (family, its keys sorted)...] of the families worth a table
    (``pipeline.evaluate.shown_families``)."""
    families = shown_families(summary, group_by)
    return [("all", ["all"])] + [(f, sorted(keys, key=natural_key)) for f, keys in sorted(families.items())]


def _img(data: str, alt: str, fmt: str = "png") -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/{fmt};base64,{data}">'


def _score(err: Dict, thresholds) -> float:
    """One number per query for ordering: the error relative to the first threshold (inf: no pose)."""
    if err["t"] is None:
        return float("inf")
    t0, r0 = thresholds[0]
    return max(err["t"] / t0, err["R"] / r0)


def _tags_text(tags: Dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in sorted(tags.items()))


TEXT_COLUMNS = ("query", "tags", "outcome", "reason", "stages", "references")


def _inputs_digest(output: Path, num_examples: int, thresholds, gt: Dict, units: Optional[str]) -> str:
    """A digest of what a report is made of: the run's records and job, the settings, the ground
    truth, and the code that draws it."""
    import hashlib

    import pixloc
    h = hashlib.sha256()
    for name in ("records.jsonl", "job.json"):
        h.update((output / name).read_bytes())
    for module in ("report.py", "report_figures.py"):  # the code that draws it
        h.update((Path(__file__).parent / module).read_bytes())
    h.update(json.dumps([pixloc.__version__, num_examples, [list(t) for t in thresholds], units,
                         sorted((k, np.round(v, 9).tolist()) for k, v in gt.items())]).encode())
    return h.hexdigest()[:16]


def _count(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def counts_text(records: List[Dict]) -> str:
    """'20 queries: 16 refined and verified, 3 rejected by verification, 1 failed. Of the 4 queries
    without a verified pose, 3 report their prior and 1 has no pose.' (the last sentence where it
    applies)."""
    by = {o: sum(outcome(r) == o for r in records) for o in OUTCOME_ORDER}
    text = (f"{_count(len(records), 'query', 'queries')}: <b>{by['refined']} refined</b> and verified, "
            f"{by['rejected']} rejected by verification, {by['failed']} failed.")
    unverified = [r for r in records if not r["success"]]
    if unverified:
        prior = sum(r.get("prior") is not None for r in unverified)
        none = len(unverified) - prior
        text += (f" Of the {_count(len(unverified), 'query', 'queries')} without a verified pose, {prior} "
                 f"{'reports its' if prior == 1 else 'report their'} prior" + (f" and {none} "
                 f"{'has' if none == 1 else 'have'} no pose." if none else "."))
    return text


def _references_text(references: List[str]) -> str:
    return ", ".join(references[:3]) + (" ..." if len(references) > 3 else "")


def query_table(records: List[Dict], errors: Dict[str, Dict], thresholds, units: str) -> str:
    """Every query, failures first, then by error (largest first); sortable by clicking a header."""
    rows = sorted(records, key=lambda r: (OUTCOME_ORDER[outcome(r)], -_score(errors[r["name"]], thresholds)
                                          if errors[r["name"]]["t"] is not None else float("-inf"), r["name"]))
    cols = ["query", "tags", "outcome", f"error t ({units})", "error R (deg)", f"refined t ({units})",
            "refined R (deg)", f"prior t ({units})", "prior R (deg)", "confidence", "reason", "stages", "references",
            "points", "iterations", "time (s)"]
    out = ["<table id='queries' class='sortable'><thead><tr>"
           + "".join(f"<th data-type='{'text' if c in TEXT_COLUMNS else 'num'}'>{html.escape(c)}</th>" for c in cols)
           + "</tr></thead><tbody>"]
    for r in rows:
        e = errors[r["name"]]
        o = outcome(r)
        num = (lambda v, spec: f"<td data-v='{v if v is not None else ''}'>{fmt(v, spec)}</td>")
        out.append(
            f"<tr class='{o}'><td>{html.escape(r['name'])}</td>"
            f"<td class='text tags'>{html.escape(_tags_text(r.get('tags', {})))}</td>"
            f"<td data-v='{OUTCOME_ORDER[o]}'>{o}</td>" + num(e["t"], ".3f") + num(e["R"], ".2f")
            + num(e["refined_t"], ".3f") + num(e["refined_R"], ".2f") + num(e["prior_t"], ".3f")
            + num(e["prior_R"], ".2f") + num(refinement_confidence(r), ".2f")
            + f"<td class='text'>{html.escape(r['reason'])}</td>"
            f"<td class='text'>{html.escape(stages_text(r))}</td>"
            f"<td class='text refs'>{html.escape(_references_text(r['references']))}</td>"
            + num(r.get("num_points"), "d") + num(r.get("iterations"), "d")
            + num(r.get("timings", {}).get("total"), ".2f") + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


SORT_SCRIPT = """
document.querySelectorAll('table.sortable').forEach(function (table) {
  var heads = table.tHead.rows[0].cells;
  Array.prototype.forEach.call(heads, function (th, col) {
    th.title = 'sort'; th.style.cursor = 'pointer';
    th.addEventListener('click', function () {
      var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
      var asc = th.dataset.order !== 'asc', num = th.dataset.type === 'num';
      rows.sort(function (a, b) {
        var x = a.cells[col], y = b.cells[col];
        if (num) {
          var u = x.dataset.v === '' ? Infinity : parseFloat(x.dataset.v);
          var v = y.dataset.v === '' ? Infinity : parseFloat(y.dataset.v);
          return asc ? u - v : v - u;
        }
        return asc ? x.textContent.localeCompare(y.textContent) : y.textContent.localeCompare(x.textContent);
      });
      Array.prototype.forEach.call(heads, function (h) { delete h.dataset.order; });
      th.dataset.order = asc ? 'asc' : 'desc';
      rows.forEach(function (r) { body.appendChild(r); });
    });
  });
  table.dataset.ready = 'true';
});
"""

STYLE = """
body{font-family:sans-serif;max-width:1280px;margin:auto;padding:0 1em;color:#222}
img{max-width:100%} h2{border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;font-size:13px;margin:0.5em 0}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:right} th{background:#f2f2f2;text-align:left}
td:first-child,th:first-child,td.text,th[data-type=text]{text-align:left}
tr.failed td{background:#fde2e2} tr.rejected td{background:#fff3d6}
th[data-order=asc]::after{content:' \\25B2'} th[data-order=desc]::after{content:' \\25BC'}
.wide{overflow-x:auto} .note{color:#666;font-size:13px}
#queries td:first-child{word-break:break-all;min-width:10em;max-width:22em}
#queries td.text{min-width:14em;text-align:left}
#queries td.refs,#queries td.tags{word-break:break-all;min-width:12em;max-width:20em}
"""


def threshold_section(records: List[Dict], gt: Dict, threshold, job: Dict, units: str) -> str:
    """The verification threshold's precision/recall trade-off over the refined queries with ground
    truth; a note instead where none of them is right (flat curves at zero); nothing without any."""
    curves = threshold_tradeoff(records, gt, threshold) if gt else None
    if curves is None:
        return ""
    head = "<h2 id='threshold'>Verification threshold</h2><p class='note'>"
    if curves[3] == 0:
        return (head + "None of the refined queries with ground truth is within "
                f"{threshold[0]:g} {html.escape(units)}, "
                f"{threshold[1]:g} deg: there is no right refinement for a minimum confidence "
                "(<code>--min-confidence</code>) to keep or reject, so no trade-off to show. Each refinement's "
                "error is in the per-query table.</p>")
    verification = job["localizer"].get("verification", {})
    return (head + "What each minimum confidence (<code>--min-confidence</code>) would keep, over the refined "
            "queries with ground truth: the fraction of accepted refinements that are right, and of right refinements "
            "that are accepted. Rejections of right poses are what the threshold is tuned on.</p>"
            + _img(tradeoff_figure(curves, threshold, float(verification.get("min_confidence", 0.5)), units),
                   "precision and recall against the minimum confidence"))


def accuracy_tables(summary: Dict, thresholds, units: str, group_by=None) -> str:
    keys = [k for k in summary["all"]["refined"] if k.startswith("recall@")]
    parts = []
    for family, fkeys in tag_families(summary, group_by):
        head = (f"<tr><th>{html.escape(family if family != 'all' else 'queries')}</th><th>n</th>"
                "<th>median t prior</th><th>median t result</th><th>median R prior</th><th>median R result</th>"
                + "".join(f"<th>within {t:g} {html.escape(units)}, {r:g}&deg;<br>prior &rarr; result</th>"
                          for t, r in thresholds)
                + "</tr>")
        rows = []
        for key in fkeys:
            p, r = summary[key]["prior"], summary[key]["refined"]
            pct = (lambda v: fmt(100 * v if v is not None else None, ".0f"))
            rows.append(f"<tr><td>{html.escape(key.split('=', 1)[-1])}</td><td>{r['count']}</td>"
                        f"<td>{fmt(p['median_t'], '.3f')}</td><td>{fmt(r['median_t'], '.3f')}</td>"
                        f"<td>{fmt(p['median_R'], '.2f')}</td><td>{fmt(r['median_R'], '.2f')}</td>"
                        + "".join(f"<td>{pct(p[k])} &rarr; <b>{pct(r[k])}</b> %</td>" for k in keys) + "</tr>")
        same = family != "all" and len(fkeys) == 1  # one value for every query: the curves of 'all'
        parts.append(f"<h3 id='family-{html.escape(family)}'>{html.escape(family)}</h3>"
                     f"<table class='accuracy'>{head}{''.join(rows)}</table>"
                     + ("" if same else _img(error_curves(summary, fkeys, units), f"cumulative errors by {family}")))
    return "".join(parts)


def failure_summary(records: List[Dict]) -> str:
    groups = reason_groups(records)
    if not groups:
        return "<p>Every query has a verified refinement.</p>"
    rows = "".join(f"<tr><td>{len(rs)}</td><td>{o}</td><td class='text'>{html.escape(rs[0]['reason'])}</td>"
                   f"<td class='text'>{html.escape(', '.join(r['name'] for r in rs[:5]))}"
                   f"{' ...' if len(rs) > 5 else ''}</td></tr>" for o, _, rs in groups)
    return ("<table id='failures'><tr><th>queries</th><th>outcome</th><th>reason (first of its kind)</th>"
            f"<th>examples</th></tr>{rows}</table><p class='note'>Rejected: refined, but the evidence did not "
            "support the pose (docs/verification.md); failed: not refined. Both report their prior.</p>")


def choose_examples(records: List[Dict], errors: Dict[str, Dict], family: Optional[str], per_condition: int,
                    thresholds, num_failures: int = 3) -> List[Tuple[Dict, str]]:
    """(record, why) per example: per value of ``family``, the best, median and worst query by error
    (by confidence without ground truth), then failures of different kinds."""
    out, seen = [], set()
    usable = [r for r in records if r["references"]]
    values = sorted({r.get("tags", {}).get(family, "") for r in usable}, key=natural_key)[:MAX_CONDITIONS] \
        if family else [""]
    labels = {1: ["median"], 2: ["best", "worst"], 3: ["best", "median", "worst"]}
    for value in values:
        group = [r for r in usable if not family or r.get("tags", {}).get(family, "") == value]
        has_gt = [r for r in group if errors[r["name"]]["t"] is not None]
        if has_gt:
            ranked = sorted(has_gt, key=lambda r: _score(errors[r["name"]], thresholds))
        else:
            ranked = sorted(group, key=lambda r: -(r.get("confidence") or 0.0))
        if not ranked or per_condition < 1:
            continue
        picks = np.unique(np.round(np.linspace(0, len(ranked) - 1, min(per_condition, len(ranked)))).astype(int))
        names = labels.get(len(picks), [f"rank {i + 1} of {len(ranked)}" for i in picks])
        for i, label in zip(picks, names):
            r = ranked[i]
            if r["name"] not in seen:
                seen.add(r["name"])
                where = f"{family}={value}: " if family else ""
                out.append((r, f"{where}{label}" + (" by error" if has_gt else " by confidence")))
    kinds = set()
    for o, kind, rs in reason_groups(usable):
        for r in rs:
            if len([x for x in out if x[1].startswith("failure")]) >= num_failures:
                break
            if r["name"] not in seen and kind not in kinds:
                seen.add(r["name"])
                kinds.add(kind)
                out.append((r, o))
    return out


def _job_text(job: Dict, reader: MapReader, units: str, records: List[Dict]) -> str:
    times = [r["timings"]["total"] for r in records if r.get("timings", {}).get("total") is not None]
    rows = [("map store", job["store"]),
            ("map", f"{len(reader.names)} reference images, {len(reader.xyz)} points, units: {units}"),
            ("model", job["model"]),
            ("prior", f"{job['prior']['name']} from {job['retrieval']['method']} retrieval (k={job['retrieval']['k']})"
                      + (f", references sharing the tag {job['retrieval']['same_tag']!r}"
                         if job["retrieval"].get("same_tag") else "")),
            ("verification", "on, min confidence {}".format(job["localizer"]["verification"]["min_confidence"])
             if job["localizer"]["verification"]["enabled"] else "off"),
            ("time per query", f"median {fmt(float(np.median(times)) if times else None, '.2f')} s "
                               f"(one worker thread)")]
    return "<table id='job'>" + "".join(f"<tr><th>{k}</th><td style='text-align:left'>{html.escape(str(v))}</td></tr>"
                                        for k, v in rows) + "</table>"


def make_report(output: Path, queries: List[QueryRecord], num_examples: int = 3,
                thresholds=None, ground_truth: Optional[Dict] = None, units: Optional[str] = None,
                group_by: Optional[List[str]] = None, reuse: bool = False) -> Path:
    """Write ``output/report.html`` from ``records.jsonl`` (and the run's ``job.json``).

    ``ground_truth`` (name -> cam_from_world or None) defaults to the queries' own; ``units``
    to those of the map's source; ``num_examples`` queries per condition (best, median, worst);
    ``group_by``: the tag families to tabulate (default: ``pipeline.evaluate.shown_families``).
    ``reuse``: keep a report made from the same inputs and code (a no-op rerun rewrites nothing)."""
    from pipeline.models import localization_model

    output = Path(output)
    thresholds = tuple(thresholds or DEFAULT_THRESHOLDS)
    records = read_records(output / "records.jsonl")
    gt = ground_truth if ground_truth is not None else {q.name: q.cam_from_world_gt for q in queries}
    gt = {k: np.asarray(v, np.float64) for k, v in gt.items() if v is not None and np.isfinite(v).all()}
    path = output / "report.html"
    inputs = _inputs_digest(output, num_examples, thresholds, gt, [units, group_by])
    if reuse and path.is_file() and f"<!-- pixloc-report-inputs {inputs} -->" in path.read_text(errors="replace"):
        return path  # made from the same records, settings and code: left untouched
    run = LocalizationJob.from_dict(json.loads((output / "job.json").read_text())["job"])  # of any schema
    job = run.to_dict()
    refiner, digest = localization_model(run.model, "cpu")
    reader = MapReader(run.store, run.features, digest)
    if units is None:
        units = map_units(map_source(run.store))
    errors = {r["name"]: query_errors(r, gt.get(r["name"])) for r in records}
    families = sorted({k for r in records for k in r.get("tags", {})})
    family = "condition" if "condition" in families else (families[0] if families else None)

    parts = [f"<h1>PixLoc localization report</h1><p id='counts'>{counts_text(records)} Ground truth for "
             f"{sum(r['name'] in gt for r in records)} of them.</p>", _job_text(job, reader, units, records)]
    parts.append("<h2 id='accuracy'>Accuracy</h2>")
    if gt:
        summary = evaluate(records, gt, thresholds)
        parts.append("<p class='note'>result: the refined pose where verification accepted it, else the prior. "
                     "Medians over the queries with a pose; recall over all queries. Curves: result solid, prior "
                     "dashed.</p>" + accuracy_tables(summary, thresholds, units, group_by))
    else:
        parts.append("<p>No ground truth: accuracy is not evaluated (pass --ground-truth POSES).</p>")
    parts.append(threshold_section(records, gt, thresholds[0], job, units))
    parts.append(f"<h2 id='failures-section'>Failures and rejections</h2>{failure_summary(records)}")
    parts.append(f"<h2 id='queries-section'>Queries</h2><p class='note'>{len(records)} rows: failed (red) and "
                 "rejected (yellow) first, then by error, largest first. Click a header to sort.</p>"
                 f"<div class='wide'>{query_table(records, errors, thresholds, units)}</div>")
    parts.append("<h2 id='map'>Top view of the map</h2>"
                 + _img(top_view(reader, records, gt, family, units), "top view"))
    parts.append("<h2 id='examples'>Examples</h2><p class='note'>Points of the query's references projected at the "
                 "prior (red) and refined (green) poses" + (", and at the ground truth (blue)" if gt else "")
                 + ".</p>")
    by_name = {q.name: q for q in queries}
    for rec, why in choose_examples([r for r in records if r["name"] in by_name], errors, family, num_examples,
                                    thresholds):
        figure = example_figure(rec, why, by_name[rec["name"]], reader, refiner.extractor, gt.get(rec["name"]), units)
        parts.append(f"<div class='example'><h3>{html.escape(rec['name'])} ({html.escape(why)})</h3>"
                     f"{_img(figure, rec['name'], 'jpeg')}</div>")
    write_atomic(path, f"<!doctype html><!-- pixloc-report-inputs {inputs} --><html><head><meta charset='utf-8'>"
                 f"<title>PixLoc report</title><style>{STYLE}</style></head><body>" + "".join(parts)
                 + f"<script>{SORT_SCRIPT}</script></body></html>")
    return path
