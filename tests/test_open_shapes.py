"""The open-shapes sources (FlightGear, TORCS, crrcsim, SweetHome3D's jar) and several
sources prepared into one data set, on forged trees; the real packages when installed."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pfnet.data.format import SPLITS, load_split
from pfnet.data.prepare import prepare_dataset
from pfnet.data.sources import flightgear as fg
from pfnet.data.sources.registry import detect_format
from pfnet.errors import ConfigError, DataError

BOX_FACES = [
    (0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)
]  # fmt: skip


def _box(sx: float, sy: float, sz: float, at=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, list]:
    corners = np.array(
        [[x, y, z] for z in (0, 1) for x, y in ((0, 0), (1, 0), (1, 1), (0, 1))], dtype=float
    )
    return corners * [sx, sy, sz] + np.asarray(at), BOX_FACES


def _ac(*parts: tuple[np.ndarray, list], extra: str = "") -> str:
    """AC3D text of one world holding one object per part (quads or triangles)."""
    body = ""
    for vertices, faces in parts:
        body += f"OBJECT poly\nnumvert {len(vertices)}\n"
        body += "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices)
        body += f"numsurf {len(faces)}\n"
        for face in faces:
            body += f"SURF 0x10\nmat 0\nrefs {len(face)}\n" + "".join(f"{k} 0 0\n" for k in face)
        body += "kids 0\n"
    return f"AC3Db\n{extra}OBJECT world\nkids {len(parts)}\n{body}"


def _airplane(span: float, length: float) -> str:
    return _ac(
        _box(length, 0.3, 0.4, (-length / 2, 0, -0.2)), _box(0.6, 0.1, span, (0, 0.1, -span / 2))
    )


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


@pytest.fixture
def flightgear_tree(tmp_path: Path) -> Path:
    root = tmp_path / "flightgear"
    for k, (span, length) in enumerate([(6, 5), (9, 4), (3, 7), (12, 8), (5, 9)]):
        _write(root / f"AI/Aircraft/T{k}/Models/t{k}.ac", _airplane(span, length))
    _write(root / "AI/Aircraft/T0/Models/Lights/Strobe.ac", _ac(_box(0.1, 0.1, 0.1)))
    _write(root / "AI/Aircraft/T1/Models/refueling/probe.ac", _ac(_box(0.1, 0.1, 2)))
    # two liveries of one mesh: identical geometry, another texture
    livery = _airplane(7, 6)
    _write(root / "Scenery/Models/Aircraft/Cessna_blue.ac", livery)
    _write(
        root / "Scenery/Models/Aircraft/Cessna_red.ac",
        livery.replace(
            "AC3Db\n",
            'AC3Db\nMATERIAL "red" rgb 1 0 0 amb 1 0 0 emis 0 0 0 spec 0 0 0 shi 1 trans 0\n',
        ),
    )
    _write(root / "Scenery/Models/Aircraft/ec-135.ac", _ac(_box(3, 1.5, 1), _box(0.1, 0.1, 8)))
    _write(root / "Scenery/Models/Aircraft/B747_services-ba.ac", _airplane(4, 4))
    _write(root / "Scenery/Models/Maritime/Civilian/Trawler.ac", _ac(_box(20, 4, 6)))
    _write(root / "Scenery/Models/Maritime/Civilian/Lighthouse.ac", _ac(_box(3, 30, 3)))
    _write(root / "Scenery/Models/Effects/cloud.ac", _ac(_box(50, 10, 50)))
    _write(root / "Scenery/Models/Transport/camaro_red.ac", _ac(_box(4.5, 1.3, 1.9)))
    _write(root / "Scenery/Models/Transport/Trailer.ac", _ac(_box(8, 2, 2)))
    _write(root / "Scenery/Models/Residential/house.ac", _ac(_box(10, 7, 8)))
    # a broken file: a count that lies
    _write(
        root / "Scenery/Models/Residential/broken.ac",
        _ac(_box(2, 2, 2)).replace("numvert 8", "numvert 80"),
    )
    return root


@pytest.fixture
def torcs_tree(tmp_path: Path) -> Path:
    root = tmp_path / "torcs"
    for name, size in (("alpha", (4.5, 1.2, 1.9)), ("beta", (3.9, 1.5, 1.7))):
        _write(root / f"cars/{name}/{name}.acc", _ac(_box(*size)))
        _write(root / f"cars/{name}/{name}-lod1.acc", _ac(_box(*size)))
    _write(root / "tracks/road/ring/ring.acc", _ac(_box(500, 1, 500)))
    _write(root / "wheels/w/wheel0.acc", _ac(_box(0.6, 0.6, 0.2)))
    return root


@pytest.fixture
def crrcsim_tree(tmp_path: Path) -> Path:
    root = tmp_path / "crrcsim"
    _write(root / "models/glider.xml", '<graphics model="glider.ac"/>')
    _write(root / "models/heli.xml", "<file>heli.ac</file>")
    _write(root / "objects/glider.ac", _airplane(15, 6))
    _write(root / "objects/heli.ac", _ac(_box(2, 1, 1), _box(0.05, 0.05, 4)))
    _write(root / "objects/hut.ac", _ac(_box(3, 3, 3)))
    return root


@pytest.fixture
def sweethome3d_jar(tmp_path: Path) -> Path:
    jar = tmp_path / "sweethome3d" / "sweethome3d.jar"
    jar.parent.mkdir(parents=True)
    res = "com/eteks/sweethome3d/io/resources"
    entries = [
        ("chair", "Chair", "40 90 40"),
        ("bed", "Bed 140x190", "150 50 200"),
        ("aquarium", "Aquarium", "100 60 40"),
    ]
    props = "id=SweetHome3D#DefaultModels\nname=Default\nlicense=GNU GPL\n"
    with zipfile.ZipFile(jar, "w") as archive:
        for k, (stem, name, scale) in enumerate(entries, start=1):
            sx, sy, sz = (float(v) for v in scale.split())
            vertices, faces = _box(sx, sy, sz)
            obj = "".join(f"v {x} {y} {z}\n" for x, y, z in vertices) + "".join(
                "f " + " ".join(str(k + 1) for k in face) + "\n" for face in faces
            )
            archive.writestr(f"{res}/{stem}.obj", obj)
            props += (
                f"id#{k}=eTeks#{stem}\nname#{k}={name}\nmodel#{k}=/{res}/{stem}.obj\n"
                f"creator#{k}=eTeks\n"
            )
        archive.writestr("com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties", props)
    return jar


def test_flightgear_categories_and_exclusions() -> None:
    assert fg.categorize("AI/Aircraft/A320/Models/A320.ac") == ("airplane", "")
    assert fg.categorize("AI/Aircraft/c182/Models/WhiteLight1.ac") == (None, "light")
    assert fg.categorize("AI/Aircraft/Dromader/Models/Lights/NavL.ac") == (None, "light")
    assert fg.categorize("AI/Aircraft/A330-MRTT/Models/refueling/refueling.ac") == (
        None,
        "aircraft_part",
    )
    assert fg.categorize("AI/Aircraft/Lightning/Models/lightning-f1a.ac") == ("airplane", "")
    assert fg.categorize("Scenery/Models/Aircraft/mil-mi-8-lowpoly.ac") == ("helicopter", "")
    assert fg.categorize("Scenery/Models/Aircraft/A310_services-ba.ac") == (None, "services_group")
    assert fg.categorize("Scenery/Models/Aircraft/glider-trailer-red.ac") == (None, "trailer")
    assert fg.categorize("Scenery/Models/Effects/cloud.ac") == (None, "effects")
    assert fg.categorize("Scenery/Models/Maritime/Civilian/CruiseShip.ac") == ("ship", "")
    assert fg.categorize("Scenery/Models/Maritime/Civilian/Lighthouse.ac") == ("other", "")
    assert fg.categorize("Scenery/Models/Maritime/Misc/Buoy-Safe-Water.ac") == ("other", "")
    assert fg.categorize("Scenery/Models/Transport/tourbus1.ac") == ("bus", "")
    assert fg.categorize("Scenery/Models/Transport/hatchback_red.ac") == ("car", "")
    assert fg.categorize("Scenery/Models/Airport/Vehicle/fire-truck-ba.ac") == ("truck", "")
    assert fg.categorize("Scenery/Models/Airport/helipad40m.ac") == ("other", "")
    assert fg.categorize("Scenery/Models/Residential/french_house_s.ac") == ("building", "")


def test_each_tree_is_detected(
    flightgear_tree: Path, torcs_tree: Path, crrcsim_tree: Path, sweethome3d_jar: Path
) -> None:
    assert detect_format(flightgear_tree) == "flightgear"
    assert detect_format(torcs_tree) == "torcs"
    assert detect_format(crrcsim_tree) == "crrcsim"
    assert detect_format(sweethome3d_jar) == "sweethome3d-app"
    assert detect_format(sweethome3d_jar.parent) == "sweethome3d-app"


def _counts(report) -> dict[str, int]:
    out: dict[str, int] = {}
    for split in SPLITS:
        for category, n in report.counts[split].items():
            out[category] = out.get(category, 0) + n
    return out


def test_several_sources_make_one_data_set(
    tmp_path: Path,
    flightgear_tree: Path,
    torcs_tree: Path,
    crrcsim_tree: Path,
    sweethome3d_jar: Path,
) -> None:
    sources = [flightgear_tree, torcs_tree, crrcsim_tree, sweethome3d_jar.parent]
    report = prepare_dataset(
        sources, tmp_path / "open", points=256, pool=1024, categories="all", workers=1
    )
    counts = _counts(report)
    # 5 AI aircraft + 1 livery kept of 2 + the glider; the helicopters; the cars
    assert counts == {
        "airplane": 7,
        "helicopter": 2,
        "ship": 1,
        "car": 3,
        "building": 1,
        "other": 2,
        "bed": 1,
        "chair": 1,
    }
    assert report.distinct["identical_merged"] == {"airplane": 1}
    assert report.distinct["kept_by_source"]["torcs"] == {"car": 2}
    # the broken file is reported by name and the rest kept
    assert [Path(p).name for p, _ in report.skipped] == ["broken.ac"]
    assert "numvert 80 declares more than" in report.skipped[0][1]
    assert report.dropped["flightgear: light"] == 1
    assert report.dropped["flightgear: aircraft_part"] == 1
    assert report.dropped["flightgear: services_group"] == 1
    assert report.dropped["flightgear: trailer"] == 1
    assert report.dropped["flightgear: effects"] == 1
    assert report.dropped["torcs: level_of_detail"] == 2
    assert report.dropped["crrcsim: scenery_prop"] == 1
    manifest = json.loads((tmp_path / "open" / "manifest.json").read_text())
    assert manifest["up_axis"] == "y" and manifest["pool"] == 1024
    assert [s["format"] for s in manifest["source"]["sources"]] == [
        "flightgear",
        "torcs",
        "crrcsim",
        "sweethome3d-app",
    ]
    shapes = manifest["shapes"]
    assert len(shapes) == report.total
    assert {s["source"] for s in shapes.values()} == {
        "flightgear",
        "torcs",
        "crrcsim",
        "sweethome3d-app",
    }
    licenses = {r["source"]: r["license"] for r in manifest["licenses"]}
    assert licenses["flightgear"] == "GPL-2+" and licenses["crrcsim"] == "GPL-2"
    assert "Free Art" in licenses["torcs"] and licenses["sweethome3d.jar"] == "GNU GPL"
    summary = report.summary()
    assert "merged by category: airplane 1" in summary and "from torcs: 2" in summary
    # the same sources and seed give the same arrays
    again = prepare_dataset(
        sources, tmp_path / "again", points=256, pool=1024, categories="all", workers=2
    )
    for split in SPLITS:
        a, b = load_split(tmp_path / "open", split), load_split(tmp_path / "again", split)
        assert np.array_equal(a.points, b.points) and list(a.name) == list(b.name)
    assert again.counts == report.counts


def test_near_copies_go_to_one_split(tmp_path: Path) -> None:
    root = tmp_path / "flightgear"
    rng = np.random.default_rng(0)
    # ten distinct aircraft, and five near-copies of the first (a tiny extra part each)
    for k in range(10):
        span, length = rng.uniform(3, 12), rng.uniform(3, 12)
        _write(root / f"AI/Aircraft/T{k}/Models/t{k}.ac", _airplane(span, length))
    base = _airplane(8.0, 6.0)
    _write(root / "AI/Aircraft/T0/Models/t0.ac", base)
    for k in range(5):
        copy = _ac(
            _box(6, 0.3, 0.4, (-3, 0, -0.2)),
            _box(0.6, 0.1, 8, (0, 0.1, -4)),
            _box(0.01 * (k + 1), 0.01, 0.01),
        )
        _write(root / f"AI/Aircraft/C{k}/Models/c{k}.ac", copy)
    report = prepare_dataset(
        root, tmp_path / "out", points=512, workers=1, distinct=True, test_fraction=0.3
    )
    assert report.distinct["identical_merged"] == {}
    pairs = {tuple(sorted(p[:2])) for p in report.distinct["near_copies"]}
    family = ["flightgear_ai_aircraft_t0_models_t0"] + [
        f"flightgear_ai_aircraft_c{k}_models_c{k}" for k in range(5)
    ]
    # every copy is found as a near-copy (of the original or of another copy)
    assert all(any(name in pair for pair in pairs) for name in family), pairs
    assert all(p[2] <= 1.5 for p in report.distinct["near_copies"])
    split_of = {
        name: split
        for split in SPLITS
        for name in load_split(tmp_path / "out", split).name.tolist()
    }
    assert set(family) <= set(split_of) and len({split_of[n] for n in family}) == 1


def test_several_sources_refuse_benchmarks_and_clashing_keys(
    tmp_path: Path, torcs_tree: Path
) -> None:
    with pytest.raises(ConfigError, match="not procedural"):
        prepare_dataset([torcs_tree, "procedural"], tmp_path / "x")
    with pytest.raises(DataError, match="also in another source"):
        prepare_dataset([torcs_tree, torcs_tree], tmp_path / "y", points=64)


REAL = {
    "flightgear": Path("/usr/share/games/flightgear"),
    "torcs": Path("/usr/share/games/torcs"),
    "crrcsim": Path("/usr/share/games/crrcsim"),
}


@pytest.mark.real_data
@pytest.mark.parametrize("name", sorted(REAL))
def test_real_trees_scan(name: str) -> None:
    from pfnet.data.sources.registry import _open_shape_sources

    if not REAL[name].is_dir():
        pytest.skip(f"{REAL[name]} is absent: apt-get install {name}-data")
    scan = _open_shape_sources()[name].scan(REAL[name])
    categories = {item.category for item in scan.items}
    minimum = {"flightgear": 1500, "torcs": 17, "crrcsim": 29}[name]
    assert len(scan.items) >= minimum
    assert {"flightgear": {"airplane", "ship", "car"}, "torcs": {"car"}, "crrcsim": {"airplane"}}[
        name
    ] <= categories


def test_the_command_line_takes_several_sources(
    tmp_path: Path, torcs_tree: Path, crrcsim_tree: Path, capsys: pytest.CaptureFixture
) -> None:
    from pfnet.cli import main

    out = tmp_path / "two"
    args = ["prepare", str(torcs_tree), str(crrcsim_tree), "--out", str(out), "--points", "64"]
    assert main([*args, "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "from torcs, crrcsim" in printed and "from torcs: 2 (car 2)" in printed
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["distinct"]["kept_by_source"] == {
        "crrcsim": {"airplane": 1, "helicopter": 1},
        "torcs": {"car": 2},
    }


def test_a_mesh_folder_may_hold_ac3d_files(tmp_path: Path) -> None:
    _write(tmp_path / "meshes/airplane/a.ac", _airplane(8, 6))
    _write(tmp_path / "meshes/airplane/b.ac", _airplane(5, 9))
    _write(tmp_path / "meshes/car/c.acc", _ac(_box(4, 1.2, 1.8)))
    report = prepare_dataset(tmp_path / "meshes", tmp_path / "out", points=64, workers=1)
    assert _counts(report) == {"airplane": 2, "car": 1} and report.format == "meshes"
