"""Training benchmarks: one PF-Net step (paper preset) and the Chamfer loss vs ``torch.cdist``.

Run as a pytest-benchmark suite (``python -m pytest benchmarks/bench_train.py
--benchmark-enable``) or as a script printing a Markdown table::

    python benchmarks/bench_train.py [--device cpu|cuda] [--steps 3]

Peak memory of a Chamfer forward + backward is measured in a fresh subprocess per method: on
the CPU as the growth of the resident set's high-water mark (``VmHWM``, reset through
``/proc/self/clear_refs``; Linux only), on CUDA with ``torch.cuda.max_memory_allocated``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch") if "pytest" in sys.modules else __import__("torch")

from pfnet.losses import chamfer_distance  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402
from pfnet.training.distributed import DistContext  # noqa: E402
from pfnet.training.loop import CompletionCollate, TrainingStep  # noqa: E402

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


def main(argv: list[str] | None = None) -> None:
    """Print the benchmark table (Markdown)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--steps", type=int, default=3, help="timed training steps")
    parser.add_argument("--skip-train", action="store_true", help="only the Chamfer table")
    args = parser.parse_args(argv)
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


if __name__ == "__main__":
    main()
