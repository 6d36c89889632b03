"""PCN and ShapeNet-55 trees laid out by their authors' own metadata, end to end.

The tests build benchmark trees in the documented layouts themselves. This script checks the
layouts against files pfnet did not write: PoinTr's ``data/PCN/PCN.json`` and ``category.txt``
and its ``data/ShapeNet55-34/ShapeNet-{55,34}``/``ShapeNet-Unseen21`` split lists, with every
listed file absent except a few that it fills with clouds sampled from real meshes (the
SweetHome3D catalogue), and PCN's released demo scans (``demo_data/*.pcd`` of
``wentaoyuan/pcn``, ASCII PCD files written by PCN's own tools) as the first test partials of
their categories. It then runs ``pfnet prepare``, ``predict --protocol`` and ``evaluate
--protocol ... --gallery`` on both trees, as a user with a partial download would.

Run: ``python benchmarks/real_layouts.py POINTR_CHECKOUT PCN_CHECKOUT OUT`` (both checkouts
are the authors' repositories; nothing is downloaded). The metric values mean nothing (the
partial scans and complete clouds come from different shapes); what is checked is that the
real metadata is read, the absent files are named and the rest is processed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from pfnet.cli import main
from pfnet.evaluation.protocols import SHAPENET_VIEWPOINTS

SH3D = Path("/usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f")


def mesh_clouds(count: int, n_points: int) -> list[np.ndarray]:
    """Surface samples of the first ``count`` SweetHome3D models (procedural shapes without the
    catalogue), centred and scaled to PCN's size."""
    from pfnet.data.sampling import sample_surface
    from pfnet.data.sources import procedural, sweethome3d
    from pfnet.data.sources.registry import load_item

    rng = np.random.default_rng(0)
    if SH3D.is_file():
        items = sweethome3d.scan(SH3D, strict=False).items[:count]
    else:
        items = procedural.scan(count).items[:count]
    clouds = []
    for k in range(count):
        mesh = load_item(items[k % len(items)], 0)
        cloud = sample_surface(mesh.vertices, mesh.faces, n_points, rng)
        clouds.append(((cloud - cloud.mean(axis=0)) / np.abs(cloud).max() / 2).astype(np.float32))
    return clouds


def write_pcd(path: Path, points: np.ndarray) -> None:
    """A binary PCD, as PCN's complete clouds are stored."""
    points = np.asarray(points, np.float32)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
        f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(points)}\nDATA binary\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode() + points.tobytes())


def pcn_tree(pointr: Path, pcn: Path, root: Path) -> int:
    """PCN's layout with PoinTr's PCN.json: one train, one val and two test shapes a category
    present; the rest of the 30,974 listed shapes absent. Returns the shapes written."""
    root.mkdir(parents=True)
    for name in ("PCN.json", "category.txt"):
        shutil.copy(pointr / "data" / "PCN" / name, root / name)
    records = json.loads((root / "PCN.json").read_text())
    clouds = iter(mesh_clouds(4 * len(records), 16384))
    written = 0
    for record in records:
        taxonomy, category = record["taxonomy_id"], record["taxonomy_name"]
        demo = pcn / "demo_data" / f"{category}.pcd"
        for split, count in (("train", 1), ("val", 1), ("test", 2)):
            for k, model in enumerate(record[split][:count]):
                cloud = next(clouds)
                write_pcd(root / split / "complete" / taxonomy / f"{model}.pcd", cloud)
                for view in range(8 if split == "train" else 1):
                    scan = root / split / "partial" / taxonomy / model / f"{view:02d}.pcd"
                    if split == "test" and k == 0 and demo.is_file():
                        scan.parent.mkdir(parents=True, exist_ok=True)
                        shutil.copy(demo, scan)
                    else:
                        seen = cloud[cloud @ SHAPENET_VIEWPOINTS[view] > 0][:1200]
                        write_pcd(scan, seen)
                written += 1
    return written


def shapenet_tree(pointr: Path, root: Path, per_split: int = 12) -> int:
    """ShapeNet-55/34's layout with PoinTr's split lists: the first ``per_split`` files of each
    ShapeNet-55 list present. Returns the files written."""
    (root / "shapenet_pc").mkdir(parents=True)
    for folder in ("ShapeNet-55", "ShapeNet-34", "ShapeNet-Unseen21"):
        shutil.copytree(pointr / "data" / "ShapeNet55-34" / folder, root / folder)
    clouds = iter(mesh_clouds(2 * per_split, 8192))
    for split in ("train", "test"):
        for file in (root / "ShapeNet-55" / f"{split}.txt").read_text().split()[:per_split]:
            np.save(root / "shapenet_pc" / file, next(clouds) * 3 + 1)  # not normalised
    return 2 * per_split


def run(step: str, args: list[str]) -> None:
    """One pfnet command, timed; exit code 2 (some files named and skipped) is expected."""
    started = time.perf_counter()
    code = main(args)
    print(f"== {step}: exit {code} in {time.perf_counter() - started:.1f} s\n")
    if code not in (0, 2):
        raise SystemExit(f"{step} failed")


def main_(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pointr", type=Path, help="a checkout of PoinTr (its data/ folder)")
    parser.add_argument("pcn", type=Path, help="a checkout of PCN (its demo_data/ folder)")
    parser.add_argument("out", type=Path, help="a new folder for the trees and the results")
    args = parser.parse_args(argv)
    if args.out.exists():
        raise SystemExit(f"{args.out} exists; name a new folder")
    out = args.out
    print(f"PCN tree: {pcn_tree(args.pointr, args.pcn, out / 'PCN')} shapes present")
    print(f"ShapeNet-55 tree: {shapenet_tree(args.pointr, out / 'ShapeNet55-34')} files present")
    for tree, data, protocol in (("PCN", "d-pcn", "pcn"), ("ShapeNet55-34", "d-sn", "shapenet55")):
        run(f"prepare {tree}", ["prepare", str(out / tree), "--out", str(out / data)])
        pred = out / f"P-{protocol}"
        run(
            f"predict {protocol}",
            ["predict", "--data", str(out / data), "--out", str(pred), "--protocol", protocol],
        )
        gallery = out / f"gallery-{protocol}.png"
        run(
            f"evaluate {protocol}",
            ["evaluate", str(pred), "--data", str(out / data), "--gallery", str(gallery)],
        )


if __name__ == "__main__":
    main_()
