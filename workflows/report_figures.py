"""The figures of the localization report, as base64 images: cumulative error curves, the top
view of the map, and the example figures (projections, features, confidence, convergence)."""

import base64
import io
import re
import textwrap
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from pipeline.evaluate import fmt, pose_errors, record_errors
from pipeline.store.reader import MapReader
from pipeline.queries import QueryRecord
from pipeline.localization.results import REJECTED, outcome, record_pose


def natural_key(text: str) -> List:
    """Sort key that orders 'seq-2' before 'seq-10'."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _png(fig, fmt: str = "png", tight: bool = True) -> str:
    """The figure as base64 PNG (plots), or JPEG (figures with photos: a tenth of the bytes)."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=80, bbox_inches="tight" if tight else None,
                **({"pil_kwargs": {"quality": 85}} if fmt == "jpeg" else {}))
    _plt().close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _colors(n: int) -> List:
    cmap = _plt().get_cmap("tab10" if n <= 10 else "tab20")
    return [cmap(i % cmap.N) for i in range(n)]


def _log_axis(ax, values: np.ndarray) -> None:
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    v = values[np.isfinite(values) & (values > 0)]
    lo, hi = (np.percentile(v, 0) * 0.8, v.max() * 1.25) if len(v) else (1e-3, 1.0)
    lo = max(lo, hi * 1e-5)
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    decades = np.log10(hi / lo)
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0,) if decades > 3 else (1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def error_curves(summary: Dict, keys: Sequence[str], units: str) -> str:
    """Cumulative distributions of camera-centre and rotation errors, one colour per condition:
    result solid, prior dashed. Queries without a pose never reach the curve's top."""
    plt = _plt()
    from matplotlib.lines import Line2D
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    handles = []
    allv = [[], []]
    for key, color in zip(keys, _colors(len(keys))):
        s = summary[key]
        for which, style in (("errors", "-"), ("prior_errors", "--")):
            e = np.asarray(s[which], float).reshape(-1, 2)
            for col, ax in enumerate(axes):
                v = np.sort(e[:, col])
                y = np.arange(1, len(v) + 1) / max(len(v), 1)
                finite = np.isfinite(v)
                ax.step(np.maximum(v[finite], 1e-6), y[finite], style, color=color, where="post", lw=1.4)
                allv[col].append(v)
        handles.append(Line2D([], [], color=color, lw=2, label=f"{key.split('=', 1)[-1]} (n={s['refined']['count']})"))
    handles += [Line2D([], [], color="k", ls="-", label="result"), Line2D([], [], color="k", ls="--", label="prior")]
    for col, (ax, label) in enumerate(zip(axes, (f"camera centre error ({units})", "rotation error (deg)"))):
        _log_axis(ax, np.concatenate(allv[col]) if allv[col] else np.zeros(0))
        ax.set_ylim(0, 1.02)
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of queries")
        ax.grid(alpha=0.3, which="both")
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.tight_layout()
    return _png(fig)


def _centre(T) -> np.ndarray:
    T = np.asarray(T, np.float64)
    return -T[:, :3].T @ T[:, 3]


def query_errors(rec: Optional[Dict], T_gt) -> Dict[str, Optional[float]]:
    """The errors of ``pipeline.evaluate.record_errors`` as table cells: ``t``, ``R`` (the result),
    ``refined_t``, ``refined_R``, ``prior_t``, ``prior_R``; None where undefined."""
    if T_gt is None:
        return {k: None for k in ("t", "R", "refined_t", "refined_R", "prior_t", "prior_R")}
    clean = (lambda x: x if np.isfinite(x) else None)
    e = record_errors(rec, T_gt)
    return {f"{prefix}{axis}": clean(value) for which, prefix in (("result", ""), ("refined", "refined_"),
                                                                  ("prior", "prior_"))
            for axis, value in zip("tR", e[which])}


def refinement_confidence(rec: Dict) -> Optional[float]:
    """Verification confidence of a refinement (None for a query that was not refined)."""
    return rec.get("confidence") if rec.get("refined") is not None else None


def _up_and_plane(reader: MapReader) -> Tuple[np.ndarray, np.ndarray]:
    """A (2, 3) basis of the ground plane (up: the mean of the reference cameras' up vectors)."""
    R = reader.cam_from_world[:, :, :3]
    up = -R[:, 1, :].mean(0)
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up)
    centres = np.stack([_centre(T) for T in reader.cam_from_world])
    flat = centres - centres.mean(0)
    flat -= np.outer(flat @ up, up)
    _, _, vt = np.linalg.svd(flat if len(flat) > 1 else np.eye(3), full_matrices=False)
    e1 = vt[0] - (vt[0] @ up) * up
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1)]), up


def top_view(reader: MapReader, records: List[Dict], gt: Dict, family: Optional[str], units: str) -> str:
    """Map points (subsampled), reference cameras, and per query its prior (x), result (a filled dot
    where verified, an open square where the prior is kept) and ground truth (*): prior to result
    dashed, result to ground truth solid black; queries coloured by their tag of ``family``. Left:
    the whole map; right: the region of the cameras."""
    plt = _plt()
    from matplotlib.lines import Line2D
    basis, _ = _up_and_plane(reader)
    refs = np.stack([_centre(T) for T in reader.cam_from_world]) @ basis.T
    rng = np.random.default_rng(0)
    pts = reader.xyz[rng.permutation(len(reader.xyz))[:6000]] @ basis.T if len(reader.xyz) else np.zeros((0, 2))
    values = sorted({r.get("tags", {}).get(family, "") for r in records}, key=natural_key) if family else [""]
    color = dict(zip(values, _colors(len(values))))
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6))
    anchor = [refs]
    for ax in axes:
        ax.scatter(pts[:, 0], pts[:, 1], s=1.5, c="0.65", lw=0, rasterized=True)
        ax.scatter(refs[:, 0], refs[:, 1], s=14, marker="^", c="k", lw=0)
    for r in records:
        c = color[r.get("tags", {}).get(family, "") if family else ""]
        prior = _centre(r["prior"]) @ basis.T if r["prior"] is not None else None
        res = _centre(record_pose(r)) @ basis.T if record_pose(r) is not None else None
        g = _centre(gt[r["name"]]) @ basis.T if gt.get(r["name"]) is not None else None
        if g is not None:
            anchor.append(g[None])
        for ax in axes:
            if prior is not None and res is not None:
                ax.plot(*np.stack([prior, res]).T, "--", color=c, lw=0.7)
            if res is not None and g is not None:
                ax.plot(*np.stack([res, g]).T, "-", color="k", lw=0.7)
            if prior is not None:
                ax.scatter(*prior, marker="x", s=22, color=c, lw=1)
            if res is not None and r["success"]:  # a verified refinement: a filled dot
                ax.scatter(*res, marker="o", s=24, color=c, edgecolors="k", lw=0.6)
            elif res is not None:  # no verified refinement: the prior is reported, an open square
                ax.scatter(*res, marker="s", s=30, facecolors="none", edgecolors=c, lw=1.0)
            if g is not None:
                ax.scatter(*g, marker="*", s=40, facecolors="none", edgecolors=c, lw=0.8)
    a = np.concatenate(anchor)
    for ax, (lo, hi), title in (
            (axes[0], (np.minimum(a.min(0), np.percentile(pts, 2, 0)), np.maximum(a.max(0), np.percentile(pts, 98, 0)))
             if len(pts) > 10 else (a.min(0), a.max(0)), "the map"),
            (axes[1], (a.min(0), a.max(0)), "the cameras")):
        pad = 0.08 * max(float((hi - lo).max()), 1e-3)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(units)
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.2)
    handles = [Line2D([], [], ls="", marker="^", color="k", label="reference cameras"),
               Line2D([], [], ls="", marker="x", color="0.3", label="prior"),
               Line2D([], [], ls="", marker="o", color="0.3", markeredgecolor="k", label="result: verified refinement"),
               Line2D([], [], ls="", marker="s", markerfacecolor="none", color="0.3",
                      label="result: prior kept (rejected or failed)"),
               Line2D([], [], ls="", marker="*", markerfacecolor="none", color="0.3", label="ground truth"),
               Line2D([], [], ls="--", color="0.3", lw=0.8, label="prior to result (the refinement's move)"),
               Line2D([], [], ls="-", color="k", lw=0.8, label="result to ground truth (the error)")]
    if family:
        handles += [Line2D([], [], ls="", marker="o", color=color[v], label=f"{family}={v}") for v in values]
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.tight_layout()
    return _png(fig)


def _project(camera, T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    p = torch.from_numpy(xyz @ T[:, :3].T + T[:, 3])
    p2d, valid = camera.to_pixloc(torch.float64).cam2image(p)
    p2d, valid = p2d.numpy(), valid.numpy()
    inside = valid & (p2d[:, 0] >= 0) & (p2d[:, 1] >= 0) & (p2d[:, 0] < camera.width) & (p2d[:, 1] < camera.height)
    return p2d[inside]


def _level_poses(record: Dict) -> List[Tuple[str, np.ndarray]]:
    steps = [("prior", np.asarray(record["prior"]))] if record["prior"] is not None else []
    for lv in record.get("per_level") or []:
        if lv.get("pose") is not None:
            steps.append((f"s{lv['scale']} L{lv['level']}", np.asarray(lv["pose"])))
    return steps


def example_figure(record: Dict, why: str, query: QueryRecord, reader: MapReader, net, T_gt, units: str) -> str:
    """Top: the query with the points of its references projected at the prior (red), refined
    (green) and ground-truth (blue) poses; the finest features (3 PCA components); the finest
    confidence. Bottom: the cost at the start and end of each level, and the error of each
    level's pose against ground truth (its update from the previous level without one)."""
    plt = _plt()
    from pipeline.images import resize_max, to_tensor
    from pipeline.localization.shard import fit_query

    query, rgb = fit_query(query)
    dbs = [reader.index[n] for n in record["references"] if n in reader.index]
    obs = reader.observations(dbs, 1)
    xyz = reader.xyz[np.unique(obs.point)]
    xyz = xyz[np.random.default_rng(0).permutation(len(xyz))[:600]]
    fig = plt.figure(figsize=(14, 7.4))
    grid = fig.add_gridspec(2, 3, height_ratios=(1.25, 1))
    ax = fig.add_subplot(grid[0, 0])
    ax.imshow(rgb)
    for T, color, label in ((record["prior"], "red", "prior"), (record["refined"], "lime", "refined"),
                            (T_gt, "deepskyblue", "ground truth")):
        if T is not None:
            p = _project(query.camera, np.asarray(T), xyz)
            ax.scatter(p[:, 0] + 0.5, p[:, 1] + 0.5, s=3, c=color, label=label, lw=0)
    ax.set_xlim(0, rgb.shape[1])
    ax.set_ylim(rgb.shape[0], 0)
    ax.legend(loc="lower right", fontsize=7, markerscale=3)
    ax.axis("off")
    e = query_errors(record, T_gt)
    err = (f"error {fmt(e['t'], '.3f')} {units} / {fmt(e['R'], '.2f')} deg, prior {fmt(e['prior_t'], '.3f')} / "
           f"{fmt(e['prior_R'], '.2f')}" if T_gt is not None else "no ground truth")
    status = outcome(record) + (f": {record['reason'].removeprefix(REJECTED)}" if record["reason"] else "")
    fig.suptitle(textwrap.fill(f"{status}; confidence {fmt(refinement_confidence(record), '.2f')}; {err}", 150),
                 fontsize=10)
    with torch.no_grad():
        pred = net(to_tensor(resize_max(rgb, 512)[0])[None])
    f = pred["features"][0][0]
    flat = f.reshape(f.shape[0], -1).T
    flat = flat - flat.mean(0)
    _, _, V = torch.pca_lowrank(flat, q=3)
    pca = (flat @ V).reshape(f.shape[1], f.shape[2], 3).numpy()
    pca = (pca - pca.min((0, 1))) / (np.ptp(pca, (0, 1)) + 1e-9)
    ax = fig.add_subplot(grid[0, 1])
    ax.imshow(pca)
    ax.set_title("finest features (3 PCA components)", fontsize=9)
    ax.axis("off")
    ax = fig.add_subplot(grid[0, 2])
    if "confidences" in pred:
        im = ax.imshow(pred["confidences"][0][0, 0].numpy(), cmap="viridis", vmin=0, vmax=1)
        fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02, label="confidence")
        ax.set_title("finest confidence", fontsize=9)
    else:
        ax.set_title("(this model has no confidences)", fontsize=9)
    ax.axis("off")

    levels = record.get("per_level") or []
    ax = fig.add_subplot(grid[1, 0])
    if levels:
        x = np.arange(len(levels))
        ax.plot(x, [lv.get("cost_start", np.nan) for lv in levels], "o--", color="0.5", label="start of level")
        ax.plot(x, [lv.get("cost_end", np.nan) for lv in levels], "o-", color="C0", label="end of level")
        ax.set_xticks(x, [f"s{lv['scale']} L{lv['level']}\n{lv['iterations']} it" for lv in levels], fontsize=8)
        costs = [lv.get(k) for lv in levels for k in ("cost_start", "cost_end")]
        if all(c is not None and c > 0 for c in costs):
            ax.set_yscale("log")
        ax.legend(fontsize=7)
    ax.set_title("robust cost per level (coarse to fine)", fontsize=9)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(grid[1, 1])
    steps = _level_poses(record)
    if steps:
        x = np.arange(len(steps))
        if T_gt is not None:
            errs = np.array([pose_errors(T, T_gt) for _, T in steps])
            what = "error against ground truth"
        else:
            errs = np.array([(0.0, 0.0)] + [pose_errors(b, a) for (_, a), (_, b) in zip(steps, steps[1:])])
            what = "update from the previous level"
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.plot(x, errs[:, 0], "o-", color="C1", label=f"t ({units})")
        ax.set_ylabel(f"t ({units})", color="C1", fontsize=8)
        twin = ax.twinx()
        twin.ticklabel_format(axis="y", useOffset=False)
        twin.plot(x, errs[:, 1], "s-", color="C2", label="R (deg)")
        twin.set_ylabel("R (deg)", color="C2", fontsize=8)
        ax.set_xticks(x, [s for s, _ in steps], fontsize=8)
        ax.set_title(f"pose per level: {what}", fontsize=9)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(grid[1, 2])
    ax.axis("off")
    ax.text(0, 1, evidence_text(record), va="top", fontsize=7.5, family="monospace")
    fig.subplots_adjust(left=0.05, right=0.95, top=0.9, bottom=0.08, wspace=0.3, hspace=0.25)  # tight_layout: 4x slower
    return _png(fig, "jpeg", tight=False)


# the verification evidence (pipeline.localization.verify), as a reader would name it: (key, label, value format)
EVIDENCE_LABELS = (
    ("confidence", "confidence", "{:.2f}"),
    ("contrast_3px", "cost lower than 3 px away", "{:.1%}"),
    ("valid", "points in view", "{:.0%}"),
    ("inliers", "inliers of the robust cost", "{:.0%}"),
    ("weighted_inliers", "  weighted by confidence", "{:.0%}"),
    ("move_t", "moved from the prior", "{:.2f} depths"),
    ("move_R", "turned from the prior", "{:.1f} deg"),
    ("last_t", "moved at the finest level", "{:.3f} depths"),
    ("last_R", "turned at the finest level", "{:.2f} deg"))


def evidence_text(record: Dict, width: int = 44) -> str:
    """The evidence panel of an example: readable names with units, then points, references (one a
    line, shortened to ``width``) and time; never wider than the panel."""
    import textwrap

    ev = {**(record.get("evidence") or {}), "confidence": record.get("confidence")}
    lines = ["evidence"]
    for key, label, spec in EVIDENCE_LABELS:
        v = ev.get(key)
        if isinstance(v, (int, float)) and np.isfinite(v):
            lines.append(f"{label:<27}{spec.format(v)}")
    lines.append(f"{'map points':<27}{record.get('num_points')}")
    lines.append(f"{'time':<27}{fmt(record.get('timings', {}).get('total'), '.2f')} s")
    lines.append("references")
    lines += [textwrap.shorten(name, width, placeholder="...") if len(name) <= width else "..." + name[-(width - 3):]
              for name in record["references"][:3]]
    return "\n".join(line[:width + 4] for line in lines)


def threshold_tradeoff(records: List[Dict], gt: Dict, threshold: Tuple[float, float]
                       ) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """What a minimum confidence c keeps, over the refined queries with ground truth: (c, precision,
    recall, right) with precision the fraction of the accepted refinements within ``threshold``
    (distance, degrees) and recall the fraction of the right refinements accepted; ``right`` is
    how many are right. None without a refined query that has ground truth."""
    rows = []
    for r in records:
        if r.get("refined") is None or gt.get(r["name"]) is None or r.get("confidence") is None:
            continue
        t, R = record_errors(r, gt[r["name"]])["refined"]
        rows.append((float(r["confidence"]), t <= threshold[0] and R <= threshold[1]))
    if not rows:
        return None
    conf, right = np.array([c for c, _ in rows]), np.array([g for _, g in rows])
    cs = np.linspace(0, 1, 101)
    kept = conf[None, :] >= cs[:, None]
    n_kept = kept.sum(1)
    good = (kept & right[None, :]).sum(1)
    precision = np.where(n_kept > 0, good / np.maximum(n_kept, 1), np.nan)
    recall = good / right.sum() if right.any() else np.full(len(cs), np.nan)
    return cs, precision, recall, int(right.sum())


def tradeoff_figure(curves, threshold: Tuple[float, float], min_confidence: float, units: str) -> str:
    """Precision and recall of verification against the minimum confidence, the run's marked."""
    plt = _plt()
    cs, precision, recall, right = curves
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    ax.plot(cs, precision, label="precision (accepted that are right)", color="tab:blue")
    ax.plot(cs, recall, label=f"recall (right that are accepted, of {right})", color="tab:orange")
    ax.axvline(min_confidence, color="k", ls="--", lw=1, label=f"this run: {min_confidence:g}")
    ax.set_xlabel("minimum confidence")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"right: refined within {threshold[0]:g} {units}, {threshold[1]:g} deg", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return _png(fig)
