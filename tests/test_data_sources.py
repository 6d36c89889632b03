"""Each source format end to end on fixtures made here: mesh folders, ShapeNet-Part, .sh3f."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pfnet.data import SWEETHOME3D_PATH, load_split, prepare_dataset, read_manifest
from pfnet.data.sources.procedural import build_shape
from pfnet.data.sources.registry import detect_format
from pfnet.data.sources.sweethome3d import category_for, parse_obj, parse_properties
from pfnet.errors import ConfigError, DataError

SPLITS = ("train", "val", "test")


def _mesh(category: str, index: int) -> trimesh.Trimesh:
    shape = build_shape(category, 0, f"{category}/{index}")
    return trimesh.Trimesh(shape.vertices, shape.faces, process=False)


def _prepare(source, out: Path, **options):
    return prepare_dataset(
        source, out, **({"points": 64, "workers": 1, "progress": False} | options)
    )


def _all_names(out: Path) -> dict[str, str]:
    names = {}
    for split in SPLITS:
        clouds = load_split(out, split)
        names |= dict(zip(clouds.name.tolist(), clouds.category.tolist(), strict=True))
    return names


@pytest.fixture
def mesh_tree(tmp_path: Path) -> Path:
    """ROOT/<category>/<file> in every supported format, point clouds and bad files."""
    root = tmp_path / "meshes"
    for category, suffixes in (
        ("Chair", ("obj", "off", "ply", "stl", "glb")),
        ("table", ("obj", "stl")),
    ):
        folder = root / category
        folder.mkdir(parents=True)
        for index, suffix in enumerate(suffixes):
            # the chairs share one stem, so their names must be made unique
            stem = "shape" if category == "Chair" else f"shape {index}"
            _mesh(category.lower(), index).export(folder / f"{stem}.{suffix}")
    (root / "Chair" / "nested").mkdir()
    _mesh("chair", 9).export(root / "Chair" / "nested" / "deep.obj")
    (root / "Chair" / "shape 0.mtl").write_text("newmtl unused\n")  # ignored suffix
    (root / "Chair" / ".hidden.obj").write_text("garbage")  # hidden: ignored
    clouds = root / "lamp"
    clouds.mkdir()
    rng = np.random.default_rng(0)
    np.savetxt(clouds / "dense.xyz", rng.normal(size=(300, 3)))
    np.save(clouds / "sparse.npy", rng.normal(size=(20, 3)).astype(np.float32))
    trimesh.PointCloud(rng.normal(size=(100, 3))).export(clouds / "cloud.ply")
    return root


def _add_bad_files(root: Path) -> dict[str, str]:
    bad = root / "broken"
    bad.mkdir()
    (bad / "empty.obj").write_text("")
    (bad / "nan.obj").write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    (bad / "flat.obj").write_text("v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n")
    (bad / "junk.ply").write_bytes(b"definitely not a ply file")
    (bad / "nopoints.xyz").write_text("# nothing\n")
    return {
        "empty.obj": "the mesh has no vertices",
        "nan.obj": "NaN or infinite",
        "flat.obj": "zero surface area",
        "junk.ply": "not a PLY file",
        "nopoints.xyz": "no points",
    }


def test_mesh_folder_end_to_end(tmp_path: Path, mesh_tree: Path) -> None:
    report = _prepare(mesh_tree, tmp_path / "out", test_fraction=0.25, val_fraction=0.0)
    assert report.format == "meshes" and report.skipped == []
    names = _all_names(tmp_path / "out")
    assert names == {
        "chair_shape": "chair", "chair_shape-2": "chair", "chair_shape-3": "chair",
        "chair_shape-4": "chair", "chair_shape-5": "chair", "chair_nested_deep": "chair",
        "table_shape_0": "table", "table_shape_1": "table",
        "lamp_dense": "lamp", "lamp_sparse": "lamp", "lamp_cloud": "lamp",
    }  # fmt: skip
    # round(0.25 · n) per category: 6 chairs → 2, 3 lamps → 1, 2 tables → round(0.5) = 0
    assert report.counts["test"] == {"chair": 2, "lamp": 1}
    assert report.counts["train"] == {"chair": 4, "lamp": 2, "table": 2}
    for split in SPLITS:
        points = load_split(tmp_path / "out", split).points
        assert points.shape[1:] == (64, 3)
        np.testing.assert_allclose(np.linalg.norm(points, axis=2).max(axis=1), 1.0, atol=1e-6)


def test_a_category_folder_named_like_the_prediction_record(tmp_path: Path) -> None:
    """A category folder called ``predictions.json`` (audit 11, N6) is prepared as
    ``predictions_json``, so predict can write its record beside the category folders."""
    root = tmp_path / "meshes"
    for category in ("predictions.json", "chair"):
        for k in range(2):
            (root / category).mkdir(parents=True, exist_ok=True)
            trimesh.creation.box(extents=(1, 1 + k, 2)).export(root / category / f"m{k}.obj")
    _prepare(root, tmp_path / "out", test_fraction=0.5, val_fraction=0.0)
    assert set(_all_names(tmp_path / "out").values()) == {"chair", "predictions_json"}


def test_mesh_folder_point_clouds_are_resampled(tmp_path: Path, mesh_tree: Path) -> None:
    _prepare(mesh_tree, tmp_path / "out", categories=["lamp"], test_fraction=0.0, val_fraction=0.0)
    clouds = load_split(tmp_path / "out", "train")
    sparse = clouds.points[clouds.name.tolist().index("lamp_sparse")]
    assert len(np.unique(sparse, axis=0)) == 20  # 20 points, 44 seeded copies
    dense = clouds.points[clouds.name.tolist().index("lamp_dense")]
    assert len(np.unique(dense, axis=0)) == 64  # IFPS of 300


def test_bad_files_are_skipped_and_reported(tmp_path: Path, mesh_tree: Path) -> None:
    expected = _add_bad_files(mesh_tree)
    report = _prepare(mesh_tree, tmp_path / "out")
    reasons = {Path(path).name: reason for path, reason in report.skipped}
    assert set(reasons) == set(expected)
    for name, fragment in expected.items():
        assert fragment in reasons[name], (name, reasons[name])
    assert all(str(mesh_tree / "broken") in path for path, _ in report.skipped)
    assert "broken" not in set(_all_names(tmp_path / "out").values())
    manifest = read_manifest(tmp_path / "out")
    assert {Path(s["path"]).name for s in manifest["skipped"]} == set(expected)
    assert "skipped 5 files:" in report.summary()


def test_strict_fails_on_a_bad_file(tmp_path: Path, mesh_tree: Path) -> None:
    _add_bad_files(mesh_tree)
    with pytest.raises(DataError, match=r"broken/empty.obj: the mesh has no vertices"):
        _prepare(mesh_tree, tmp_path / "out", strict=True, categories="broken")
    assert not (tmp_path / "out").exists()
    # in a process pool too: the first failure stops the run
    many = mesh_tree / "many"
    many.mkdir()
    for index in range(20):
        _mesh("chair", index).export(many / f"ok{index:02d}.obj")
    (many / "zz_bad.obj").write_text("v 0 0 0\n")
    with pytest.raises(DataError, match=r"many/zz_bad.obj: the mesh has no vertices"):
        _prepare(mesh_tree, tmp_path / "out", strict=True, categories="many", workers=2)
    assert not (tmp_path / "out").exists()


def test_every_shape_failing_is_an_error(tmp_path: Path, mesh_tree: Path) -> None:
    _add_bad_files(mesh_tree)
    with pytest.raises(DataError, match="every shape failed"):
        _prepare(mesh_tree, tmp_path / "out", categories="broken")


def test_source_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="nowhere: no such file or folder"):
        _prepare(tmp_path / "nowhere", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="the source folder is empty"):
        _prepare(tmp_path / "empty", tmp_path / "out")
    (tmp_path / "odd" / "cat").mkdir(parents=True)
    (tmp_path / "odd" / "cat" / "notes.md").write_text("hello")
    with pytest.raises(DataError, match="cannot detect the format .*give the format"):
        _prepare(tmp_path / "odd", tmp_path / "out")
    with pytest.raises(DataError, match="no shapes found; expected"):
        _prepare(tmp_path / "odd", tmp_path / "out", format="meshes")
    with pytest.raises(ConfigError, match="count applies only to the procedural format"):
        _prepare(tmp_path / "odd", tmp_path / "out", format="meshes", count=3)
    with pytest.raises(ConfigError, match="the procedural format takes the source 'procedural'"):
        _prepare(tmp_path / "odd", tmp_path / "out", format="procedural")
    with pytest.raises(DataError, match="no .sh3f catalogue found"):
        _prepare(tmp_path / "odd", tmp_path / "out", format="sweethome3d")
    assert detect_format("procedural") == "procedural" and detect_format(None) == "procedural"


# ShapeNet-Part -------------------------------------------------------------------------------


@pytest.fixture
def shapenet_tree(tmp_path: Path) -> Path:
    root = tmp_path / "shapenetcore_partanno_segmentation_benchmark_v0"
    synsets = {"Airplane": "02691156", "Chair": "03001627"}
    (root / "train_test_split").mkdir(parents=True)
    (root / "synsetoffset2category.txt").write_text(
        "".join(f"{name}\t{synset}\n" for name, synset in synsets.items())
    )
    rng = np.random.default_rng(1)
    lists: dict[str, list[str]] = {split: [] for split in SPLITS}
    for synset in synsets.values():
        (root / synset / "points").mkdir(parents=True)
        for index in range(5):
            shape_id = f"{synset[-3:]}abc{index}"
            np.savetxt(
                root / synset / "points" / f"{shape_id}.pts", rng.normal(size=(150, 3)), fmt="%.6f"
            )
            lists[SPLITS[min(index, 2)] if index < 3 else "train"].append(
                f"shape_data/{synset}/{shape_id}"
            )
    lists["test"].append("shape_data/03001627/missing0")
    (root / "03001627" / "points" / "unlisted.pts").write_text("0 0 0\n1 1 1\n")
    for split, entries in lists.items():
        (root / "train_test_split" / f"shuffled_{split}_file_list.json").write_text(
            json.dumps(entries)
        )
    return root


def test_shapenet_part_end_to_end(tmp_path: Path, shapenet_tree: Path) -> None:
    report = _prepare(shapenet_tree, tmp_path / "out", points=128)
    assert report.format == "shapenet-part"
    assert report.counts == {
        "train": {"airplane": 3, "chair": 3},
        "val": {"airplane": 1, "chair": 1},
        "test": {"airplane": 1, "chair": 1},
    }
    assert [(Path(p).name, r) for p, r in report.skipped] == [
        ("missing0.pts", "listed in shuffled_test_file_list.json but missing")
    ]
    test = load_split(tmp_path / "out", "test")
    assert test.name.tolist() == ["airplane_156abc2", "chair_627abc2"]
    assert read_manifest(tmp_path / "out")["split"] == "from the source"
    assert len(np.unique(test.points[0], axis=0)) == 128  # IFPS of the 150 points
    with pytest.raises(DataError, match="missing0.pts: listed in shuffled_test_file_list.json"):
        _prepare(shapenet_tree, tmp_path / "strict", strict=True)


def test_shapenet_part_categories_and_errors(tmp_path: Path, shapenet_tree: Path) -> None:
    report = _prepare(shapenet_tree, tmp_path / "out", categories="Chair")
    assert report.counts["train"] == {"chair": 3}
    (shapenet_tree / "train_test_split" / "shuffled_val_file_list.json").write_text("{}")
    with pytest.raises(DataError, match="shuffled_val_file_list.json: expected a JSON list"):
        _prepare(shapenet_tree, tmp_path / "bad")
    (shapenet_tree / "train_test_split" / "shuffled_val_file_list.json").unlink()
    with pytest.raises(DataError, match="shuffled_val_file_list.json: missing split list"):
        _prepare(shapenet_tree, tmp_path / "bad")
    (shapenet_tree / "synsetoffset2category.txt").write_text("Airplane 02691156 extra\n")
    with pytest.raises(
        DataError, match=r"synsetoffset2category.txt:1: expected '<Category> <synset>'"
    ):
        _prepare(shapenet_tree, tmp_path / "bad")


# SweetHome3D ---------------------------------------------------------------------------------


def _obj_text(category: str, index: int, quads: bool = False) -> str:
    shape = build_shape(category, 0, f"{category}/{index}")
    lines = ["# exported", "mtllib model.mtl", "o part"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in shape.vertices * 100]
    lines += ["vt 0 0", "vn 0 1 0", "usemtl wood"]
    lines += [f"f {a + 1}/1/1 {b + 1}/1/1 {c + 1}/1/1" for a, b, c in shape.faces]
    return "\n".join(lines) + "\n"


_CATALOGUE = r"""# PluginFurnitureCatalog.properties
id=SweetHome3D#Test
name=Test catalog
license=Creative Commons Attribution 3.0 license
provider=www.example.org

id#1=Test#chair1
name#1=Caf\u00e9 chair
category#1=Living room
model#1=/test/chair1/chair1.obj
width#1=50
depth#1=50
height#1=90
creator#1=Alice

id#2=Test#table1
name#2=Dining \
    table
category#2=Kitchen
model#2=/test/table1/table1.obj
modelRotation#2=1 0 0 0 0 1 0 -1 0
width#2=120
depth#2=80
height#2=75
creator#2=Bob

id#3=Test#bulb
name#3=Bulb
category#3=Lights
model#3=/test/bulb/bulb.obj
width#3=3
depth#3=3
height#3=5
lightSourceX#3=0.5
creator#3=Carol

id#4=Test#toothbrush
name#4=Toothbrush
category#4=Bathroom
model#4=/test/toothbrush/toothbrush.obj
width#4=2
depth#4=2
height#4=18
creator#4=Dan

id#5=Test#lost
name#5=Lost lamp
category#5=Lights
model#5=/test/lost/lost.obj
width#5=30
depth#5=30
height#5=60
lightSourceX#5=0.5
creator#5=Eve

id#6=Test#lamp1
name#6=Desk lamp
category#6=Lights
model#6=/test/lamp1/lamp1.obj
width#6=20
depth#6=20
height#6=45
lightSourceX#6=0.5
creator#6=Frank
"""


@pytest.fixture
def sh3f(tmp_path: Path) -> Path:
    """A catalogue in the real layout: properties, OBJ/MTL folders, an icon, a licence."""
    path = tmp_path / "catalogues" / "Test.sh3f"
    path.parent.mkdir()
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("LICENSE.TXT", "CC-BY 3.0")
        archive.writestr("PluginFurnitureCatalog.properties", _CATALOGUE.encode("iso-8859-1"))
        archive.writestr("test/chair1/chair1.obj", _obj_text("chair", 1))
        archive.writestr("test/chair1/chair1.mtl", "newmtl wood\nmap_Kd wood.jpg\n")
        archive.writestr("test/table1/table1.obj", _obj_text("table", 2))
        archive.writestr("test/bulb/bulb.obj", _obj_text("lamp", 3))
        archive.writestr("test/toothbrush/toothbrush.obj", _obj_text("lamp", 4))
        archive.writestr("test/lamp1/lamp1.obj", _obj_text("lamp", 5))
        archive.writestr("test/chair1.png", b"\x89PNG")
    return path


def test_sweethome3d_end_to_end(tmp_path: Path, sh3f: Path) -> None:
    assert detect_format(sh3f) == "sweethome3d" and detect_format(sh3f.parent) == "sweethome3d"
    report = _prepare(sh3f.parent, tmp_path / "out", test_fraction=0.0, val_fraction=0.0)
    names = _all_names(tmp_path / "out")
    assert names == {"test_chair1": "chair", "test_table1": "table", "test_lamp1": "lamp"}
    assert report.dropped == {"light_source": 1, "unmatched": 1}  # the bulb; the toothbrush
    assert [(Path(p.split(":/")[0]).name, p.split(":/")[1], r) for p, r in report.skipped] == [
        ("Test.sh3f", "test/lost/lost.obj", "the model file is not in the catalogue")
    ]
    manifest = read_manifest(tmp_path / "out")
    assert manifest["licenses"] == [
        {
            "source": "Test.sh3f",
            "catalogue": "Test catalog",
            "license": "Creative Commons Attribution 3.0 license",
            "provider": "www.example.org",
            "models": 3,
            "creators": ["Alice", "Bob", "Frank"],
        }
    ]
    assert manifest["credits"] == {
        "test_chair1": "Alice",
        "test_lamp1": "Frank",
        "test_table1": "Bob",
    }
    assert manifest["up_axis"] == "y"
    everything = _prepare(
        sh3f, tmp_path / "all", categories="all", test_fraction=0.0, val_fraction=0.0
    )
    assert everything.counts["train"] == {"chair": 1, "lamp": 1, "other": 1, "table": 1}


def test_sweethome3d_model_rotation_is_applied(tmp_path: Path, sh3f: Path) -> None:
    _prepare(sh3f, tmp_path / "out", categories="table", test_fraction=0.0, val_fraction=0.0)
    stored = load_split(tmp_path / "out", "train").points[0]
    shape = build_shape("table", 0, "table/2")
    # y-up table: the catalogue matrix maps z to y, so the stored cloud's y extent is the model's z
    rotated = shape.vertices @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float).T
    extent = np.ptp(stored, axis=0)
    expected = np.ptp(rotated, axis=0)
    np.testing.assert_allclose(extent / extent.max(), expected / expected.max(), atol=0.05)


def test_sweethome3d_broken_catalogue(tmp_path: Path, sh3f: Path) -> None:
    (sh3f.parent / "Broken.sh3f").write_bytes(b"not a zip")
    report = _prepare(sh3f.parent, tmp_path / "out")
    assert (
        str(sh3f.parent / "Broken.sh3f"),
        "cannot read the catalogue: File is not a zip file",
    ) in report.skipped
    with pytest.raises(DataError, match="Broken.sh3f: cannot read the catalogue"):
        _prepare(sh3f.parent, tmp_path / "strict", strict=True)


def test_parse_properties() -> None:
    text = (
        "# comment\n! also\nkey1=plain\nkey2 = sp\\u00e9cial\\: \\=x\nkey3:colon\n"
        "key4 long \\\n   value\n\nkey\\ 5=v\n"
    )
    assert parse_properties(text) == {
        "key1": "plain",
        "key2": "spécial: =x",
        "key3": "colon",
        "key4": "long value",
        "key 5": "v",
    }


@pytest.mark.parametrize(
    ("name", "category"),
    [
        ("Chair", "chair"), ("Bar stool", "chair"), ("Armchair ottoman", "chair"),
        ("Bedside table", "table"), ("Desk", "table"), ("Table tennis bat", "other"),
        ("Table fan", "other"), ("Desk lamp", "lamp"), ("Street light", "lamp"),
        ("Flashlight", "other"), ("Corner sofa", "sofa"), ("Futon couch", "sofa"),
        ("Bunk bed", "bed"), ("Crib", "bed"), ("Wardrobe", "cabinet"), ("Chest freezer", "other"),
        ("Seat Leon", "car"), ("City bus", "car"), ("Sitting female", "person"),
        ("Woman shoes", "other"), ("Toothbrush", "other"),
    ],
)  # fmt: skip
def test_category_keywords(name: str, category: str) -> None:
    assert category_for(name) == category


def test_parse_obj_matches_trimesh() -> None:
    text = _obj_text("sofa", 0)
    vertices, faces = parse_obj(text.encode())
    mesh = trimesh.load(
        trimesh.util.wrap_as_stream(text), file_type="obj", process=False, skip_materials=True
    )
    np.testing.assert_allclose(vertices, mesh.vertices)
    assert len(faces) == len(mesh.faces)
    area = np.linalg.norm(
        np.cross(*(vertices[faces[:, 1:]] - vertices[faces[:, :1]]).transpose(1, 0, 2)), axis=1
    )
    assert np.isclose(area.sum() / 2, mesh.area)


def test_parse_obj_polygons_references_and_errors() -> None:
    text = (
        "v 0 0 0\r\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\n"
        "f 1 2 3 4 5\nf 1//1 2//1\nf -3/1 -2/2 -1/3\nl 1 2\nvt 0 0\nf 1/1/1 2/2/2 3/3/3"
    )
    vertices, faces = parse_obj(text.encode())
    assert vertices.shape == (5, 3)
    # the pentagon gives a fan of three triangles; the two-vertex face is dropped
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4], [2, 3, 4], [0, 1, 2]]
    with pytest.raises(DataError, match="the OBJ file is empty"):
        parse_obj(b"")
    with pytest.raises(DataError, match="the OBJ file has no vertices"):
        parse_obj(b"# nothing\n")
    with pytest.raises(DataError, match="malformed vertex lines"):
        parse_obj(b"v 0 0\nv 1 1\n")
    with pytest.raises(DataError, match="a face refers to a vertex that does not exist"):
        parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(DataError, match=r"malformed vertex lines \(a value is not a number\)"):
        parse_obj(b"v 0 0 zero\n")
    with pytest.raises(DataError, match=r"malformed face lines \(a value is not a number\)"):
        parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 three\n")
    with pytest.raises(DataError, match="mixed index formats on one line"):
        parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2 3/3\n")
    assert parse_obj(b"v 0 0 0\n")[1].shape == (0, 3)


@pytest.mark.real_data
def test_real_sweethome3d_catalogues(tmp_path: Path) -> None:
    if not SWEETHOME3D_PATH.is_dir():
        pytest.skip(f"{SWEETHOME3D_PATH} is absent: apt-get install sweethome3d-furniture")
    report = _prepare(SWEETHOME3D_PATH, tmp_path / "sh3d", points=256, workers=2)
    counts = {
        c: sum(report.counts[s].get(c, 0) for s in SPLITS)
        for c in read_manifest(tmp_path / "sh3d")["categories"]
    }
    assert set(counts) == {"bed", "cabinet", "car", "chair", "lamp", "person", "sofa", "table"}
    assert counts["chair"] >= 50 and counts["table"] >= 40 and counts["car"] >= 15
    assert report.skipped == [] and report.dropped["unmatched"] > 500
    licenses = {record["source"]: record for record in report.manifest["licenses"]}
    assert set(licenses) == {
        "BlendSwap-CC-0.sh3f",
        "BlendSwap-CC-BY.sh3f",
        "KatorLegaz.sh3f",
        "Reallusion.sh3f",
        "Scopia.sh3f",
    }
    assert "Creative Commons Attribution 3.0" in licenses["Scopia.sh3f"]["license"]


def test_a_catalogue_member_that_inflates_too_far_is_skipped_as_it_is_read(
    tmp_path: Path, sh3f: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pfnet.data.sources import sweethome3d

    monkeypatch.setattr(sweethome3d, "MAX_MODEL_BYTES", 200_000)
    bomb = sh3f.parent / "Bomb.sh3f"
    with zipfile.ZipFile(sh3f) as original, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as out:
        for info in original.infolist():
            data = original.read(info)
            if info.filename == "test/chair1/chair1.obj":  # ~1 MB of comments, ~1 KB packed
                data = b"# padding\n" * 100_000 + data
            out.writestr(info.filename, data)
    sh3f.unlink()
    report = _prepare(bomb.parent, tmp_path / "out", test_fraction=0.0, val_fraction=0.0)
    reasons = {p.split(":/")[1]: r for p, r in report.skipped}
    assert "bytes unpacked, above the 200000 accepted" in reasons["test/chair1/chair1.obj"]
    assert "test_chair1" not in _all_names(tmp_path / "out")
