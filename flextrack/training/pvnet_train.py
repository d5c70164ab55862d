"""The training loop: render views once, then train on composited patches, resumably.

The run is bounded by steps and by wall time, whichever comes first; the learning rate follows a
cosine over that progress, so a run cut short by its time budget still ends with a low rate.
State (network, optimiser, sampler RNG, loss history, elapsed time) is checkpointed every
`save_every_s` seconds and at the end, so `--resume` continues where a run stopped.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from estimators.objects import ObjectModel
from flextrack.training.pvnet_data import PatchSampler, RenderedViews, render_views, room_textures, targets
from flextrack.training.pvnet_model import PvnetNet


@dataclass
class TrainConfig:
    steps: int = 8000
    batch: int = 16
    size: int = 128  # training patch side, network-input px
    seed: int = 0
    views: int = 4000  # object-only renders
    minutes: float = 55.0  # wall-time budget for the optimisation
    lr: float = 2e-3
    width: int = 32  # channel width of the network
    turn_deg: float = 45.0  # in-plane turn augmentation, +- degrees
    threads: int = 2
    save_every_s: float = 60.0


def pvnet_loss(out: torch.Tensor, mask: torch.Tensor, vec: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mask BCE + smooth-L1 on the unit vectors inside the true mask (PVNet's losses)."""
    seg = F.binary_cross_entropy_with_logits(out[:, 0], mask)
    weight = mask[:, None]
    vl = F.smooth_l1_loss(out[:, 1:] * weight, vec * weight, reduction="sum")
    vl = vl / (weight.sum() * vec.shape[1] + 1.0)
    return seg, vl


def lr_at(progress: float, base: float) -> float:
    warm = min(1.0, progress / 0.02)
    return base * warm * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0))))


def train(obj: ObjectModel, out_dir: Path, cfg: TrainConfig, resume: bool = False, tqdm=None,
          init: Path | None = None) -> Path:
    """Trains and returns the checkpoint path; out_dir receives views.npz, checkpoint.pt, log.json.

    `init`: a checkpoint whose network weights start a new run (fine-tuning; ignored on resume).
    """
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = out_dir / "checkpoint.pt"
    views_path = out_dir / "views.npz"

    if views_path.exists():
        views = RenderedViews.load(views_path)
    else:
        bar = tqdm(total=cfg.views, desc="render views") if tqdm else None
        views = render_views(obj.model_path, obj.keypoints, obj.diameter_m, cfg.views, cfg.seed,
                             progress=bar.update if bar else None)
        if bar:
            bar.close()
        views.save(views_path)
    if views.keypoints.shape[1] != len(obj.keypoints):
        raise ValueError(f"{views_path} has {views.keypoints.shape[1]} keypoints, the object {len(obj.keypoints)}")

    net = PvnetNet(len(obj.keypoints), cfg.width)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sampler = PatchSampler(views, cfg.size, cfg.seed + 1, room_textures(), turn_deg=cfg.turn_deg)
    state = {"step": 0, "elapsed_s": 0.0, "history": []}
    if resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, weights_only=False)
        net.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sampler.rng.bit_generator.state = ck["sampler_rng"]
        state = ck["state"]
    elif init is not None:
        net.load_state_dict(torch.load(init, weights_only=False, map_location="cpu")["model"])
        state["init"] = str(init)

    def save():
        torch.save({"model": net.state_dict(), "optimizer": opt.state_dict(), "sampler_rng": sampler.rng.bit_generator.state,
                    "state": state, "config": asdict(cfg), "keypoints_O": obj.keypoints,
                    "object_model": str(obj.model_path), "diameter_m": obj.diameter_m}, ckpt_path)
        (out_dir / "log.json").write_text(json.dumps({"config": asdict(cfg), **state}))

    budget_s = cfg.minutes * 60.0
    progress = lambda: max(state["step"] / cfg.steps, state["elapsed_s"] / budget_s)
    bar = tqdm(total=cfg.steps, initial=state["step"], desc="train", mininterval=5) if tqdm else None
    net.train()
    last_save = time.monotonic()
    t_prev = time.monotonic()
    run = None  # running means for the progress bar
    while progress() < 1.0:
        imgs, masks, kps = sampler.batch(cfg.batch)
        m, v = targets(masks, kps)
        x = torch.from_numpy(imgs).permute(0, 3, 1, 2).float() / 255.0
        for g in opt.param_groups:
            g["lr"] = lr_at(progress(), cfg.lr)
        out = net(x)
        seg, vl = pvnet_loss(out, torch.from_numpy(m), torch.from_numpy(v))
        opt.zero_grad()
        (seg + vl).backward()
        opt.step()
        now = time.monotonic()
        state["elapsed_s"] += now - t_prev
        t_prev = now
        state["step"] += 1
        cur = {"seg": seg.item(), "vec": vl.item()}
        run = cur if run is None else {k: 0.98 * run[k] + 0.02 * cur[k] for k in cur}
        if state["step"] % 25 == 0:
            state["history"].append([state["step"], state["elapsed_s"], seg.item(), vl.item()])
        if bar:
            bar.update(1)
            bar.set_postfix(seg=f"{run['seg']:.4f}", vec=f"{run['vec']:.4f}", lr=f"{opt.param_groups[0]['lr']:.1e}")
        if now - last_save > cfg.save_every_s:
            save()
            last_save = now
    if bar:
        bar.close()
    save()
    return ckpt_path


def plot_loss(history: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = np.asarray(history, dtype=float).reshape(-1, 4)
    fig, ax = plt.subplots(figsize=(7, 4))
    if len(h):
        k = max(1, len(h) // 50)
        smooth = lambda y: np.convolve(y, np.ones(k) / k, mode="valid")
        ax.semilogy(h[:, 0], h[:, 2], alpha=0.25, color="C0")
        ax.semilogy(h[:, 0], h[:, 3], alpha=0.25, color="C1")
        ax.semilogy(h[k - 1:, 0], smooth(h[:, 2]), color="C0", label="mask BCE")
        ax.semilogy(h[k - 1:, 0], smooth(h[:, 3]), color="C1", label="vector smooth-L1")
        ax.legend()
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
