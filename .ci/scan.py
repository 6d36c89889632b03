"""CI helper for the light-install check: write a scan, or compare two completion folders.

python .ci/scan.py SCAN.xyz                 a half sphere of radius 30 (2,500 points)
python .ci/scan.py --compare DIR_A DIR_B    every PLY of A equals B's within the
                                            tested tolerance (1e-4 x radius)
"""

import sys
from pathlib import Path

import numpy as np

RADIUS = 30.0

if sys.argv[1] == "--compare":
    from pfnet.io import read_point_cloud

    a, b = Path(sys.argv[2]), Path(sys.argv[3])
    files = sorted(p.name for p in a.glob("*.ply"))
    assert files and files == sorted(p.name for p in b.glob("*.ply")), (files, list(b.iterdir()))
    worst = max(np.abs(read_point_cloud(a / f) - read_point_cloud(b / f)).max() for f in files)
    assert worst <= 1e-4 * RADIUS, worst
    print(f"{len(files)} files agree: max abs difference {worst:.2g} (radius {RADIUS:g})")
else:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(2500, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 0] = np.abs(points[:, 0])
    np.savetxt(sys.argv[1], points * RADIUS + [5.0, -2.0, 1.0], fmt="%.6f")
