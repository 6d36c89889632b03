"""The heading reader (pfnet.data.heading: NumPy; pfnet.models.heading: its torch network) and
the ``heading`` frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pfnet.data.heading import load_reader
from pfnet.data.scan_frame import FRAMES, scan_frame, up_rotation
from pfnet.errors import ConfigError, DataError

torch = pytest.importorskip("torch")

from pfnet.models.heading import HeadingNet, save_reader, soft_targets  # noqa: E402


def _trained_looking(bins: int = 12, seed: int = 0) -> HeadingNet:
    """A small net with batch-norm statistics and affine terms away from their defaults, so
    that folding them into the layers is checked."""
    torch.manual_seed(seed)
    net = HeadingNet(bins=bins, point_widths=(8, 16), head_widths=(12,))
    for module in net.modules():
        if isinstance(module, torch.nn.BatchNorm1d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.5, 2.0)
            module.weight.data.uniform_(0.5, 1.5)
            module.bias.data.uniform_(-0.2, 0.2)
    return net.eval()


def _cloud(n: int = 300, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, 3)) * [0.8, 0.3, 0.4]).astype(np.float32)


def test_the_numpy_reader_scores_as_the_torch_network(tmp_path: Path) -> None:
    net = _trained_looking()
    path = save_reader(net, tmp_path / "reader.safetensors", points=64, card={"data": "forged"})
    reader = load_reader(path)
    assert (reader.bins, reader.points, reader.card) == (12, 64, {"data": "forged"})
    samples = np.stack([reader.sample(_cloud(seed=s)) for s in range(5)])
    assert samples.shape == (5, 64, 3)
    with torch.no_grad():
        expected = net(torch.from_numpy(samples)).numpy()
    np.testing.assert_allclose(reader.logits(samples), expected, rtol=1e-4, atol=1e-4)
    small = reader.sample(_cloud(n=10))  # fewer points than the input: repeated cyclically
    np.testing.assert_array_equal(small[10:20], small[:10])


def test_the_reading_is_the_best_bin_refined_by_its_neighbours() -> None:
    from pfnet.data.heading import decode_headings

    scores = np.zeros((3, 12))
    scores[0, 7] = 20.0  # only bin 7: its centre, 7.5 bins of 30°
    scores[1, 7] = scores[1, 8] = 20.0  # two bins alike: between them
    scores[2, 0] = scores[2, 11] = 20.0  # across 0
    np.testing.assert_allclose(
        decode_headings(scores), np.radians([225.0, 240.0, 0.0]) % (2 * np.pi), atol=1e-6
    )


def test_a_heading_turns_with_the_scan(tmp_path: Path) -> None:
    """The reader reads the aligned cloud, the same for every turn of a scan; the heading is
    the scan's main axis less that reading, so it turns with the scan."""
    from pfnet.data.heading import aligned_input, decode_headings

    reader = load_reader(
        save_reader(_trained_looking(), tmp_path / "r.safetensors", points=64, card={})
    )
    cloud = _cloud().astype(np.float64)
    aligned, angle = aligned_input(cloud)
    (heading,) = reader.headings([cloud])
    read = decode_headings(reader.logits(reader.sample(aligned)[None]))[0]
    assert heading == pytest.approx((angle - read) % (2 * np.pi), abs=1e-9)
    for turn in (0.4, 2.5, 5.0):
        (turned,) = reader.headings([cloud @ up_rotation(turn, 1).T])
        gap = np.angle(np.exp(1j * (turned - heading - turn)))
        assert abs(gap) < 1e-3
    assert reader.headings([]).shape == (0,)


def test_soft_targets_wrap_around_the_turn() -> None:
    targets = soft_targets(np.array([0.0, math.pi]), bins=12)
    np.testing.assert_allclose(targets.sum(axis=1), 1.0, rtol=1e-6)
    assert targets[0, 0] == pytest.approx(targets[0, 11])  # 0 sits between bins 11 and 0
    assert targets[1].argmax() in (5, 6)


def test_reader_files_that_are_not_readers_are_refused(tmp_path: Path) -> None:
    from safetensors.numpy import save_file

    with pytest.raises(DataError, match="heading reader .*missing.safetensors not found"):
        load_reader(tmp_path / "missing.safetensors")
    other = tmp_path / "other.safetensors"
    save_file({"w": np.zeros(3, np.float32)}, str(other), metadata={"format": "else"})
    with pytest.raises(DataError, match="is not a pfnet heading reader file"):
        load_reader(other)
    broken = tmp_path / "broken.safetensors"
    save_file(
        {"point.0.weight": np.zeros((4, 3), np.float32), "point.0.bias": np.zeros(4, np.float32)},
        str(broken),
        metadata={"format": "pfnet-heading-reader", "version": "1", "bins": "8", "points": "8"},
    )
    with pytest.raises(DataError, match="broken header"):
        load_reader(broken)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"not a safetensors file")
    with pytest.raises(DataError, match="cannot be read"):
        load_reader(garbage)


def test_the_heading_frame_turns_a_partial_back_to_the_data_sets_heading() -> None:
    assert "heading" in FRAMES
    canonical = _cloud().astype(np.float64)
    angle = 2.1
    turned = canonical @ up_rotation(angle, 1).T
    np.testing.assert_allclose(
        scan_frame(turned, heading=angle).apply(turned),
        scan_frame(canonical).apply(canonical),
        atol=1e-5,
    )
    with pytest.raises(ConfigError, match="aligned or heading, not both"):
        scan_frame(turned, aligned=True, heading=angle)


def test_every_path_of_a_heading_model_reads_the_heading(monkeypatch: pytest.MonkeyPatch) -> None:
    """input_frame (complete, predict, the benchmarks' protocols) turns a heading model's
    input back by what the reader reads: a reader that reads the true turn gives the
    unturned partial's frame."""
    from pfnet.data import heading as module
    from pfnet.inference.predict import input_frame

    angle = 4.0
    read = []

    class Reader:
        def headings(self, partials):
            read.append(len(partials))
            return np.array([angle])

    monkeypatch.setattr(module, "load_reader", lambda path=None: Reader())
    canonical = _cloud().astype(np.float64)
    turned = canonical @ up_rotation(angle, 1).T + [3.0, -1.0, 2.0]
    got = input_frame(turned, "heading").apply(turned)
    np.testing.assert_allclose(got, scan_frame(canonical).apply(canonical), atol=1e-5)
    assert read == [1]


def _run(tmp_path: Path, **changes) -> Path:
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125, **changes)
    torch.manual_seed(0)
    path = tmp_path / f"run-{len(list(tmp_path.iterdir()))}.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def test_a_scan_run_in_the_data_sets_heading_ships_in_the_heading_frame(tmp_path: Path) -> None:
    from pfnet.inference.checkpoint import write_shipped
    from pfnet.inference.shipped import read_metadata

    turned = _run(tmp_path, frame="scan", crop="turned", augment_rotate=False)
    path = write_shipped(turned, tmp_path / "m.safetensors", frame="heading")
    assert read_metadata(path)[0]["frame"] == "heading"
    assert read_metadata(write_shipped(turned, tmp_path / "s.safetensors"))[0]["frame"] == "scan"
    with pytest.raises(ConfigError, match="of the scan frame cannot be shipped as aligned"):
        write_shipped(turned, tmp_path / "x.safetensors", frame="aligned")
    rotated = _run(tmp_path, frame="scan", crop="turned", augment_rotate=True)
    with pytest.raises(ConfigError, match="only a run trained with --crop turned"):
        write_shipped(rotated, tmp_path / "x.safetensors", frame="heading")
    plain = _run(tmp_path, frame="scan", crop="viewpoint", augment_rotate=False)
    with pytest.raises(ConfigError, match="only a run trained with --crop turned"):
        write_shipped(plain, tmp_path / "x.safetensors", frame="heading")
    aligned = _run(tmp_path, frame="aligned", crop="turned", augment_rotate=False)
    with pytest.raises(ConfigError, match="of the aligned frame cannot be shipped as heading"):
        write_shipped(aligned, tmp_path / "x.safetensors", frame="heading")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_the_heading_frame_of_a_data_set(
    tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Training partials keep the data set's heading (no reader); turned validation partials
    are read back by the reader, as complete reads a scan."""
    from pfnet.data import heading as module
    from pfnet.data.dataset import CompletionDataset
    from pfnet.data.scan_frame import scan_angle

    read = []

    class Reader:  # reads every heading right
        def headings(self, partials):
            read.append(len(partials))
            return np.array([scan_angle(index[0])])

    index = [0]
    monkeypatch.setattr(module, "load_reader", lambda path=None: Reader())
    train = CompletionDataset(tiny_dataset, "train", crop="turned", frame="heading", up_axis=1)
    plain = CompletionDataset(tiny_dataset, "train", crop="turned", frame="scan", up_axis=1)
    np.testing.assert_array_equal(train[3]["partial"].numpy(), plain[3]["partial"].numpy())
    assert read == []
    val = CompletionDataset(tiny_dataset, "val", frame="heading", up_axis=1)
    unturned = CompletionDataset(tiny_dataset, "val", frame="scan", up_axis=1, turn_test=False)
    for i in range(3):
        index[0] = i
        np.testing.assert_allclose(
            val[i]["missing"].numpy(), unturned[i]["missing"].numpy(), atol=1e-5
        )
    assert read == [1, 1, 1]
    with pytest.raises(ConfigError, match="the heading frame reads y-up partials"):
        CompletionDataset(tiny_dataset, "val", frame="heading", up_axis=2)[0]


def test_the_heading_reader_script_writes_a_reader(tiny_dataset: Path, tmp_path: Path) -> None:
    from scripts import load_script

    script = load_script("heading_reader")
    out = tmp_path / "reader.safetensors"
    script.main(
        ["--data", str(tiny_dataset), "--val-data", str(tiny_dataset), "--steps", "3",
         "--batch-size", "4", "--eval-every", "2", "--out", str(out)]
    )  # fmt: skip
    reader = load_reader(out)
    assert [entry["step"] for entry in reader.card["log"]] in ([2], [2, 3])
    assert reader.card["best"]["all"]["n"] == 8  # the tiny data set's val shapes
    assert reader.headings([_cloud()]).shape == (1,)
    errors = script.angle_errors(np.array([0.1, 6.2]), np.array([6.2, 0.1]))
    np.testing.assert_allclose(errors, np.degrees([2 * np.pi - 6.1] * 2))
    with pytest.raises(SystemExit):
        script.main(["--data", "x", "--val-data", "x", "--steps", "0", "--out", str(out)])
    with pytest.raises(SystemExit, match="training needs --data and --out"):
        script.main(["--val-data", "x"])
    figures = script.evaluate(out, tiny_dataset, "val")
    assert figures["all"]["n"] == 8 * 5 and 0.0 <= figures["half_turn_off"] <= 1.0


def test_the_heading_oracle_takes_the_better_candidate(tiny_dataset: Path, tmp_path: Path) -> None:
    import json

    from scripts import load_script

    checkpoint = _run(tmp_path, frame="aligned")
    out = tmp_path / "oracle.json"
    load_script("heading_oracle").main(
        ["--data", str(tiny_dataset), "--checkpoint", str(checkpoint), "--json", str(out)]
    )
    figures = json.loads(out.read_text())["figures"]
    two = figures["the better of the two turns (oracle)"]["cd_l2"]
    four = figures["the best of the four (oracle)"]["cd_l2"]
    assert two <= figures["as the frame gives it"]["cd_l2"]
    assert two <= figures["half a turn"]["cd_l2"]
    assert four <= two and four <= figures["reflected"]["cd_l2"]
    rules = ("the farthest reach", "the fewest on the partial", "the nearest the mirror images")
    for rule in rules:  # a pick is no oracle
        assert figures[f"{rule}, of the four"]["cd_l2"] >= four
        assert figures[f"{rule}, of the two turns"]["cd_l2"] >= two
    assert 0.0 <= figures["half a turn better"] <= 1.0


def test_the_mirror_distance_is_the_mean_distance_to_the_nearest_image() -> None:
    from scripts import load_script

    distance = load_script("heading_oracle").mirror_distance
    detail = np.array([[[0.0, 0, 0], [10, 0, 0]], [[0, 0, 0], [0, 0, 0]]], np.float32)
    images = [np.array([[0.0, 0, 3], [10, 4, 0]], np.float32), np.zeros((0, 3), np.float32)]
    np.testing.assert_allclose(distance(detail, images), [(3.0 + 4.0) / 2, 0.0], rtol=1e-6)
