"""Speed of the force models (SetTransformerLSTM, 256 points x the config's features, T = 16): the network
of `configs/<model>.yaml`, the paper's `proposed` (default) or the project's smaller `visionforce`.
Inference runs through `ForceRegressor` with the config's `symmetry_turns` (visionforce: each clip and its
mirror, two network passes per prediction), as `train.py test` and `vfdata predict` run it.

Prints, for each variant (eager / torch.compile, fp32 / bf16 autocast, fused / unfused attention):
- inference throughput, batched (frames/s; target >= 2,000 on 2 CPU cores),
- single-clip latency (ms per 16-frame clip, batch 1),
- training throughput (frames/s, forward + backward + AdamW step; target >= 400 on 2 CPU cores).

    python bench/bench_models.py [--model proposed|visionforce] [--threads 2] [--device cpu|cuda] [--quick]

Timings on a shared machine vary with its load: the script prints the load average next to them.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time

import torch
import yaml
from torch.nn.attention import SDPBackend, sdpa_kernel

from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.training.config_files import CONFIGS

T, N = 16, 256


def config_args(model: str) -> tuple[dict, int]:
    """The SetTransformerLSTM arguments and the `symmetry_turns` of a training config (`configs/<model>.yaml`)."""
    config = yaml.safe_load((CONFIGS / f"{model}.yaml").read_text())
    return dict(config["model"]["model"]["init_args"]), int(config["model"].get("symmetry_turns", 0))


def clips(batch: int, channels: int, device: str) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {
        "tokens": torch.randn(batch, T, N, channels, generator=g).to(device),
        "valid": (torch.rand(batch, T, N, generator=g) > 0.1).to(device),
        "force": torch.randn(batch, T, 3, generator=g).to(device),
    }


def timed(fn, min_seconds: float, device: str, warmup: int = 2) -> tuple[float, float]:
    """(wall seconds per call: median of repeated timings after warm-up; CPU seconds per call of
    this process divided by the threads, i.e. the wall time it would take with the cores to itself)."""
    for _ in range(warmup):
        fn()
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    sync()
    times, start, cpu_start = [], time.perf_counter(), time.process_time()
    while time.perf_counter() - start < min_seconds or len(times) < 3:
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    cpu = (time.process_time() - cpu_start) / len(times) / torch.get_num_threads()
    times.sort()
    return times[len(times) // 2], cpu


def precision(bf16: bool, device: str):
    return torch.autocast(device, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()


def attention(fused: bool):
    return contextlib.nullcontext() if fused else sdpa_kernel(SDPBackend.MATH)


def bench_variant(compiled: bool, bf16: bool, fused: bool, args) -> dict[str, float]:
    torch.manual_seed(0)
    network, turns = config_args(args.model)
    model = SetTransformerLSTM(**network).to(args.device)
    run = torch.compile(model) if compiled else model
    regressor = ForceRegressor(model, symmetry_turns=turns)
    object.__setattr__(regressor, "_compiled", run)  # as ForceRegressor(compile_model=True) holds it
    channels = network["in_features"]
    out = {}

    regressor.eval()
    batch = clips(args.batch, channels, args.device)
    single = clips(1, channels, args.device)
    with torch.inference_mode(), precision(bf16, args.device), attention(fused):
        s, cpu = timed(lambda: regressor(batch), args.seconds, args.device)
        out["infer_fps"], out["infer_fps_cpu"] = args.batch * T / s, args.batch * T / cpu
        s, cpu = timed(lambda: regressor(single), args.seconds, args.device)
        out["latency_ms"], out["latency_ms_cpu"] = s * 1e3, cpu * 1e3

    regressor.train()
    optimiser = regressor.configure_optimizers()
    train_batch = clips(args.train_batch, channels, args.device)

    def step():
        with precision(bf16, args.device), attention(fused):
            loss = regressor._loss(run(train_batch["tokens"], train_batch["valid"]), train_batch["force"])
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()

    s, cpu = timed(step, args.seconds, args.device)
    out["train_fps"], out["train_fps_cpu"] = args.train_batch * T / s, args.train_batch * T / cpu
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=["proposed", "visionforce"], default="proposed",
                        help="whose network: configs/<model>.yaml (default proposed)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch", type=int, default=16, help="clips per inference batch")
    parser.add_argument("--train-batch", type=int, default=16, help="clips per training batch")
    parser.add_argument("--seconds", type=float, default=5.0, help="minimum timing per figure")
    parser.add_argument("--quick", action="store_true", help="eager and compiled fp32 fused only")
    parser.add_argument("--variant", choices=[f"{c}-{p}-{a}" for c in ("eager", "compiled") for p in ("fp32", "bf16")
                                              for a in ("fused", "math")], help="only this variant")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_float32_matmul_precision("high")
    variants = [(False, False, True), (True, False, True)]
    if not args.quick:
        variants += [(False, False, False), (False, True, True), (True, True, True)]
    if args.variant:
        compiled, precision_name, attn = args.variant.split("-")
        variants = [(compiled == "compiled", precision_name == "bf16", attn == "fused")]
    device_name = torch.cuda.get_device_name() if args.device == "cuda" else f"CPU, {args.threads} threads"
    network, turns = config_args(args.model)
    print(
        f"SetTransformerLSTM of configs/{args.model}.yaml, clips of T={T} frames x N={N} points x "
        f"C={network['in_features']}, {max(1, 2 * turns)} view(s) per prediction; {device_name}; "
        f"inference batch {args.batch} clips, training batch {args.train_batch} clips"
    )
    print("wall figures, and in brackets the same from this process's CPU time / threads (what the cores "
          "would give it alone; on a loaded machine the wall figures are lower)")
    print(f"{'variant':34}{'infer frames/s':>22}{'1-clip ms':>18}{'train frames/s':>20}{'load avg':>10}")
    for compiled, bf16, fused in variants:
        name = ", ".join(
            [
                "compiled" if compiled else "eager",
                "bf16" if bf16 else "fp32",
                "fused attn" if fused else "math attn",
            ]
        )
        r = bench_variant(compiled, bf16, fused, args)
        load = os.getloadavg()[0]
        infer = f"{r['infer_fps']:.0f} ({r['infer_fps_cpu']:.0f})"
        latency = f"{r['latency_ms']:.1f} ({r['latency_ms_cpu']:.1f})"
        train = f"{r['train_fps']:.0f} ({r['train_fps_cpu']:.0f})"
        print(f"{name:34}{infer:>22}{latency:>18}{train:>20}{load:>10.1f}", flush=True)
    print(
        "targets (2 CPU cores): inference >= 2,000 frames/s; training >= 400 frames/s; "
        "paper: 37,000 frames/s on an RTX A5000"
    )


if __name__ == "__main__":
    main()
