"""A run folder never mixes two runs (issue 59): --overwrite removes every file of the earlier run, a
resume goes on with its checkpoint's config unless told otherwise on its command line, best.pt compares
like with like, run.json's best follows best.pt, and a resume runs on as many processes as saved it.

On the toy prepared dataset of test_baselines_train.py (4 frames, 2 steps per epoch), so that none of this
needs ../shared/data.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from test_baselines_train import toy_config, write_toy_dataset
from test_faults import cli, files, one_error_line

from baselines import train as train_module
from baselines.checkpoint import CheckpointError, load_checkpoint, peek, rng_state, save_checkpoint
from baselines.evaluate import evaluate
from baselines.models import load_config
from baselines.run_folder import RUN_FOLDER_FILES, ConfigChange, config_changes
from baselines.train import lr_factor, setup, train
from pipeline.manifest import PreparedData

# 4 toy frames, 2 per step, validated on the train split (the toy data has no other)
TRAIN = (
    "--preset tiny --modality lidar --batch-size 2 --path-points 10 --no-aux-seg --set train.threads=1 "
    "--set train.log_every=1 --set train.val_split=train --set train.warmup_iters=2"
).split()


def validated_config(epochs: int):
    config = toy_config("lidar", epochs=epochs)
    config.train.val_split = "train"
    return config


def run_json(run: Path) -> dict:
    return json.loads((run / "run.json").read_text())


@pytest.fixture(scope="module")
def toy_data(tmp_path_factory) -> Path:
    return write_toy_dataset(tmp_path_factory.mktemp("run_folder"), frames=4)


def test_overwrite_removes_every_file_of_the_earlier_run_and_resume_never_loads_its_old_weights(
    toy_data, tmp_path
):
    run = tmp_path / "run"
    train(validated_config(epochs=2), toy_data, run)
    evaluate(run, device="cpu", floor=False, bootstrap=0)
    (run / "notes.txt").write_text("the user's")
    written = {path.name for path in run.iterdir()} - {"notes.txt"}
    # RUN_FOLDER_FILES knows every file of a run and its evaluation: --overwrite removes them all
    assert written <= set(RUN_FOLDER_FILES)
    expected = {"checkpoint.pt", "checkpoint.prev.pt", "best.pt", "tb", "metrics.json", "predictions.parquet",
                "frame_counts.parquet", "log.jsonl", "val.jsonl"}  # fmt: skip
    assert expected <= written

    # a new run that stops before its first checkpoint (a kill) leaves none of the earlier run's files
    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(train_module, "train_one_epoch", killed)
        with pytest.raises(KeyboardInterrupt):
            train(validated_config(epochs=2), toy_data, run, overwrite=True)
    left = {path.name for path in run.iterdir()}
    assert left - {"tb"} == {"config.json", "run.json", "log.jsonl", "val.jsonl", "notes.txt"}
    assert (run / "notes.txt").read_text() == "the user's"
    assert (run / "val.jsonl").read_text() == "" and "best" not in run_json(run)
    # resumed, it is refused in one line: the earlier run's weights are never loaded
    with pytest.raises(CheckpointError, match="checkpoint.pt: no such checkpoint.*--overwrite"):
        train(load_config(run / "config.json"), toy_data, run, resume=True)
    one_error_line(cli("train", "--out", run, "--resume"), "no such checkpoint", "--overwrite")


def test_a_folder_holding_any_file_of_a_run_is_refused_without_overwrite(toy_data, tmp_path):
    run = tmp_path / "run"
    train(validated_config(epochs=1), toy_data, run)
    stale = tmp_path / "stale"
    stale.mkdir()
    shutil.copyfile(run / "checkpoint.pt", stale / "checkpoint.pt")  # no config.json beside it
    before = files(stale)
    args = ["train", "--data", toy_data, "--out", stale, *TRAIN, "--epochs", 1]
    one_error_line(cli(*args), str(stale), "holds a run already (checkpoint.pt)", "--overwrite")
    one_error_line(cli(*args, "--resume", "--overwrite"), "--resume and --overwrite")
    assert files(stale) == before


def test_a_config_changed_by_hand_is_refused_and_a_set_on_resume_is_logged(toy_data, tmp_path):
    run = tmp_path / "run"
    result = cli("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 2, "--stop-after", 1)
    assert result.exit_code == 0, result.output
    trained = json.loads((run / "config.json").read_text())
    assert load_checkpoint(run / "checkpoint.pt")["config"] == load_config(run / "config.json").to_dict()
    lr = trained["train"]["lr"]

    edited = {**trained, "train": {**trained["train"], "lr": 2 * lr}}
    (run / "config.json").write_text(json.dumps(edited))
    before = files(run)
    error = one_error_line(cli("train", "--out", run, "--resume"), "checkpoint.pt: trained with", "train.lr")
    assert f"train.lr={lr}" in error and f"--set train.lr={2 * lr}" in error
    assert files(run) == before  # nothing of the run was touched
    (run / "config.json").write_text(json.dumps(trained))
    before = files(run)
    refused = cli("train", "--out", run, "--resume", "--set", "encoder.channels=8")  # told, but no fit
    one_error_line(refused, "--set encoder.channels=8 on --resume", "it shapes the model")
    assert files(run) == before

    result = cli("train", "--out", run, "--resume", "--set", f"train.lr={2 * lr}")
    assert result.exit_code == 0, result.output
    assert f"resumed at step 2 with train.lr {lr} -> {2 * lr}" in result.output
    assert json.loads((run / "config.json").read_text()) == edited
    assert run_json(run)["config_changes"] == [
        {"field": "train.lr", "before": lr, "after": 2 * lr, "step": 2}
    ]
    checkpoint = load_checkpoint(run / "checkpoint.pt")
    assert checkpoint["step"] == 4 and checkpoint["config"]["train"]["lr"] == 2 * lr
    # the steps after the resume ran with the new learning rate (the schedule's factor over it)
    config = load_config(run / "config.json")
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [1, 2, 3, 4]
    assert log[1]["lr"] == pytest.approx(lr * lr_factor(2, 4, config))
    assert log[2]["lr"] == pytest.approx(2 * lr * lr_factor(3, 4, config))


def test_config_changes_keep_a_change_logged_from_the_checkpoints_step_on():
    trained = {"model": "lanegap", "train": {"lr": 1.0, "epochs": 2, "betas": [0.9, 0.99]}}
    going_on = {"model": "lanegap", "train": {"lr": 2.0, "epochs": 3, "betas": [0.9, 0.99]}, "new": {"x": 1}}
    where = (Path("run/checkpoint.pt"), Path("run/config.json"))
    told = config_changes(trained, going_on, {"train.lr", "train.epochs"}, [], 4, *where)
    assert told == [ConfigChange("train.epochs", 2, 3, 4), ConfigChange("train.lr", 1.0, 2.0, 4)]
    # a resume from step 4 again (its run stopped before a checkpoint) keeps what the first logged
    logged = [{"field": "train.lr", "before": 1.0, "after": 2.0, "step": 4}]
    assert config_changes(trained, going_on, {"train.epochs"}, logged, 4, *where) == told[:1]
    # a change logged before the checkpoint's step is the checkpoint's own: this one is not explained
    with pytest.raises(CheckpointError) as refused:
        config_changes(trained, going_on, {"train.epochs"}, [{**logged[0], "step": 2}], 4, *where)
    assert str(refused.value) == (
        "run/checkpoint.pt: trained with train.lr=1.0, but run/config.json has train.lr=2.0, a change not "
        "given on the command line: give it with --resume as --set train.lr=2.0 (then it is logged in "
        "run.json), or put train.lr=1.0 back"
    )
    tuples = {"model": "lanegap", "train": {"lr": 1.0, "epochs": 2, "betas": [0.9, 0.9]}}
    with pytest.raises(CheckpointError, match="train.betas=0.9,0.99, but .* has train.betas=0.9,0.9"):
        config_changes(trained, tuples, set(), [], 4, *where)


def test_another_best_metric_or_frame_subset_starts_the_best_anew(toy_data, tmp_path):
    run = tmp_path / "run"
    args = ["--best-metric", "directed_topo_f1", "--stop-after", 1]
    result = cli("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 3, *args)
    assert result.exit_code == 0, result.output
    first = run_json(run)["best"]
    assert (first["metric"], first["step"], first["eval_frames"]) == ("directed_topo_f1", 2, 0)

    result = cli("train", "--out", run, "--resume", "--best-metric", "miou", "--stop-after", 1)
    assert result.exit_code == 0, result.output
    said = [line for line in result.output.splitlines() if "starts anew" in line]
    assert said == [
        f"best.pt starts anew: it holds the best directed_topo_f1 on all of 'train' ({first['value']:.4f} at "
        "step 2); this run validates by miou on all of 'train'"
    ]
    validations = [json.loads(line) for line in (run / "val.jsonl").read_text().splitlines()]
    # the next validation is the best whatever its value: it is never compared with another metric's
    best = run_json(run)["best"]
    assert (best["metric"], best["step"], best["value"]) == ("miou", 4, validations[-1]["miou"])
    assert load_checkpoint(run / "best.pt")["step"] == 4
    assert run_json(run)["best_restarts"] == [{"step": 2, "previous": first, "now": "miou on all of 'train'"}]

    result = cli("train", "--out", run, "--resume", "--eval-frames", 1)
    assert result.exit_code == 0, result.output
    assert "this run validates by miou on 1 frames of 'train' drawn by seed 0" in result.output
    last = json.loads((run / "val.jsonl").read_text().splitlines()[-1])
    best = run_json(run)["best"]
    assert (last["step"], last["frames"]) == (6, 1)
    assert (best["step"], best["eval_frames"], best["value"]) == (6, 1, last["miou"])
    assert [entry["step"] for entry in run_json(run)["best_restarts"]] == [2, 4]
    assert run_json(run)["summary"]["best"] == best


def test_run_json_names_a_best_only_once_best_pt_holds_it_and_resume_repairs_a_kill_between(
    toy_data, tmp_path, monkeypatch
):
    copy = shutil.copyfile

    def stopped_at_best(source, target, **kwargs):  # the run stops between checkpoint.pt and best.pt
        if Path(target).name.startswith(".best.pt"):
            raise OSError("stopped before best.pt")
        return copy(source, target, **kwargs)

    run = tmp_path / "run"
    monkeypatch.setattr(shutil, "copyfile", stopped_at_best)
    with pytest.raises(OSError, match="stopped before best.pt"):
        train(validated_config(epochs=1), toy_data, run)
    monkeypatch.undo()
    checkpoint = load_checkpoint(run / "checkpoint.pt")
    assert checkpoint["best"]["step"] == checkpoint["step"] == 2
    assert not (run / "best.pt").exists() and "best" not in run_json(run)

    train(load_config(run / "config.json"), toy_data, run, resume=True)  # every epoch done: repairs only
    assert peek(run / "best.pt") == {"step": 2, "sha256": checkpoint["sha256"]}
    assert run_json(run)["best"] == checkpoint["best"]


def test_a_plain_resume_of_a_run_from_before_the_best_recorded_how_it_was_measured_keeps_its_best(
    toy_data, tmp_path, capsys
):
    """A checkpoint, best.pt and run.json of the earlier version: their best is metric, value, epoch and
    step only. Its split, frames and seed are those of the config the checkpoint was trained with, so a plain
    resume keeps it (before, it restarted the best and the next validation replaced best.pt, even a worse
    one). The recorded value, 2, is above any F1: no validation may replace it."""
    run = tmp_path / "run"
    config = validated_config(epochs=2)
    train(config, toy_data, run, stop_after=1)
    old = {"metric": config.train.best_metric, "value": 2.0, "epoch": 1, "step": 2}
    state = {k: v for k, v in load_checkpoint(run / "checkpoint.pt").items() if k != "sha256"}
    assert set(state["best"]) == {"metric", "value", "epoch", "step", "split", "eval_frames", "seed"}
    (run / "checkpoint.pt").unlink()
    save_checkpoint({**state, "best": old}, run / "checkpoint.pt")
    shutil.copyfile(run / "checkpoint.pt", run / "best.pt")
    (run / "run.json").write_text(json.dumps({**run_json(run), "best": old}))
    capsys.readouterr()

    train(load_config(run / "config.json"), toy_data, run, resume=True)
    assert "starts anew" not in capsys.readouterr().err
    record = run_json(run)
    kept = {**old, "split": "train", "eval_frames": 0, "seed": 0}
    assert "best_restarts" not in record and record["best"] == record["summary"]["best"] == kept
    assert [json.loads(line)["step"] for line in (run / "val.jsonl").read_text().splitlines()] == [2, 4]
    assert peek(run / "best.pt")["step"] == 2  # step 4's validation did not replace it
    assert load_checkpoint(run / "checkpoint.pt")["best"] == kept


def test_a_resume_on_fewer_or_more_processes_than_saved_the_checkpoint_is_refused(toy_data):
    config = validated_config(epochs=1)
    trainer = setup(config, PreparedData.open(toy_data)).trainer
    two = trainer.state(0, 0, config, [rng_state(), rng_state()], {})
    with pytest.raises(CheckpointError, match=r"2 process\(es\), this run has 1: .*--nproc_per_node 2\)"):
        trainer.load(two, world_size=1)
    one = trainer.state(0, 0, config, [rng_state()], {})
    with pytest.raises(CheckpointError, match=r"1 process\(es\), this run has 2: .*--nproc_per_node 1\)"):
        trainer.load(one, world_size=2)
    trainer.load(one, world_size=1)
    assert all(torch.equal(v, one["model"][k]) for k, v in trainer.model.state_dict().items())


def test_each_option_given_on_resume_is_applied_as_a_told_change_or_refused_by_name(toy_data, tmp_path):
    """Before, `cli train --resume` silently dropped --batch-size, --accumulate, --model, --preset,
    --modality, --path-points, --bezier-points, --aux-seg, --pretrained and --from-scratch."""
    run = tmp_path / "run"
    result = cli("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 2, "--stop-after", 1)
    assert result.exit_code == 0, result.output
    weights = tmp_path / "r18.pth"
    weights.write_bytes(b"")
    before = files(run)
    refused = {
        ("--batch-size", "4"): "train.batch_size=2, and another batch changes the steps per epoch",
        ("--set", "train.batch_size=4"): "train.batch_size=2, and another batch",
        ("--model", "maptr"): "model='lanegap', and the checkpoint holds that model's weights",
        ("--preset", "gpu"): "preset='tiny', and the preset sized every section",
        ("--modality", "camera"): "encoder.modality='lidar', and it shapes the model",
        ("--path-points", "20"): "decoder.path_points=10, and it shapes the model",
        ("--bezier-points", "5"): "decoder.bezier_points=0, and it shapes the model",
        ("--aux-seg",): "decoder.aux_seg=False, and it shapes the model",
        ("--pretrained", weights): "encoder.backbone_weights='', and the checkpoint holds the backbone's",
    }
    for args, why in refused.items():
        shown = " ".join(map(str, args))
        error = one_error_line(cli("train", "--out", run, "--resume", *args), why)
        assert error.startswith(f"error: {shown} on --resume: the run in {run} was trained with "), error
        assert error.endswith("(leave the option out, or start another run in another --out)")
    assert files(run) == before  # refused before any work

    # the run's own command line again, with --resume: its options change nothing; --accumulate 2 splits
    # each batch of 2 in two micro-batches, 2 steps per epoch as before: a told change, logged
    again = ("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 2, "--from-scratch")
    result = cli(*again, "--model", "lanegap", "--resume", "--accumulate", 2)
    assert result.exit_code == 0, result.output
    assert "resumed at step 2 with train.accumulate 0 -> 2" in result.output
    assert run_json(run)["config_changes"] == [
        {"field": "train.accumulate", "before": 0, "after": 2, "step": 2}
    ]
    assert load_config(run / "config.json").train.accumulate == 2
    checkpoint = load_checkpoint(run / "checkpoint.pt")
    assert checkpoint["step"] == 4 and checkpoint["config"]["train"]["accumulate"] == 2
    assert "micro-batch" in result.output and "2 micro-batch(es) x 1 frames" in result.output


def test_micro_batches_changed_on_resume_that_change_the_steps_per_epoch_are_refused(tmp_path):
    # 6 frames in batches of 4: one step an epoch (the last 2 frames dropped) in one micro-batch of 4, but
    # two in micro-batches of 2 (3 of them: a step of 2, then one of 1)
    data = write_toy_dataset(tmp_path, frames=6)
    run = tmp_path / "run"
    args = [*TRAIN, "--batch-size", 4]
    result = cli("train", "--data", data, "--out", run, *args, "--epochs", 2, "--stop-after", 1)
    assert result.exit_code == 0, result.output
    config = load_config(run / "config.json")
    s = setup(config, PreparedData.open(data))
    assert s.steps_per_epoch == config.train.steps_per_epoch(6, 1) == 1  # as the loader makes them
    config.train.accumulate = 2
    assert config.train.steps_per_epoch(6, 1) == 2
    before = files(run)
    error = one_error_line(
        cli("train", "--out", run, "--resume", "--accumulate", 2), "train.accumulate 0 -> 2"
    )
    assert error == (
        "error: train.accumulate 0 -> 2 on --resume: 2 optimiser steps per epoch, the checkpoint's run had 1 "
        "(the epoch's last frames split otherwise): its step count, schedule and place in the epoch stand on "
        "them; resume with the micro-batches it had or with ones that keep 1"
    )
    assert files(run) == before


def test_no_from_scratch_on_resume_is_refused_where_it_changes_the_run_and_accepted_where_it_does_not(
    tmp_path,
):
    """Before, `--resume --no-from-scratch` was neither applied, refused nor logged: resuming a
    --from-scratch paper run with it asks to freeze and BatchNorm-eval a backbone the checkpoint trained."""
    from baselines.models import resolve_config, resume_config

    for from_scratch, (run, refused, accepted) in {
        True: ("scratch", False, True),
        False: ("pretrained", True, False),
    }.items():
        out = tmp_path / run
        out.mkdir()
        config = resolve_config("paper", "lidar", from_scratch=from_scratch)
        (out / "config.json").write_text(json.dumps(config.to_dict()))
        (out / "run.json").write_text("{}")
        with pytest.raises(ValueError) as error:
            resume_config(out, {"from_scratch": refused}, [])
        frozen = config.encoder.backbone_frozen_stages
        flag = "--from-scratch" if refused else "--no-from-scratch"
        assert str(error.value).startswith(f"{flag} on --resume: the run in {out} was trained with "
                                           f"encoder.backbone_frozen_stages={frozen}, and it sets which")
        resumed, told = resume_config(out, {"from_scratch": accepted}, [])
        assert resumed.to_dict() == config.to_dict() and told == set()


def test_options_set_in_train_options_count_on_resume_from_python(toy_data, tmp_path):
    """`launch` takes its options from TrainOptions alone: before, a resume read only a separate `given`
    dict, so that a field set in TrainOptions but left out of it was silently ignored."""
    from baselines.launch import TrainOptions, launch

    run = tmp_path / "run"
    result = cli("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 2, "--stop-after", 1)
    assert result.exit_code == 0, result.output
    before = files(run)
    with pytest.raises(ValueError) as refused:
        launch(TrainOptions(out=run, resume=True, batch_size=4))
    assert str(refused.value).startswith(f"--batch-size 4 on --resume: the run in {run} was trained with "
                                         "train.batch_size=2, and another batch changes the steps per epoch")
    assert files(run) == before
    launched = launch(TrainOptions(out=run, resume=True, batch_size=2, accumulate=2))
    assert launched.config.model == "lanegap" and launched.config.preset == "tiny"
    assert launched.config.train.accumulate == 2 and launched.data == toy_data
    changes = [{"field": "train.accumulate", "before": 0, "after": 2, "step": 2}]
    assert run_json(run)["config_changes"] == changes
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 4


def test_a_set_on_resume_that_reshapes_the_model_is_refused_by_name_before_any_work(
    toy_data, tmp_path, monkeypatch
):
    """Before, a --set of a field that shapes the model but that KEPT_ON_RESUME does not list passed the
    check of the options and failed only when the checkpoint's weights were loaded, after the dataset, the
    model and the validation were built. Now the models of the two configs are compared on the meta device
    and the --set items that reshape it are named; the others of the command line are not."""
    import baselines.launch

    run = tmp_path / "run"
    result = cli("train", "--data", toy_data, "--out", run, *TRAIN, "--epochs", 2, "--stop-after", 1)
    assert result.exit_code == 0, result.output
    trained = load_config(run / "config.json")
    before = files(run)

    def never(*args, **kwargs):
        raise AssertionError("the refused resume started training")

    monkeypatch.setattr(baselines.launch, "train", never)
    lr, channels, paths = trained.train.lr, trained.encoder.channels, trained.decoder.num_paths
    refused = {
        ("--set", f"decoder.num_paths={paths + 2}", "--set", f"train.lr={2 * lr}"): (
            f"--set decoder.num_paths={paths + 2} on --resume: the run in {run} was trained with "
            f"decoder.num_paths={paths}, and it shapes the model, whose weights the checkpoint holds: a "
            "resume goes on with it"
        ),
        ("--set", f"encoder.channels={2 * channels}", "--set", f"decoder.num_paths={paths + 2}"): (
            f"--set encoder.channels={2 * channels} --set decoder.num_paths={paths + 2} on --resume: the run "
            f"in {run} was trained with encoder.channels={channels}, decoder.num_paths={paths}, and they "
            "shape the model, whose weights the checkpoint holds: a resume goes on with them"
        ),
    }
    for args, why in refused.items():
        error = one_error_line(cli("train", "--out", run, "--resume", *args), why)
        assert error.startswith(f"error: {why}"), error
    assert files(run) == before  # nothing written
    # a field of the same sections that keeps every shape is a told change, as before
    from baselines.models import resume_config

    dropout = trained.decoder.dropout
    config, told = resume_config(run, {}, [f"decoder.dropout={dropout / 2}", "train.lr=0.5"])
    assert told == {"decoder.dropout", "train.lr"} and config.decoder.dropout == dropout / 2
