"""`pfnet train` and the training loop on the procedural `tiny_dataset` (CPU)."""

from __future__ import annotations

import json
import math
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.cli import main  # noqa: E402
from pfnet.data import prepare_dataset  # noqa: E402
from pfnet.errors import ConfigError, DataError  # noqa: E402
from pfnet.inference.checkpoint import load_checkpoint, read_checkpoint  # noqa: E402
from pfnet.models import MODELS  # noqa: E402
from pfnet.training import preset_config, train  # noqa: E402
from pfnet.training.step import TrainingStep  # noqa: E402

# The small preset with more, smaller batches: ~6 steps per epoch on the 24 training shapes.
FAST = preset_config("small").replace(batch_size=4, epochs=12)


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def _without_times(rows: list[dict]) -> list[dict]:
    return [
        {k: v for k, v in row.items() if k not in ("time_s", "compute_s", "train_s")}
        for row in rows
    ]


@pytest.mark.slow
def test_pfnet_learns_on_the_tiny_dataset(tiny_dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    summary = train(FAST, tiny_dataset, run, device="cpu", progress=False)
    rows = _rows(run)
    assert [r["epoch"] for r in rows] == list(range(13))
    untrained = rows[0]["val_cd_l2"]
    assert summary["best_val_cd_l2"] < 0.6 * untrained
    assert rows[-1]["val_cd_l2"] < untrained
    assert min(r["cd_detail"] for r in rows[-5:]) < 0.6 * rows[1]["cd_detail"]
    assert {"loss_d", "adv_g", "cd_primary", "cd_secondary", "lr", "alpha"} <= set(rows[1])
    assert summary["epochs"] == 12 and not summary["interrupted"]
    for name in ("last.pt", "best.pt", "log.jsonl", "curves.png", "config.json"):
        assert (run / name).stat().st_size > 0
    assert (run / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in run.iterdir() if p.name.startswith(".")]  # no temporary files left
    best = read_checkpoint(run / "best.pt")
    assert best["epoch"] == summary["best_epoch"]
    assert best["metrics"]["val_cd_l2"] == summary["best_val_cd_l2"]
    # best.pt holds what inference needs, not the optimiser states of last.pt.
    assert "optimizer_g" not in best and "discriminator" not in best
    assert (run / "best.pt").stat().st_size < 0.5 * (run / "last.pt").stat().st_size


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_model_trains_through_the_cli_and_reloads(
    name: str, tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / name
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--preset", "small"]
    argv += ["--model", name, "--epochs", "1", "--batch-size", "9", "--width", "0.125"]
    assert main([*argv, "--device", "cpu"]) == 0
    assert f"trained {name} for 1 epoch(s) on 1 process(es)" in capsys.readouterr().out
    # A plain weights_only load: no pickled code in the checkpoint.
    raw = torch.load(run / "last.pt", weights_only=True)
    assert raw["config"]["model"] == name and raw["epoch"] == 1
    assert (raw["discriminator"] is not None) == (name == "pfnet")
    model, config = load_checkpoint(run / "best.pt")
    assert not model.training and type(model) is MODELS[name]
    assert (config.n_points, config.n_missing, config.missing_ratio) == (512, 128, 0.25)
    with torch.no_grad():
        assert model(torch.rand(1, 384, 3)).detail.shape == (1, 128, 3)
    rows = _rows(run)
    assert len(rows) == 2 and all(map(torch.isfinite, map(torch.tensor, rows[1].values())))


def test_the_l1_chamfer_loss_trains_logs_the_l2_measure_and_stays_in_its_run(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["train", "--data", str(tiny_dataset), "--preset", "small", "--model"]
    argv += ["mlp", "--epochs", "1", "--batch-size", "8", "--width", "0.125"]
    for chamfer in ("l2", "l1"):
        run = tmp_path / chamfer
        assert main([*argv, "--out", str(run), "--chamfer", chamfer, "--device", "cpu"]) == 0
        assert json.loads((run / "config.json").read_text())["chamfer"] == chamfer
        row = _rows(run)[1]
        # The MLP's loss is its one Chamfer term: the logged CD-L2 itself on l2, the mean
        # distances on l1.
        if chamfer == "l2":
            assert row["loss_g"] == pytest.approx(row["cd_detail"])
        else:
            assert row["loss_g"] != pytest.approx(row["cd_detail"], rel=0.05)
    capsys.readouterr()
    resume = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "l1"), "--resume"]
    assert main([*resume, "--chamfer", "l2", "--device", "cpu"]) == 1
    assert "cannot change chamfer when resuming" in capsys.readouterr().err


def _interrupt_at(monkeypatch: pytest.MonkeyPatch, call: int) -> None:
    """Deliver a real SIGINT during the ``call``-th training step."""
    original = TrainingStep.__call__
    calls = []

    def step(self, batch, alpha):
        calls.append(1)
        if len(calls) == call:
            signal.raise_signal(signal.SIGINT)
        return original(self, batch, alpha)

    monkeypatch.setattr(TrainingStep, "__call__", step)


@pytest.mark.usefixtures("sigint_as_in_a_terminal")
@pytest.mark.parametrize("ema", [0.0, 0.9])
def test_ctrl_c_saves_and_resume_equals_an_uninterrupted_run(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ema: float
) -> None:
    config = FAST.replace(epochs=2, batch_size=5, width=0.125, ema=ema)  # 5 steps per epoch
    whole = tmp_path / "whole"
    train(config, tiny_dataset, whole, device="cpu", progress=False)

    split = tmp_path / "split"
    before = signal.getsignal(signal.SIGINT)
    with monkeypatch.context() as patch:
        _interrupt_at(patch, 7)  # epoch 2, batch 2
        summary = train(config, tiny_dataset, split, device="cpu", progress=False)
    assert summary["interrupted"] and summary["epochs"] == 1 and summary["batches_done"] == 2
    assert signal.getsignal(signal.SIGINT) is before  # handler restored
    state = read_checkpoint(split / "last.pt")
    assert (state["epoch"], state["batches_done"]) == (1, 2)

    resumed = train(config, tiny_dataset, split, device="cpu", progress=False, resume=True)
    assert not resumed["interrupted"] and resumed["epochs"] == 2
    assert _without_times(_rows(split)) == _without_times(_rows(whole))
    a = read_checkpoint(whole / "last.pt")
    b = read_checkpoint(split / "last.pt")
    assert (a["average"] is None) == (ema == 0)
    assert ("val_live_cd_l2" in _rows(whole)[-1]) == (ema > 0)
    models = {key: a[key] for key in ("model", "discriminator")}
    if ema:
        assert a["average"]["updates"] == b["average"]["updates"] == 10
        models["average"] = a["average"]["model"]
    for key, weights in models.items():
        for name, tensor in weights.items():
            expected = b["average"]["model"] if key == "average" else b[key]
            assert torch.equal(tensor, expected[name]), f"{key}.{name}"


@pytest.mark.usefixtures("sigint_as_in_a_terminal")
def test_ctrl_c_through_the_cli_exits_130_and_resume_extends_the_run(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--preset", "small"]
    argv += ["--model", "mlp", "--epochs", "1", "--batch-size", "8", "--width", "0.125"]
    with monkeypatch.context() as patch:
        _interrupt_at(patch, 2)
        assert main(argv) == 130
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--resume"]) == 0
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--resume",
                 "--epochs", "2"]) == 0  # fmt: skip
    assert [r["epoch"] for r in _rows(run)] == [0, 1, 2]


def test_resume_with_more_epochs_follows_the_longer_runs_schedule(
    tiny_dataset: Path, tmp_path: Path
) -> None:
    """A run sized to its length (the small preset) extended by ``--resume --epochs`` takes
    the longer run's rates from where it stopped, not the shorter run's decayed one (the
    demo times 2 epochs, then resumes for its budget: it trained at 1/25 of its rate)."""
    from pfnet.training.schedule import lr_factor

    config = FAST.replace(model="mlp", width=0.125, batch_size=8)  # 3 steps an epoch
    short, longer = config.replace(epochs=2), config.replace(epochs=8)
    train(short, tiny_dataset, tmp_path / "short", device="cpu", progress=False)
    assert [r["lr"] for r in _rows(tmp_path / "short")[1:]] == pytest.approx([5e-4, 1e-4])
    train(longer, tiny_dataset, tmp_path / "short", device="cpu", progress=False, resume=True)
    train(longer, tiny_dataset, tmp_path / "whole", device="cpu", progress=False)
    extended, whole = (_rows(tmp_path / run)[1:] for run in ("short", "whole"))
    assert [r["lr"] for r in extended[2:]] == pytest.approx([r["lr"] for r in whole[2:]])
    assert whole[2]["lr"] == pytest.approx(5e-4 * lr_factor(longer, 2))
    assert [r["lr"] / 5e-4 for r in whole] == pytest.approx([1, 1, 1, 1, 0.2, 0.2, 0.04, 0.04])


def test_scheduler_states_of_before_resume_on_the_runs_schedule() -> None:
    """Checkpoints written with StepLR and MultiStepLR states resume on the closed form."""
    from pfnet.training.schedule import lr_factor, make_scheduler, resume_scheduler

    config = FAST.replace(epochs=10, lr=1.0)  # drops at epochs 5 and 8 (0.5, 0.75 of 10)
    old = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    multistep = torch.optim.lr_scheduler.MultiStepLR(old, milestones=[5, 8], gamma=0.2)
    for _ in range(6):
        old.step()
        multistep.step()
    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    optimizer.load_state_dict(old.state_dict())
    scheduler = make_scheduler(optimizer, config)
    resume_scheduler(scheduler, multistep.state_dict())
    assert optimizer.param_groups[0]["lr"] == pytest.approx(0.2) == lr_factor(config, 6)
    rates = []
    for _ in range(4):
        optimizer.step()
        scheduler.step()
        rates.append(optimizer.param_groups[0]["lr"])
    assert rates == pytest.approx([0.2, 0.04, 0.04, 0.04])
    assert scheduler.get_last_lr() == pytest.approx([0.04])


def test_run_folder_and_resume_errors(tiny_dataset: Path, tmp_path: Path) -> None:
    config = FAST.replace(model="mlp", epochs=1, width=0.125)
    run = tmp_path / "run"
    with pytest.raises(DataError, match="last.pt does not exist"):
        train(config, tiny_dataset, run, device="cpu", resume=True)
    train(config, tiny_dataset, run, device="cpu", progress=False)
    with pytest.raises(ConfigError, match="already holds a run .*resume it to continue"):
        train(config, tiny_dataset, run, device="cpu")
    with pytest.raises(ConfigError, match="cannot change lr when resuming: .* trained with 0.0005"):
        train(config.replace(lr=0.5), tiny_dataset, run, device="cpu", resume=True)
    afile = tmp_path / "file"
    afile.write_text("x")
    with pytest.raises(ConfigError, match="exists and is not a folder"):
        train(config, tiny_dataset, afile, device="cpu")


def test_bad_data_and_sizes_are_rejected(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(DataError, match="nowhere"):
        train(FAST, tmp_path / "nowhere", tmp_path / "run", device="cpu")
    with pytest.raises(ConfigError, match="n_points is 2048 but the clouds in .* have 512"):
        train(FAST.replace(n_points=2048), tiny_dataset, tmp_path / "run", device="cpu")
    # 0.3 · 512 = 154 missing points: the pyramid decoder needs a multiple of 128.
    with pytest.raises(ConfigError, match="model 'pfnet' with 512 points and missing_ratio 0.3"):
        train(FAST.replace(missing_ratio=0.3), tiny_dataset, tmp_path / "run", device="cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            train(FAST, tiny_dataset, tmp_path / "run", device="cuda")
    with pytest.raises(ConfigError, match="device must be auto, cpu, cuda"):
        train(FAST, tiny_dataset, tmp_path / "run", device="tpu")


def test_cli_reports_errors_in_one_line(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "r")]
    assert main([*argv, "--epochs", "0"]) == 1
    err = capsys.readouterr().err
    assert "pfnet train: error: epochs must be an integer in [1, 1,000,000]; got 0" in err
    assert main([*argv, "--preset", "small", "--missing-ratio", "0.3"]) == 1
    assert "multiple of 128" in capsys.readouterr().err
    # The library speaks of resuming; the command names its option.
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "last.pt").write_bytes(b"")
    assert main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "old")]) == 1
    assert "already holds a run (last.pt); pass --resume to continue" in capsys.readouterr().err


def test_a_last_batch_of_one_trains(tiny_dataset: Path, tmp_path: Path) -> None:
    # 24 training shapes in batches of 23: the second batch holds one cloud. One loader
    # worker: batches are made in another process (started by a fork server).
    config = FAST.replace(epochs=1, batch_size=23, width=0.125, workers=1)
    summary = train(config, tiny_dataset, tmp_path / "run", device="cpu", progress=False)
    assert summary["epochs"] == 1
    assert torch.isfinite(torch.tensor(summary["final"]["loss_g"]))


def test_an_empty_val_split_trains_without_validation(tiny_dataset: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    empty = np.zeros(0, "<U1")
    np.savez(data / "val.npz", points=np.zeros((0, 512, 3), np.float32), category=empty, name=empty)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["splits"]["val"] = {"total": 0, "categories": {}}  # a consistent data set
    (data / "manifest.json").write_text(json.dumps(manifest))
    config = FAST.replace(model="mlp", epochs=1, width=0.125)
    summary = train(config, data, tmp_path / "run", device="cpu", progress=False)
    assert summary["best_val_cd_l2"] is None and summary["best_epoch"] == 1
    rows = _rows(tmp_path / "run")
    assert rows[0] == {"epoch": 0} and "val_cd_l2" not in rows[1]
    assert (tmp_path / "run" / "best.pt").is_file()


def test_bf16_autocast_stays_close_to_fp32(tiny_dataset: Path, tmp_path: Path) -> None:
    config = FAST.replace(epochs=1, batch_size=6, width=0.125)
    runs = {}
    for precision in ("fp32", "bf16"):
        run = tmp_path / precision
        train(config.replace(precision=precision), tiny_dataset, run, device="cpu", progress=False)
        runs[precision] = _rows(run)[1]
    fp32, bf16 = runs["fp32"], runs["bf16"]
    for key in ("cd_detail", "cd_primary", "cd_secondary", "loss_d", "val_cd_l2"):
        assert bf16[key] == pytest.approx(fp32[key], rel=0.1), key
    assert bf16[key] != fp32[key]  # it did run in another precision


def test_chamfer_stays_float32_under_autocast() -> None:
    from pfnet.training.losses import chamfer_distance

    generator = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 300, 3, generator=generator)
    gt = torch.rand(2, 200, 3, generator=generator)
    exact = chamfer_distance(pred, gt)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under = chamfer_distance(pred.bfloat16(), gt)
    reference = chamfer_distance(pred.bfloat16().float(), gt)
    for a, b in zip(under, reference, strict=True):
        assert a.dtype == torch.float32 and torch.allclose(a, b, rtol=1e-6)
    assert not torch.equal(exact[0], under[0])  # the bf16 input itself was rounded


@pytest.mark.slow
def test_compiled_training_matches_and_saves_plain_weights(tiny_dataset: Path, tmp_path: Path):
    config = FAST.replace(model="mlp", epochs=1, batch_size=8, width=0.125)  # 3 equal batches
    plain = train(config, tiny_dataset, tmp_path / "plain", device="cpu", progress=False)
    compiled = train(
        config.replace(compile=True), tiny_dataset, tmp_path / "compiled", device="cpu",
        progress=False,
    )  # fmt: skip
    assert compiled["final"]["cd_detail"] == pytest.approx(plain["final"]["cd_detail"], rel=1e-3)
    raw = torch.load(tmp_path / "compiled" / "last.pt", weights_only=True)
    assert raw["config"]["compile"] is True
    assert not any("_orig_mod" in key for key in raw["model"])
    load_checkpoint(tmp_path / "compiled" / "best.pt")


def test_save_every_and_the_files_a_run_writes(tiny_dataset: Path, tmp_path: Path) -> None:
    from pfnet.training.config import SaveSchedule

    assert SaveSchedule.parse("10min") == SaveSchedule(seconds=600.0)
    assert SaveSchedule.parse("90s") == SaveSchedule(seconds=90.0)
    assert SaveSchedule.parse("1h") == SaveSchedule(seconds=3600.0)
    assert SaveSchedule.parse("3") == SaveSchedule(epochs=3)
    for bad in ("0", "0s", "-1", "ten", "5 parsecs", ""):
        with pytest.raises(ConfigError, match="save_every must be"):
            SaveSchedule.parse(bad)
    # Every 2 epochs: after epoch 2 last.pt holds epoch 2, at the end epoch 3.
    saved: list[tuple[str, int]] = []
    import pfnet.inference.checkpoint

    original = pfnet.inference.checkpoint.save_checkpoint

    def spy(path, state):
        saved.append((Path(path).name, state["epoch"]))
        original(path, state)

    config = FAST.replace(model="mlp", epochs=3, width=0.125, save_every="2")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pfnet.inference.checkpoint, "save_checkpoint", spy)
        summary = train(config, tiny_dataset, tmp_path / "run", device="cpu", progress=False)
    assert [e for name, e in saved if name == "last.pt"] == [2, 3]
    assert {e for name, e in saved if name == "best.pt"} <= {1, 2, 3}
    assert summary["checkpoint_write_s"] > 0
    rows = _rows(tmp_path / "run")
    assert all(0 < r["compute_s"] <= r["time_s"] for r in rows[2:])


def test_a_run_sized_in_steps_follows_its_fractional_schedule(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 24 shapes in batches of 5: 5 steps an epoch; 13 steps = 3 epochs, the last one partial.
    config = FAST.replace(
        model="mlp",
        width=0.125,
        batch_size=5,
        steps=13,
        lr_milestones=(0.5,),
        lr_gamma=0.1,
        warmup_steps=2,
        alpha_fractions=((0.0, 0.01), (0.5, 0.1)),
    )
    summary = train(config, tiny_dataset, tmp_path / "run", device="cpu", progress=False)
    rows = _rows(tmp_path / "run")[1:]
    assert summary["epochs"] == 3 and [r["step"] for r in rows] == [5, 10, 13]
    # The lr after each epoch's last step: ×0.1 from step round(0.5 · 13) = 6 on.
    assert [r["lr"] for r in rows] == pytest.approx([5e-4, 5e-5, 5e-5])
    assert [r["alpha"] for r in rows] == [0.01, 0.1, 0.1]
    state = read_checkpoint(tmp_path / "run" / "last.pt")
    assert state["scheduler_g"]["last_epoch"] == 13


def test_the_learning_rate_schedule_per_step() -> None:
    from pfnet.training.schedule import alpha_at, make_scheduler, schedule_note

    config = FAST.replace(steps=100, lr=1.0, lr_milestones=(0.5, 0.8), lr_gamma=0.5)
    config = config.replace(warmup_steps=4)
    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=config.lr)
    scheduler = make_scheduler(optimizer, config)
    lrs = []
    for _ in range(100):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs[:5] == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0])
    assert lrs[49] == 1.0 and lrs[50] == 0.5 and lrs[79] == 0.5 and lrs[80] == 0.25
    fractions = config.replace(alpha_fractions=((0.0, 0.01), (0.15, 0.05), (0.4, 0.1)))
    assert [alpha_at(fractions, 0, s) for s in (0, 14, 15, 39, 40, 99)] == [
        0.01, 0.01, 0.05, 0.05, 0.1, 0.1,
    ]  # fmt: skip
    epochs = preset_config("paper")  # the authors' epochs 30 and 80
    assert [alpha_at(epochs, e, 10**6) for e in (29, 30, 80)] == [0.01, 0.05, 0.1]
    # The published small runs: 12 steps an epoch, StepLR every 40 of 200 epochs.
    fixed = preset_config("small").replace(epochs=200, lr_step=40, schedule="fixed")
    note = schedule_note(fixed, 12)
    assert note is not None and note.startswith("only 480 of the run's 2400 optimiser steps")
    # the small preset's own schedule is sized to whatever --epochs it gets
    sized = preset_config("small").replace(epochs=100)
    assert sized.schedule == "run"
    note = schedule_note(sized, 12)
    assert note is not None and "only 600 of the run's 1200" in note and "0.5 of 100 epochs" in note
    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    scheduler = make_scheduler(optimizer, sized.replace(lr=1.0))
    per_epoch = []
    for _ in range(100):
        per_epoch.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert per_epoch[49] == 1.0 and per_epoch[50] == 0.2 and per_epoch[75] == pytest.approx(0.04)
    assert [alpha_at(sized, e, 0) for e in (0, 14, 15, 40, 99)] == [0.01, 0.01, 0.05, 0.1, 0.1]
    assert schedule_note(config.replace(steps=10_000), 12) is None
    assert schedule_note(preset_config("paper"), 340) is None  # ShapeNet-Part: 13,600 steps


def test_the_cosine_decay_per_step_and_per_epoch() -> None:
    from pfnet.training.schedule import make_scheduler, schedule_note

    def rates(config, n: int) -> list[float]:
        optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=config.lr)
        scheduler = make_scheduler(optimizer, config)
        out = []
        for _ in range(n):
            out.append(optimizer.param_groups[0]["lr"])
            optimizer.step()
            scheduler.step()
        return out

    # 4 warm-up steps, then a half cosine over the other 100 from 1 to 0.2 ** 2 = 0.04
    config = FAST.replace(steps=104, lr=1.0, lr_gamma=0.2, warmup_steps=4, lr_decay="cosine")
    lrs = rates(config, 104)
    assert lrs[:4] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    naive = [0.04 + 0.96 * 0.5 * (1 + math.cos(math.pi * (s - 4) / 100)) for s in range(4, 104)]
    assert lrs[4:] == pytest.approx(naive)
    assert lrs[54] == pytest.approx(0.52) and all(a > b for a, b in zip(lrs[4:], lrs[5:]))
    # no milestones: nothing to fall to, the rate stays
    assert set(rates(config.replace(lr_milestones=()), 104)[4:]) == {1.0}
    # an epoch run sized to the run: the same curve per epoch, no warm-up
    epochs = preset_config("small").replace(epochs=10, lr=1.0, lr_decay="cosine")
    per_epoch = rates(epochs, 10)
    assert per_epoch == pytest.approx(
        [0.04 + 0.96 * 0.5 * (1 + math.cos(math.pi * e / 10)) for e in range(10)]
    )
    note = schedule_note(epochs.replace(epochs=100), 12)
    assert note is not None and "only 600 of the run's 1200" in note and "cosine" in note
    assert schedule_note(config.replace(steps=10_000), 12) is None


def test_schedule_config_errors() -> None:
    with pytest.raises(ConfigError, match=r"steps must be an integer in \[1, 100,000,000\]"):
        FAST.replace(steps=0)
    with pytest.raises(ConfigError, match="lr_milestones must be increasing fractions"):
        FAST.replace(lr_milestones=(0.8, 0.5))
    with pytest.raises(ConfigError, match="lr_milestones must be increasing fractions"):
        FAST.replace(lr_milestones=(1.5,))
    with pytest.raises(ConfigError, match="alpha_fractions must be a list of"):
        FAST.replace(alpha_fractions=((0.1, 0.01),))
    with pytest.raises(ConfigError, match="warmup_steps must be an integer >= 0"):
        FAST.replace(warmup_steps=-1)
    with pytest.raises(ConfigError, match="and at most the run's steps; got 1000000000000"):
        FAST.replace(steps=1, warmup_steps=10**12)  # the seventh audit: accepted
    with pytest.raises(ConfigError, match="lr_decay must be one of step, cosine; got 'linear'"):
        FAST.replace(lr_decay="linear")
    with pytest.raises(ConfigError, match="cosine needs a run sized to its length"):
        preset_config("paper").replace(lr_decay="cosine")


def test_augmented_training_runs_and_needs_a_known_up_axis(
    tiny_dataset: Path, tmp_path: Path
) -> None:
    config = FAST.replace(model="mlp", epochs=1, width=0.125, augment_rotate=True)
    config = config.replace(augment_scale=0.1, augment_jitter=0.005)
    summary = train(config, tiny_dataset, tmp_path / "run", device="cpu", progress=False)
    assert summary["epochs"] == 1
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["up_axis"] = "as in the source"
    (data / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ConfigError, match="augment_rotate: rotation about the up axis needs"):
        train(config, data, tmp_path / "other", device="cpu")
    with pytest.raises(ConfigError, match=r"augment_scale must be a number in \[0, 1\)"):
        config.replace(augment_scale=1.0)


def test_val_data_validates_on_another_data_sets_split(tiny_dataset: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    prepare_dataset(
        None, other, format="procedural", points=512, seed=5, count=6, categories=["chair"],
        test_fraction=0.25, val_fraction=0.5, workers=1, progress=False,
    )  # fmt: skip
    config = FAST.replace(model="mlp", epochs=1, width=0.125)
    runs = {}
    for name, val_data in (("own", None), ("other", other)):
        run = tmp_path / f"run-{name}"
        train(config, tiny_dataset, run, device="cpu", progress=False, val_data=val_data)
        runs[name] = _rows(run)
    # the same training (same seed, same data), validated on different shapes
    assert runs["own"][1]["loss_g"] == runs["other"][1]["loss_g"]
    assert runs["own"][1]["val_cd_l2"] != runs["other"][1]["val_cd_l2"]
    with pytest.raises(ConfigError, match="is inside the input"):
        train(config, tiny_dataset, other / "run", device="cpu", progress=False, val_data=other)


def test_val_views_validate_every_shape_at_all_five_viewpoints(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pfnet.data.dataset import CompletionDataset
    from pfnet.evaluation.metrics import sample_metrics, summarize

    assert preset_config("small").val_views == 5 and preset_config("paper").val_views == 1
    config = FAST.replace(model="pfnet-vanilla", epochs=1, width=0.125, frame="shape")
    runs = {}
    for views in (1, 5):
        run = tmp_path / f"views-{views}"
        train(config.replace(val_views=views), tiny_dataset, run, device="cpu", progress=False)
        runs[views] = _rows(run)
        assert json.loads((run / "config.json").read_text())["val_views"] == views
    assert runs[1][1]["loss_g"] == runs[5][1]["loss_g"]  # the same training, other scans
    # what the log says is the network's mean over categories on the 5 cuts of each shape
    model, _ = load_checkpoint(tmp_path / "views-5" / "best.pt")
    model.eval()
    five = CompletionDataset(tiny_dataset, "val", crop="test", views=5)
    items = [five[j] for j in range(len(five))]
    with torch.no_grad():
        detail = model(torch.stack([item["partial"] for item in items])).detail.numpy()
    metrics = sample_metrics(detail, np.stack([item["missing"].numpy() for item in items]))
    expected = summarize(metrics, [item["category"] for item in items])["mean"]["cd_l2"]
    assert runs[5][-1]["val_cd_l2"] == pytest.approx(expected, rel=1e-4)
    assert runs[1][-1]["val_cd_l2"] != pytest.approx(expected, rel=1e-4)
    code = main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "cli"),
                 "--preset", "small", "--val-views", "3", "--epochs", "1"])  # fmt: skip
    assert code == 1 and "val_views must be 1 or 5; got 3" in capsys.readouterr().err


def test_init_from_fine_tunes_from_a_trained_generator(tiny_dataset: Path, tmp_path: Path) -> None:
    config = FAST.replace(model="pfnet-vanilla", epochs=1, width=0.125)
    first = tmp_path / "first"
    train(config, tiny_dataset, first, device="cpu", progress=False)
    start, _ = load_checkpoint(first / "best.pt")
    # a learning rate of 1e-12 leaves the weights where fine-tuning starts them
    tuned = tmp_path / "tuned"
    fine = config.replace(init_from=str(first / "best.pt"), lr=1e-12)
    train(fine, tiny_dataset, tuned, device="cpu", progress=False)
    after, _ = load_checkpoint(tuned / "best.pt")
    recorded = read_checkpoint(tuned / "best.pt")["config"]["init_from"]
    assert recorded == str(first / "best.pt")  # recorded with the run
    weights = {k: v for k, v in start.state_dict().items() if k.endswith("weight")}
    for key, value in weights.items():
        np.testing.assert_allclose(after.state_dict()[key], value, atol=1e-6, err_msg=key)
    fresh = tmp_path / "fresh"  # ... which a run without init_from does not
    train(config.replace(lr=1e-12, seed=1), tiny_dataset, fresh, device="cpu", progress=False)
    other, _ = load_checkpoint(fresh / "best.pt")
    assert any(not np.allclose(other.state_dict()[k], v, atol=1e-3) for k, v in weights.items())
    # a width the trained one's does not go into a whole number of times
    with pytest.raises(ConfigError, match=r"is another network: width 0.125 \(run: 0.1875\)"):
        train(fine.replace(width=0.1875), tiny_dataset, tmp_path / "wide", device="cpu")
    with pytest.raises(ConfigError, match="contains the input"):  # best.pt would be replaced
        train(fine, tiny_dataset, first, device="cpu", progress=False)
    code = main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "cli"),
                 "--init-from", "no-such-model", "--epochs", "1"])  # fmt: skip
    assert code == 1


def test_the_weight_average_is_what_validation_scores_and_best_pt_holds(
    tiny_dataset: Path, tmp_path: Path
) -> None:
    config = FAST.replace(model="pfnet-vanilla", epochs=1, width=0.125, ema=0.99)
    run = tmp_path / "ema"
    train(config, tiny_dataset, run, device="cpu", progress=False)
    state = read_checkpoint(run / "last.pt")
    best = read_checkpoint(run / "best.pt")
    assert state["average"]["updates"] == 6 and best["epoch"] == 1
    live, average = state["model"], state["average"]["model"]
    for name, tensor in best["model"].items():  # one epoch: best.pt is the end's average
        assert torch.equal(tensor, average[name]), name
    assert any(not torch.equal(live[k], average[k]) for k in live if k.endswith("weight"))
    # Inference from last.pt gives the average too, not the live weights.
    from_last, _ = load_checkpoint(run / "last.pt")
    for name, tensor in from_last.state_dict().items():
        assert torch.equal(tensor, average[name]), name
    # The logged validation is the average's: score best.pt again, the same way.
    from pfnet.training.loop import Trainer

    rows = _rows(run)
    # ... and the live weights are scored beside it, on the same trajectory
    assert all("val_live_cd_l2" in row for row in rows)
    assert rows[0]["val_live_cd_l2"] == rows[0]["val_cd_l2"]  # epoch 0: a copy of them
    assert rows[-1]["val_live_cd_l2"] != rows[-1]["val_cd_l2"]
    generator, _ = load_checkpoint(run / "best.pt")
    trainer = Trainer(config, tiny_dataset, tmp_path / "scored", _cpu_context(), resume=False)
    trainer.step.average.model.load_state_dict(generator.state_dict())
    assert trainer.validate()["val_cd_l2"] == pytest.approx(rows[-1]["val_cd_l2"], rel=1e-6)
    with pytest.raises(ConfigError, match=r"ema must be a number in \[0, 1\)"):
        config.replace(ema=1.0)
    code = main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "cli"),
                 "--ema", "0.9", "--steps", "2", "--batch-size", "4", "--width", "0.125",
                 "--preset", "small", "--device", "cpu"])  # fmt: skip
    assert code == 0
    assert read_checkpoint(tmp_path / "cli" / "last.pt")["config"]["ema"] == 0.9


def test_grad_clip_clips_the_generators_gradient_and_logs_its_norm(tiny_dataset: Path) -> None:
    from pfnet.data.dataset import CompletionDataset
    from pfnet.training.batches import CompletionCollate
    from pfnet.training.step import TrainingStep

    dataset = CompletionDataset(tiny_dataset, "train", crop="viewpoint")
    batch = CompletionCollate(True, centre_targets=True)([dataset[i] for i in range(4)])
    config = FAST.replace(model="pfnet-vanilla", width=0.125, n_points=512)
    steps = {}
    for clip in (0.0, 1e-6, 1e9):
        step = TrainingStep(config.replace(grad_clip=clip), _cpu_context())
        start = {k: v.clone() for k, v in step.generator.state_dict().items()}
        losses = step(batch, alpha=0.01)
        grads = [p.grad for p in step.generator.parameters() if p.grad is not None]
        norm = float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])))
        moved = max(
            float((v - start[k]).abs().max())
            for k, v in step.generator.state_dict().items()
            if k.endswith("weight")
        )
        steps[clip] = (losses, norm, moved)
    plain, clipped, loose = steps[0.0], steps[1e-6], steps[1e9]
    assert "grad_norm" not in plain[0]  # off: the paper's step, nothing logged
    assert loose[0]["grad_norm"] == pytest.approx(plain[1], rel=1e-5)  # the norm before
    assert loose[2] == pytest.approx(plain[2], rel=1e-6)  # a loose bound changes nothing
    assert clipped[1] == pytest.approx(1e-6, rel=1e-4)  # the gradient stepped with
    assert clipped[2] < plain[2] / 10  # Adam's first step shrinks once eps dominates
    with pytest.raises(ConfigError, match=r"grad_clip must be a number >= 0 \(0: off\)"):
        config.replace(grad_clip=-1.0)


def _cpu_context():
    from pfnet.training import distributed

    return distributed.setup("cpu")


def test_batchnorm_freeze_is_a_fraction_of_the_run() -> None:
    from pfnet.training.schedule import batchnorm_frozen

    steps = FAST.replace(steps=1000, batchnorm_freeze=0.1)
    assert [batchnorm_frozen(steps, 0, s) for s in (0, 99, 100, 999)] == [False, False, True, True]
    # never before BATCHNORM_FREEZE_MIN_STEPS steps, however early the fraction comes
    short = FAST.replace(steps=100, batchnorm_freeze=0.05)
    assert [batchnorm_frozen(short, 0, s) for s in (5, 49, 50)] == [False, False, True]
    epochs = FAST.replace(epochs=20, batchnorm_freeze=0.25)
    assert [batchnorm_frozen(epochs, e, 999) for e in (0, 4, 5, 19)] == [False, False, True, True]
    off = FAST.replace(steps=10, batchnorm_freeze=0.0)
    assert not any(batchnorm_frozen(off, 0, s) for s in range(10))
    # the small preset freezes at 5 % of the run (with the clip), the paper's never
    assert (preset_config("small").batchnorm_freeze, preset_config("small").grad_clip) == (0.05, 2)
    assert (preset_config("paper").batchnorm_freeze, preset_config("paper").grad_clip) == (0, 0)
    for bad in (1.0, -0.1, "0.1"):
        with pytest.raises(ConfigError, match=r"batchnorm_freeze must be a fraction of the run"):
            FAST.replace(batchnorm_freeze=bad)


def test_a_frozen_batchnorm_keeps_its_statistics_and_goes_on_learning(tiny_dataset: Path) -> None:
    from pfnet.data.dataset import CompletionDataset
    from pfnet.training.batches import CompletionCollate

    dataset = CompletionDataset(tiny_dataset, "train", crop="viewpoint")
    batch = CompletionCollate(True, centre_targets=True)([dataset[i] for i in range(4)])
    config = FAST.replace(model="pfnet", width=0.125, n_points=512)
    moved = {}
    for frozen in (False, True):
        step = TrainingStep(config, _cpu_context())
        with torch.no_grad():  # statistics of this batch, as a run that froze them has
            for layer in step.batchnorms:
                layer.momentum = 1.0
            step.generator(batch["partial"], batch["scale_indices"])
            for layer in step.batchnorms:
                layer.momentum = 0.1
        step.batchnorm_frozen = frozen
        start = {k: v.clone() for k, v in step.generator.state_dict().items()}
        step.generator.eval()
        step.generator.train()  # as validation leaves it: the step freezes the layers again
        step(batch, alpha=0.01)
        state = step.generator.state_dict()
        moved[frozen] = {k for k in state if not torch.equal(state[k], start[k])}
    stats = {k for k in moved[False] if k.endswith(("running_mean", "running_var"))}
    assert stats and not stats & moved[True]  # the batch statistics no longer go in
    learned = {k for k in moved[False] if k.endswith(("weight", "bias"))}
    assert moved[True] == learned  # every weight still learns, BatchNorm's scale and shift too
    assert any(k.startswith("encoder.") and k.endswith(".1.weight") for k in learned)


def test_a_run_freezes_its_batchnorm_statistics_where_the_config_says(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pfnet.training import schedule

    monkeypatch.setattr(schedule, "BATCHNORM_FREEZE_MIN_STEPS", 0)  # a six-step run
    # Constant schedules, so that the first two steps of both runs are the same steps.
    config = FAST.replace(
        model="pfnet-vanilla", width=0.125, lr_milestones=(), alpha_fractions=((0.0, 0.1),)
    )
    train(
        config.replace(steps=2, batchnorm_freeze=0.0), tiny_dataset, tmp_path / "two", device="cpu"
    )
    train(
        config.replace(steps=6, batchnorm_freeze=1 / 3), tiny_dataset, tmp_path / "six",
        device="cpu",
    )  # fmt: skip
    two = read_checkpoint(tmp_path / "two" / "last.pt")["model"]
    six = read_checkpoint(tmp_path / "six" / "last.pt")["model"]
    stats = [k for k in two if k.endswith(("running_mean", "running_var"))]
    assert stats
    for key in stats:  # frozen after step 2 of 6: steps 3 to 6 left them as step 2 did
        assert torch.equal(two[key], six[key]), key
    assert not torch.equal(two["decoder.fc1.weight"], six["decoder.fc1.weight"])
