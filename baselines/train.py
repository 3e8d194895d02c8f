"""One training loop for the baselines: CPU or CUDA (AMP), one process or DDP under `torchrun`.

RUN_DIR gets config.json (the resolved config), run.json (data folder, processes, per-process and
effective batch size, micro-batches accumulated per step, the schedule and where its epochs came from,
the dataset's target parameters, the best validation so far; a resume's config changes and restarts of
the best: baselines/run_folder.py), log.jsonl (one line per logged step and
per skipped step; the losses are means over the processes), val.jsonl (one line per validation: its
step, epoch, frames, seconds and every F1, baselines/validate.py), tb/ (TensorBoard event files of the
same), and the checkpoints of baselines/checkpoint.py: checkpoint.pt at every epoch's end and every
train.checkpoint_every steps (model, optimiser, scheduler, scaler, every rank's RNG state and where the
epoch's sampler stands, so that `resume=True` continues exactly where the run stopped, inside an epoch
too), checkpoint.prev.pt (the one before) and best.pt (by train.best_metric). Only rank 0 writes.

A step whose loss or gradient norm is not finite is not applied (no optimiser or scheduler step); it is
counted and logged, and train.max_bad_steps of them in a row stop the run (TrainingStopped). Under fp16 an
overflow (a finite loss, gradients beyond fp16's range) is the GradScaler's to handle while it backs off;
at a loss scale of 1 or less it counts as such a step.
"""

from __future__ import annotations

import math
import os
import random
import time
from collections.abc import Collection
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from rich import progress as bars
from rich.console import Console
from rich.progress import Progress
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler

from baselines.checkpoint import CheckpointError, rng_state, set_rng_state
from baselines.config import PAPER_EPOCHS, Config
from baselines.data import Batch, PreparedDataset, collate
from baselines.device import amp_settings, cuda_settings
from baselines.models import build, check_backbone_weights, without_pretrained_weights
from baselines.models.base import Built
from baselines.run_folder import Best, RunFolder, check_steps_per_epoch
from baselines.validate import Validation
from pipeline import progress
from pipeline.manifest import PreparedData

console = Console(stderr=True)


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


class TrainingStopped(ValueError):
    """train.max_bad_steps steps in a row were not finite; the message says which, and where to resume."""


def setup_process(config: Config) -> tuple[torch.device, int, int]:
    """(device, rank, world size): DDP when `torchrun` set WORLD_SIZE > 1 (NCCL on CUDA, gloo on CPU)."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size > 1:
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    rank = dist.get_rank() if world_size > 1 else 0
    if torch.cuda.is_available():
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
        cuda_settings(device)
    else:
        device = torch.device("cpu")
    if config.train.threads:
        torch.set_num_threads(config.train.threads)
    config.train.micro_batches(world_size)  # a batch size that does not split is refused before any work
    return device, rank, world_size


def use_dataset_schedule(config: Config, data: PreparedData) -> str:
    """train.epochs 0 (the paper preset) takes the paper's schedule of the prepared dataset's kind
    (PAPER_EPOCHS); returns where the epochs came from, for run.json and the report."""
    if config.train.epochs:
        return "set (preset or --epochs)"
    kind = data.kind
    if kind not in PAPER_EPOCHS:
        manifest = data.path / "manifest.json"
        raise ValueError(f"{manifest}: no dataset kind ({', '.join(PAPER_EPOCHS)}) to take the paper's "
                         "schedule from: give --epochs")  # fmt: skip
    config.train.epochs = PAPER_EPOCHS[kind]
    return f"the paper's {kind} schedule"


def use_dataset_range(config: Config, data: PreparedData, master: bool) -> None:
    """The BEV grid covers what the dataset was cropped to, at the preset's cell size (the tiny
    preset's 40 x 20 cells of 1.5 m over 30 x 60 m become 67 x 33 over 50 x 100 m)."""
    crop = data.crop
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


def batch_norm_statistics(model: torch.nn.Module) -> list[torch.Tensor]:
    """The running statistics of every BatchNorm: a forward pass in training mode moves them."""
    return [
        tensor
        for module in model.modules()
        if isinstance(module, torch.nn.modules.batchnorm._BatchNorm) and module.track_running_stats
        for tensor in (module.running_mean, module.running_var, module.num_batches_tracked)
    ]


@dataclass
class Step:
    """What one optimiser step returns: the losses (means over the micro-batches, detached, on the device),
    the gradient norm before clipping, and whether it was applied."""

    losses: dict[str, torch.Tensor]
    grad_norm: torch.Tensor
    applied: bool
    overflow: bool  # fp16 only: the GradScaler's overflow (a finite loss, gradients beyond fp16), skipped
    loss_scale: float = 0.0  # an overflow's: the GradScaler's scale that the gradients overflowed at


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
    step: int = 0  # batches stepped through, applied or skipped: the position in the schedule
    bad_in_a_row: int = 0  # non-finite steps in a row, fp16 overflows at a loss scale of 1 or less among them
    skipped: int = 0  # non-finite steps, in all
    last_applied: int = 0  # the step of the last applied one: a streak of skipped steps began after it

    def train_step(self, batches: list[Batch]) -> Step:
        """One optimiser step on the micro-batches of one batch: their gradients add up, each loss weighted
        by 1 / their number (as mmcv's GradientCumulativeOptimizerHook; one batch of them all when they
        hold as many targets, up to BatchNorm). A loss or gradient norm that is not finite (on any process)
        leaves the weights, the optimiser and the schedule as they were. Reading that flag is the step's one
        wait for the device."""
        self.optimizer.zero_grad(set_to_none=True)
        statistics = batch_norm_statistics(self.model)
        kept = [tensor.clone() for tensor in statistics]  # a skipped step's forward must not move them
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
        finite = torch.stack([torch.isfinite(mean["loss"]), torch.isfinite(grad_norm)]).float()
        if isinstance(self.trained, DistributedDataParallel):
            dist.all_reduce(finite, op=dist.ReduceOp.MIN)  # every process skips the same steps
        loss_finite, grad_finite = (bool(flag) for flag in finite.tolist())
        applied = loss_finite and grad_finite
        overflow = self.scaler.is_enabled() and loss_finite and not grad_finite
        # read before update() backs it off, and on overflows only (reading it waits for the device)
        loss_scale = self.scaler.get_scale() if overflow else 0.0
        if applied:
            self.scaler.step(self.optimizer)
            self.scheduler.step()
        else:
            torch._foreach_copy_(statistics, kept)
        self.scaler.update()  # fp16: a skipped step lowers the loss scale
        self.step += 1
        # An overflow is the scaler's to handle while halving the scale can bring the gradients into fp16's
        # range; at a scale of 1 or less they overflow unscaled, and a scaler that keeps backing off would
        # skip every step of the run: such an overflow is a bad step like a NaN loss.
        if applied:
            self.bad_in_a_row, self.last_applied = 0, self.step
        elif not overflow or loss_scale <= 1:
            self.bad_in_a_row += 1
        self.skipped += not applied
        return Step(mean, grad_norm.detach(), applied, overflow, loss_scale)

    def state(self, epoch: int, epoch_steps: int, config: Config, rng_states: list[dict], best: dict) -> dict:
        """The full state: `epoch` epochs done and `epoch_steps` steps into the next one."""
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(),
            "epoch": epoch,
            "epoch_steps": epoch_steps,
            "step": self.step,
            "skipped": self.skipped,
            "bad_in_a_row": self.bad_in_a_row,
            "last_applied": self.last_applied,
            "best": best,
            "rng": rng_states,
            "config": config.to_dict(),
        }

    def load(self, checkpoint: dict, world_size: int) -> None:
        """Restore the weights, optimiser, schedule and counts of a loaded checkpoint (the RNG state is
        restored by `train`, once the epoch's batches are drawn), on as many processes as it was saved
        by: on more, some would have no random streams; on fewer, some streams would be dropped. The
        optimiser's settings stay the config's (a resume may change train.lr and the like)."""
        saved_by = len(checkpoint["rng"])
        if saved_by != world_size:
            raise CheckpointError(
                f"the checkpoint holds the random streams of {saved_by} process(es), this run has "
                f"{world_size}: resume with as many (torchrun --nproc_per_node {saved_by})"
            )
        settings = [{k: v for k, v in g.items() if k != "params"} for g in self.optimizer.param_groups]
        try:
            self.model.load_state_dict(checkpoint["model"])
        except RuntimeError as error:  # a resume's --set of a field that shapes the model
            first = str(error).splitlines()[1].strip() if "\n" in str(error) else str(error)
            raise CheckpointError(f"the checkpoint's weights do not fit the model of this config ({first}): "
                                  "a resume keeps the model's shape") from error  # fmt: skip
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        self.scheduler.load_state_dict(checkpoint["scheduler"])
        self.scaler.load_state_dict(checkpoint["scaler"])
        # the config's learning rates and AdamW settings, which the loaded state dicts replaced by theirs
        for group, own in zip(self.optimizer.param_groups, settings, strict=True):
            group.update({k: own[k] for k in ("initial_lr", "betas", "eps", "weight_decay")})
        self.scheduler.base_lrs = [own["initial_lr"] for own in settings]
        for group, base, factor in zip(self.optimizer.param_groups, self.scheduler.base_lrs,
                                       self.scheduler.lr_lambdas, strict=True):  # fmt: skip
            group["lr"] = base * factor(self.scheduler.last_epoch)  # LambdaLR's own formula
        self.scheduler._last_lr = [group["lr"] for group in self.optimizer.param_groups]
        self.step = checkpoint["step"]
        self.skipped = checkpoint.get("skipped", 0)
        self.bad_in_a_row = checkpoint.get("bad_in_a_row", 0)
        self.last_applied = checkpoint.get("last_applied", self.step)  # older: taken as saved before a streak


def mean_losses(losses: dict[str, torch.Tensor], distributed: bool) -> dict[str, torch.Tensor]:
    """The losses averaged over the processes (detached): with the normalisers summed over processes
    (blocks.mean_over_processes), the loss of the whole batch, as one process would compute it."""
    values = torch.stack([value.detach().float() for value in losses.values()])
    if distributed:
        dist.all_reduce(values)
        values /= dist.get_world_size()
    return dict(zip(losses, values, strict=True))


def all_rng_states(distributed: bool) -> list[dict]:
    if not distributed:
        return [rng_state()]
    states: list = [None] * dist.get_world_size()
    dist.all_gather_object(states, rng_state())
    return states


class EpochSampler(DistributedSampler):
    """DistributedSampler (its order depends on (seed, epoch) only) that can start an epoch part-way:
    `skip` of this process's samples are left out of the next epoch drawn, and of that one only."""

    skip = 0

    def __iter__(self):
        indices = list(super().__iter__())
        skip, self.skip = self.skip, 0
        return iter(indices[skip:])


@dataclass
class Setup:
    """Everything `train` sets up before its first step (`setup`)."""

    config: Config
    built: Built
    trainer: Trainer
    dataset: PreparedDataset
    sampler: EpochSampler
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

    def batches(self, skip_steps: int = 0, restore: dict | None = None):
        """The epoch's batches, each the list of its micro-batches (the last may hold fewer), from
        `skip_steps` steps in. `restore`: an RNG state to set as an uninterrupted run had it there: the
        loader draws its workers' seed from torch's RNG when it makes an epoch's iterator (every epoch, or
        the first one with persistent workers), a draw the uninterrupted run made before its checkpoint
        inside an epoch, and after it at an epoch's end."""
        self.sampler.skip = skip_steps * self.accumulate * self.loader.batch_size
        drawn_after = restore is not None and skip_steps == 0 and not self.loader.persistent_workers
        if drawn_after:
            set_rng_state(restore)
        iterator = iter(self.loader)
        if restore is not None and not drawn_after:
            set_rng_state(restore)
        group: list[Batch] = []
        for batch in iterator:
            group.append(batch)
            if len(group) == self.accumulate:
                yield group
                group = []
        if group:
            yield group


def setup(config: Config, data: PreparedData, resume: bool = False) -> Setup:
    """The process (DDP under torchrun), the BEV grid and schedule of the dataset, the model and its loss
    on the device (built from the same seed on every rank; on resume without reading the pretrained
    weights, which the checkpoint holds), the loader, the optimiser and its schedule, AMP."""
    if not resume:
        check_backbone_weights(config)
    device, rank, world_size = setup_process(config)
    train_config = config.train
    use_dataset_range(config, data, rank == 0)
    schedule = use_dataset_schedule(config, data)
    micro_batch, accumulate = train_config.micro_batches(world_size)
    # The same seed on every rank builds the same model; the ranks' streams differ from here on.
    torch.manual_seed(train_config.seed)
    built = build(without_pretrained_weights(config) if resume else config).to(device)
    model = built.model
    random.seed(train_config.seed + rank)
    np.random.seed(train_config.seed + rank)
    torch.manual_seed(train_config.seed + rank)

    dataset = PreparedDataset(data, train_config.train_split, config, built.needs)
    # One sampler for one or many processes: its order depends on (seed, epoch) only.
    sampler = EpochSampler(dataset, num_replicas=world_size, rank=rank, shuffle=True, seed=train_config.seed)
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
    return Setup(config, built, trainer, dataset, sampler, loader, accumulate, total_steps, schedule, device,
                 rank, world_size)  # fmt: skip


def validation_epochs(config: Config) -> set[int]:
    """The epochs (1-based) after which the run validates: every train.eval_every and the last one."""
    epochs, every = config.train.epochs, config.train.eval_every
    return {epochs, *(range(every, epochs + 1, every) if every > 0 else ())}


@dataclass
class Tally:
    """This run's steps, the seconds they took (the waits for data included), the seconds of those waits
    since the last log line, the last loss, and the seconds the checkpoints held the steps up."""

    steps: int = 0
    seconds: float = 0.0
    wait: float = 0.0
    since_log: float = 0.0
    loss: float = float("nan")
    checkpoint_stall: list[float] = field(default_factory=list)
    last_step: int = 0  # where this run ends (--stop-after: before the schedule's end), logged like the last

    def speed(self) -> float:
        return self.steps / self.seconds if self.seconds else 0.0


def log_step(s: Setup, run: RunFolder, tally: Tally, epoch: int, step: Step) -> None:
    """A log line (and TensorBoard scalars) of a logged or skipped step; every rank takes part."""
    losses = mean_losses(step.losses, s.distributed)
    values = {name: float(value) for name, value in losses.items()}
    if step.applied:
        tally.loss = values["loss"]
    if not run.master:
        return
    batch_size = s.config.train.batch_size
    record = {
        "step": s.trainer.step,
        "epoch": epoch + 1,
        "lr": s.trainer.optimizer.param_groups[0]["lr"],
        **values,
        "grad_norm": float(step.grad_norm),
        "steps_per_s": tally.speed(),
        "samples_per_s": tally.speed() * batch_size,
        "data_wait_share": tally.wait / tally.since_log if tally.since_log else 0.0,
    }
    scalars = {f"loss/{name}": value for name, value in values.items()}
    scalars |= {"lr": record["lr"], "grad_norm": record["grad_norm"]}
    scalars |= {f"speed/{name}": record[name] for name in ("steps_per_s", "samples_per_s", "data_wait_share")}
    if s.device.type == "cuda":
        scalars["gpu/peak_memory_gib"] = torch.cuda.max_memory_allocated(s.device) / 2**30
    if not step.applied:
        kind = "fp16 overflow" if step.overflow else "non-finite"
        record["skipped"] = kind
        console.print(f"step {record['step']}: skipped ({kind}: {not_finite(record)})", highlight=False)
    scalars["skipped_steps"] = s.trainer.skipped
    run.log(record, scalars)
    tally.wait = tally.since_log = 0.0


def not_finite(record: dict) -> str:
    """The names of a step record's values that are not finite, e.g. `loss, loss_cls, grad_norm`."""
    names = [k for k, v in record.items() if isinstance(v, float) and not math.isfinite(v)]
    return ", ".join(names) or "none"


def stop_if_diverged(s: Setup, run: RunFolder, step: Step) -> None:
    """train.max_bad_steps non-finite steps in a row (fp16 overflows at a loss scale of 1 or less among
    them) end the run with one line: the step, what was not finite, and how to go on."""
    trainer, limit = s.trainer, s.config.train.max_bad_steps
    if not limit or trainer.bad_in_a_row < limit:
        return
    values = {name: float(value) for name, value in mean_losses(step.losses, s.distributed).items()}
    values["grad_norm"] = float(step.grad_norm)
    where = not_finite(values)
    change = "another --set train.lr=..."
    if step.overflow:
        where += (f" (fp16 gradients overflowing at a loss scale of {step.loss_scale:g}: overflows count "
                  "once the scale is down to 1)")  # fmt: skip
        change = "--set train.amp=false (fp32) or " + change
    last = run.last_checkpoint
    if last is None:
        go_on = f"no checkpoint was written yet: start again (--overwrite) with {change}"
    elif step.overflow and last[2] is not None and last[1] > trainer.last_applied:
        # a checkpoint saved during the overflows holds good weights (a skipped step leaves them) but the
        # scale they brought down: under fp16 a resume goes on from that scale and overflows at once
        at_once = ", at which fp16 overflows at once" if last[2] <= 1 else ""
        go_on = (f"the last checkpoint is {last[0]} (step {last[1]}; its weights are good, its loss scale "
                 f"{last[2]:g}{at_once}): --resume from it with {change}")  # fmt: skip
    else:
        go_on = f"the last good checkpoint is {last[0]} (step {last[1]}): --resume from it with {change}"
    raise TrainingStopped(
        f"step {trainer.step}: {trainer.bad_in_a_row} steps in a row with a non-finite loss or gradient norm "
        f"(--max-bad-steps {limit}; not finite at this step: {where}), none of them applied; {go_on}"
    )


def train_one_epoch(s: Setup, epoch: int, run: RunFolder, tally: Tally, bar: Progress, task,
                    skip_steps: int = 0, restore: dict | None = None) -> None:  # fmt: skip
    """One pass over the training split (from `skip_steps` in, `restore`: Setup.batches): a step per batch
    (its losses averaged over the processes), the progress bar, a log line every train.log_every steps, at
    the last and every skipped one, a checkpoint every train.checkpoint_every steps."""
    trainer, train_config = s.trainer, s.config.train
    trainer.model.train()
    s.sampler.set_epoch(epoch)
    batch_size, every = train_config.batch_size, train_config.checkpoint_every
    epoch_end = (epoch + 1) * s.steps_per_epoch
    batches = s.batches(skip_steps, restore)
    last = time.perf_counter()
    while True:
        group = next(batches, None)  # the step time below includes this wait for data
        waited = time.perf_counter()
        if group is None:
            break
        step = trainer.train_step(group)
        now = time.perf_counter()
        tally.seconds += now - last
        tally.since_log += now - last
        tally.wait += waited - last
        tally.steps += 1
        number = trainer.step
        # the losses are averaged over the processes (a collective) and read on logged steps only
        ends = number in (s.total_steps, tally.last_step)  # the schedule's or this run's last step
        if number % train_config.log_every == 0 or ends or not step.applied:
            log_step(s, run, tally, epoch, step)
        bar.update(task, advance=1, epoch=epoch + 1, loss=tally.loss, speed=tally.speed() * batch_size)
        stop_if_diverged(s, run, step)
        if every and number % every == 0 and number < epoch_end:
            now = time.perf_counter()
            states = all_rng_states(s.distributed)  # every rank takes part
            epoch_steps = number - epoch * s.steps_per_epoch
            state = trainer.state(epoch, epoch_steps, s.config, states, run.best_record())
            run.save(state, best=False)
            tally.checkpoint_stall.append(time.perf_counter() - now)
        last = time.perf_counter()


def validate(s: Setup, validation: Validation, run: RunFolder, epoch: int) -> bool:
    """Validate (every rank), log it, and say whether it is the best so far by train.best_metric. The
    training's RNG streams are left as they were: validating does not change the training."""
    states = rng_state()
    record = {"step": s.trainer.step, "epoch": epoch, **validation(s.built)}
    set_rng_state(states)
    metric = s.config.train.best_metric
    best = run.best is None or record[metric] > run.best.value
    if best:
        run.best = Best.of(record, s.config)
    if run.master:
        run.log_validation(record)
        f1s = ", ".join(f"{name} {record[name]:.3f}" for name in dict.fromkeys(("directed_topo_f1", metric)))
        console.print(f"validation at epoch {epoch} (step {record['step']}, {record['frames']} frames of "
                      f"{record['split']}, {record['seconds']:.1f} s): {f1s}{' (best)' if best else ''}",
                      highlight=False)  # fmt: skip
    return best


def progress_bar(master: bool) -> Progress:
    columns = [
        bars.TextColumn("epoch {task.fields[epoch]}"),
        bars.BarColumn(),
        bars.MofNCompleteColumn(),
        bars.TextColumn("loss {task.fields[loss]:.3f}  {task.fields[speed]:.1f} samples/s"),
        bars.TimeElapsedColumn(),
        bars.TextColumn("left"),
        bars.TimeRemainingColumn(),  # the bar counts the whole run's steps: the time left for all of it
    ]
    return Progress(*columns, console=console, disable=not master)


def validation_plan(config: Config, data: PreparedData) -> str:
    """What run.json says of the validation during training."""
    train_config = config.train
    if not data.split_sizes.get(train_config.val_split):
        return f"none: split {train_config.val_split!r} of {data.path} has no frames"
    frames = f"{train_config.eval_frames} frames" if train_config.eval_frames else "all frames"
    every = f"every {train_config.eval_every} epoch(s) and " if train_config.eval_every else ""
    return f"{every}after the last epoch, {frames} of {train_config.val_split!r}"


def run_record(s: Setup, data: PreparedData, validation: str) -> dict:
    """run.json of a new run: the data, the processes and batch sizes, the schedule, the validation plan,
    the device and the dataset's target parameters."""
    config = s.config
    return {
        "data": str(data.path.resolve()),
        "world_size": s.world_size,
        "batch_per_process": config.train.batch_size // s.world_size,
        "accumulate": s.accumulate,  # micro-batches per optimiser step, in each process
        "batch_per_forward": config.train.batch_size // s.world_size // s.accumulate,
        "effective_batch_size": config.train.batch_size,  # processes x micro-batches x frames
        "epochs": config.train.epochs,
        "schedule": s.schedule,
        "validation": validation,
        "device": s.device.type,
        "targets": data.targets,  # cli eval / score / train --resume compare them
    }


def begin(s: Setup, run: RunFolder, data: PreparedData, resume: bool, told: Collection[str],
          plan: str) -> tuple[int, int, dict | None]:  # fmt: skip
    """A new run's config.json and run.json, or a resume's checkpoint restored (the config's changes
    logged); returns the epoch to start at, the steps of it already done and this rank's RNG state."""
    config = s.config
    if not resume:
        run.start(config, run_record(s, data, plan))
        return 0, 0, None
    checkpoint = run.resume(data, config, told)
    check_steps_per_epoch(checkpoint.get("config"), config.train, len(s.dataset), s.world_size)
    s.trainer.load(checkpoint, s.world_size)
    run.resumed(checkpoint, config)
    return checkpoint["epoch"], checkpoint.get("epoch_steps", 0), checkpoint["rng"][s.rank]


def announce(s: Setup, plan: str) -> None:
    """One line on the console: the model, the data, the steps and the batch's make-up."""
    config = s.config
    parameters = sum(p.numel() for p in s.trainer.model.parameters())
    console.print(
        f"{config.model} {config.encoder.modality}: {parameters / 1e6:.2f} M parameters, "
        f"{len(s.dataset)} frames, {s.steps_per_epoch} steps per epoch x {config.train.epochs} epochs "
        f"({s.schedule}), batch {config.train.batch_size} = {s.world_size} process(es) x {s.accumulate} "
        f"micro-batch(es) x {s.loader.batch_size} frames, on {s.device.type}; validation {plan}"
    )


def run_epochs(s: Setup, run: RunFolder, validation: Validation | None, epochs: range, skip_steps: int,
               restore: dict | None) -> Tally:  # fmt: skip
    """Train `epochs`, the first from `skip_steps` on with `restore` (a resume inside it); validate when
    due and save the checkpoint at every epoch's end."""
    tally = Tally(last_step=min(epochs.stop * s.steps_per_epoch, s.total_steps))
    due = validation_epochs(s.config) if validation is not None else set()
    try:
        with progress_bar(run.master) as bar, progress.holding(bar):
            task = bar.add_task("train", total=s.total_steps, completed=s.trainer.step, epoch=epochs.start,
                                loss=0.0, speed=0.0)  # fmt: skip
            for epoch in epochs:
                train_one_epoch(s, epoch, run, tally, bar, task, skip_steps, restore)
                skip_steps, restore = 0, None
                best = validate(s, validation, run, epoch + 1) if epoch + 1 in due else False
                states = all_rng_states(s.distributed)  # every rank takes part
                run.save(s.trainer.state(epoch + 1, 0, s.config, states, run.best_record()), best)
    finally:
        run.close()
    return tally


def summarise(s: Setup, run: RunFolder, tally: Tally) -> dict:
    """The run's summary (run.json's and `train`'s): loss, steps, speed, skipped steps, the best."""
    batch_size = s.config.train.batch_size
    stalls = tally.checkpoint_stall
    summary = {
        "final_loss": tally.loss,
        "steps": s.trainer.step,
        "epochs": s.config.train.epochs,
        "schedule": s.schedule,
        "train_seconds": tally.seconds,
        "steps_per_s": tally.speed(),
        "samples_per_s": tally.speed() * batch_size,
        "skipped_steps": s.trainer.skipped,
        "best": run.best_record(),
        # the longest a step waited for a checkpoint inside an epoch (its copy to the host)
        "checkpoint_stall_s": max(stalls) if stalls else None,
    }
    if s.device.type == "cuda":  # this process's peak; every rank holds the same model and batch size
        summary["gpu_memory_gib"] = torch.cuda.max_memory_allocated(s.device) / 2**30
    return summary


def train(config: Config, data_dir: Path, out_dir: Path, resume: bool = False, stop_after: int = 0,
          overwrite: bool = False, told: Collection[str] = ()) -> dict:  # fmt: skip
    """Train `config` on the prepared dataset `data_dir`; returns a summary (loss, steps/s, seconds).

    resume: continue from out_dir/checkpoint.pt. stop_after: end this run after that many epochs
    (0: run to config.train.epochs), e.g. to fit a time-limited job; a later resume carries on.
    overwrite: start afresh in a folder that holds a run, every file of the earlier run removed first
    (refused otherwise: the two runs would mix). told: on resume, the config fields (section.field) set
    on the command line, which may differ from the checkpoint's (run_folder.config_changes).
    """
    out_dir = Path(out_dir)
    RunFolder.check_free(out_dir, resume, overwrite)
    data = PreparedData.open(data_dir)
    s = setup(config, data, resume)
    plan = validation_plan(config, data)
    validation = None
    if not plan.startswith("none"):
        validation = Validation(config, data, s.built.needs, s.device, s.trainer.autocast_dtype, s.rank,
                                s.world_size)  # fmt: skip
    run = RunFolder(out_dir, master=s.rank == 0)
    start_epoch, skip_steps, restore = begin(s, run, data, resume, told, plan)
    if run.master:
        announce(s, plan)
    run.open_logs(s.trainer.step)
    epochs = config.train.epochs
    last_epoch = min(epochs, start_epoch + stop_after) if stop_after else epochs
    tally = run_epochs(s, run, validation, range(start_epoch, last_epoch), skip_steps, restore)
    summary = summarise(s, run, tally)
    run.finish(summary)
    if s.distributed:
        dist.barrier()
        dist.destroy_process_group()
    return summary
