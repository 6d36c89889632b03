"""CI helper for the light-install check: write real scans, or compare two completion folders.

python .ci/scan.py DIR                      write DIR/scan.xyz and DIR/scan2.ply: two catalogue
                                            chairs of Debian's sweethome3d-furniture (procedural
                                            chairs without it) cut as a scanner sees them, in
                                            millimetres, as text and as binary PLY
python .ci/scan.py --compare DIR_A DIR_B    every PLY of A equals B's within the tested
                                            tolerance (1e-4 x the completed cloud's radius)
"""

import sys
import tempfile
from pathlib import Path

import numpy as np


def compare() -> None:
    from pfnet.io.clouds import read_point_cloud

    a, b = Path(sys.argv[2]), Path(sys.argv[3])
    files = sorted(p.name for p in a.glob("*.ply"))
    assert files and files == sorted(p.name for p in b.glob("*.ply")), (files, list(b.iterdir()))
    worst, radius = 0.0, np.inf
    for name in files:
        ours, theirs = read_point_cloud(a / name), read_point_cloud(b / name)
        worst = max(worst, float(np.abs(ours - theirs).max()))
        if name.endswith("_completed.ply"):
            centred = theirs - theirs.mean(axis=0)
            radius = min(radius, float(np.linalg.norm(centred, axis=1).max()))
    assert np.isfinite(radius) and worst <= 1e-4 * radius, (worst, radius)
    print(f"{len(files)} files agree: max abs difference {worst:.2g} (radius {radius:.4g})")


def write_scans() -> None:
    from pfnet.data import SWEETHOME3D_PATH, load_split, prepare_dataset
    from pfnet.geometry import crop_by_viewpoint
    from pfnet.io.clouds import write_ply

    out = Path(sys.argv[1])
    real = SWEETHOME3D_PATH.is_dir()
    with tempfile.TemporaryDirectory() as scratch:
        data = Path(scratch) / "data"
        source = SWEETHOME3D_PATH if real else None
        count = None if real else 4
        prepare_dataset(source, data, points=3000, categories=["chair"], count=count, workers=1)
        shapes = load_split(data, "test").points
    viewpoint = np.array([1.0, 0.0, 1.0], np.float32)
    scans = []
    for k in range(2):
        partial, _ = crop_by_viewpoint(shapes[k % len(shapes)], viewpoint, n_missing=750)
        scans.append(partial * 850.0 + np.array([1e4, -300.0, 52.0], np.float32))  # mm
    np.savetxt(out / "scan.xyz", scans[0], fmt="%.3f")
    write_ply(out / "scan2.ply", scans[1])
    kind = "SweetHome3D" if real else "procedural"
    print(f"wrote {out}/scan.xyz and {out}/scan2.ply ({kind} chairs)")


if __name__ == "__main__":  # prepare's workers import this module again
    compare() if sys.argv[1] == "--compare" else write_scans()
