"""Physically based renders of nplps's synthetic surfaces with Mitsuba 3 (issue 20, item 5).

    pip install ".[bench]"            # mitsuba, never a runtime dependency of nplps
    apt-get install libllvm19         # for the fast llvm_ad_rgb variant (else scalar_rgb, slower)
    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        python benchmarks/pbr/render.py sphere --material diffuse --size 64 --out pbr-sphere.npz

The surface is one of ``nplps.make_scene``'s (pinhole camera, 27 near point lights): its vertex
depths, at pixel corners, become a triangle mesh (each pixel's quad split in two). The sensor is
built from the rig's K with ``look_at(origin 0, target +z, up -y)``, which puts Mitsuba's film
pixels on nplps's (u, v) = (column, row) with the OpenCV axes; the principal point must be the
film centre, ``((W - 1) / 2, (H - 1) / 2)``, as the synthetic scenes have it. A point emitter of
intensity I gives a Lambertian surface of reflectance rho the radiance rho / pi * I cos / r^2, so
nplps's light intensity is I / pi. ``max_depth`` 2 is direct light only.

The .npz holds images (k, H, W) float32, the rig as JSON, the true depth (H+1, W+1) and gauge
(``distance``: the scene's mean depth as nplps defines it), normals
(H, W, 3) and mask, the material and the render time. ``benchmarks/pbr/run.py`` reconstructs it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np

import nplps

MATERIALS = ("diffuse", "roughplastic", "roughplastic-smooth", "principled", "principled-smooth")


def bsdf(material: str) -> dict[str, Any]:
    """Return the Mitsuba BSDF of a material name (reflectance 0.5 for the diffuse control)."""
    if material == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5] * 3}}
    if material.startswith("roughplastic"):
        alpha = 0.1 if material.endswith("smooth") else 0.3
        return {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": alpha,
            "diffuse_reflectance": {"type": "rgb", "value": [0.5] * 3},
        }
    if material.startswith("principled"):
        roughness = 0.2 if material.endswith("smooth") else 0.4
        return {
            "type": "principled",
            "base_color": {"type": "rgb", "value": [0.5] * 3},
            "roughness": roughness,
            "specular": 0.5,
        }
    raise SystemExit(f"unknown material {material!r}: one of {', '.join(MATERIALS)}")


def mesh_of(scene: nplps.Scene) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertices (N, 3) and triangles (M, 3) of the scene's surface inside its mask."""
    K = np.asarray(scene.rig.camera["K"], dtype=np.float64)
    z = scene.depth
    h, w = z.shape[0] - 1, z.shape[1] - 1
    rows, cols = np.mgrid[0 : h + 1, 0 : w + 1]
    x = (cols - 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows - 0.5 - K[1, 2]) / K[1, 1] * z
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    finite = np.isfinite(vertices).all(1)
    index = np.arange((h + 1) * (w + 1)).reshape(h + 1, w + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    keep = scene.mask.ravel() & finite[a] & finite[b] & finite[c] & finite[d]
    triangles = np.concatenate([np.stack([a, c, b], 1)[keep], np.stack([a, d, c], 1)[keep]])
    return np.where(finite[:, None], vertices, 0.0), triangles


def render(scene: nplps.Scene, material: str, spp: int, max_depth: int) -> tuple[np.ndarray, float]:
    """Render one image per light of the scene's rig; return them (k, H, W) and the seconds taken."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() and _llvm() else "scalar_rgb")
    vertices, triangles = mesh_of(scene)
    mesh = mi.Mesh("surface", vertex_count=len(vertices), face_count=len(triangles))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(triangles.astype(np.uint32).ravel())
    params.update()
    mesh.set_bsdf(mi.load_dict(bsdf(material)))
    K = np.asarray(scene.rig.camera["K"], dtype=np.float64)
    h, w = scene.mask.shape
    if abs(K[0, 2] - (w - 1) / 2) > 1e-9 or abs(K[1, 2] - (h - 1) / 2) > 1e-9 or K[0, 0] != K[1, 1]:
        raise SystemExit("the sensor needs square pixels and the principal point at the image centre")
    sensor = {
        "type": "perspective",
        "fov": float(np.degrees(2 * np.arctan(w / 2 / K[0, 0]))),
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }
    start = time.perf_counter()
    images = []
    for position, intensity in zip(scene.rig.positions, scene.rig.intensities, strict=True):
        emitter = {"type": "point", "position": [float(v) for v in position]}
        emitter["intensity"] = {"type": "rgb", "value": [float(np.pi * v) for v in intensity]}
        world = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": max_depth},
                "sensor": sensor,
                "surface": mesh,
                "light": emitter,
            }
        )
        images.append(np.asarray(mi.render(world))[..., 0])
    return np.asarray(images, dtype=np.float32), time.perf_counter() - start


def _llvm() -> bool:
    return bool(os.environ.get("DRJIT_LIBLLVM_PATH"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("shape", choices=("sphere", "bumps", "saddle", "cube"))
    parser.add_argument("--material", default="diffuse", choices=MATERIALS)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--max-depth", type=int, default=2, help="2: direct light only")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    scene = nplps.make_scene(args.shape, n=args.size, seed=args.seed, camera="pinhole")
    images, seconds = render(scene, args.material, args.spp, args.max_depth)
    np.savez_compressed(
        args.out,
        images=images,
        rig=json.dumps(scene.rig.to_dict()),
        depth=scene.depth,
        distance=scene.mean_depth,
        normals=scene.normals,
        mask=scene.mask,
        material=args.material,
        seconds=seconds,
    )
    print(f"{args.shape} {args.material} {args.size}^2 x {len(images)} lights: {seconds:.1f} s -> {args.out}")


if __name__ == "__main__":
    main()
