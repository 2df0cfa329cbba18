"""A self-contained HTML report of a localization run: accuracy per condition and example queries."""

import base64
import html
import io
import json
from collections import Counter
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

from pipeline.evaluate import evaluate, fmt
from pipeline.features import FeatureConfig
from pipeline.images import read_image
from pipeline.map_reader import MapReader
from pipeline.queries import QueryRecord
from pipeline.results import outcome, read_records, record_pose


def _png(fig) -> str:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def error_curves(summary: Dict) -> str:
    """Cumulative distributions of translation and rotation errors per condition (refined solid, prior dashed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, (key, s) in enumerate(summary.items()):
        color = f"C{i % 10}"
        for which, style in (("errors", "-"), ("prior_errors", "--")):
            e = np.asarray(s[which], float).reshape(-1, 2)
            for ax, col in zip(axes, (0, 1)):
                v = np.sort(e[:, col])
                y = np.arange(1, len(v) + 1) / max(len(v), 1)
                finite = np.isfinite(v)
                ax.step(v[finite], y[finite], style, color=color, where="post",
                        label=f"{key} ({'refined' if which == 'errors' else 'prior'})")
    for ax, label in zip(axes, ("camera centre error (scene units)", "rotation error (deg)")):
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of queries")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="lower right")
    return _png(fig)


def _project(camera, T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    p = torch.from_numpy(xyz @ T[:, :3].T + T[:, 3])
    p2d, valid = camera.to_pixloc(torch.float64).cam2image(p)
    return p2d.numpy()[valid.numpy()]


def example_figure(record: Dict, query: QueryRecord, reader: MapReader, net) -> str:
    """The query with map points projected at the prior (red) and refined (green) pose, and the
    finest feature map (first 3 PCA components) and confidence map."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pipeline.images import resize_max, to_tensor

    rgb = read_image(query.path)
    dbs = [reader.index[n] for n in record["references"] if n in reader.index]
    obs = reader.observations(dbs, 1)
    xyz = reader.xyz[np.unique(obs.point)]
    xyz = xyz[np.random.default_rng(0).permutation(len(xyz))[:800]]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    axes[0].imshow(rgb)
    for T, color, label in ((record["prior"], "red", "prior"), (record_pose(record), "lime", "refined")):
        if T is not None:
            p = _project(query.camera, np.asarray(T), xyz)
            axes[0].scatter(p[:, 0] + 0.5, p[:, 1] + 0.5, s=2, c=color, label=label)
    axes[0].legend(loc="lower right", fontsize=7)
    axes[0].set_title(f"{record['name']} ({'refined' if record['success'] else 'failed: ' + record['reason'][:40]})",
                      fontsize=8)
    with torch.no_grad():
        pred = net(to_tensor(resize_max(rgb, 512)[0])[None])
    f = pred["features"][0][0]
    flat = f.reshape(f.shape[0], -1).T
    flat = flat - flat.mean(0)
    _, _, V = torch.pca_lowrank(flat, q=3)
    pca = (flat @ V).reshape(f.shape[1], f.shape[2], 3).numpy()
    pca = (pca - pca.min((0, 1))) / (np.ptp(pca, (0, 1)) + 1e-9)
    axes[1].imshow(pca)
    axes[1].set_title("finest features (PCA)", fontsize=8)
    if "confidences" in pred:
        axes[2].imshow(pred["confidences"][0][0, 0].numpy(), cmap="viridis", vmin=0, vmax=1)
        axes[2].set_title("finest confidence", fontsize=8)
    else:
        axes[2].set_title("(this model has no confidences)", fontsize=8)
    for ax in axes:
        ax.axis("off")
    return _png(fig)


def make_report(output: Path, queries: List[QueryRecord], num_examples: int = 3,
                thresholds=None, ground_truth: Optional[Dict] = None) -> Path:
    """Write ``output/report.html`` from ``records.jsonl`` (and the run's ``job.json``);
    ``ground_truth`` (name -> cam_from_world or None) defaults to the queries' own."""
    from pipeline.shard import localization_model

    records = read_records(output / "records.jsonl")
    gt = ground_truth if ground_truth is not None else {q.name: q.cam_from_world_gt for q in queries}
    gt = {k: v for k, v in gt.items() if v is not None}
    by = Counter(outcome(r) for r in records)
    parts = [f"<h1>PixLoc localization report</h1><p>{len(records)} queries: {by['refined']} refined, "
             f"{by['rejected']} rejected by verification, {by['failed']} failed (those keep their prior).</p>"]
    if gt:
        summary = evaluate(records, gt, **({"thresholds": thresholds} if thresholds else {}))
        keys = [k for k in summary["all"]["refined"] if k.startswith("recall@")]
        rows = "".join(
            f"<tr><td>{html.escape(name)}</td><td>{which}</td><td>{s[which]['count']}</td>"
            f"<td>{fmt(s[which]['median_t'], '.3f')}</td><td>{fmt(s[which]['median_R'], '.2f')}</td>"
            + "".join(f"<td>{fmt(100 * s[which][k] if s[which][k] is not None else None, '.1f')}%</td>"
                      for k in keys) + "</tr>"
            for name, s in summary.items() for which in ("prior", "refined"))
        parts.append("<h2>Accuracy per condition</h2><table border=1 cellpadding=4><tr><th>condition</th>"
                     "<th>poses</th><th>n</th><th>median t</th><th>median R (deg)</th>"
                     + "".join(f"<th>{html.escape(k)}</th>" for k in keys) + f"</tr>{rows}</table>")
        parts.append(f'<h2>Cumulative errors</h2><img src="data:image/png;base64,{error_curves(summary)}">')
    job = json.loads((output / "job.json").read_text())["job"]
    fconf = dict(job["features"])
    fconf["image_scales"] = tuple(fconf["image_scales"])
    refiner, digest = localization_model(job["model"], "cpu")
    reader = MapReader(job["store"], FeatureConfig(**fconf), digest)
    by_name = {q.name: q for q in queries}
    parts.append("<h2>Examples</h2>")
    for rec in [r for r in records if r["name"] in by_name and r["references"]][:num_examples]:
        figure = example_figure(rec, by_name[rec["name"]], reader, refiner.extractor)
        parts.append(f'<img src="data:image/png;base64,{figure}">')
    path = output / "report.html"
    path.write_text("<!doctype html><html><head><meta charset='utf-8'><title>PixLoc report</title>"
                    "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}img{max-width:100%}"
                    "</style></head><body>" + "".join(parts) + "</body></html>")
    return path


