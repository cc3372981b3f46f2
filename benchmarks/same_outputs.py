"""Are two runs' monitoring outputs the same, array for array?

Compares the tracks (``report.json`` ``tracks``, ``tracks.csv``) and every layer mesh
(``meshes/layer_*.ply``: vertices, faces and each per-vertex scalar field) of two run folders.
File bytes may differ (another writer, another header comment); the arrays may not. Used to
show that a change meant to keep behaviour (a reorganisation, a new PLY writer) kept it:

    dm2 run --out runs/before        # on the old code
    dm2 run --out runs/after         # on the new code
    python benchmarks/same_outputs.py runs/before runs/after

Exit 0 when everything is equal, 1 otherwise (each difference printed).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
from plyfile import PlyData


def _mesh_arrays(path: Path) -> dict[str, np.ndarray]:
    ply = PlyData.read(str(path))
    vertex = ply["vertex"].data
    arrays = {name: np.asarray(vertex[name]) for name in vertex.dtype.names}
    faces = ply["face"].data["vertex_indices"]
    arrays["faces"] = np.vstack(faces) if len(faces) else np.empty((0, 3), dtype=np.int32)
    return arrays


def compare(a: Path, b: Path) -> list[str]:
    diffs: list[str] = []
    tracks_a = json.loads((a / "report.json").read_text())["tracks"]
    tracks_b = json.loads((b / "report.json").read_text())["tracks"]
    if tracks_a != tracks_b:
        diffs.append(f"report.json tracks differ ({len(tracks_a)} against {len(tracks_b)})")
    with open(a / "tracks.csv") as fa, open(b / "tracks.csv") as fb:
        if list(csv.reader(fa)) != list(csv.reader(fb)):
            diffs.append("tracks.csv rows differ")
    meshes_a = sorted(p.name for p in (a / "meshes").glob("layer_*.ply"))
    meshes_b = sorted(p.name for p in (b / "meshes").glob("layer_*.ply"))
    if meshes_a != meshes_b:
        diffs.append(f"layer meshes differ: {meshes_a} against {meshes_b}")
    for name in sorted(set(meshes_a) & set(meshes_b)):
        ma, mb = _mesh_arrays(a / "meshes" / name), _mesh_arrays(b / "meshes" / name)
        if ma.keys() != mb.keys():
            diffs.append(f"{name}: fields {sorted(ma)} against {sorted(mb)}")
        for key in sorted(ma.keys() & mb.keys()):
            if ma[key].shape != mb[key].shape or not np.array_equal(ma[key], mb[key]):
                diffs.append(f"{name}: {key} differs")
    return diffs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    args = ap.parse_args()
    diffs = compare(args.before, args.after)
    n = len(list((args.before / "meshes").glob("layer_*.ply")))
    for d in diffs:
        print("DIFFERENT:", d)
    if not diffs:
        print(f"same: tracks and {n} layer meshes (vertices, faces, every scalar field)")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
