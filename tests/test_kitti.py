"""KITTI cars (issue 17): the PCN release's layout through prepare, predict and evaluate, the
pose normalisation against the pose the cars were placed with, Fidelity and MMD against a
brute force, and the error paths."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from brute import capture_panels, naive_fps, nearest_distances, needs_runtime, write_pcd

from pfnet.cli import main
from pfnet.data import load_split, prepare_dataset
from pfnet.data.kitti import kitti_input, load_boxes, object_pose
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.benchmarks import evaluate_kitti, load_references

KATOR = Path("/usr/share/sweethome3d/furniture/KatorLegaz.sh3f")  # five cars
LENGTH = 4.0  # metres, the length the cars are scaled to
# PoinTr's corner order as far as it matters: corners 0 and 3 span the length (+x).
CORNER_SIGNS = np.array(
    [
        [-1, -1, -1],
        [-1, 1, -1],
        [-1, -1, 1],
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, 1],
        [1, -1, 1],
        [1, 1, 1],
    ],
    dtype=np.float64,
)
# (model id, car, yaw, points kept): car 1 twice, one car with more than 2,048 points
CARS = [
    ("frame_0_car_0", 0, 0.3, 600),
    ("frame_0_car_1", 1, -1.2, 2500),
    ("frame_7_car_0", 2, 2.5, 350),
    ("frame_7_car_1", 1, 1.0, 900),
]


def car_surfaces(count: int) -> list[np.ndarray]:
    """Real cars (SweetHome3D, y up) sampled and turned into a car frame: z up, length along
    +x, the box centred at the origin, LENGTH metres long."""
    from pfnet.data.sampling import sample_surface
    from pfnet.data.sources import sweethome3d
    from pfnet.data.sources.registry import load_item

    if not KATOR.is_file():  # pragma: no cover
        pytest.skip("Debian's sweethome3d-furniture is not installed")
    items = [i for i in sweethome3d.scan(KATOR, strict=False).items if i.category == "car"]
    rng = np.random.default_rng(0)
    cars = []
    for item in items[:count]:
        mesh = load_item(item, 0)
        y_up = sample_surface(mesh.vertices, mesh.faces, 6000, rng)
        car = np.stack([y_up[:, 0], -y_up[:, 2], y_up[:, 1]], axis=1)  # z up
        extent = car.max(axis=0) - car.min(axis=0)
        if extent[1] > extent[0]:  # length along y: turn it onto x
            car = np.stack([car[:, 1], -car[:, 0], car[:, 2]], axis=1)
        car -= (car.min(axis=0) + car.max(axis=0)) / 2
        cars.append(car * LENGTH / (car[:, 0].max() - car[:, 0].min()))
    return cars


def turn(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def kitti_tree(tmp_path_factory) -> tuple[Path, dict]:
    """The KITTI layout of the PCN release: KITTI.json, cars/<id>.pcd (the half of each car
    facing the sensor at the origin), bboxes/<id>.txt (8 corners). Returns the root and, per
    id, the car-frame points kept (what pose normalisation must give back, / LENGTH)."""
    root = tmp_path_factory.mktemp("kitti") / "KITTI"
    surfaces = car_surfaces(3)
    truth = {}
    for k, (model, car, yaw, kept) in enumerate(CARS):
        points = surfaces[car]
        half = (points.max(axis=0) - points.min(axis=0)) / 2
        rotation = turn(yaw)
        centre = np.array([8.0 + 4 * k, 5.0 * (-1) ** k, -0.9])
        sensor = points @ rotation.T + centre
        seen = (sensor - centre) @ -centre > 0  # the side facing the sensor
        order = np.flatnonzero(seen)[:kept]
        write_pcd(root / "cars" / f"{model}.pcd", sensor[order])
        corners = (CORNER_SIGNS * half) @ rotation.T + centre
        (root / "bboxes").mkdir(parents=True, exist_ok=True)
        np.savetxt(root / "bboxes" / f"{model}.txt", corners)
        truth[model] = points[order].astype(np.float32)
    record = {
        "taxonomy_id": "kitti-car",
        "taxonomy_name": "Car",
        "test": [c[0] for c in CARS],
        "train": [],
        "val": [],
    }
    (root / "KITTI.json").write_text(json.dumps([record], indent=4))
    return root, truth


@pytest.fixture(scope="module")
def references(tmp_path_factory) -> Path:
    """Reference cars: SweetHome3D's cars prepared as a data set (category car)."""
    out = tmp_path_factory.mktemp("refs") / "cars"
    prepare_dataset(KATOR, out, points=1024, categories=["car"], workers=1, progress=False, seed=0)
    return out


def pointr_normalize(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """PoinTr's NormalizeObjectPose (datasets/data_transforms.py lines 116-131), written out."""
    box = box.astype(np.float32).astype(np.float64)
    centre = (box.min(0) + box.max(0)) / 2
    box = box - centre
    yaw = np.arctan2(box[3, 1] - box[0, 1], box[3, 0] - box[0, 0])
    rotation = turn(yaw)
    box = box @ rotation
    scale = box[3, 0] - box[0, 0]
    cloud = (points.astype(np.float64) - centre) @ rotation / scale
    return cloud @ np.array([[1, 0, 0], [0, 0, 1], [0, 1, 0]])


# ---------------------------------------------------------------- pose normalisation


def test_pose_normalisation_recovers_the_car_frame(kitti_tree):
    root, truth = kitti_tree
    for model, _, _, _ in CARS:
        from pfnet.io.clouds import read_point_cloud

        points = read_point_cloud(root / "cars" / f"{model}.pcd")
        box = np.loadtxt(root / "bboxes" / f"{model}.txt")
        pose = object_pose(box)
        # the pose the car was placed with, undone: car frame / length, y and z swapped
        want = truth[model][:, [0, 2, 1]] / LENGTH
        np.testing.assert_allclose(pose.apply(points), want, atol=2e-6)
        np.testing.assert_allclose(pose.apply(points), pointr_normalize(points, box), atol=1e-6)
        np.testing.assert_allclose(pose.invert(pose.apply(points)), points, atol=1e-4)
        given = kitti_input(points, box)
        if len(points) > 2048:  # reduced by IFPS from the first point
            expected = naive_fps(pose.apply(points), 2048)
            np.testing.assert_array_equal(given, expected)
        else:
            np.testing.assert_array_equal(given, pose.apply(points))


def test_object_pose_refuses_boxes_without_length():
    box = np.zeros((8, 3))
    with pytest.raises(DataError, match="corners 0 and 3 of the box coincide"):
        object_pose(box, "b.txt")
    with pytest.raises(DataError, match=r"b.txt: a box must be 8 finite corners"):
        object_pose(np.ones((7, 3)), "b.txt")


# ---------------------------------------------------------------- end to end


@needs_runtime
def test_kitti_prepare_predict_evaluate(kitti_tree, references, tmp_path, capsys, monkeypatch):
    root, truth = kitti_tree
    data, pred = tmp_path / "data", tmp_path / "pred"
    assert main(["prepare", str(root), "--out", str(data)]) == 0  # auto-detected
    cars = load_split(data, "test")
    assert cars.categories == ["car"] and list(cars.name) == sorted(c[0] for c in CARS)
    manifest = json.loads((data / "manifest.json").read_text())
    assert manifest["benchmark"]["protocol"] == "kitti"
    assert manifest["splits"]["train"]["total"] == 0
    boxes = load_boxes(data, "test", len(cars))
    np.testing.assert_allclose(
        boxes[0], np.loadtxt(root / "bboxes" / f"{cars.name[0]}.txt"), rtol=1e-6
    )

    assert main(["predict", "--data", str(data), "--out", str(pred), "--protocol", "kitti"]) == 0
    assert "--protocol kitti --references CARS" in capsys.readouterr().out
    record = json.loads((pred / "predictions.json").read_text())
    assert record["files"] == {"endings": [".npy"], "names": {"car": list(cars.name)}}
    inputs = {}
    for model, *_ in CARS:
        points = truth[model]
        completion = np.load(pred / "car" / f"{model}.npy")
        box = np.loadtxt(root / "bboxes" / f"{model}.txt")
        from pfnet.io.clouds import read_point_cloud

        sensor = read_point_cloud(root / "cars" / f"{model}.pcd")
        given = pointr_normalize(sensor, box).astype(np.float32)
        if len(given) > 2048:
            given = naive_fps(given, 2048)
        inputs[model] = given
        n_in = min(len(points), 2048)
        assert completion.shape == (n_in + 512, 3)
        np.testing.assert_allclose(completion[:n_in], given, atol=1e-6)  # the input first
        assert np.abs(completion).max() < 2  # in the normalised frame: about one unit long

    js, table = tmp_path / "r.json", tmp_path / "r.csv"
    args = ["evaluate", str(pred), "--data", str(data), "--references", str(references)]
    assert main([*args, "--json", str(js), "--csv", str(table)]) == 0  # protocol as recorded
    out = capsys.readouterr().out
    assert "protocol kitti, 4 of 4 completions scored against" in out
    assert "Fidelity" in out and "MMD" in out
    report = json.loads(js.read_text())
    assert report["protocol"] == "kitti" and report["scale"] == 1000
    assert report["headline"] == "mmd" and report["categories"]["car"]["n"] == 4

    # independently: every pair by brute force, in float64
    ref_clouds = [
        c for split in ("train", "val", "test") for c in load_split(references, split).points
    ]
    assert report["references"]["n"] == len(ref_clouds) == 5
    fids, mmds = [], []
    with table.open(encoding="utf-8") as fh:
        rows = {r["name"]: r for r in csv.DictReader(fh)}
    for model in sorted(inputs):
        completion = np.load(pred / "car" / f"{model}.npy").astype(np.float64)
        fid = (nearest_distances(inputs[model], completion) ** 2).mean()
        every = [
            (nearest_distances(completion, r) ** 2).mean()
            + (nearest_distances(r, completion) ** 2).mean()
            for r in np.asarray(ref_clouds, np.float64)
        ]
        fids.append(fid)
        mmds.append(min(every))
        assert float(rows[model]["mmd"]) == pytest.approx(min(every) * 1000, rel=1e-5)
        assert float(rows[model]["fidelity"]) == pytest.approx(fid * 1000, rel=1e-4, abs=1e-9)
    assert report["categories"]["car"]["mmd"] == pytest.approx(np.mean(mmds) * 1000, rel=1e-5)
    assert report["mean"]["fidelity"] == pytest.approx(np.mean(fids) * 1000, rel=1e-4, abs=1e-9)
    # the completion holds its input: PF-Net's Fidelity is 0, as PoinTr's is (its table: 0.000)
    assert report["mean"]["fidelity"] == pytest.approx(0.0, abs=1e-6)

    # the gallery: the car's input, its completion, the reference car nearest to it
    drawn, gallery = capture_panels(monkeypatch), tmp_path / "g.png"
    assert main([*args, "--gallery", str(gallery), "--gallery-count", "2"]) == 0
    (picked,) = drawn
    assert len(picked) == 2 and gallery.read_bytes()[:4] == b"\x89PNG"
    for label, panels in picked:
        model = label.split("/")[1]
        assert [title for title, _ in panels] == ["input", "completion", "nearest reference"]
        np.testing.assert_allclose(panels[0][1][0][0], inputs[model], atol=1e-6)
        np.testing.assert_array_equal(panels[1][1][0][0], np.load(pred / "car" / f"{model}.npy"))
        split, name = rows[model]["nearest_reference"].split("/")
        refs = load_split(references, split)
        np.testing.assert_array_equal(panels[2][1][0][0], refs.points[list(refs.name).index(name)])

    # a completion without its input: Fidelity measures the input's distance to it
    np.save(pred / "car" / f"{CARS[0][0]}.npy", np.load(pred / "car" / f"{CARS[0][0]}.npy")[-512:])
    got = evaluate_kitti(pred, data, references)
    completion = np.load(pred / "car" / f"{CARS[0][0]}.npy").astype(np.float64)
    want = (nearest_distances(inputs[CARS[0][0]], completion) ** 2).mean()
    assert got.per_sample["fidelity"][0] == pytest.approx(want, rel=1e-5)
    assert want > 0


# ---------------------------------------------------------------- error paths


def test_kitti_bad_files_are_named_and_the_rest_prepared(kitti_tree, tmp_path):
    root, _ = kitti_tree
    broken = tmp_path / "KITTI"
    shutil.copytree(root, broken)
    (broken / "bboxes/frame_0_car_1.txt").unlink()
    (broken / "cars/frame_7_car_0.pcd").write_text("not a pcd")
    np.savetxt(broken / "bboxes/frame_7_car_1.txt", np.ones((7, 3)))
    report = prepare_dataset(broken, tmp_path / "d", format="kitti", progress=False)
    reasons = dict(report.skipped)
    assert (
        "the box of frame_0_car_1.pcd is missing"
        in reasons[str(broken / "bboxes/frame_0_car_1.txt")]
    )
    assert "truncated header (no 'DATA' line)" in reasons[str(broken / "cars/frame_7_car_0.pcd")]
    assert (
        "a box has 8 corners, this file holds 7 points"
        in reasons[str(broken / "bboxes/frame_7_car_1.txt")]
    )
    assert report.counts["test"] == {"car": 1}
    with pytest.raises(DataError, match="the box of frame_0_car_1.pcd is missing"):
        prepare_dataset(broken, tmp_path / "d2", strict=True, progress=False)
    (broken / "KITTI.json").write_text("{not json")
    with pytest.raises(DataError, match="KITTI.json: cannot read the category file"):
        prepare_dataset(broken, tmp_path / "d3", progress=False)


@needs_runtime
def test_kitti_option_errors(kitti_tree, references, tiny_dataset, tmp_path, capsys):
    root, _ = kitti_tree
    data, pred = tmp_path / "data", tmp_path / "pred"
    prepare_dataset(root, data, progress=False)
    assert main(["predict", "--data", str(data), "--out", str(pred), "--protocol", "kitti"]) == 0
    capsys.readouterr()
    base = ["evaluate", str(pred), "--data", str(data)]
    assert main(base) == 1
    assert "the kitti protocol needs --references CARS" in capsys.readouterr().err
    assert main([*base, "--references", str(tmp_path / "nowhere")]) == 1
    assert "references: " in capsys.readouterr().err
    with pytest.raises(DataError, match="no cloud of the category 'car' \\(categories: chair"):
        load_references(tiny_dataset)
    with pytest.raises(DataError, match="its clouds hold no points"):
        load_references(data)
    assert main([*base, "--references", str(references), "--protocol", "pcn"]) == 1
    assert "made with the kitti protocol" in capsys.readouterr().err
    assert main([*base, "--references", str(references), "--split", "val"]) == 1
    assert "holds predictions of the 'test' split" in capsys.readouterr().err
    (pred / "car" / "frame_7_car_0.npy").unlink()
    assert main([*base, "--references", str(references)]) == 2
    assert "1 sample(s) have no prediction file: car/frame_7_car_0" in capsys.readouterr().err
    other = ["predict", "--data", str(tiny_dataset), "--out", str(tmp_path / "p2")]
    assert main([*other, "--protocol", "kitti"]) == 1
    assert "the kitti protocol needs a data set prepared from its benchmark" in (
        capsys.readouterr().err
    )
    assert main([*other, "--protocol", "kitti", "--missing-ratio", "0.5"]) == 1
    assert "the kitti protocol takes no missing ratio" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="scored by evaluate_kitti"):
        from pfnet.evaluation.benchmarks import evaluate_benchmark

        evaluate_benchmark(pred, data, "kitti")


# ---------------------------------------------------------------- MMD's branch and bound


def every_pair_cd(comp: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """CD-L2 of ``comp`` to every reference, by float64 brute force."""
    return np.array(
        [
            (nearest_distances(comp, ref) ** 2).mean() + (nearest_distances(ref, comp) ** 2).mean()
            for ref in refs
        ]
    )


def one_at_a_time(comps: np.ndarray, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pruned search's own exact value of every pair (one reference per call: nothing to
    prune), reduced to the minimum and lowest index among ties, as every pair would be."""
    from pfnet.evaluation.metrics import minimal_matching_distance

    every = np.stack(
        [minimal_matching_distance(comps, refs[j : j + 1])[0] for j in range(len(refs))]
    )
    return every.min(axis=0), every.argmin(axis=0)


def boxy_cars(rng: np.random.Generator, count: int, n: int) -> np.ndarray:
    """Cars as points on boxes of close proportions: the nearest and the runners-up differ by
    little, as the real reference cars do."""
    clouds = []
    for _ in range(count):
        size = rng.uniform([3.8, 1.6, 1.2], [4.6, 2.0, 1.6])
        axis = rng.integers(0, 3, n)
        p = rng.uniform(-0.5, 0.5, (n, 3))
        p[np.arange(n), axis] = rng.choice([-0.5, 0.5], n)
        clouds.append(p * size / 4.0)
    return np.stack(clouds).astype(np.float32)


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
def test_mmd_search_equals_every_pair_bit_for_bit():
    from pfnet.evaluation.metrics import minimal_matching_distance

    rng = np.random.default_rng(17)
    refs = boxy_cars(rng, 40, 600)
    comps = np.stack(
        [refs[j] * rng.uniform(0.98, 1.02, 3) for j in (4, 4, 31, 12, 0)]
        + [boxy_cars(rng, 1, 600)[0]]
    ).astype(np.float32)
    dist, index = minimal_matching_distance(comps, refs)
    want, want_index = one_at_a_time(comps, refs)
    np.testing.assert_array_equal(index, want_index)
    np.testing.assert_array_equal(dist, want)  # the same float64 bits
    for k, comp in enumerate(comps):
        brute = every_pair_cd(comp, refs)
        assert index[k] == int(np.argmin(brute))
        assert dist[k] == pytest.approx(brute.min(), rel=1e-6)


def test_mmd_adversarial_sets():
    from pfnet.evaluation.metrics import minimal_matching_distance

    rng = np.random.default_rng(3)
    car = boxy_cars(rng, 1, 500)[0]
    far = car + np.float32(50.0)
    refs = np.stack([far, car, far * 1.01, car, car]).astype(np.float32)
    # a completion equal to three identical references: distance 0, the lowest of them
    dist, index = minimal_matching_distance(car[None], refs)
    assert (dist[0], index[0]) == (0.0, 1)
    # every reference far from the completions; completions of one repeated point
    comps = np.stack([car + np.float32(-200.0), np.full((500, 3), 7.0, np.float32)])
    dist, index = minimal_matching_distance(comps, refs)
    want, want_index = one_at_a_time(comps, refs)
    np.testing.assert_array_equal(index, want_index)
    np.testing.assert_array_equal(dist, want)
    # tiny clouds (no coarse levels) and collinear ones
    tiny_refs = rng.normal(size=(30, 3, 3)).astype(np.float32)
    tiny_comps = rng.normal(size=(4, 2, 3)).astype(np.float32)
    line = np.zeros((20, 300, 3), np.float32)
    line[:, :, 0] = np.linspace(0, 1, 300) * rng.uniform(0.5, 1.5, (20, 1))
    for comps, refs in ((tiny_comps, tiny_refs), (line[:3] * 1.01, line)):
        dist, index = minimal_matching_distance(comps, refs)
        want, want_index = one_at_a_time(comps, refs)
        np.testing.assert_array_equal(index, want_index)
        np.testing.assert_array_equal(dist, want)
        for k, comp in enumerate(comps):
            assert dist[k] == pytest.approx(every_pair_cd(comp, refs).min(), rel=1e-6, abs=1e-12)


def test_mmd_takes_completions_of_different_sizes():
    from pfnet.evaluation.metrics import minimal_matching_distance

    rng = np.random.default_rng(8)
    refs = boxy_cars(rng, 12, 400)
    comps = [boxy_cars(rng, 1, n)[0] for n in (300, 17, 400, 1)]
    dist, index = minimal_matching_distance(comps, refs)
    for k, comp in enumerate(comps):
        one = minimal_matching_distance(comp[None], refs)
        assert (dist[k], index[k]) == (one[0][0], one[1][0])
    empty = minimal_matching_distance([], refs)
    assert empty[0].shape == (0,) and empty[1].dtype == np.int64
    with pytest.raises(ValueError, match=r"completions\[1\] must be an \(N, 3\) array"):
        minimal_matching_distance([comps[0], comps[1][:, :2]], refs)
    with pytest.raises(ValueError, match="completions"):
        minimal_matching_distance([comps[0], np.zeros((0, 3), np.float32)], refs)
    from pfnet._core import minimal_matching

    with pytest.raises(ValueError, match="counts must add up to the 5 completion points"):
        minimal_matching(np.zeros((5, 3), np.float32), [2, 2], refs)
