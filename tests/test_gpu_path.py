"""The CUDA path's settings that the CPU can check: the paper preset's pretrained backbone (refused
without weights, mmdet's frozen stages), a run that no longer needs its weights file (eval, resume),
the paper's schedule per dataset, the image settings of real and synthetic data, pinned batches, the
FPS's precision, and `make gpu-check`'s schedule (equal epochs, the fixed one without step times) and its
archive of finished runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from baselines.config import EncoderConfig
from baselines.data import Batch, PreparedDataset, collate
from baselines.evaluate import evaluate
from baselines.layers.bev_encoder import CameraEncoder
from baselines.layers.resnet import build_resnet
from baselines.models import check_backbone_weights, load_config, resolve_config
from baselines.train import train, use_dataset_schedule
from benchmark.metric.table import parse_metrics
from benchmark.tables import eval_table
from cli import app
from pipeline.manifest import PreparedData, is_synthetic
from tests.test_baselines_train import toy_config, write_toy_dataset


def test_the_paper_preset_refuses_a_random_backbone_before_any_work(tmp_path):
    out = tmp_path / "run"
    args = ["train", "--data", str(tmp_path), "--out", str(out), "--model", "maptr"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "--pretrained FILE" in lines[0] and "--from-scratch" in lines[0], lines
    assert "resnet50(weights='IMAGENET1K_V1')" in lines[0] and not out.exists()
    result = CliRunner().invoke(app, [*args, "--pretrained", str(tmp_path / "moved.pth")])
    assert result.exit_code == 1 and "--pretrained " in result.output and "no such file" in result.output
    scratch = resolve_config("paper", model="maptr", from_scratch=True)
    assert (scratch.encoder.backbone_frozen_stages, scratch.encoder.backbone_norm_eval) == (-1, False)
    check_backbone_weights(scratch)  # said on purpose
    check_backbone_weights(resolve_config("paper", modality="lidar"))  # no camera, no backbone
    check_backbone_weights(resolve_config("paper", backbone_weights="resnet50.pth"))
    for preset in ("tiny", "gpu"):
        check_backbone_weights(resolve_config(preset))


STEM = ["conv1", "bn1"]


@pytest.mark.parametrize(
    ("stages", "frozen"), [(-1, []), (0, STEM), (1, [*STEM, "layer1"]), (2, [*STEM, "layer1", "layer2"])]
)
def test_frozen_stages_count_as_mmdets(stages, frozen):
    config = EncoderConfig(backbone="resnet18", backbone_width=8, bev_h=4, bev_w=2, channels=16,
                           backbone_frozen_stages=stages)  # fmt: skip
    backbone = CameraEncoder(config).backbone
    for name, module in backbone.named_children():
        trainable = {p.requires_grad for p in module.parameters()}
        if trainable:
            assert trainable == {name not in frozen}, name
    assert resolve_config("paper", backbone_weights="x").encoder.backbone_frozen_stages == 1  # MapTR's


def test_eval_and_resume_need_no_pretrained_file(tmp_path):
    """The checkpoint holds every weight: moving the --pretrained file away breaks neither."""
    data = write_toy_dataset(tmp_path, frames=2)
    weights = tmp_path / "backbone.pth"
    torch.save(build_resnet("resnet18", 16).state_dict(), weights)
    config = toy_config("camera", epochs=1)
    config.encoder.backbone_weights = str(weights)
    config.train.val_split = "train"
    run = tmp_path / "run"
    train(config, data, run)
    weights.rename(tmp_path / "elsewhere.pth")
    chosen = parse_metrics("lanegap,openlanev2")
    metrics = evaluate(run, data, "train", "cpu", floor=False, bootstrap=0, metrics=chosen)
    assert metrics["frames"] == 2 and metrics["precision"] == "fp32"
    # --metric: the other metric under its name in metrics.json, beside LaneGAP's
    written = json.loads((run / "metrics.json").read_text())
    assert written["openlanev2"]["frames"] == 2 and "directed" in written
    table, notes = eval_table(metrics)
    assert any(note.startswith("fps: batch 1 on cpu in fp32") for note in notes)
    resumed = load_config(run / "config.json")
    resumed.train.epochs = 2
    assert train(resumed, data, run, resume=True, told={"train.epochs"})["steps"] == 2


def test_the_paper_schedule_is_the_datasets(tmp_path, synth_prepared):
    for kind, epochs in (("av2", 24), ("nuscenes", 110)):
        config = resolve_config("paper", from_scratch=True)
        assert config.train.epochs == 0
        schedule = use_dataset_schedule(config, PreparedData.open(synth_prepared[kind]))
        assert schedule == f"the paper's {kind} schedule"
        assert config.train.epochs == epochs
    explicit = resolve_config("paper", epochs=3, from_scratch=True)
    schedule = use_dataset_schedule(explicit, PreparedData.open(synth_prepared["nuscenes"]))
    assert schedule == "set (preset or --epochs)"
    assert explicit.train.epochs == 3
    (tmp_path / "manifest.json").write_text(json.dumps({"root": "x"}))
    with pytest.raises(ValueError, match="no dataset kind .* give --epochs"):
        use_dataset_schedule(resolve_config("paper", from_scratch=True), PreparedData.open(tmp_path))


def test_real_data_gets_the_papers_image_scales_and_synthetic_data_its_own(
    synth_raw, synth_prepared, tmp_path
):
    assert is_synthetic(synth_raw / "av2" / "sensor") and is_synthetic(synth_raw / "nuscenes")
    assert not is_synthetic(write_toy_dataset(tmp_path).parent / "raw")
    for preset in ("paper", "gpu"):
        data = resolve_config(preset, from_scratch=True).data
        assert data.image_settings("nuscenes", False) == (0.5, 0.0)  # the paper's, uncropped
        assert data.image_settings("av2", False) == (0.3, 0.0)
        assert data.image_settings("av2", True) == (1.0, 0.4)  # the synthetic images as written
    gpu = resolve_config("gpu").data
    assert not gpu.cache_samples and gpu.num_workers > 0
    config = resolve_config("gpu", modality="camera")
    dataset = PreparedDataset(PreparedData.open(synth_prepared["av2"]), "train", config)
    assert dataset.synthetic
    sample = dataset[0]
    for camera, size in zip(
        dataset.frames[0]["cameras"], sample.image_sizes, strict=True
    ):  # scale 1, crop 40 %
        assert size.tolist() == [camera["height"] - int(0.4 * camera["height"]), camera["width"]]


def test_a_batch_pins_every_tensor(monkeypatch, tmp_path):
    """DataLoader(pin_memory=True) calls Batch.pin_memory: every tensor of the sensors and targets."""
    pinned = []
    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda self: pinned.append(self) or self)
    toy = PreparedData.open(write_toy_dataset(tmp_path, frames=2))
    dataset = PreparedDataset(toy, "train", toy_config("fusion"))
    batch = collate([dataset[0], dataset[1]])
    assert isinstance(batch.pin_memory(), Batch)
    tensors = [v for v in vars(batch.sensors).values() if isinstance(v, torch.Tensor)]
    tensors += [batch.targets.seg, *batch.targets.paths]
    assert len(tensors) == 11 and {id(t) for t in tensors} <= {id(t) for t in pinned}  # 8 sensor fields


def test_run_json_says_the_schedule_and_the_accumulation(tmp_path):
    data = write_toy_dataset(tmp_path, frames=4)
    config = toy_config("lidar", epochs=1)
    config.train.batch_size, config.train.accumulate = 4, 2
    summary = train(config, data, tmp_path / "run")
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert (run["accumulate"], run["batch_per_forward"], run["effective_batch_size"]) == (2, 2, 4)
    assert run["epochs"] == 1 and run["schedule"] == "set (preset or --epochs)"
    assert summary["steps"] == 1  # 4 frames, one optimiser step of two micro-batches
    assert Path(tmp_path / "run" / "checkpoint.pt").is_file()


def test_the_gpu_check_gives_every_model_the_epochs_that_fit_all_four(synth_prepared, tmp_path):
    from tools.gpu_check import MODELS, equal_epochs

    # the synthetic av2 train split: its frames at the gpu preset's batch of 8 make its steps per epoch
    config = resolve_config("gpu", modality="lidar")
    frames = len(PreparedDataset(PreparedData.open(synth_prepared["av2"]), "train", config))
    steps = frames // 8
    assert steps >= 1
    bench = tmp_path / "bench_step.json"

    def epochs_for(step_s: dict[str, float], train_seconds: float) -> int:
        bench.write_text(json.dumps([{"model": m, "step_s": step_s[m]} for m in MODELS]))
        return equal_epochs(bench, synth_prepared["av2"], train_seconds)

    # one epoch of all four takes steps x 1.0 s: 3.5 of them fit, so 3 for every model, the slowest too
    step_s = {"lanegap": 0.2, "hdmapnet": 0.4, "maptr": 0.25, "stsu": 0.15}
    assert epochs_for(step_s, train_seconds=3.5 * steps) == 3
    assert epochs_for(step_s, train_seconds=0.5 * steps) == 1  # at least one
    assert epochs_for(step_s, train_seconds=1000.0 * steps) == 16  # at most the gpu preset's
    bench.write_text(json.dumps([{"model": "lanegap", "step_s": 0.1}]))
    with pytest.raises(SystemExit, match="no step time of hdmapnet, maptr, stsu"):
        equal_epochs(bench, synth_prepared["av2"], 100.0)


def test_without_step_times_the_gpu_check_trains_the_short_fixed_schedule(tmp_path):
    from tools.gpu_check import FALLBACK_EPOCHS, schedule

    prepared = tmp_path / "not_read"  # neither the fixed schedule nor --epochs reads the data
    epochs, why = schedule(None, False, None, prepared, 110.0)
    assert epochs == FALLBACK_EPOCHS == 2 and "bench_step failed" in why
    assert schedule(5, False, None, prepared, 110.0) == (5, "--epochs")
    assert schedule(None, True, None, prepared, 110.0) == (1, "--smoke")


def test_the_gpu_check_archives_each_finished_run(tmp_path):
    import tarfile

    from tools.gpu_check import export_runs

    runs, results = tmp_path / "runs", tmp_path / "out"
    results.mkdir()
    for model, files in (
        ("lanegap", ("metrics.json", "run.json", "checkpoint.pt")),
        ("maptr", ("run.json",)),
    ):
        (runs / model).mkdir(parents=True)
        for name in files:
            (runs / model / name).write_text(f"{model} {name}")
    archive = export_runs(runs, results)
    with tarfile.open(archive) as tar:  # maptr is still training: no metrics.json yet
        assert sorted(tar.getnames()) == ["runs/lanegap/metrics.json", "runs/lanegap/run.json"]
        assert tar.extractfile("runs/lanegap/run.json").read() == b"lanegap run.json"
    assert sorted(path.name for path in results.iterdir()) == ["runs.tar.gz"]


def test_a_failed_bench_step_command_shows_the_tail_of_its_output():
    import subprocess

    from tools.bench_step import failure_message

    stderr = "".join(f"line {i}\n" for i in range(40)) + "ValueError: no frames\n"
    done = subprocess.CompletedProcess(["cli"], 1, stdout="progress\n", stderr=stderr)
    lines = failure_message(["prepare", "--dataset", "av2"], done).splitlines()
    assert lines[0] == "bench_step: cli prepare --dataset av2 failed (exit 1):"
    assert lines[1:] == [*(f"line {i}" for i in range(11, 40)), "ValueError: no frames"]
    quiet = subprocess.CompletedProcess(["cli"], 2, stdout="only stdout\n", stderr="")
    assert failure_message(["synth"], quiet).splitlines()[1:] == ["only stdout"]


def test_a_model_that_fails_does_not_stop_the_gpu_check(tmp_path, monkeypatch):
    """`gpu_check --smoke` with MapTR's training failing for real (its `cli train` reads a folder that holds
    no data): the other three train and are evaluated, summary.json records MapTR's command, exit status and
    the last lines of its output, the report covers the three, and the check exits non-zero. The other
    commands stand in for the CPU's 90 s of training a model (BENCHMARKS.md): each writes the files its real
    command writes that the check reads."""
    import sys

    from tools import gpu_check

    real_cli, commands = gpu_check.cli, []

    def cli(*args: str) -> None:
        commands.append(args)
        option = dict(zip(args[1::2], args[2::2], strict=False))
        if args[0] == "train" and option["--model"] == "maptr":
            failing = [*args]
            failing[failing.index("--data") + 1] = str(tmp_path / "no_data")
            return real_cli(*failing)
        if args[0] == "train":
            run, model = Path(option["--out"]), option["--model"]
            run.mkdir(parents=True)
            for name in ("checkpoint.pt", "predictions.parquet"):
                (run / name).write_bytes(b"")
            summary = {"steps": 1, "steps_per_s": 0.5, "train_seconds": 2.0, "samples_per_s": 1.0}
            (run / "run.json").write_text(json.dumps({"model": model, "epochs": 1, "summary": summary}))
        if args[0] == "eval":
            f1 = {"lanegap": 0.6, "hdmapnet": 0.4, "stsu": 0.3}[Path(option["--run"]).name]
            directed = {"topo": {"f1": f1}, "junction_topo": {"f1": f1 / 2}}
            floor = {"other_log_sensors": {"directed": {"topo": {"f1": 0.1}}},
                     "best_constant": {"directed": {"topo": {"f1": 0.2}}}}  # fmt: skip
            metrics = {"directed": directed, "floor": floor, "fps": 3.0, "precision": "fp32", "device": "cpu"}
            (Path(option["--run"]) / "metrics.json").write_text(json.dumps(metrics))
        if args[0] == "report":
            (tmp_path / "out" / "report").mkdir()
            (tmp_path / "out" / "report" / "report.md").write_text("report")

    monkeypatch.setattr(gpu_check, "cli", cli)
    monkeypatch.setattr(gpu_check, "PHASES", [])
    out, results = tmp_path / "out", tmp_path / "results"
    argv = ["gpu_check", "--smoke", "--out", str(out), "--results", str(results), "--workers", "1"]
    monkeypatch.setattr(sys, "argv", argv)
    assert gpu_check.main() == 1
    finished = ["lanegap", "hdmapnet", "stsu"]
    assert [args[2] for args in commands if args[0] == "train"] == ["lanegap", "hdmapnet", "maptr", "stsu"]
    assert [Path(args[2]).name for args in commands if args[0] == "eval"] == finished
    assert [args for args in commands if args[0] == "report"] == [
        ("report", *(f"--runs={out / 'runs' / model}" for model in ("hdmapnet", "lanegap", "stsu")), "--out",
         str(out / "report")),
    ]  # fmt: skip
    for written in (out / "summary.json", results / "summary.json"):
        summary = json.loads(written.read_text())
        assert summary["complete"] and [row["model"] for row in summary["rows"]] == finished
        (failure,) = summary["failures"]
        assert failure["stage"] == "maptr" and failure["exit_status"] == 1
        assert failure["command"].startswith("train --model maptr --preset gpu --data ")
        no_data = tmp_path / "no_data"
        assert failure["last_lines"][-1] == (
            f"error: {no_data / 'frames'}: no such table (is {no_data} a prepared dataset?)"
        )
    assert [row["topo"] for row in summary["rows"]] == [0.6, 0.4, 0.3]


def test_the_gpu_check_names_only_the_files_it_wrote_when_every_model_fails(tmp_path, monkeypatch):
    """Every model's training fails: no run finished, so no report is made, and the closing line names
    summary.json alone (it said `wrote .../report/report.md` before, a file that did not exist)."""
    import io
    import sys

    from rich.console import Console

    from tools import gpu_check

    def cli(*args: str) -> None:
        if args[0] == "train":
            raise gpu_check.CommandFailed(" ".join(args), 1, ["error: out of memory"])
        assert args[0] in ("synth", "prepare"), args  # no eval and no report without a finished run
        Path(args[args.index("--out") + 1]).mkdir(parents=True)  # their --out, as they make it

    shown = io.StringIO()
    monkeypatch.setattr(gpu_check, "cli", cli)
    monkeypatch.setattr(gpu_check, "PHASES", [])
    monkeypatch.setattr(gpu_check, "console", Console(file=shown, width=1000))
    out = tmp_path / "out"
    monkeypatch.setattr(sys, "argv", ["gpu_check", "--smoke", "--out", str(out), "--workers", "1"])
    assert gpu_check.main() == 1
    assert not (out / "report").exists()
    (wrote,) = [line for line in shown.getvalue().splitlines() if line.startswith("wrote ")]
    assert wrote == f"wrote {out / 'summary.json'}"
    summary = json.loads((out / "summary.json").read_text())
    assert [failure["stage"] for failure in summary["failures"]] == ["lanegap", "hdmapnet", "maptr", "stsu"]


def test_the_gpu_check_reads_a_tie_in_junction_topo_as_a_tie():
    """A smoke run's four models at J-TOPO F1 0 were said to be "led by" all four; the lead is read as
    the table shows it (3 decimals)."""
    from tools.gpu_check import MODELS, junction_topo_lead

    def rows(*scores: float) -> list[dict]:
        return [{"model": model, "junction_topo": score} for model, score in zip(MODELS, scores)]

    def lead(*scores: float) -> str:
        return junction_topo_lead(rows(*scores))

    claim = " (the paper's claim: LaneGAP leads; the report's summary says whether a lead is beyond the "
    assert lead(0.0, 0.0, 0.0, 0.0).startswith(
        "Junction TOPO F1 is level: lanegap, hdmapnet, maptr, stsu at 0.000" + claim
    )
    assert lead(0.4, 0.40004, 0.1, 0.2).startswith(
        "Junction TOPO F1 is led by lanegap and hdmapnet, level at 0.400" + claim
    )
    assert lead(0.3, 0.5, 0.1, 0.2).startswith("Junction TOPO F1 is led by hdmapnet at 0.500 (")
    assert lead(0.3).startswith("Junction TOPO F1 0.300: lanegap is the only model with a score, no lead")
    # a diverged model's nan leads nothing (it led when it came first)
    nan = float("nan")
    led = "Junction TOPO F1 is led by hdmapnet at 0.500 (lanegap: no finite score) (the paper's claim"
    assert lead(nan, 0.5, 0.1, 0.2).startswith(led)
    assert lead(nan, nan) == "Junction TOPO F1: no model has a finite score, no lead to read"
