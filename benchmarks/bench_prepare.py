"""Benchmark ``pfnet prepare`` on Debian's SweetHome3D furniture catalogues (820 models).

Run on demand (not part of the test suite)::

    python -m pytest benchmarks/bench_prepare.py --benchmark-only -p no:cacheprovider

Times the whole preparation (read the ZIPs, parse the OBJs, sample 2,048 points per model,
normalise, write the dataset) with the default worker count, for every model
(``--categories all``) and for the default category set, beside the anchor of the issue: a
single-process loop that loads every model with trimesh and samples it (about 27 s on the
2-core build machine).
"""

from __future__ import annotations

import io
import zipfile

import pytest

from pfnet.data import SWEETHOME3D_PATH, prepare_dataset
from pfnet.data.sampling import normalize, sample_surface, shape_rng
from pfnet.data.sources.sweethome3d import parse_obj, scan

pytestmark = pytest.mark.skipif(
    not SWEETHOME3D_PATH.is_dir(),
    reason=f"{SWEETHOME3D_PATH} is absent: apt-get install sweethome3d-furniture",
)


def _prepare(out, categories):
    return prepare_dataset(
        SWEETHOME3D_PATH, out, categories=categories, overwrite=True, progress=False
    )


def test_prepare_full_catalogue(benchmark, tmp_path):
    report = benchmark.pedantic(_prepare, args=(tmp_path / "all", "all"), rounds=2)
    assert report.total == 820


def test_prepare_default_categories(benchmark, tmp_path):
    report = benchmark.pedantic(_prepare, args=(tmp_path / "default", None), rounds=3)
    assert report.total > 250


def _models():
    """``(open ZIP, OBJ member)`` of every catalogue model; each ZIP opened once."""
    items = scan(SWEETHOME3D_PATH).items
    archives = {path: zipfile.ZipFile(path) for path in {item.args[0] for item in items}}
    return [(archives[item.args[0]], item.args[1]) for item in items]


def test_single_process_trimesh_loop(benchmark):
    """The anchor: trimesh's OBJ loader in one process (materials skipped), then sampling."""
    import trimesh

    models = _models()

    def run():
        for archive, member in models:
            mesh = trimesh.load(
                io.BytesIO(archive.read(member)),
                file_type="obj",
                skip_materials=True,
                process=False,
                force="mesh",
            )
            normalize(mesh.sample(2048, seed=0))
        return len(models)

    assert benchmark.pedantic(run, rounds=1) == 820


def test_single_process_vectorised_parser(benchmark):
    """The same loop with pfnet's vectorised OBJ parser, still in one process."""

    models = _models()

    def run():
        for archive, member in models:
            vertices, faces = parse_obj(archive.read(member))
            normalize(sample_surface(vertices, faces, 2048, shape_rng(0, member)))
        return len(models)

    assert benchmark.pedantic(run, rounds=1) == 820
