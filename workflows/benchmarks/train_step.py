"""Benchmark: training steps per CPU hour on one thread, per change, with what is not the model.

Every variant trains the same pairs (the config's sources, drawn for steps 0 to N by the run's step
sampler, read before timing) from the same initial weights in a fresh process on one torch thread,
after three untimed steps; its figure is the process's CPU seconds per step, turned into steps per
CPU hour. Variants, each adding to the one above: ``today`` (the training step before this work:
glibc's default large blocks, the network in the default memory layout), ``freed memory reused``
(``pipeline.runtime.keep_freed_memory``), ``channels-last`` (the network's activations; the default
now: ``pixloc.training.Trainer``), and ``encoder frozen`` (the steps of a config's
``freeze_encoder_steps``: no gradient for the encoder). Rounds alternate the variants, so that the
machine's drift falls on all of them. Beside them, what is not the model: the CPU milliseconds to
draw a pair of each source (images cached, as after the first pass), which ``workers`` moves to
other processes, and the seconds of one validation pair.
"""

import argparse
import multiprocessing
import time
from pathlib import Path
from typing import Dict, List

import numpy as np
import torch

VARIANTS = ("today", "freed memory reused", "channels-last", "encoder frozen")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="lite0", help="training config whose sources and settings to use")
    p.add_argument("--data-root", type=Path, help="default $PIXLOC_SHARED/data or ../shared/data")
    p.add_argument("--work", type=Path, default=Path("outputs/benchmark-train-step"),
                   help="generated and triangulated training data (kept for reruns)")
    p.add_argument("--steps", type=int, default=30, help="timed steps per variant and round")
    p.add_argument("--rounds", type=int, default=2, help="rounds over the variants")
    p.set_defaults(func=main)


def _setup(args_dict: Dict):
    from workflows.train import StepSampler, load_config
    from workflows.training_sources import load_sources
    run = load_config(args_dict["config"])
    sources, _ = load_sources(list(run.data), args_dict["data_root"], args_dict["work"], run.camera())
    datasets = [s.dataset(run.pairs) for s in sources]
    p = np.array([s.weight for s in sources]) / sum(s.weight for s in sources)
    return run, sources, datasets, StepSampler(datasets, p, run.seed, run.batch_size)


def _variant(variant: str, args_dict: Dict) -> float:
    """CPU seconds per step of ``variant``, in this (fresh) process."""
    from dataclasses import replace
    from pipeline.runtime import keep_freed_memory
    from pixloc.nets.registry import load_refiner
    from pixloc.training import Trainer
    torch.set_num_threads(1)
    level = VARIANTS.index(variant)
    if level >= 1:
        keep_freed_memory()
    run, _, _, sampler = _setup(args_dict)
    steps = args_dict["steps"]
    batches = [sampler(step)[1] for step in range(steps + 3)]
    torch.manual_seed(0)
    conf = replace(run.trainer, freeze_encoder_steps=10 ** 9 if level >= 3 else 0, encoder_lr_scale=1.0)
    trainer = Trainer(load_refiner(run.model), conf, channels_last=level >= 2)
    for batch in batches[:3]:
        trainer.step(batch)
    start = time.process_time()
    for batch in batches[3:]:
        trainer.step(batch)
    return (time.process_time() - start) / steps


def not_the_model(args_dict: Dict) -> Dict[str, float]:
    """Milliseconds (CPU) to draw a pair of each source, images cached; seconds per validation pair."""
    from pixloc.nets.registry import load_refiner
    from pixloc.training import Trainer
    from workflows.train import validate
    torch.set_num_threads(1)
    run, sources, datasets, _ = _setup(args_dict)
    out = {}
    for source, data in zip(sources, datasets):
        rng = np.random.default_rng(0)
        for _ in range(3):
            data.sample(rng)  # reads and caches the images
        start = time.process_time()
        for _ in range(10):
            data.sample(rng)
        out[f"draw a pair: {source.name}"] = 1000 * (time.process_time() - start) / 10
    pairs = datasets[0].fixed(6, seed=0)
    trainer = Trainer(load_refiner(run.model), run.trainer)
    start = time.process_time()
    validate(trainer, pairs)
    out["validation pair (s)"] = (time.process_time() - start) / len(pairs)
    return out


def _in_fresh_process(context, fn, *args):
    """``fn(*args)`` in a new process (glibc's settings are a process's), which then exits by itself."""
    pool = context.Pool(1)
    try:
        return pool.apply(fn, args)
    finally:
        pool.close()
        pool.join()


def main(args: argparse.Namespace) -> int:
    from workflows.training_sources import default_data_root
    args_dict = {"config": args.config, "data_root": args.data_root or default_data_root(), "work": args.work,
                 "steps": args.steps}
    args.work.mkdir(parents=True, exist_ok=True)
    context = multiprocessing.get_context("spawn")
    times: Dict[str, List[float]] = {v: [] for v in VARIANTS}
    for k in range(args.rounds):
        for variant in VARIANTS:
            times[variant].append(_in_fresh_process(context, _variant, variant, args_dict))
            print(f"round {k + 1}: {variant}: {times[variant][-1]:.3f} CPU s per step", flush=True)
    extra = _in_fresh_process(context, not_the_model, args_dict)
    base = np.mean(times["today"])
    print(f"\nconfig {args.config}, {args.steps} steps per variant and round, {args.rounds} rounds, one thread\n")
    print("| variant, each adds to the one above | CPU s per step | steps per CPU hour | vs today |")
    print("| --- | ---: | ---: | ---: |")
    for variant in VARIANTS:
        s = float(np.mean(times[variant]))
        print(f"| {variant} | {s:.3f} | {3600 / s:,.0f} | {base / s:.2f}x |")
    print("\n| not the model | CPU |\n| --- | ---: |")
    for key, value in extra.items():
        print(f"| {key} | {value:.1f} ms |" if "draw" in key else f"| {key} | {value:.2f} s |")
    return 0
