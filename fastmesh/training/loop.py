"""The training loop shared by the three networks.

Single process on CPU, or several through ``torchrun`` (DDP: gloo on CPU, nccl on
GPUs).  Batches are length-bucketed (sequences of similar cost together, padded to
a token budget), the batch schedule is a pure function of (seed, epoch), and each
batch's augmentation is seeded from (seed, epoch, batch index): so resuming from a
checkpoint replays exactly the batches an uninterrupted run would have seen.

Outputs in ``--out``: ``model.safetensors`` + ``config.json`` (latest), ``best/`` (lowest
validation loss), ``train_state.pt`` (optimizer and position, for ``--resume``),
and ``log.jsonl`` (one JSON object per logged step: readable with ``jq`` or pandas).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from ..models.checkpoint import config_from_dict, load_model, save_model
from .augment import AugmentConfig
from .data import MeshDataset, load_dataset
from .prefetch import BatchMaker


@dataclass
class TrainConfig:
    model: dict = field(default_factory=dict)  # overrides of the network's config dataclass
    batch_cost: int = 6000  # padded tokens (vertex) or vertices (face/enhancer) per batch and process
    max_batch: int = 32
    lr: float = 6e-4
    min_lr_ratio: float = 0.1
    weight_decay: float = 0.05
    warmup: int = 200
    steps: int = 20000  # length of the cosine schedule; training stops here or at max_minutes
    max_minutes: float = 0.0  # wall-clock budget (0 = none)
    grad_clip: float = 1.0
    log_every: int = 20
    eval_every: int = 500
    ckpt_every: int = 200
    val_batches: int = 16
    seed: int = 0
    threads: int = 0  # torch intra-op threads (0 = all cores / world size)
    amp: str = "auto"  # "auto" (GPU: bf16 or fp16, CPU: off) | "bf16" | "fp16" | "off"
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    max_vertices: int = 0  # skip training meshes above this (0 = all); the face task's N^2 cost needs it
    workers: int = 0  # processes making training batches ahead of the step (0 = in the training process)


def load_train_config(path: str | None, overrides: dict | None = None) -> TrainConfig:
    d = json.loads(Path(path).read_text()) if path else {}
    d.update(overrides or {})
    return config_from_dict(TrainConfig, d)


def _autocast(device: torch.device, amp: str):
    if amp == "off":
        return contextlib.nullcontext()
    if amp == "auto":
        # On a CPU, float32: without bf16 instructions (our AMD EPYC development machines) bf16 autocast made
        # a vertex-decoder step about 8x slower, and no CPU we train on has them.
        if device.type == "cpu":
            return contextlib.nullcontext()
        amp = "bf16" if torch.cuda.is_bf16_supported() else "fp16"
    dtype = torch.bfloat16 if amp == "bf16" else torch.float16
    return torch.autocast(device_type=device.type, dtype=dtype)


def make_batches(costs: np.ndarray, indices: np.ndarray, budget: int, max_batch: int,
                 rng: np.random.Generator) -> list[np.ndarray]:
    """Length-bucketed batches: sort by cost inside random chunks, cut at the padded budget, shuffle."""
    idx = rng.permutation(indices)
    chunk = max_batch * 50
    batches = []
    for c in range(0, len(idx), chunk):
        part = idx[c:c + chunk]
        part = part[np.argsort(costs[part], kind="stable")]
        cur: list[int] = []
        for i in part:
            longest = max([costs[j] for j in cur] + [costs[i]])
            if cur and (longest * (len(cur) + 1) > budget or len(cur) >= max_batch):
                batches.append(np.array(cur))
                cur = []
            cur.append(int(i))
        if cur:
            batches.append(np.array(cur))
    return [batches[i] for i in rng.permutation(len(batches))]


def _is_main() -> bool:
    return not dist.is_initialized() or dist.get_rank() == 0


def train(task, data: str | MeshDataset, out: str, cfg: TrainConfig, resume: bool = False,
          log=print, init: str | None = None) -> dict:
    """Train ``task`` (see ``training.tasks``) on a dataset cache; return the last log record.

    ``init`` starts from the weights (and network config) of a saved model instead of a
    random initialisation, with a fresh optimizer and schedule: how the shipped weights
    are trained further on new data.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = _device(cfg, world)
    ds = load_dataset(data) if isinstance(data, (str, os.PathLike)) else data
    outdir = Path(out)
    model, state = _start(task, outdir, cfg, resume, init, log)
    model.to(device).train()
    opt = _optimizer(model, cfg, state)
    step, epoch, pos, best = (0, 0, 0, float("inf")) if state is None else (
        state["step"], state["epoch"], state["pos"], state["best"])
    ddp_model = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    train_idx, val_idx = _train_indices(ds, cfg), ds.indices("val")
    costs = task.costs(ds)
    t0 = time.time()
    last_log, items, record = time.time(), 0, {}
    logs = _Log(outdir, cfg, log)
    stop = False
    with BatchMaker(task, ds, cfg, cfg.workers) as maker:
        while not stop:
            batches = make_batches(costs, train_idx, cfg.batch_cost, cfg.max_batch,
                                   np.random.default_rng([cfg.seed, epoch]))
            for batch in maker.epoch(batches[rank::world], epoch, pos, rank):
                loss, n, gnorm = _step(task, ddp_model, model, opt, batch, _lr_at(cfg, step), cfg, device)
                step, pos, items = step + 1, pos + 1, items + n
                if step % cfg.log_every == 0 and _is_main():
                    now = time.time()
                    record = {"step": step, "epoch": epoch, "loss": round(loss.item(), 5), "lr": _lr_at(cfg, step),
                              "grad_norm": round(float(gnorm), 4),
                              "items_per_s": round(items * world / (now - last_log), 1),
                              "elapsed_s": round(now - t0, 1)}
                    last_log, items = now, 0
                    logs.write(record)
                out_of_time = cfg.max_minutes and (time.time() - t0) > cfg.max_minutes * 60
                finished = step >= cfg.steps or out_of_time
                if step % cfg.eval_every == 0 or finished:
                    val = evaluate(task, ddp_model, ds, val_idx, costs, cfg, device)
                    model.train()
                    if _is_main():
                        record = {"step": step, "epoch": epoch, "val": val, "elapsed_s": round(time.time() - t0, 1)}
                        best = _validated(model, task, outdir, logs, record, best)
                if (step % cfg.ckpt_every == 0 or finished) and _is_main():
                    _checkpoint(model, task, opt, outdir, {"step": step, "epoch": epoch, "pos": pos, "best": best})
                if finished:
                    stop = True
                    break
            if not stop:
                epoch, pos = epoch + 1, 0
    logs.close()
    if world > 1:
        dist.barrier()
    return record


def _device(cfg: TrainConfig, world: int) -> torch.device:
    """This process's device (its rank's GPU, else the CPU with ``cfg.threads`` torch threads, by default the
    cores shared out among ``world`` processes), the process group joined when there are several."""
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    if torch.cuda.is_available():
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
        return device
    torch.set_num_threads(cfg.threads or max(1, (os.cpu_count() or 1) // world))
    return torch.device("cpu")


def _start(task, outdir: Path, cfg: TrainConfig, resume: bool, init: str | None, log) -> tuple:
    """(the model on the CPU, the saved optimizer and position or None): resumed from ``outdir``, started from
    ``init``, or built fresh from ``cfg.model`` with seed ``cfg.seed``."""
    state_path = outdir / "train_state.pt"
    if resume and state_path.exists():
        model, _ = load_model(outdir, device="cpu")
        return model, torch.load(state_path, map_location="cpu", weights_only=False)
    torch.manual_seed(cfg.seed)  # same initial weights on every run (and every rank) with the same seed
    model = task.build_model(cfg.model)
    if init:
        model = _init_from(task, model, init, bool(cfg.model), log)
    return model, None


def _optimizer(model, cfg: TrainConfig, state: dict | None) -> torch.optim.AdamW:
    """AdamW with weight decay on the matrices that are not embeddings, none on the rest; its state resumed
    from ``state`` where there is one."""
    decay = [p for n, p in model.named_parameters() if p.ndim >= 2 and "emb" not in n]
    no_decay = [p for n, p in model.named_parameters() if not (p.ndim >= 2 and "emb" not in n)]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": cfg.weight_decay},
                             {"params": no_decay, "weight_decay": 0.0}], lr=cfg.lr, betas=(0.9, 0.95))
    if state is not None:
        opt.load_state_dict(state["optimizer"])
    return opt


def _train_indices(ds: MeshDataset, cfg: TrainConfig) -> np.ndarray:
    """The training split's items, without those over ``cfg.max_vertices`` vertices where it is set."""
    train_idx = ds.indices("train")
    if cfg.max_vertices:
        train_idx = train_idx[ds.num_vertices()[train_idx] <= cfg.max_vertices]
    return train_idx


def _lr_at(cfg: TrainConfig, s: int) -> float:
    """The learning rate of step ``s``: linear warm-up, then cosine down to ``cfg.min_lr_ratio``."""
    if s < cfg.warmup:
        return cfg.lr * (s + 1) / cfg.warmup
    t = min(1.0, (s - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _step(task, ddp_model, model, opt, batch: dict, lr: float, cfg: TrainConfig, device: torch.device) -> tuple:
    """One optimiser step on ``batch`` at learning rate ``lr``; returns (loss, items, gradient norm)."""
    for g in opt.param_groups:
        g["lr"] = lr
    batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
    with _autocast(device, cfg.amp):
        loss, n = task.loss(ddp_model, batch)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    opt.step()
    return loss, n, gnorm


def _validated(model, task, outdir: Path, logs: _Log, record: dict, best: float) -> float:
    """Log a validation ``record``; the model saved as ``best/`` where its loss beats ``best``.  The best loss."""
    logs.write(record)
    if record["val"]["loss"] < best:
        save_model(model, task.kind, outdir / "best", extra={"train": {"step": record["step"], "val": record["val"]}})
        return record["val"]["loss"]
    return best


def _checkpoint(model, task, opt, outdir: Path, position: dict) -> None:
    """The model and ``train_state.pt`` (optimizer, step, epoch, pos, best) written so a run resumes exactly."""
    save_model(model, task.kind, outdir, extra={"train": {"step": position["step"]}})
    state_path = outdir / "train_state.pt"
    torch.save({"optimizer": opt.state_dict(), **position}, str(state_path) + ".tmp")
    os.replace(str(state_path) + ".tmp", state_path)


class _Log:
    """``log.jsonl`` in the run's folder (the main process only, which also writes ``train_config.json``)
    and the ``log`` callback, each record as one JSON line."""

    def __init__(self, outdir: Path, cfg: TrainConfig, log):
        self.log, self.file = log, None
        if _is_main():
            outdir.mkdir(parents=True, exist_ok=True)
            (outdir / "train_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
            self.file = open(outdir / "log.jsonl", "a")

    def write(self, record: dict) -> None:
        self.file.write(json.dumps(record) + "\n")
        self.file.flush()
        self.log(json.dumps(record))

    def close(self) -> None:
        if self.file:
            self.file.close()


def _init_from(task, model, init: str, have_config: bool, log):
    """The model to start from for ``--init``.

    Without a network config the saved network is used as it is.  With one (``--config``)
    the configured network keeps its fresh initialisation except for every tensor the saved
    network has under the same name and shape: so an architecture change (say anchored
    encoder queries) still starts from the trained decoder layers and embeddings.
    """
    saved, meta = load_model(init, device="cpu")
    if meta["kind"] != task.kind:
        raise ValueError(f"--init {init} holds a {meta['kind']} network, not {task.kind}")
    if not have_config:
        return saved
    own, theirs = model.state_dict(), saved.state_dict()
    taken = {k: v.to(own[k].dtype) for k, v in theirs.items() if k in own and own[k].shape == v.shape}
    model.load_state_dict(taken, strict=False)
    fresh = sorted(set(own) - set(taken))
    if _is_main():
        log(json.dumps({"init": init, "tensors_loaded": len(taken), "tensors_fresh": fresh}))
    return model


@torch.no_grad()
def evaluate(task, model, ds: MeshDataset, val_idx: np.ndarray, costs: np.ndarray, cfg: TrainConfig,
             device: torch.device) -> dict:
    """Mean validation loss over a fixed set of batches (no augmentation, fixed seeds)."""
    model.eval()
    if len(val_idx) == 0:
        return {"loss": float("nan")}
    batches = make_batches(costs, val_idx, cfg.batch_cost, cfg.max_batch, np.random.default_rng(12345))
    total, count = 0.0, 0
    for i, b in enumerate(batches[: cfg.val_batches]):
        batch = {k: v.to(device) for k, v in task.make_batch(ds, b, np.random.default_rng(i), cfg,
                                                              train=False).items()}
        with _autocast(device, cfg.amp):
            loss, n = task.loss(model, batch)
        total += float(loss) * n
        count += n
    out = {"loss": round(total / max(count, 1), 5)}
    if hasattr(task, "evaluate"):  # optional task metrics (e.g. edge precision/recall/F1 of the face model)
        out.update(task.evaluate(model, ds, val_idx, cfg, device))
    return out
