"""Reconstruct the renders of ``benchmarks/pbr/render.py`` and print the errors against the truth.

    python benchmarks/pbr/run.py pbr-*.npz [--robust tukey]

Per file: the mean normal error (degrees, mesh normals against the true ones inside the mask) at
the true distance and with ``depth="auto"``, and the distance error of the search.
"""

from __future__ import annotations

import argparse
import json
import warnings

import numpy as np

import nplps


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+")
    parser.add_argument("--robust", default=None, choices=("cauchy", "tukey"))
    args = parser.parse_args()
    print("file | material | normals at the true distance (deg) | normals with auto (deg) | distance error of auto")
    for path in args.files:
        data = np.load(path)
        rig = nplps.Rig.from_dict(json.loads(str(data["rig"])))
        mask, truth = data["mask"], data["normals"]
        distance = float(data["distance"])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            known = nplps.reconstruct(
                data["images"], rig, depth=distance, mask=mask, iterations=50, tol=1e-8, robust=args.robust
            )
            auto = nplps.reconstruct(data["images"], rig, depth="auto", mask=mask, robust=args.robust)
        assert auto.distance is not None
        found = float(auto.distance.distance[0])
        print(
            f"{path} | {data['material']} | {angles(known.normals[mask], truth[mask]).mean():.3f} | "
            f"{angles(auto.normals[mask], truth[mask]).mean():.3f} | {100 * (found / distance - 1):+.2f} %"
        )


if __name__ == "__main__":
    main()
