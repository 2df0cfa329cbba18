"""``pixloc train``: end-to-end training from a YAML config (data sources, schedule), with
per-step metrics in CSV, validation, curves, checkpoints, exact resume and model export.

Output folder::

    config.yaml        the resolved configuration
    metrics.csv        one row per step: losses, reprojection errors in pixels, gradient norm, time
    validation.csv     one row per validation: median reprojection error and recall of fixed pairs
    curves.png         training loss and validation error against steps
    checkpoint.pt      the last checkpoint (model, optimiser, step, torch random state, wall time);
                       the pairs of step k are drawn from a generator seeded by (seed, k)
    model.pt           the model in the project's format, loadable with --model PATH
    model_best.pt      the model at the validation with the lowest median error (best.json: which)
    data/              generated synthetic scenes and triangulations
"""

import argparse
import csv
import json
import logging
import platform
import time
from dataclasses import asdict, dataclass, field, fields, replace
from importlib import resources
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import yaml

from pipeline.runtime import keep_freed_memory
from pipeline.textfiles import read_yaml
from pipeline.scene import CameraRecord
from pipeline.data.training_data import PairConfig, PairDataset
from pixloc.nets.registry import load_refiner, save_model
from pixloc.training import Trainer, TrainConfig, reprojection_px

from .locks import output_lock
from .options import at_least, build, check_keys
from .training_sources import SYNTHETIC, default_data_root, load_sources

logger = logging.getLogger(__name__)
TRAIN_KEYS = ("error_px/init", "error_px", "total", "reprojection_error/init", "reprojection_error/0",
              "reprojection_error/1", "reprojection_error/2", "grad_norm", "lr")
VAL_KEYS = ("error_px_init_median", "error_px_median", "recall_1px", "recall_5px", "loss")


@dataclass(frozen=True)
class TrainingRun:
    """A training run as its YAML config says. The config is flat: the run's own keys (these
    fields), the optimiser's by ``pixloc.training.TrainConfig``'s names (``lr``, ``ema``,
    ``num_iters`` ...) and the pairs' by ``pipeline.data.training_data.PairConfig``'s (``max_size``,
    ``init_range`` ...); each default lives in its dataclass alone, and any other key is refused
    with the nearest valid name.

    data, validation, held_out_sources: source entries (``load_sources``); held_out: the names
    kept out of training, for the model card. steps: total steps; decay_steps: where a cosine
    schedule ends (default ``steps``). batch_size: pairs per step; workers: data loading
    processes. val_pairs, val_every, checkpoint_every: validation and checkpoint cadence.
    synthetic_camera: the camera of synthetic scenes (model, width, height, params)."""

    data: Tuple[Dict, ...] = ()
    validation: Tuple[Dict, ...] = ()
    held_out: Tuple[str, ...] = ()
    held_out_sources: Tuple[Dict, ...] = ()
    description: str = ""
    architecture: str = "lite0"
    model: str = "lite0-imagenet"
    steps: int = 1000
    decay_steps: Optional[int] = None
    seed: int = 0
    batch_size: int = 1
    workers: int = 0
    val_pairs: int = 24
    val_every: int = 100
    checkpoint_every: int = 100
    synthetic_camera: Tuple[str, int, int, Tuple[float, ...]] = ("PINHOLE", 320, 240, (250.0, 250.0, 160.0, 120.0))
    trainer: TrainConfig = field(default_factory=TrainConfig)
    pairs: PairConfig = field(default_factory=PairConfig)

    def __post_init__(self):
        # before: a run with steps 0 or lr 0 started preparing its data (minutes of SIFT), then failed or did nothing
        problems = [f"{k} {v} (at least 1)" for k, v in (
            ("steps", self.steps), ("batch_size", self.batch_size), ("val_every", self.val_every),
            ("checkpoint_every", self.checkpoint_every), ("num_iters", self.trainer.num_iters),
            ("decay_steps", 1 if self.decay_steps is None else self.decay_steps)) if v < 1]
        problems += [f"{k} {v} (not negative)" for k, v in (("workers", self.workers), ("val_pairs", self.val_pairs))
                     if v < 0]
        problems += [] if self.trainer.lr > 0 else [f"lr {self.trainer.lr} (positive)"]
        camera = self.camera().check()
        problems += [f"synthetic_camera: {camera}"] if camera else []
        if problems:
            raise ValueError(f"training: {', '.join(problems)}.")

    @classmethod
    def from_dict(cls, config: Dict, where: str = "training config") -> "TrainingRun":
        nested = {"trainer": {f.name for f in fields(TrainConfig)} - {"total_steps"},
                  "pairs": {f.name for f in fields(PairConfig)}}
        own = {f.name for f in fields(cls)} - set(nested)
        check_keys(config, own | nested["trainer"] | nested["pairs"], where)
        names = {next((f"{n}.{k}" for n, keys in nested.items() if k in keys), k): k for k in config}
        try:
            run = build(cls, {key: config[k] for key, k in names.items()}, where=where, names=names)
        except ValueError as e:  # the range checks of __post_init__ do not know the file
            if str(e).startswith(where):
                raise
            raise ValueError(f"{where}: {str(e).removeprefix('training: ')}") from None
        return replace(run, trainer=replace(run.trainer, total_steps=run.decay_steps or run.steps))

    def to_dict(self) -> Dict:
        """The flat config, every key resolved (written to the run folder as config.yaml)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("trainer", "pairs")}
        out.update({k: v for k, v in asdict(self.trainer).items() if k != "total_steps"})
        out.update(asdict(self.pairs))
        return _plain(out)

    def camera(self) -> CameraRecord:
        """The camera of the synthetic scenes."""
        m, w, h, params = self.synthetic_camera
        return CameraRecord(m, int(w), int(h), tuple(params))


def _plain(value):
    """Tuples as lists, for YAML."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def load_config(spec: str, overrides: Optional[Dict] = None) -> TrainingRun:
    """A config file, or the name of a packaged one (workflows/presets/training/NAME.yaml), with
    ``overrides`` (flat keys, as the command line sets them) on top."""
    path = Path(spec)
    if not path.is_file():
        packaged = resources.files(__package__) / "presets" / "training" / f"{spec}.yaml"
        if not packaged.is_file():
            raise ValueError(f"Training config {spec!r} is neither a file nor a packaged config.")
        path = Path(str(packaged))
    config = read_yaml(path, "training config")
    return TrainingRun.from_dict({**config, **(overrides or {})}, f"training config {path}")


class StepSampler:
    """The pairs of each training step, drawn from a generator seeded by (seed, step) alone: the
    same pairs in-process or in any worker process, and after a resume."""

    def __init__(self, datasets: List[PairDataset], p: np.ndarray, seed: int, batch_size: int = 1):
        self.datasets, self.p, self.seed, self.batch_size = datasets, p, seed, batch_size

    def __call__(self, step: int):
        """(source index, pairs) of step ``step`` (counted from 0); one source per step."""
        rng = np.random.default_rng([self.seed, step])
        k = int(rng.choice(len(self.datasets), p=self.p))
        return k, [self.datasets[k].sample(rng) for _ in range(self.batch_size)]


class _Steps(torch.utils.data.IterableDataset):
    def __init__(self, sampler: StepSampler, start: int, stop: int):
        self.sampler, self.start, self.stop = sampler, start, stop

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        n, i = (info.num_workers, info.id) if info else (1, 0)
        for step in range(self.start + i, self.stop, n):  # the loader takes workers in turn: steps in order
            yield self.sampler(step)


def _as_is(x):
    return x


def step_batches(sampler: StepSampler, start: int, stop: int, workers: int = 0):
    """The batches of steps [start, stop), read in ``workers`` processes (0: in this one)."""
    if workers <= 0:
        return (sampler(step) for step in range(start, stop))
    return torch.utils.data.DataLoader(_Steps(sampler, start, stop), batch_size=None, num_workers=workers,
                                       collate_fn=_as_is, prefetch_factor=4, persistent_workers=False)


def validate(trainer: Trainer, pairs) -> Dict[str, float]:
    """Median reprojection errors (pixels) and recall at 1 and 5 px of fixed pairs (with the
    averaged weights, when the config averages them)."""
    init, final, losses = [], [], []
    with torch.no_grad(), trainer.averaged() as model:
        model.eval()
        for batch in pairs:
            batch = batch.to(trainer.device)
            pred = model(batch, num_iters=trainer.conf.num_iters)
            losses.append(float(model.loss(pred, batch)["total"].mean()))
            init.append(float(reprojection_px(batch.query_from_ref_init, batch).mean()))
            final.append(float(reprojection_px(pred["query_from_ref"][-1], batch).mean()))
    final_a = np.array(final)
    return {"error_px_init_median": float(np.median(init)), "error_px_median": float(np.median(final_a)),
            "recall_1px": float((final_a < 1).mean()), "recall_5px": float((final_a < 5).mean()),
            "loss": float(np.mean(losses))}


class CsvLog:
    """Rows appended to a CSV file; on resume, rows after the checkpoint's step are dropped."""

    def __init__(self, path: Path, keys, resume_step: int):
        self.path, self.keys = path, ("step", "time") + tuple(keys)
        rows = []
        if resume_step and path.is_file():
            with open(path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, self.keys)
            w.writeheader()
            w.writerows(rows)

    def write(self, row: Dict) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.keys, extrasaction="ignore").writerow(row)


def read_csv(path: Path) -> Dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    def number(v):
        try:
            return float(v)
        except (TypeError, ValueError):
            return np.nan
    return {k: np.array([number(r[k]) for r in rows]) for k in (rows[0].keys() if rows else []) if k != "source"}


def plot_curves(out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    train, val = read_csv(out / "metrics.csv"), read_csv(out / "validation.csv")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    if len(train.get("step", [])):
        k = max(1, min(50, len(train["step"]) // 10))
        smooth = np.convolve(train["total"], np.ones(k) / k, mode="valid")
        axes[0].plot(train["step"], train["total"], color="0.8", lw=0.5, label="loss (per step)")
        axes[0].plot(train["step"][k - 1:], smooth, color="C0", label=f"loss (mean of {k})")
        axes[0].set_yscale("log")
    axes[0].set_xlabel("step")
    axes[0].set_title("training loss")
    axes[0].legend()
    if len(val.get("step", [])):
        axes[1].plot(val["step"], val["error_px_median"], "o-", label="refined")
        axes[1].plot(val["step"], val["error_px_init_median"], "--", color="0.5", label="initial pose")
        axes[1].set_yscale("log")
    axes[1].set_xlabel("step")
    axes[1].set_title("validation: median reprojection error (px)")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)
    return out / "curves.png"


def contact_sheet(run: TrainingRun, out: Path, data_root: Path, pairs_per_source: int = 2, seed: int = 0) -> Path:
    """``out/contact_sheet.jpg``: sampled training pairs of every source of ``run`` (and its
    validation), each as reference | query, the pair's points at the truth in the reference
    (green) and in the query at the initial pose (red) and at the truth (green)."""
    import cv2
    pconf = run.pairs
    sources, _ = load_sources(list(run.data + run.validation), data_root, out / "data", run.camera())
    rng = np.random.default_rng(seed)
    rows, size = [], pconf.max_size

    def draw(image, camera, T, p3d, mask, colour):
        p2d, valid = camera.cam2image(T.transform(p3d))
        for x, y in p2d[0][(valid & mask)[0]].numpy()[::4]:
            cv2.circle(image, (int(x), int(y)), 1, colour, -1)

    for src in sources:
        ds = src.dataset(pconf)
        for _ in range(pairs_per_source):
            b = ds.sample(rng)
            tiles = []
            for image, camera, poses in ((b.image_ref, b.camera_ref, [(None, (0, 200, 0))]),
                                         (b.image_query, b.camera_query, [(b.query_from_ref_init, (230, 30, 30)),
                                                                          (b.query_from_ref_gt, (0, 200, 0))])):
                im = np.ascontiguousarray((image[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8))
                for T, colour in poses:
                    if T is None:
                        T = type(b.query_from_ref_gt).from_Rt(torch.eye(3), torch.zeros(3)).reshape(1)
                    draw(im, camera, T, b.p3d_ref, b.mask_points, colour)
                canvas = np.full((size, size, 3), 255, np.uint8)
                canvas[:im.shape[0], :im.shape[1]] = im[:size, :size]
                tiles.append(canvas)
            row = np.concatenate(tiles, 1)
            cv2.putText(row, src.name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
            rows.append(row)
    sheet = np.concatenate([np.concatenate(rows[k:k + 2] + [np.full_like(rows[0], 255)] * (2 - len(rows[k:k + 2])), 1)
                            for k in range(0, len(rows), 2)], 0)
    path = out / "contact_sheet.jpg"
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
    return path


def train(run, out: Path, data_root: Path, resume: bool = True, threads: int = 0) -> Dict:
    """Train (or resume) as ``run`` (a ``TrainingRun``, or its flat config) says; returns the final
    validation metrics. Two runs at once into one ``out`` are refused (its lock): they would write
    over each other's checkpoint."""
    if not isinstance(run, TrainingRun):
        run = TrainingRun.from_dict(run)
    with output_lock(out):
        return _train(run, out, data_root, resume, threads)


def _train(run: "TrainingRun", out: Path, data_root: Path, resume: bool, threads: int) -> Dict:
    keep_freed_memory()  # a step frees and allocates the same large blocks: reuse them
    if threads:
        torch.set_num_threads(threads)
    (out / "config.yaml").write_text(yaml.safe_dump(run.to_dict(), sort_keys=False))
    model, arch = run.model, run.architecture
    pconf, camera = run.pairs, run.camera()
    sources, skipped = load_sources(list(run.data), data_root, out / "data", camera)
    if not sources:
        raise ValueError("No training data: every source of the config is missing.")
    datasets = [s.dataset(pconf) for s in sources]
    p = np.array([s.weight for s in sources]) / np.sum([s.weight for s in sources])
    sampler = StepSampler(datasets, p, run.seed, run.batch_size)
    workers = run.workers
    val_sources, _ = load_sources(list(run.validation), data_root, out / "data", camera)
    val_pairs = [b for s in val_sources for b in s.dataset(pconf).fixed(run.val_pairs, seed=0)]

    refiner = load_refiner(model)
    tconf = run.trainer
    trainer = Trainer(refiner, tconf)
    torch.manual_seed(run.seed)
    wall = 0.0
    ckpt_path = out / "checkpoint.pt"
    if resume and ckpt_path.is_file():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        trainer.load_state_dict(state["trainer"])
        wall = float(state["wall_time"])
        logger.info("Resumed from %s at step %d.", ckpt_path, trainer.step_count)
    start = trainer.step_count
    train_log = CsvLog(out / "metrics.csv", TRAIN_KEYS + ("source",), start)
    val_log = CsvLog(out / "validation.csv", VAL_KEYS, start)
    steps = run.steps
    val_every, ckpt_every = run.val_every, run.checkpoint_every
    info = {"architecture": arch, "init": model, "data": [s.name for s in sources], "skipped_data": skipped,
            "held_out": list(run.held_out), "max_size": pconf.max_size, "lr": tconf.lr, "ema": tconf.ema,
            "hardware": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
                        f"{tconf.device}"
                        + (f" ({torch.cuda.get_device_name()})" if tconf.device.startswith("cuda") else "")}

    def checkpoint():
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save({"trainer": trainer.state_dict(), "wall_time": wall}, tmp)
        tmp.replace(ckpt_path)
        with trainer.averaged() as model:
            save_model(model, arch, out / "model.pt",
                       {**info, "steps": trainer.step_count, "wall_time_s": round(wall, 1), "validation": last_val})

    best_path = out / "best.json"
    best = json.loads(best_path.read_text()) if start and best_path.is_file() else {}
    if best.get("step", 0) > start:  # the best of a future that the resume dropped
        best = {}

    def keep_if_best(step: int, val: Dict[str, float]) -> None:
        if best and val["error_px_median"] >= best["error_px_median"]:
            return
        best.clear()
        best.update({"step": step, **val})
        with trainer.averaged() as model:
            save_model(model, arch, out / "model_best.pt",
                       {**info, "steps": step, "wall_time_s": round(wall, 1), "validation": val})
        best_path.write_text(json.dumps(best, indent=1))

    last_val: Dict[str, float] = {}
    if start == 0 and val_pairs:
        last_val = validate(trainer, val_pairs)
        val_log.write({"step": 0, "time": 0.0, **last_val})
        keep_if_best(0, last_val)
    from tqdm import tqdm
    progress = tqdm(range(start, steps), initial=start, total=steps, desc="training", unit="step",
                    disable=None)
    batches = iter(step_batches(sampler, start, steps, workers))
    for _ in progress:
        t0 = time.perf_counter()
        k, pairs = next(batches)
        metrics = trainer.step(pairs)
        wall += time.perf_counter() - t0
        train_log.write({**metrics, "time": round(wall, 2), "source": sources[k].name})
        progress.set_postfix(loss=f"{metrics['total']:.3g}", px=f"{metrics['error_px']:.2f}")
        step = trainer.step_count
        if val_pairs and (step % val_every == 0 or step == steps):
            t0 = time.perf_counter()
            last_val = validate(trainer, val_pairs)
            wall += time.perf_counter() - t0
            val_log.write({"step": step, "time": round(wall, 2), **last_val})
            logger.info("step %d: validation median error %.2f px (initial %.2f px), recall@1px %.2f",
                        step, last_val["error_px_median"], last_val["error_px_init_median"],
                        last_val["recall_1px"])
            keep_if_best(step, last_val)
        if step % ckpt_every == 0 or step == steps:
            checkpoint()
    if trainer.step_count == start:  # nothing to do: keep the outputs consistent anyway
        checkpoint()
    plot_curves(out)
    return last_val


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="lite0", help="YAML config file, or a packaged one's name (default lite0)")
    p.add_argument("--output", type=Path, required=True, help="run folder (resumed if it has a checkpoint)")
    p.add_argument("--data-root", type=Path, default=None,
                   help="folder of the real data sources (default $PIXLOC_SHARED/data or ../shared/data)")
    p.add_argument("--steps", type=int, help="total steps (overrides the config)")
    p.add_argument("--lr", type=float, help="learning rate (overrides the config)")
    p.add_argument("--max-size", type=at_least(16), help="longer image side (overrides the config)")
    p.add_argument("--synthetic-only", action="store_true", help="use only the config's synthetic sources")
    p.add_argument("--grad-checkpointing", action="store_true", help="trade compute for memory")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--contact-sheet", action="store_true",
                   help="only write OUTPUT/contact_sheet.jpg: sampled pairs of every source, to check them by eye")
    p.add_argument("--threads", type=at_least(0), default=0, help="torch threads (default: torch's choice)")
    p.add_argument("--device", help="cpu or cuda (overrides the config; default cpu)")
    p.add_argument("--amp", action="store_true", help="on a GPU: the network in bfloat16 autocast")
    p.add_argument("--batch-size", type=int, help="pairs per step (overrides the config; default 1)")
    p.add_argument("--workers", type=int, help="data loading processes (overrides the config; default 0)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    overrides = {key: getattr(args, key) for key in ("steps", "lr", "max_size", "device", "batch_size", "workers")
                 if getattr(args, key) is not None}
    overrides.update({key: True for key in ("grad_checkpointing", "amp") if getattr(args, key)})
    run = load_config(args.config, overrides)
    from .executor import check_device
    check_device(run.trainer.device)
    from .logs import colmap_to_file
    colmap_to_file(args.output)  # the SfM and triangulation of map sources log there, not on the terminal
    if args.synthetic_only:
        run = replace(run, data=tuple(d for d in run.data if d["kind"] == SYNTHETIC))
    if args.contact_sheet:
        print(f"contact sheet: {contact_sheet(run, args.output, args.data_root or default_data_root())}")
        return 0
    val = train(run, args.output, args.data_root or default_data_root(), resume=not args.restart,
                threads=args.threads)
    print(f"model: {args.output / 'model.pt'}  curves: {args.output / 'curves.png'}")
    if val:
        print(f"validation: median error {val['error_px_median']:.2f} px (initial {val['error_px_init_median']:.2f}"
              f" px), recall@1px {val['recall_1px']:.2f}, recall@5px {val['recall_5px']:.2f}")
    return 0
