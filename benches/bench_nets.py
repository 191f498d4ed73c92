"""Networks: forward time and peak memory of the paper model, training step of the small model.

Usage: ``python benches/bench_nets.py [--json PATH] [--quick] [--threads N]``. Rows:

* ``paper encode``: ``VVLocNet.encode`` of one frame (B=1, 4 cameras of 256×448), no grad;
  peak memory = rise of the process's peak RSS during the call (CPU) or
  ``torch.cuda.max_memory_allocated`` (GPU).
* ``paper decode+interact``: decoder + interactor of 4 padded hypotheses (per call).
* ``small encode`` and ``small train step``: one frame, and one optimisation step on a triplet
  (3 frames × 4 cameras of 96×160; triplet + yaw circle + translation bias + hinge losses, Adam).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

from _common import print_table, write_json
from vvloc import losses
from vvloc.nets import ModelConfig, VVLocNet


def _rig(batch: int, cameras: int, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    k = torch.tensor([[w / 2, 0.0, (w - 1) / 2], [0.0, w / 2, (h - 1) / 2], [0.0, 0.0, 1.0]])
    axes = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    ext = torch.eye(4).repeat(batch, cameras, 1, 1)
    for m in range(cameras):
        a = 2 * math.pi * m / cameras
        rz = torch.tensor(
            [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
        )
        ext[:, m, :3, :3] = rz @ axes
        ext[:, m, 2, 3] = 1.5
    return k.expand(batch, cameras, 3, 3).clone(), ext


def _inputs(cfg: ModelConfig, batch: int, cameras: int, device: torch.device):
    gen = torch.Generator().manual_seed(0)
    h, w = cfg.image_height, cfg.image_width
    imgs = torch.randint(0, 256, (batch, cameras, 3, h, w), dtype=torch.uint8, generator=gen)
    intr, ext = _rig(batch, cameras, h, w)
    return imgs.to(device), intr.to(device), ext.to(device)


def _reset_peak_rss() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _rss_mib(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _measure(fn, device: torch.device, repeat: int) -> tuple[float, float]:
    """(median seconds, peak memory MiB of the first call).

    CPU: rise of the peak resident set (VmHWM, reset through /proc/self/clear_refs) over the
    resident set before the first call; GPU: ``max_memory_allocated`` over the allocation before.
    """
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    else:
        _reset_peak_rss()
        base = _rss_mib("VmRSS")
    fn()  # first call, also the warm-up
    if device.type == "cuda":
        torch.cuda.synchronize()
        peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        peak = _rss_mib("VmHWM") - base
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2], peak


def _train_step(model: VVLocNet, opt: torch.optim.Optimizer, batch) -> None:
    imgs, intr, ext, translation, yaw = batch
    out = model.encode(imgs, intr, ext)
    g = out.global_desc.view(3, 1, -1)
    loc = out.local_desc.view(3, 1, *out.local_desc.shape[1:])
    bev = out.bev.view(3, 1, *out.bev.shape[1:])
    ds, dt = losses.aligned_descriptors(model, bev[0], loc[1], translation, yaw)
    cost_neg = losses.matching_cost(*model.interact(loc[0], loc[2]))
    total = (
        losses.triplet_loss(g[0], g[1], g[2])
        + losses.yaw_circle_loss(ds, dt)
        + losses.translation_bias_loss(model, bev[0], loc[1], translation, yaw)
        + losses.hinge_loss(losses.matching_cost(ds, dt), cost_neg)
    )
    opt.zero_grad()
    total.backward()
    opt.step()


def run(device: torch.device, quick: bool) -> list[dict]:
    rows = []
    repeat = 1 if quick else 3
    torch.manual_seed(0)
    small = VVLocNet(ModelConfig.small()).to(device)
    scfg = small.config
    imgs, intr, ext = _inputs(scfg, 1, 4, device)
    small.eval()
    with torch.no_grad():
        sec, mem = _measure(lambda: small.encode(imgs, intr, ext), device, max(repeat, 3))
    rows.append(
        dict(case="small encode (B=1, M=4)", device=device.type, ms=1e3 * sec, peak_mib=mem)
    )
    small.train()
    opt = torch.optim.Adam(small.parameters(), lr=1e-4)
    timgs, tintr, text = _inputs(scfg, 3, 4, device)
    batch = (
        timgs,
        tintr,
        text,
        torch.tensor([[1.0, -0.5]], device=device),
        torch.tensor([0.3], device=device),
    )
    sec, mem = _measure(lambda: _train_step(small, opt, batch), device, max(repeat, 3))
    rows.append(
        dict(
            case="small train step (triplet, 3x4 cams)",
            device=device.type,
            ms=1e3 * sec,
            peak_mib=mem,
        )
    )
    paper = VVLocNet(ModelConfig.paper()).to(device).eval()
    cfg = paper.config
    imgs, intr, ext = _inputs(cfg, 1, 4, device)
    with torch.no_grad():
        sec, mem = _measure(lambda: paper.encode(imgs, intr, ext), device, repeat)
        rows.append(
            dict(case="paper encode (B=1, M=4)", device=device.type, ms=1e3 * sec, peak_mib=mem)
        )
        polar = torch.randn(4, cfg.num_angles, cfg.num_radii, cfg.channels, device=device)
        tgt = torch.randn(4, cfg.num_angles, cfg.channels, device=device)
        sec, mem = _measure(lambda: paper.interact(paper.decode_polar(polar), tgt), device, repeat)
        rows.append(
            dict(case="paper decode+interact (N=4)", device=device.type, ms=1e3 * sec, peak_mib=mem)
        )
    return rows


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quick", action="store_true", help="one timed repetition")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: default)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op threads")
    rows = run(torch.device("cpu"), args.quick)
    if torch.cuda.is_available():
        rows += run(torch.device("cuda"), args.quick)
    for r in rows:
        r["threads"] = torch.get_num_threads()
    print_table(rows, ["case", "device", "threads", "ms", "peak_mib"])
    if args.json:
        write_json(args.json, "nets", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
