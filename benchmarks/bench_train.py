"""Training benchmarks: one PF-Net step (paper preset), the Chamfer loss vs ``torch.cdist``,
and whole epochs: where an epoch's wall time goes.

Run as a pytest-benchmark suite (``python -m pytest benchmarks/bench_train.py
--benchmark-enable``) or as a script printing Markdown tables::

    python benchmarks/bench_train.py [--device cpu|cuda] [--steps 3]
    python benchmarks/bench_train.py --epochs-only --data data/sh3d [--epochs 6]

The epoch table trains real runs (``pfnet train``'s loop) on a prepared data set: the small
preset (both presets on CUDA, fp32 and bf16). The marginal wall time of an epoch is
``(T(1 + K epochs) - T(1 epoch)) / K`` measured from outside, after a warm-up run (so it holds
start-up apart and counts everything else: data loading, validation, logging, checkpoints,
plots); the compute time is the logged ``compute_s`` (training and validation steps) of
epochs 2 and later.

Peak memory of a Chamfer forward + backward is measured in a fresh subprocess per method: on
the CPU as the growth of the resident set's high-water mark (``VmHWM``, reset through
``/proc/self/clear_refs``; Linux only), on CUDA with ``torch.cuda.max_memory_allocated``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch") if "pytest" in sys.modules else __import__("torch")

from pfnet.training.batches import CompletionCollate  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402
from pfnet.training.distributed import DistContext  # noqa: E402
from pfnet.training.losses import chamfer_distance  # noqa: E402
from pfnet.training.step import TrainingStep  # noqa: E402

CHAMFER_SIZES = [(36, 512, 512), (36, 2048, 2048)]  # (B, P, G): the loss's size; a full cloud


def cdist_chamfer(pred, gt):
    """Brute force: the full ``(B, P, G)`` matrix of ``torch.cdist``, squared."""
    d = torch.cdist(pred, gt).square()
    return d.min(2).values.mean(1), d.min(1).values.mean(1)


METHODS = {"ours (chunked)": chamfer_distance, "torch.cdist": cdist_chamfer}


def _clouds(batch: int, n_pred: int, n_gt: int, device: str):
    generator = torch.Generator().manual_seed(0)
    pred = (torch.rand(batch, n_pred, 3, generator=generator) * 2 - 1).to(device)
    gt = (torch.rand(batch, n_gt, 3, generator=generator) * 2 - 1).to(device)
    return pred.requires_grad_(), gt


def chamfer_step(method, pred, gt) -> None:
    """Forward + backward of the summed Chamfer terms."""
    pred.grad = None
    pred_to_gt, gt_to_pred = method(pred, gt)
    (pred_to_gt + gt_to_pred).sum().backward()
    if pred.is_cuda:
        torch.cuda.synchronize()


def _peak_memory_child(name: str, batch: int, n_pred: int, n_gt: int, device: str) -> float:
    """Run in a subprocess: peak extra memory (MiB) of one forward + backward."""
    pred, gt = _clouds(batch, n_pred, n_gt, device)
    method = METHODS[name]
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        chamfer_step(method, pred, gt)
        return (torch.cuda.max_memory_allocated() - base) / 2**20
    # Reset the kernel's resident-set high-water mark (Linux >= 4.0), then read it back.
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    base = _status_kib("VmRSS")
    chamfer_step(method, pred, gt)
    return (_status_kib("VmHWM") - base) / 1024


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def peak_memory_mib(name: str, batch: int, n_pred: int, n_gt: int, device: str) -> float:
    """Peak extra memory of one Chamfer forward + backward, measured in a fresh process."""
    code = (
        "import json, sys; sys.path.insert(0, {path!r}); import bench_train as b; "
        "print(json.dumps(b._peak_memory_child(*json.loads(sys.argv[1]))))"
    ).format(path=str(__import__("pathlib").Path(__file__).parent))
    args = json.dumps([name, batch, n_pred, n_gt, device])
    out = subprocess.run(
        [sys.executable, "-c", code, args], capture_output=True, text=True, check=True
    )
    return float(out.stdout.strip().splitlines()[-1])


def time_chamfer(name: str, batch: int, n_pred: int, n_gt: int, device: str, repeats: int = 5):
    """Median seconds of a Chamfer forward + backward."""
    pred, gt = _clouds(batch, n_pred, n_gt, device)
    chamfer_step(METHODS[name], pred, gt)  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        chamfer_step(METHODS[name], pred, gt)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def paper_step(device: str, batch_size: int = 36, model: str = "pfnet"):
    """A :class:`TrainingStep` of the paper preset (2048 points, 25 % missing) and a batch."""
    config = preset_config("paper").replace(model=model, n_points=2048, batch_size=batch_size)
    context = DistContext(0, 1, 0, torch.device(device))
    step = TrainingStep(config, context)
    rng = np.random.default_rng(0)
    items = []
    for i in range(batch_size):
        cloud = rng.normal(size=(2048, 3)).astype(np.float32)
        cloud /= np.linalg.norm(cloud, axis=1, keepdims=True)
        complete = torch.from_numpy(cloud)
        items.append(
            {
                "partial": complete[512:],
                "missing": complete[:512],
                "complete": complete,
                "category": "sphere",
                "index": i,
            }
        )
    collate = CompletionCollate(step.generator.multi_resolution, step.multi_stage)
    return step, collate(items)


def time_train_step(device: str, steps: int = 3, batch_size: int = 36) -> float:
    """Median seconds of one PF-Net training step (D step + G step), collate excluded."""
    step, batch = paper_step(device, batch_size)
    step(batch, 0.01)  # warm-up
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        step(batch, 0.01)
        if device == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_collate(batch_size: int = 36) -> float:
    """Seconds to collate a paper batch (the Rust IFPS of inputs and centre targets)."""
    collate = CompletionCollate(multi_resolution=True, centre_targets=True)
    rng = np.random.default_rng(0)
    items = [
        {
            "partial": torch.from_numpy(rng.random((1536, 3), dtype=np.float32)),
            "missing": torch.from_numpy(rng.random((512, 3), dtype=np.float32)),
            "complete": torch.zeros(2048, 3),
            "category": "x",
            "index": i,
        }
        for i in range(batch_size)
    ]
    start = time.perf_counter()
    collate(items)
    return time.perf_counter() - start


# -- pytest-benchmark ----------------------------------------------------------------------


@pytest.mark.parametrize("size", CHAMFER_SIZES, ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("name", list(METHODS))
def test_chamfer_forward_backward(benchmark, name: str, size: tuple[int, int, int]) -> None:
    pred, gt = _clouds(*size, "cpu")
    benchmark.extra_info["peak_mib"] = peak_memory_mib(name, *size, "cpu")
    benchmark.pedantic(chamfer_step, args=(METHODS[name], pred, gt), rounds=3, warmup_rounds=1)


def test_pfnet_paper_train_step(benchmark) -> None:
    step, batch = paper_step("cpu")
    benchmark.pedantic(step, args=(batch, 0.01), rounds=2, warmup_rounds=1)


def time_epochs(
    data: str, preset: str, device: str, epochs: int = 5, precision: str = "fp32", **changes
) -> dict[str, float]:
    """Where the wall time of a run's epochs goes (see the module docstring)."""
    import tempfile

    from pfnet.training import train

    config = preset_config(preset).replace(precision=precision, **changes)
    with tempfile.TemporaryDirectory() as tmp:
        # A throwaway epoch first: the first run in a process pays one-time costs (imports,
        # thread pools, CUDA context) that would shrink the marginal estimate.
        train(config.replace(epochs=1), data, f"{tmp}/warm", device=device, progress=False)
        started = time.perf_counter()
        train(config.replace(epochs=1), data, f"{tmp}/one", device=device, progress=False)
        one = time.perf_counter() - started
        started = time.perf_counter()
        summary = train(
            config.replace(epochs=1 + epochs), data, f"{tmp}/many", device=device, progress=False
        )
        many = time.perf_counter() - started
        rows = [json.loads(line) for line in open(f"{tmp}/many/log.jsonl").read().splitlines()][2:]
        steps = math.ceil(len(np.load(f"{data}/train.npz")["name"]) / config.batch_size)
    compute = statistics.mean(r["compute_s"] for r in rows)
    marginal = (many - one) / epochs
    return {
        "epoch_wall_s": marginal,
        "epoch_compute_s": compute,
        "overhead": marginal / compute,
        "step_s": statistics.mean(r["train_s"] for r in rows) / steps,
        "checkpoint_write_s": summary["checkpoint_write_s"],
        "startup_s": one - marginal,
    }


def main(argv: list[str] | None = None) -> None:
    """Print the benchmark table (Markdown)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--steps", type=int, default=3, help="timed training steps")
    parser.add_argument("--skip-train", action="store_true", help="only the Chamfer table")
    parser.add_argument("--data", help="a prepared data set: also time whole epochs on it")
    parser.add_argument("--epochs", type=int, default=5, help="epochs timed after the first")
    parser.add_argument("--epochs-only", action="store_true", help="only the epoch table")
    args = parser.parse_args(argv)
    if args.epochs_only:
        print_epoch_table(args.data, args.device, args.epochs)
        return
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    print("\n| Chamfer fwd+bwd (B×P×G) | method | time | peak extra memory |")
    print("|---|---|---|---|")
    for size in CHAMFER_SIZES:
        for name in METHODS:
            seconds = time_chamfer(name, *size, args.device)
            peak = peak_memory_mib(name, *size, args.device)
            label = "×".join(map(str, size))
            print(f"| {label} | {name} | {seconds * 1000:.1f} ms | {peak:.0f} MiB |")
    if not args.skip_train:
        seconds = time_train_step(args.device, args.steps)
        print(f"\nPF-Net paper preset, batch 36, D + G step on {args.device}: {seconds:.2f} s/step")
        print(f"collate of a batch of 36 (Rust IFPS, CPU): {time_collate() * 1000:.1f} ms")
    if args.data:
        print_epoch_table(args.data, args.device, args.epochs)


def print_epoch_table(data: str | None, device: str, epochs: int) -> None:
    """The epoch table: small preset (and, on CUDA, the paper preset) in each precision."""
    if data is None:
        raise SystemExit("--data DIR (a data set made by pfnet prepare) is needed for epochs")
    runs = [("small", "fp32")]
    if device == "cuda":
        runs = [(p, q) for p in ("small", "paper") for q in ("fp32", "bf16")]
    print(f"\n| {data}, {device} | step | epoch compute | epoch wall | wall ÷ compute "
          "| checkpoint writes (background) | start-up |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for preset, precision in runs:
        workers = 0 if device == "cpu" else 4
        r = time_epochs(data, preset, device, epochs, precision, workers=workers)
        print(
            f"| {preset}, {precision} | {r['step_s'] * 1000:.0f} ms | {r['epoch_compute_s']:.2f} s"
            f" | {r['epoch_wall_s']:.2f} s | {r['overhead']:.2f} | "
            f"{r['checkpoint_write_s']:.2f} s in all | {r['startup_s']:.1f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
