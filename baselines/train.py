"""One training loop for the baselines: CPU or CUDA (AMP), one process or DDP under `torchrun`.

RUN_DIR gets config.json (the resolved config), run.json (data folder, processes, per-process and
effective batch size, micro-batches accumulated per step, the schedule and where its epochs came from,
the dataset's target parameters), log.jsonl (one line per logged step; the losses
are means over the processes) and checkpoint.pt (every epoch: model, optimiser, scheduler, scaler and
every rank's RNG state, so that `resume=True` continues exactly where the run stopped). Only rank 0
writes.

Checkpoints are written atomically and carry the sha256 of their content; the one they replace is kept
as checkpoint.prev.pt. They load with weights_only=True (a crafted file cannot run code), and a damaged
one is never loaded: resume falls back to checkpoint.prev.pt, saying so in one line.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import pickle
import random
import time
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler

from baselines.config import PAPER_EPOCHS, Config
from baselines.data import Batch, PreparedDataset, collate, dataset_range
from baselines.models import build, check_backbone_weights, without_pretrained_weights
from pipeline import io
from pipeline.manifest import check_targets, dataset_targets

console = Console(stderr=True)
CHECKPOINT, PREVIOUS = "checkpoint.pt", "checkpoint.prev.pt"


def lr_factor(step: int, total_steps: int, config: Config) -> float:
    """Linear warm-up from warmup_ratio, then cosine decay to min_lr_ratio (mmcv's CosineAnnealing)."""
    train = config.train
    progress = min(step / max(total_steps, 1), 1.0)
    cosine = train.min_lr_ratio + (1 - train.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))
    if step < train.warmup_iters:
        cosine *= train.warmup_ratio + (1 - train.warmup_ratio) * step / train.warmup_iters
    return cosine


def build_optimizer(model: torch.nn.Module, config: Config) -> torch.optim.AdamW:
    train = config.train
    backbone, rest = [], []
    for name, parameter in model.named_parameters():
        if parameter.requires_grad:
            (backbone if name.startswith("encoder.camera.backbone.") else rest).append(parameter)
    groups = [{"params": rest, "lr": train.lr}]
    if backbone:  # MapTR trains the pretrained image backbone at a tenth of the learning rate
        groups.append({"params": backbone, "lr": train.lr * train.backbone_lr_mult})
    return torch.optim.AdamW(
        groups, lr=train.lr, betas=train.betas, eps=train.eps, weight_decay=train.weight_decay
    )


def rng_state() -> dict:
    name, keys, position, has_gauss, cached = np.random.get_state()
    return {  # plain types and tensors only: checkpoints load with weights_only=True (no pickle)
        "python": random.getstate(),
        "numpy": [name, keys.tolist(), position, has_gauss, cached],
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    name, keys, position, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.array(keys, np.uint32), position, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def amp_settings(device: torch.device, enabled: bool) -> tuple[torch.dtype | None, bool]:
    """(autocast dtype or None, whether a GradScaler is needed)."""
    if device.type != "cuda" or not enabled:
        return None, False
    if torch.cuda.is_bf16_supported():
        return torch.bfloat16, False
    return torch.float16, True


class CheckpointError(ValueError):
    """A checkpoint that is missing, damaged or refused; the message names the file, in one line."""


def content_digest(state: object) -> str:
    """sha256 of a checkpoint's content: every tensor's dtype, shape and bytes, every plain value."""
    digest = hashlib.sha256()

    def feed(value: object) -> None:
        if isinstance(value, torch.Tensor):
            flat = value.detach().cpu().contiguous().reshape(-1)
            digest.update(f"tensor {flat.dtype} {tuple(value.shape)};".encode())
            digest.update(flat.view(torch.uint8).numpy())
        elif isinstance(value, dict):
            digest.update(f"dict {len(value)};".encode())
            for key, item in value.items():
                feed(key)
                feed(item)
        elif isinstance(value, list | tuple):
            digest.update(f"list {len(value)};".encode())
            for item in value:
                feed(item)
        else:
            digest.update(f"{type(value).__name__} {value!r};".encode())

    feed(state)
    return digest.hexdigest()


def save_checkpoint(state: dict, path: Path) -> None:
    """`state` and its sha256 to `path`, atomically; the file it replaces becomes checkpoint.prev.pt."""
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save({**state, "sha256": content_digest(state)}, tmp)
    if path.exists():
        os.replace(path, path.with_name(PREVIOUS))
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    """The content of a checkpoint written by save_checkpoint, on the CPU, once its sha256 matches.
    weights_only=True: tensors and plain values only, so that a crafted file cannot run code."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        needs = [line.strip() for line in str(error).splitlines() if "GLOBAL" in line]
        raise CheckpointError(
            f"{path}: refused: it holds objects other than tensors and plain values, which are never "
            f"unpickled ({needs[0] if needs else 'not a plain checkpoint'})"
        ) from error
    except Exception as error:  # torch raises RuntimeError, EOFError, ... on a damaged file
        first = str(error).splitlines()[0].split(". ")[0] if str(error) else type(error).__name__
        raise CheckpointError(f"{path}: unreadable, truncated or not a checkpoint ({first})") from error
    if not isinstance(checkpoint, dict) or "sha256" not in checkpoint:
        raise CheckpointError(f"{path}: no checksum: not a checkpoint of this version of cli train")
    if content_digest({k: v for k, v in checkpoint.items() if k != "sha256"}) != checkpoint["sha256"]:
        raise CheckpointError(f"{path}: corrupted: its content does not match the sha256 stored in it")
    return checkpoint


def resume_checkpoint(out_dir: Path, master: bool) -> dict:
    """checkpoint.pt, or checkpoint.prev.pt (said in one line) when checkpoint.pt is missing or damaged;
    the damaged file is moved to checkpoint.bad.pt, so that the next save does not keep it as previous."""
    try:
        return load_checkpoint(out_dir / CHECKPOINT)
    except CheckpointError as error:
        if not (out_dir / PREVIOUS).is_file():
            raise
        checkpoint = load_checkpoint(out_dir / PREVIOUS)
        if master:
            notice = f"{error}; resuming from {PREVIOUS} (epoch {checkpoint['epoch']})"
            console.print(notice, soft_wrap=True, markup=False, highlight=False)  # one line, as it is
            if (out_dir / CHECKPOINT).exists():
                os.replace(out_dir / CHECKPOINT, out_dir / "checkpoint.bad.pt")
        return checkpoint


def setup_process(config: Config) -> tuple[torch.device, int, int]:
    """(device, rank, world size): DDP when `torchrun` set WORLD_SIZE > 1 (NCCL on CUDA, gloo on CPU)."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1:
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    rank = dist.get_rank() if world_size > 1 else 0
    if torch.cuda.is_available():
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
        torch.backends.cudnn.benchmark = True
        # TF32 for the fp32 matrix products and convolutions that autocast leaves in fp32; the geometry
        # (camera projection, sampling grids, curves) is not a matrix product (pipeline/camera.py)
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    else:
        device = torch.device("cpu")
    if config.train.threads:
        torch.set_num_threads(config.train.threads)
    config.train.micro_batches(world_size)  # a batch size that does not split is refused before any work
    return device, rank, world_size


def use_dataset_schedule(config: Config, data_dir: Path) -> str:
    """train.epochs 0 (the paper preset) takes the paper's schedule of the prepared dataset's kind
    (PAPER_EPOCHS); returns where the epochs came from, for run.json and the report."""
    if config.train.epochs:
        return "set (preset or --epochs)"
    manifest = Path(data_dir) / "manifest.json"
    kind = json.loads(manifest.read_text()).get("dataset") if manifest.is_file() else None
    if kind not in PAPER_EPOCHS:
        raise ValueError(f"{manifest}: no dataset kind (nuscenes or av2) to take the paper's schedule from: "
                         "give --epochs")  # fmt: skip
    config.train.epochs = PAPER_EPOCHS[kind]
    return f"the paper's {kind} schedule"


def use_dataset_range(config: Config, data_dir: Path, master: bool) -> None:
    """The BEV grid covers what the dataset was cropped to, at the preset's cell size (the tiny
    preset's 40 x 20 cells of 1.5 m over 30 x 60 m become 67 x 33 over 50 x 100 m)."""
    crop = dataset_range(data_dir)
    encoder = config.encoder
    if crop is None or (tuple(encoder.x_range), tuple(encoder.y_range)) == crop:
        return
    (x0, x1), (y0, y1) = encoder.x_range, encoder.y_range
    cell_w, cell_h = (x1 - x0) / encoder.bev_w, (y1 - y0) / encoder.bev_h
    (new_x0, new_x1), (new_y0, new_y1) = crop
    bev_w, bev_h = max(1, round((new_x1 - new_x0) / cell_w)), max(1, round((new_y1 - new_y0) / cell_h))
    if master:
        console.print(f"BEV grid from the dataset: x {crop[0]}, y {crop[1]} m in {bev_h} x {bev_w} cells "
                        f"(the preset had x {encoder.x_range}, y {encoder.y_range} in {encoder.bev_h} x "
                        f"{encoder.bev_w})")  # fmt: skip
    encoder.x_range, encoder.y_range, encoder.bev_w, encoder.bev_h = crop[0], crop[1], bev_w, bev_h


@dataclass
class Trainer:
    """What one training step needs, and the state a checkpoint keeps."""

    model: torch.nn.Module  # the model itself (what the checkpoint stores)
    trained: torch.nn.Module  # the model, or its DDP wrapper (what the step calls)
    criterion: torch.nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LambdaLR
    scaler: torch.amp.GradScaler
    autocast_dtype: torch.dtype | None
    device: torch.device
    grad_clip: float
    step: int = 0

    def train_step(self, batches: list[Batch]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """One optimiser step on the micro-batches of one batch: their gradients add up, each loss weighted
        by 1 / their number (as mmcv's GradientCumulativeOptimizerHook; one batch of them all when they
        hold as many targets, up to BatchNorm). Returns the losses (their mean over the micro-batches,
        detached; on the device, unsynchronised) and the gradient norm before clipping."""
        self.optimizer.zero_grad(set_to_none=True)
        dtype, weight = self.autocast_dtype, 1.0 / len(batches)
        mean: dict[str, torch.Tensor] = {}
        for index, batch in enumerate(batches):
            batch = batch.to(self.device)
            # DDP averages the gradients over the processes once, in the last micro-batch's backward
            accumulating = index < len(batches) - 1 and isinstance(self.trained, DistributedDataParallel)
            with self.trained.no_sync() if accumulating else nullcontext():
                with torch.autocast(self.device.type, dtype=dtype) if dtype else nullcontext():
                    outputs = self.trained(batch.sensors)
                losses = self.criterion(outputs, batch.targets)
                self.scaler.scale(losses["loss"] * weight).backward()
            for name, value in losses.items():
                mean[name] = mean.get(name, 0.0) + value.detach() * weight
        self.scaler.unscale_(self.optimizer)
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        self.step += 1
        return mean, grad_norm

    def save(self, path: Path, epoch: int, config: Config, rng_states: list[dict]) -> None:
        checkpoint = {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(),
            "epoch": epoch,
            "step": self.step,
            "rng": rng_states,
            "config": config.to_dict(),
        }
        save_checkpoint(checkpoint, path)

    def load(self, checkpoint: dict, rank: int) -> int:
        """Restore the state of a loaded checkpoint; returns the epoch to start from."""
        if len(checkpoint["rng"]) <= rank:
            raise CheckpointError(
                f"the checkpoint holds the RNG states of {len(checkpoint['rng'])} process(es): resume with "
                "as many (torchrun --nproc_per_node)"
            )
        self.model.load_state_dict(checkpoint["model"])
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        self.scheduler.load_state_dict(checkpoint["scheduler"])
        self.scaler.load_state_dict(checkpoint["scaler"])
        set_rng_state(checkpoint["rng"][rank])
        self.step = checkpoint["step"]
        return checkpoint["epoch"]


def mean_losses(losses: dict[str, torch.Tensor], distributed: bool) -> dict[str, torch.Tensor]:
    """The losses averaged over the processes (detached): with the normalisers summed over processes
    (blocks.mean_over_processes), the loss of the whole batch, as one process would compute it."""
    values = torch.stack([value.detach().float() for value in losses.values()])
    if distributed:
        dist.all_reduce(values)
        values /= dist.get_world_size()
    return dict(zip(losses, values, strict=True))


def logged_lines(path: Path) -> list[str]:
    """The complete lines of a log (a kill can cut the last one short)."""
    return [line for line in path.read_text().splitlines(keepends=True) if line.endswith("\n")]


def all_rng_states(distributed: bool) -> list[dict]:
    if not distributed:
        return [rng_state()]
    states: list = [None] * dist.get_world_size()
    dist.all_gather_object(states, rng_state())
    return states


@dataclass
class Setup:
    """Everything `train` sets up before its first step (`setup`)."""

    config: Config
    trainer: Trainer
    dataset: PreparedDataset
    sampler: DistributedSampler
    loader: DataLoader  # micro-batches; `accumulate` of them make one optimiser step
    accumulate: int
    total_steps: int  # optimiser steps
    schedule: str  # where the epochs came from (use_dataset_schedule)
    device: torch.device
    rank: int
    world_size: int

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def steps_per_epoch(self) -> int:
        return math.ceil(len(self.loader) / self.accumulate)

    def batches(self):
        """The epoch's batches, each the list of its micro-batches (the last may hold fewer)."""
        group: list[Batch] = []
        for batch in self.loader:
            group.append(batch)
            if len(group) == self.accumulate:
                yield group
                group = []
        if group:
            yield group


def setup(config: Config, data_dir: Path, resume: bool = False) -> Setup:
    """The process (DDP under torchrun), the BEV grid and schedule of the dataset, the model and its loss
    on the device (built from the same seed on every rank; on resume without reading the pretrained
    weights, which the checkpoint holds), the loader, the optimiser and its schedule, AMP."""
    if not resume:
        check_backbone_weights(config)
    device, rank, world_size = setup_process(config)
    train_config = config.train
    use_dataset_range(config, data_dir, rank == 0)
    schedule = use_dataset_schedule(config, data_dir)
    micro_batch, accumulate = train_config.micro_batches(world_size)
    # The same seed on every rank builds the same model; the ranks' streams differ from here on.
    torch.manual_seed(train_config.seed)
    built = build(without_pretrained_weights(config) if resume else config).to(device)
    model = built.model
    random.seed(train_config.seed + rank)
    np.random.seed(train_config.seed + rank)
    torch.manual_seed(train_config.seed + rank)

    dataset = PreparedDataset(data_dir, train_config.train_split, config, built.needs)
    # One sampler for one or many processes: its order depends on (seed, epoch) only.
    sampler = DistributedSampler(
        dataset, num_replicas=world_size, rank=rank, shuffle=True, seed=train_config.seed
    )
    workers = min(config.data.num_workers, os.cpu_count() or 1)
    loader = DataLoader(
        dataset,
        batch_size=micro_batch,
        sampler=sampler,
        num_workers=workers,
        collate_fn=collate,
        pin_memory=device.type == "cuda",  # Batch.pin_memory: asynchronous copies to the GPU
        drop_last=len(dataset) >= train_config.batch_size,
        persistent_workers=workers > 0,
        prefetch_factor=4 if workers > 0 else None,
    )
    total_steps = math.ceil(len(loader) / accumulate) * train_config.epochs
    optimizer = build_optimizer(model, config)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: lr_factor(step, total_steps, config)
    )
    autocast_dtype, needs_scaler = amp_settings(device, train_config.amp)
    trained = (
        DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
        if world_size > 1
        else model
    )
    trainer = Trainer(model, trained, built.loss, optimizer, scheduler,
                      torch.amp.GradScaler("cuda", enabled=needs_scaler), autocast_dtype, device,
                      train_config.grad_clip)  # fmt: skip
    return Setup(config, trainer, dataset, sampler, loader, accumulate, total_steps, schedule, device, rank,
                 world_size)  # fmt: skip


class RunFolder:
    """RUN_DIR (the module's docstring): a new run or one resumed, its log and its checkpoints. Only
    rank 0 (`master`) writes."""

    def __init__(self, path: Path, master: bool):
        self.path, self.master = path, master
        self.log_file = None

    @staticmethod
    def check_free(path: Path, resume: bool, overwrite: bool) -> None:
        """Refuse to start afresh in a folder that holds a run: its checkpoint and log would be replaced."""
        if not resume and not overwrite and (path / "config.json").exists():
            raise ValueError(f"{path} holds a run already: continue it with --resume, start it afresh with "
                             "--overwrite, or choose another --out")  # fmt: skip

    def start(self, s: Setup, data_dir: Path) -> int:
        """A new run: config.json, run.json and an empty log; returns the first epoch, 0."""
        config = s.config
        if self.master:
            self.path.mkdir(parents=True, exist_ok=True)
            config.save(self.path / "config.json")
            run = {
                "data": str(data_dir.resolve()),
                "world_size": s.world_size,
                "batch_per_process": config.train.batch_size // s.world_size,
                "accumulate": s.accumulate,  # micro-batches per optimiser step, in each process
                "batch_per_forward": config.train.batch_size // s.world_size // s.accumulate,
                "effective_batch_size": config.train.batch_size,  # processes x micro-batches x frames
                "epochs": config.train.epochs,
                "schedule": s.schedule,
                "device": s.device.type,
                "targets": dataset_targets(data_dir),  # cli eval / score / train --resume compare them
            }
            (self.path / "run.json").write_text(json.dumps(run, indent=2) + "\n")
            (self.path / "log.jsonl").write_text("")
        return 0

    def resume(self, trainer: Trainer, data_dir: Path, rank: int) -> int:
        """Continue the run: refuse stale data (the dataset must have the targets the run was trained on),
        restore its checkpoint (resume_checkpoint) and drop the log lines of steps after it (an interrupted
        epoch); returns the epoch to start from."""
        targets = json.loads((self.path / "run.json").read_text()).get("targets", {})
        check_targets(targets, data_dir, f"the run {self.path}")
        epoch = trainer.load(resume_checkpoint(self.path, self.master), rank)
        if self.master:
            lines = logged_lines(self.path / "log.jsonl")
            kept = "".join(line for line in lines if json.loads(line)["step"] <= trainer.step)
            io.write_atomic(self.path / "log.jsonl", lambda tmp: tmp.write_text(kept))
        return epoch

    def open_log(self) -> None:
        if self.master:
            self.log_file = (self.path / "log.jsonl").open("a")

    def log(self, record: dict) -> None:
        self.log_file.write(json.dumps(record) + "\n")
        self.log_file.flush()

    def save(self, trainer: Trainer, epoch: int, config: Config, rng_states: list[dict]) -> None:
        if self.master:
            trainer.save(self.path / CHECKPOINT, epoch, config, rng_states)

    def finish(self, summary: dict) -> None:
        """Close the log; the summary into run.json."""
        if self.log_file is not None:
            self.log_file.close()
        if self.master:
            run = json.loads((self.path / "run.json").read_text())
            io.write_json(self.path / "run.json", {**run, "summary": summary})


@dataclass
class Tally:
    """This run's steps, the seconds they took (the waits for data included) and the last loss."""

    steps: int = 0
    seconds: float = 0.0
    loss: float = float("nan")


def train_one_epoch(s: Setup, epoch: int, run: RunFolder, tally: Tally, progress: Progress, task) -> None:
    """One pass over the training split: a step per batch (its losses averaged over the processes), the
    progress bar, a log line every train.log_every steps and at the last step."""
    trainer, train_config = s.trainer, s.config.train
    trainer.model.train()
    s.sampler.set_epoch(epoch)
    epoch_start = last = time.perf_counter()
    for batches in s.batches():  # the step time below includes the wait for data
        losses, grad_norm = trainer.train_step(batches)
        now = time.perf_counter()
        tally.seconds += now - last
        last = now
        tally.steps += 1
        speed = tally.steps / tally.seconds
        step = trainer.step
        # the losses reach the host on logged steps only: a read each step would wait for the GPU
        logged = step % train_config.log_every == 0 or step == s.total_steps
        if logged:
            losses = mean_losses(losses, s.distributed)  # every rank takes part
            tally.loss = float(losses["loss"])
        progress.update(task, advance=1, epoch=epoch + 1, loss=tally.loss, speed=speed)
        if run.master and logged:
            run.log({
                "step": step,
                "epoch": epoch + 1,
                "lr": trainer.optimizer.param_groups[0]["lr"],
                **{k: float(v) for k, v in losses.items()},
                "grad_norm": float(grad_norm),
                "steps_per_s": speed,
                "samples_per_s": speed * train_config.batch_size,
                "epoch_seconds": time.perf_counter() - epoch_start,
            })  # fmt: skip


def progress_bar(master: bool) -> Progress:
    columns = [
        TextColumn("epoch {task.fields[epoch]}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.3f}  {task.fields[speed]:.2f} steps/s"),
        TimeElapsedColumn(),
    ]
    return Progress(*columns, console=console, disable=not master)


def train(config: Config, data_dir: Path, out_dir: Path, resume: bool = False, stop_after: int = 0,
          overwrite: bool = False) -> dict:  # fmt: skip
    """Train `config` on the prepared dataset `data_dir`; returns a summary (loss, steps/s, seconds).

    resume: continue from out_dir/checkpoint.pt. stop_after: end this run after that many epochs
    (0: run to config.train.epochs), e.g. to fit a time-limited job; a later resume carries on.
    overwrite: start afresh in a folder that holds a run (refused otherwise: its checkpoint and log
    would be replaced).
    """
    data_dir, out_dir = Path(data_dir), Path(out_dir)
    RunFolder.check_free(out_dir, resume, overwrite)
    s = setup(config, data_dir, resume)
    run = RunFolder(out_dir, master=s.rank == 0)
    if resume:
        start_epoch = run.resume(s.trainer, data_dir, s.rank)
    else:
        start_epoch = run.start(s, data_dir)
    if run.master:
        parameters = sum(p.numel() for p in s.trainer.model.parameters())
        console.print(
            f"{config.model} {config.encoder.modality}: {parameters / 1e6:.2f} M parameters, "
            f"{len(s.dataset)} frames, {s.steps_per_epoch} steps per epoch x {config.train.epochs} epochs "
            f"({s.schedule}), batch {config.train.batch_size} = {s.world_size} process(es) x {s.accumulate} "
            f"micro-batch(es) x {s.loader.batch_size} frames, on {s.device.type}"
        )
    run.open_log()
    tally = Tally()
    epochs = config.train.epochs
    with progress_bar(run.master) as progress:
        task = progress.add_task(
            "train", total=s.total_steps, completed=s.trainer.step, epoch=start_epoch, loss=0.0, speed=0.0
        )
        for epoch in range(start_epoch, min(epochs, start_epoch + stop_after) if stop_after else epochs):
            train_one_epoch(s, epoch, run, tally, progress, task)
            states = all_rng_states(s.distributed)  # every rank takes part
            run.save(s.trainer, epoch + 1, config, states)
    batch_size = config.train.batch_size
    summary = {
        "final_loss": tally.loss,
        "steps": s.trainer.step,
        "epochs": epochs,
        "schedule": s.schedule,
        "train_seconds": tally.seconds,
        "steps_per_s": tally.steps / tally.seconds if tally.seconds else 0.0,
        "samples_per_s": tally.steps * batch_size / tally.seconds if tally.seconds else 0.0,
    }
    if s.device.type == "cuda":  # this process's peak; every rank holds the same model and batch size
        summary["gpu_memory_gib"] = torch.cuda.max_memory_allocated(s.device) / 2**30
    run.finish(summary)
    if s.distributed:
        dist.barrier()
        dist.destroy_process_group()
    return summary
