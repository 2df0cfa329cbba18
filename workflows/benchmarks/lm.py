"""Benchmark: LM iterations per second, batched vs one problem at a time.

Synthetic featuremetric problems (random smooth 128-channel feature maps,
points seen by a 640x480 camera at stride 4, reference features sampled at
the true pose, a perturbed initial pose) with a fixed number of iterations
(no early stopping), on the CPU by default. The baseline solves the same
problems one at a time with the same solver; the ratio is the gain of
batching.
"""

import argparse
import time
from typing import List, Tuple

import torch

from pixloc.geometry import Camera, Pose
from pixloc.optim import ConstantDamping, FeaturemetricProblem, LevenbergMarquardt


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--problems", type=int, nargs="+", default=[1, 16], help="batch sizes")
    parser.add_argument("--points", type=int, nargs="+", default=[1000, 10000], help="points per problem")
    parser.add_argument("--channels", type=int, default=128, help="feature channels of the problems")
    parser.add_argument("--iters", type=int, default=10, help="LM iterations per solve")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (best is kept)")
    parser.add_argument("--device", default="cpu", help="torch device")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")


def make_problems(B: int, N: int, C: int, device, seed: int = 0) -> Tuple[FeaturemetricProblem, Pose]:
    g = torch.Generator().manual_seed(seed)
    cam = Camera(torch.tensor([160.0, 120.0, 130.0, 130.0, 79.5, 59.5])).reshape(1).expand(B)
    H, W = 120, 160
    # Smooth random maps: upsampled noise, so that the cost has a basin.
    coarse = torch.randn(B, C, H // 8, W // 8, generator=g)
    F_query = torch.nn.functional.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=False)
    F_query = torch.nn.functional.normalize(F_query, dim=1)
    p2d = torch.rand(B, N, 2, generator=g) * torch.tensor([W - 20.0, H - 20.0]) + 10
    depth = 2 + 3 * torch.rand(B, N, 1, generator=g)
    p3d_cam = torch.cat([(p2d - cam.c[:, None]) / cam.f[:, None], torch.ones_like(depth)], -1) * depth
    T_gt = Pose.identity(B)
    xi = torch.randn(B, 6, generator=g) * torch.tensor([0.03] * 3 + [0.01] * 3)
    T_init = Pose.exp(xi) @ T_gt
    F_ref = torch.nn.functional.grid_sample(
        F_query, (p2d / torch.tensor([W - 1.0, H - 1.0]) * 2 - 1)[:, None], align_corners=True
    )[:, :, 0].transpose(1, 2)
    W_ref = torch.rand(B, N, generator=g)
    W_query = torch.rand(B, H, W, generator=g)
    problem = FeaturemetricProblem(p3d_cam.to(device), F_ref.to(device), F_query.to(device),
                                   cam.to(device), W_ref.to(device), W_query.to(device))
    return problem, T_init.to(device)


def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _time(fn, device, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        best = min(best, time.perf_counter() - t0)
    return best


def run(problems: List[int], points: List[int], C: int, iters: int, repeats: int, device: str):
    solver = LevenbergMarquardt(ConstantDamping(1e-2), num_iters=iters).train()  # train(): no early stop
    rows = []
    for N in points:
        for B in problems:
            problem, T_init = make_problems(B, N, C, device)
            with torch.no_grad():
                t_batched = _time(lambda: solver(problem, T_init), device, repeats)
                singles = [(problem.index(i), T_init[[i]]) for i in range(B)]
                t_single = _time(lambda: [solver(p, t) for p, t in singles], device, repeats)
            rows.append(dict(B=B, N=N, single=B * iters / t_single, batched=B * iters / t_batched,
                             speedup=t_single / t_batched))
    return rows


def main(args: argparse.Namespace) -> int:
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"LM iterations per second (problem-iterations / s), {args.channels} channels, "
          f"{args.iters} iterations per solve, device {args.device}, {torch.get_num_threads()} threads")
    print(f"{'problems':>8} {'points':>7} {'one at a time':>14} {'batched':>10} {'batched / one':>14}")
    for r in run(args.problems, args.points, args.channels, args.iters, args.repeats, args.device):
        print(f"{r['B']:>8} {r['N']:>7} {r['single']:>14.1f} {r['batched']:>10.1f} {r['speedup']:>13.2f}x")
    return 0
