"""`cli train` for runs of days (issue 50): validation during training equal to `cli eval`, the best
checkpoint, TensorBoard events, exact resume after kill -9 inside an epoch, non-finite steps skipped.

On the toy prepared dataset of test_baselines_train.py (validated on its train split), so that none of
this needs ../shared/data.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_baselines_train import toy_config, write_toy_dataset
from test_faults import REPO, TRAIN, cli, logged_steps, one_error_line, same_weights, wait_for

from baselines import train as train_module
from baselines.checkpoint import load_checkpoint
from baselines.train import TrainingStopped, setup, train, validation_epochs
from baselines.validate import VAL_METRICS, chosen_frames
from pipeline.manifest import PreparedData

STEPS_PER_EPOCH = 6  # test_faults' toy run: 12 frames, 2 per step, 3 epochs
# every path kept, so that the scores compared are not all 0 (3 epochs score no path above 0.5)
LONG = [*TRAIN, "--checkpoint-every", "4", "--set", "decoder.score_threshold=0.0", "--best-metric",
        "directed_topo_f1"]  # the toy lanes have no junction: their Junction TOPO F1 is 0 at every epoch


def records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def validated_run(tmp_path_factory) -> tuple[Path, Path]:
    """(toy data, a 3-epoch run validated after every epoch, its checkpoints written every 4 steps too)."""
    root = tmp_path_factory.mktemp("long_runs")
    data = write_toy_dataset(root, frames=12)
    run = root / "run"
    result = cli("train", "--data", data, "--out", run, *LONG)
    assert result.exit_code == 0, result.output
    return data, run


def test_validation_during_training_equals_cli_eval_and_names_the_best(validated_run, tmp_path):
    data, run = validated_run
    validations = records(run / "val.jsonl")
    assert [(v["epoch"], v["step"], v["frames"]) for v in validations] == [
        (1, 6, 12),
        (2, 12, 12),
        (3, 18, 12),
    ]
    assert all(v["split"] == "train" and v["seconds"] > 0 for v in validations)
    assert all(0 <= v[name] <= 1 for v in validations for name in VAL_METRICS)
    assert all(v["directed_topo_f1"] > 0 and v["miou"] > 0 for v in validations)
    assert len({v["directed_topo_f1"] for v in validations}) == 3  # each validation scores its own weights

    result = cli("eval", "--run", run, "--device", "cpu", "--no-floor", "--bootstrap", 0)
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["weights"] == {"checkpoint": "last", "file": "checkpoint.pt", "epoch": 3, "step": 18}
    last = validations[-1]
    for mode in ("directed", "undirected"):
        for metric in ("topo", "junction_topo"):
            assert last[f"{mode}_{metric}_f1"] == metrics[mode][metric]["f1"], (mode, metric)
    assert last["miou"] == metrics["miou"] and last["frames"] == metrics["frames"]

    # best.pt: the first validation with the highest --best-metric, in run.json and the summary
    first_best = validations[int(np.argmax([v["directed_topo_f1"] for v in validations]))]
    record = json.loads((run / "run.json").read_text())
    best = {"metric": "directed_topo_f1", "value": first_best["directed_topo_f1"],
            "epoch": first_best["epoch"], "step": first_best["step"],
            "split": "train", "eval_frames": 0, "seed": 0}  # fmt: skip
    assert record["best"] == best == record["summary"]["best"]
    assert load_checkpoint(run / "best.pt")["step"] == best["step"]
    result = cli(
        "eval", "--run", run, "--device", "cpu", "--no-floor", "--bootstrap", 0, "--checkpoint", "best"
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["weights"]["file"] == "best.pt" and metrics["weights"]["step"] == best["step"]
    assert metrics["directed"]["topo"]["f1"] == best["value"]

    # a run that never validated has no best.pt, and says so in one line
    (tmp_path / "nobest").mkdir()
    for name in ("config.json", "run.json", "checkpoint.pt"):
        (tmp_path / "nobest" / name).write_bytes((run / name).read_bytes())
    one_error_line(
        cli("eval", "--run", tmp_path / "nobest", "--checkpoint", "best"), "best.pt", "--eval-every"
    )


def test_validating_does_not_change_the_training(validated_run, tmp_path):
    """A run validated after every epoch and one validated after the last only train the same weights:
    validation leaves the RNG streams (the loader's seed draws) as they were."""
    data, validated = validated_run
    result = cli("train", "--data", data, "--out", tmp_path / "once", *LONG, "--eval-every", 0)
    assert result.exit_code == 0, result.output
    assert len(records(tmp_path / "once" / "val.jsonl")) == 1
    assert same_weights(tmp_path / "once", validated)


def test_tensorboard_events_hold_every_tag(validated_run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    _, run = validated_run
    events = EventAccumulator(str(run / "tb")).Reload()
    tags = set(events.Tags()["scalars"])
    expected = {"loss/loss", "loss/cls", "loss/points", "lr", "grad_norm", "speed/steps_per_s",
                "speed/samples_per_s", "speed/data_wait_share", "skipped_steps",
                *(f"val/{name}" for name in VAL_METRICS), "val/seconds"}  # fmt: skip
    assert expected <= tags, expected - tags
    assert [e.step for e in events.Scalars("loss/loss")] == list(range(1, 19))
    validations = records(run / "val.jsonl")
    junction = events.Scalars("val/directed_junction_topo_f1")
    assert [(e.step, e.value) for e in junction] == [
        (v["step"], pytest.approx(v["directed_junction_topo_f1"])) for v in validations
    ]
    log = records(run / "log.jsonl")
    assert all(0 <= r["data_wait_share"] < 1 and r["samples_per_s"] == 2 * r["steps_per_s"] for r in log)


@pytest.mark.parametrize("workers", [0, 2])
def test_killed_inside_an_epoch_after_a_checkpoint_resumes_to_the_same_weights(
    validated_run, tmp_path, workers
):
    """With loader workers (persistent: the loader draws their seed from torch's RNG at the first epoch
    alone) and without (a draw every epoch)."""
    data, straight = validated_run
    loader = ["--set", f"data.num_workers={workers}"]
    if workers:
        straight = tmp_path / "straight"
        result = cli("train", "--data", data, "--out", straight, *LONG, *loader)
        assert result.exit_code == 0, result.output
    run = tmp_path / "run"
    command = [sys.executable, "-m", "cli", "train", "--data", data, "--out", run, *LONG, *loader]
    process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def written(step: int) -> bool:
        try:
            return torch.load(run / "checkpoint.pt", weights_only=True)["step"] == step
        except (FileNotFoundError, RuntimeError, EOFError):
            return False

    # step 8 is epoch 2's second step: the checkpoint written there holds where its sampler stood
    wait_for(lambda: (run / "log.jsonl").is_file() and 9 in logged_steps(run) and written(8), process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    checkpoint = load_checkpoint(run / "checkpoint.pt")
    assert (checkpoint["step"], checkpoint["epoch"], checkpoint["epoch_steps"]) == (8, 1, 2)
    assert max(logged_steps(run)) >= 9  # killed after steps that the checkpoint does not hold
    result = cli("train", "--out", run, "--resume")
    assert result.exit_code == 0, result.output
    assert logged_steps(run) == list(range(1, 3 * STEPS_PER_EPOCH + 1))
    assert (
        load_checkpoint(run / "checkpoint.pt")["sha256"]
        == load_checkpoint(straight / "checkpoint.pt")["sha256"]
    )
    assert same_weights(run, straight)
    assert (run / "val.jsonl").read_text() != "" and [
        {k: v for k, v in r.items() if k != "seconds"} for r in records(run / "val.jsonl")
    ] == [{k: v for k, v in r.items() if k != "seconds"} for r in records(straight / "val.jsonl")]


class NonFiniteAt(torch.nn.Module):
    """A model's loss whose total is NaN at the given calls (1-based): a step that diverged."""

    def __init__(self, loss: torch.nn.Module, calls: set[int] | range):
        super().__init__()
        self.loss, self.calls, self.count = loss, calls, 0

    def forward(self, outputs, targets):
        losses = self.loss(outputs, targets)
        self.count += 1
        if self.count in self.calls:
            losses = {**losses, "loss": losses["loss"] * float("nan")}
        return losses


def nan_loss_at(monkeypatch, calls) -> None:
    from baselines.models import build

    def with_nan(config):
        built = build(config)
        built.loss = NonFiniteAt(built.loss, calls)
        return built

    monkeypatch.setattr(train_module, "build", with_nan)


def test_a_non_finite_step_changes_nothing_and_the_run_goes_on(tmp_path, monkeypatch):
    data = write_toy_dataset(tmp_path, frames=6)
    config = toy_config("lidar", epochs=2)
    nan_loss_at(monkeypatch, {2})
    s = setup(config, PreparedData.open(data))
    trainer = s.trainer
    first, second, third = [group for group, _ in zip(s.batches(), range(3), strict=False)]
    assert trainer.train_step(first).applied
    weights = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    moments = [state["exp_avg"].clone() for state in trainer.optimizer.state.values()]
    lr, scheduled = trainer.optimizer.param_groups[0]["lr"], trainer.scheduler.last_epoch
    step = trainer.train_step(second)
    assert not step.applied and not torch.isfinite(step.losses["loss"])
    assert all(torch.equal(v, weights[k]) for k, v in trainer.model.state_dict().items())
    assert all(torch.equal(s_["exp_avg"], m) for s_, m in zip(trainer.optimizer.state.values(), moments))
    assert (trainer.optimizer.param_groups[0]["lr"], trainer.scheduler.last_epoch) == (lr, scheduled)
    assert (trainer.step, trainer.skipped, trainer.bad_in_a_row) == (2, 1, 1)
    assert trainer.train_step(third).applied and trainer.bad_in_a_row == 0
    assert not all(torch.equal(v, weights[k]) for k, v in trainer.model.state_dict().items())

    # through train(): the step is logged as skipped, and the run ends with finite weights
    nan_loss_at(monkeypatch, {4})
    summary = train(config, data, tmp_path / "run")
    assert summary["steps"] == 6 and summary["skipped_steps"] == 1 and np.isfinite(summary["final_loss"])
    log = records(tmp_path / "run" / "log.jsonl")
    assert [r["step"] for r in log if "skipped" in r] == [4] and np.isnan(log[3]["loss"])
    assert all(
        torch.isfinite(v).all() for v in load_checkpoint(tmp_path / "run" / "checkpoint.pt")["model"].values()
    )


def test_steps_not_finite_in_a_row_stop_the_run_in_one_line(tmp_path, monkeypatch):
    data = write_toy_dataset(tmp_path, frames=12)
    nan_loss_at(monkeypatch, range(4, 100))
    config = toy_config("lidar", epochs=3)
    config.train.checkpoint_every, config.train.max_bad_steps = 2, 3
    with pytest.raises(TrainingStopped) as stopped:
        train(config, data, tmp_path / "run")
    message = str(stopped.value)
    assert message.startswith("step 6: 3 steps in a row with a non-finite loss or gradient norm")
    assert "not finite at this step: loss, grad_norm" in message
    # step 4's checkpoint holds step 3's weights: a skipped step leaves them as they were
    assert f"the last good checkpoint is {tmp_path / 'run' / 'checkpoint.pt'} (step 4)" in message
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["step"] == 4  # written, whole
    assert "\n" not in message

    # from the command line: one error line, exit code 1
    nan_loss_at(monkeypatch, range(1, 100))
    args = ["train", "--data", data, "--out", tmp_path / "cli", *TRAIN, "--max-bad-steps", 2]
    one_error_line(
        cli(*args), "step 2: 2 steps in a row", "--max-bad-steps 2", "no checkpoint was written yet"
    )


def test_the_validation_subset_is_fixed_by_the_seed():
    chosen = chosen_frames(100, 10, seed=0)
    assert len(set(chosen.tolist())) == 10 and np.all(np.diff(chosen) > 0)
    assert np.array_equal(chosen, chosen_frames(100, 10, seed=0))
    assert not np.array_equal(chosen, chosen_frames(100, 10, seed=1))
    assert np.array_equal(chosen_frames(5, 10, seed=0), np.arange(5))
    assert np.array_equal(chosen_frames(5, 0, seed=0), np.arange(5))


def test_the_epochs_validated_are_every_n_and_the_last():
    config = toy_config(epochs=5)
    for every, epochs in ((0, [5]), (1, [1, 2, 3, 4, 5]), (2, [2, 4, 5]), (7, [5])):
        config.train.eval_every = every
        assert sorted(validation_epochs(config)) == epochs
