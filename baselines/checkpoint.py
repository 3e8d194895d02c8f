"""A run's checkpoints: the full training state in one file, written atomically with the sha256 of its
content, loaded with weights_only=True (a crafted file cannot run code), never loaded when damaged.

RUN_DIR keeps checkpoint.pt (the latest), checkpoint.prev.pt (the one before; resume falls back to it,
saying so in one line, when checkpoint.pt is damaged; the damaged one becomes checkpoint.bad.pt) and best.pt
(a copy of the checkpoint of the best validation so far). A
paper-preset checkpoint is ~430 MiB: `CheckpointWriter` copies the state off the device and hashes and
writes it on a thread of its own, so that a step waits only for the copy (docs/EXPERIMENTS.md).
"""

from __future__ import annotations

import copy
import hashlib
import os
import pickle
import random
import shutil
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from rich.console import Console

console = Console(stderr=True)
CHECKPOINT, PREVIOUS, BEST = "checkpoint.pt", "checkpoint.prev.pt", "best.pt"
DAMAGED = "checkpoint.bad.pt"
CHOICES = {"last": CHECKPOINT, "best": BEST}  # cli eval --checkpoint


class CheckpointError(ValueError):
    """A checkpoint that is missing, damaged or refused; the message names the file, in one line."""


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


def copy_atomic(source: Path, target: Path) -> None:
    """`source`'s bytes to `target`, which readers see whole or not at all."""
    tmp = target.with_name(f".{target.name}.tmp")
    shutil.copyfile(source, tmp)
    os.replace(tmp, target)


def peek(path: Path) -> dict | None:
    """The step and sha256 of a checkpoint file without reading its tensors (memory-mapped), or None when
    it is missing or unreadable; to tell which checkpoint a file is, never to load it (load_checkpoint)."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        return {"step": checkpoint["step"], "sha256": checkpoint["sha256"]}
    except Exception:  # missing, damaged or not a checkpoint: the caller treats it as none
        return None


def on_host(value):
    """A copy of a state (nested dicts, lists, tensors) on the CPU that later steps cannot change."""
    if isinstance(value, torch.Tensor):
        return value.detach().to("cpu", copy=True)
    if isinstance(value, dict):
        return {key: on_host(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(on_host(item) for item in value)
    return copy.deepcopy(value)


class CheckpointWriter:
    """Writes checkpoints on a thread of its own, one at a time: `write` copies the state to the host and
    returns; `wait` blocks until the last one is on disk and raises what its writing raised."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def write(self, state: dict, path: Path, copies: list[Path] = (), then: Callable[[], None] | None = None
              ) -> None:  # fmt: skip
        """`state` to `path` (save_checkpoint), then the file copied to each of `copies` (e.g. best.pt),
        each atomically, then `then()` (e.g. run.json's record of best.pt: written once best.pt holds
        those weights), all on the writer's thread."""
        self.wait()  # never two at once: checkpoint.prev.pt must be the one before
        snapshot = on_host(state)

        def run() -> None:
            try:
                save_checkpoint(snapshot, path)
                for copy_path in copies:
                    copy_atomic(path, copy_path)
                if then is not None:
                    then()
            except BaseException as error:  # re-raised in the training thread by wait()
                self._error = error

        self._thread = threading.Thread(target=run, name=f"write {path.name}", daemon=False)
        self._thread.start()

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error


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


def resume_checkpoint(out_dir: Path, master: bool) -> tuple[dict, Path]:
    """(the content, the file) of checkpoint.pt, or of checkpoint.prev.pt (said in one line) when
    checkpoint.pt is missing or damaged; the damaged file is moved to checkpoint.bad.pt, so that the next
    save does not keep it as previous."""
    if not (out_dir / CHECKPOINT).is_file() and not (out_dir / PREVIOUS).is_file():
        raise CheckpointError(f"{out_dir / CHECKPOINT}: no such checkpoint: the run stopped before it wrote "
                              "its first; start it afresh with --overwrite")  # fmt: skip
    try:
        return load_checkpoint(out_dir / CHECKPOINT), out_dir / CHECKPOINT
    except CheckpointError as error:
        if not (out_dir / PREVIOUS).is_file():
            raise
        checkpoint = load_checkpoint(out_dir / PREVIOUS)
        if master:
            notice = f"{error}; resuming from {PREVIOUS} (epoch {checkpoint['epoch']})"
            console.print(notice, soft_wrap=True, markup=False, highlight=False)  # one line, as it is
            if (out_dir / CHECKPOINT).exists():
                os.replace(out_dir / CHECKPOINT, out_dir / DAMAGED)
        return checkpoint, out_dir / PREVIOUS
