"""Physically based renders with Mitsuba 3 for the glossy (issue 20) and interreflection (issue 21) benchmarks.

    pip install mitsuba==3.9.1        # never a runtime dependency of nplps
    apt-get install libllvm19         # for the fast llvm_ad_rgb variant (else scalar_rgb, slower)
    export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
    python benchmarks/pbr/render.py sphere --material diffuse --size 64 --out pbr-sphere.npz
    python benchmarks/pbr/render.py --all --size 256 --out-dir /work/pbr-data/256
    python benchmarks/pbr/render.py --gi --size 256 --spp 256 --out-dir /work/pbr-data/gi

Scenes (``SHAPES``): ``sphere`` and ``bumps`` (the surfaces and masks of ``nplps.make_scene``),
``shadows`` (a tilted plane with a tall post and a step that cast shadows onto it) and ``torus``
(a tilted torus, its visible surface found by ray casting the analytic torus through the pixel
corners); for interreflections (``--gi``, ``CONCAVE``) ``bowl`` (the inside of a spherical cap
seen from above) and ``sheet`` (a corrugated sheet across the image, rendered 25 mm past it on
every side). ``--gi`` renders ``GI_SET`` twice: with global illumination (``--max-depth``, 12 by
default) and as the direct-only twin (2). Every surface is a pinhole height field given by its
vertex depths at the pixel corners, the representation nplps reconstructs, so the ground truth is
exact: the rendered mesh is that surface, each pixel's quad split into two triangles (only the
pixels of the mask exist, except on the sheet).

The camera is nplps's pinhole camera of ``make_scene`` (object 100 mm across at 200 mm); the rig
(``make_rig``) has 16 point lights in two rings around the camera (``--lights 24`` / ``32``: three /
four rings). Frames: nplps's pixel (row r, column c) has its centre at (u, v) = (c, r) and vertex
(r, c) on the ray through (c - 1/2, r - 1/2); Mitsuba's film pixel (r, c) covers [c, c + 1] x
[r, r + 1] of its continuous film coordinates, so the principal point (cx, cy) of K sits at film
coordinates (cx + 1/2, cy + 1/2). The sensor is ``look_at(origin 0, target +z, up -y)``: film x then
runs along +x and film y along +y, as OpenCV's. A point emitter of intensity I lights a Lambertian
surface of reflectance rho with radiance rho / pi * I cos / r^2, so the emitter gets pi times
nplps's light intensity and the diffuse control equals ``nplps.render(depth, rig, albedo=0.5)``.
``max_depth`` 2 is direct light only (the control must be); larger values add interreflections.

The .npz holds images (k, H, W) float32 (or float16 with ``--float16``), the rig as JSON, the
true vertex depth (H+1, W+1), ``distance`` (the gauge nplps's ``depth=`` takes: the geometric
mean depth of the vertices the mask uses), the true facet normals (H, W, 3), the mask, ``shadow``
(k, H, W) float16, the share of each pixel in each light's cast shadow (``cast_shadows``), the shape,
material, spp, max_depth, variant and render seconds. ``benchmarks/pbr/run.py`` reconstructs it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

import nplps

SHAPES = ("sphere", "bumps", "shadows", "torus")  # the --all set (issue 20)
CONCAVE = ("bowl", "sheet")  # the concave shapes of the interreflection set (issue 21)
MATERIALS = ("diffuse", "roughplastic-0.1", "roughplastic-0.3", "principled-0.3", "principled-0.5")
# The --gi set: each (shape, material) rendered with global illumination and as a direct-only twin.
GI_SET = (
    ("bowl", "diffuse"),
    ("bowl", "diffuse-0.8"),
    ("sheet", "diffuse"),
    ("torus", "diffuse"),
    ("shadows", "diffuse"),
)
SIZE_MM = 100.0  # lateral object size at the working distance
DISTANCE_MM = 200.0  # working distance
REFLECTANCE = 0.5  # diffuse reflectance of every material (the control's albedo)


def reflectance(material: str) -> float:
    """Return the diffuse reflectance of a material name (the true albedo of a ``diffuse`` one).

    ``diffuse-R`` is Lambertian with reflectance R (``diffuse``: 0.5); every other material has a
    diffuse part of reflectance 0.5.
    """
    kind, _, value = material.partition("-")
    if kind == "diffuse" and value:
        try:
            number = float(value)
        except ValueError:
            number = float("nan")
        if not 0 < number <= 1:
            raise SystemExit(f"diffuse-R needs 0 < R <= 1, got {material!r}")
        return number
    return REFLECTANCE


def bsdf(material: str) -> dict[str, Any]:
    """Return the Mitsuba BSDF of a material: ``diffuse``, ``diffuse-R``, ``roughplastic-A``, ``principled-R``."""
    grey = {"type": "rgb", "value": [REFLECTANCE] * 3}
    kind, _, value = material.partition("-")
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [reflectance(material)] * 3}}
    try:
        number = float(value)
    except ValueError:
        number = float("nan")
    if kind == "roughplastic" and number > 0:
        return {"type": "roughplastic", "distribution": "ggx", "alpha": number, "diffuse_reflectance": grey}
    if kind == "principled" and number > 0:
        return {"type": "principled", "base_color": grey, "roughness": number, "specular": 0.5, "metallic": 0.0}
    raise SystemExit(f"unknown material {material!r}: diffuse, diffuse-R, roughplastic-ALPHA or principled-ROUGHNESS")


def camera(n: int) -> dict[str, Any]:
    """Return nplps's pinhole camera of an n x n image (``make_scene``'s: the object spans the view)."""
    f = n * DISTANCE_MM / SIZE_MM
    c = (n - 1) / 2
    return {"model": "pinhole", "K": [[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]], "distortion": [0.0] * 5}


# The rings of the rig, 8 lights each: (radius mm, z mm, turn in steps of 45 degrees). The first
# two are the 16-light benchmark rig; ``--lights 24`` / ``32`` add the third / fourth.
RINGS = ((100.0, 0.0, 0.0), (180.0, 20.0, 0.5), (140.0, 10.0, 0.25), (60.0, 0.0, 0.75))


def make_rig(n: int, lights: int = 16) -> nplps.Rig:
    """Return the benchmark's rig: ``lights`` point lights (16 by default) in rings around the camera.

    8 lights on a ring of radius 100 mm in the camera plane and 8 on a ring of radius 180 mm
    20 mm in front of it, turned by half a step; with 24 lights also 8 on a ring of 140 mm 10 mm
    in front (turned by a quarter step), with 32 also 8 on a ring of 60 mm in the camera plane
    (three quarters of a step): ``RINGS``, light i on ring i // 8. The first 16 lights are the
    same for every count. Intensities (nplps units) unequal by up to +-15 % and scaled so that
    images are of order 0.1-1 (float16 keeps them).
    """
    if lights % 8 or not 16 <= lights <= 8 * len(RINGS):
        raise SystemExit(f"--lights takes 16, 24 or 32, got {lights}")
    points = []
    for i in range(lights):
        ring = i // 8
        radius, z, turn = RINGS[ring]
        angle = 2 * np.pi * (i % 8 + turn) / 8
        intensity = DISTANCE_MM**2 * (1.0 + 0.15 * np.sin(1.7 * i))
        points.append(nplps.PointLight([radius * np.cos(angle), radius * np.sin(angle), z], float(intensity)))
    return nplps.Rig(camera(n), points)


def vertex_rays(n: int, margin: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return the (x, y) at z = 1 of the rays through the pixel corners, each (n+1, n+1).

    With a ``margin`` of m pixels the grid goes on past the image on every side: (n+1+2m)^2
    corners, the image's corner (r, c) at [m + r, m + c].
    """
    K = np.asarray(camera(n)["K"])
    rows, cols = np.mgrid[-margin : n + 1 + margin, -margin : n + 1 + margin].astype(np.float64)
    return (cols - 0.5 - K[0, 2]) / K[0, 0], (rows - 0.5 - K[1, 2]) / K[1, 1]


def _sigmoid(t: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * t))


def shadows_surface(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertex depths and mask of the cast-shadow scene.

    A plane tilted by about 6 degrees at 215 mm with a round post 30 mm tall (radius 12 mm,
    smooth edge 2 mm) and a step 10 mm tall along x = 25 mm; the lights at 100-180 mm from the
    axis throw the post's and the step's shadows 10-30 mm across the plane. Lateral positions
    are taken on the rays at the working distance, as ``make_scene`` does.
    """
    x, y = vertex_rays(n)
    X, Y = x * DISTANCE_MM, y * DISTANCE_MM
    depth = DISTANCE_MM + 15.0 + 0.1 * X + 0.04 * Y
    depth -= 30.0 * _sigmoid((12.0 - np.hypot(X + 12.0, Y - 8.0)) / 2.0)
    depth -= 10.0 * _sigmoid((X - 25.0) / 1.5)
    return depth, np.ones((n, n), dtype=bool)


def torus_surface(n: int, tilt: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertex depths and mask of the torus, by ray casting the analytic torus.

    Major radius 30 mm, minor radius 12 mm, centre on the axis at 205 mm, its axis turned by
    `tilt` degrees about x from the viewing axis. Each corner ray is sphere-traced on the
    torus's exact signed distance. A pixel is in the mask when its 4 corners hit, they span
    less than 4 mm in depth (no occlusion edge inside the pixel) and its facet faces the camera
    (cosine to the ray above 0.4: steeper facets near the silhouette cost nplps 0.09° even on its own
    exact renders, 0.02° without them); only the largest 4-connected part of these pixels is kept.
    """
    x, y = vertex_rays(n)
    d = np.stack([x, y, np.ones_like(x)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    t = np.radians(tilt)
    centre = np.array([0.0, 0.0, DISTANCE_MM + 5.0])
    frame = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(t), np.sin(t)], [0.0, -np.sin(t), np.cos(t)]])
    major, minor = 30.0, 12.0

    def sdf(s: np.ndarray) -> np.ndarray:
        local = (s[..., None] * d - centre) @ frame.T
        return np.hypot(np.hypot(local[..., 0], local[..., 1]) - major, local[..., 2]) - minor

    s = np.full(x.shape, 100.0)
    for _ in range(2000):
        step = sdf(s)
        s = np.where(s < 400.0, s + step, s)
        if np.all((np.abs(step) < 1e-11) | (s >= 400.0)):
            break
    hit = (np.abs(sdf(s)) < 1e-7) & (s < 400.0)
    depth = np.where(hit, s * d[..., 2], np.nan)
    corners = np.stack([depth[:-1, :-1], depth[:-1, 1:], depth[1:, :-1], depth[1:, 1:]])
    hits = np.isfinite(corners).all(0)
    filled = np.where(np.isfinite(corners), corners, 0.0)
    mask = hits & (filled.max(0) - filled.min(0) < 4.0)
    with np.errstate(invalid="ignore"):
        normals = facet_normals(np.where(np.isfinite(depth), depth, DISTANCE_MM), n)
        centres = np.stack([(x[:-1, :-1] + x[1:, 1:]) / 2, (y[:-1, :-1] + y[1:, 1:]) / 2, np.ones((n, n))], -1)
        facing = -(normals * centres).sum(-1) / np.linalg.norm(centres, axis=-1)
    mask &= facing > 0.4
    return np.where(np.isfinite(depth), depth, DISTANCE_MM), largest_part(mask)


def facing(depth: np.ndarray, n: int) -> np.ndarray:
    """Return the cosine (n, n) between each facet's normal and the direction to the camera."""
    x, y = vertex_rays(n)
    normals = facet_normals(depth, n)
    centres = np.stack([(x[:-1, :-1] + x[1:, 1:]) / 2, (y[:-1, :-1] + y[1:, 1:]) / 2, np.ones((n, n))], -1)
    return -(normals * centres).sum(-1) / np.linalg.norm(centres, axis=-1)


def bowl_surface(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertex depths and mask of the bowl: the inside of a spherical cap seen from above.

    The rim is a circle of radius 35 mm in the plane z = 200 mm, centred on the optical axis, the
    bottom 20 mm deeper (a sphere of radius 40.6 mm centred 20.6 mm in front of the rim plane).
    Each corner ray meets the inside at the sphere's far intersection; the rim does not hide any
    of it from the camera (the wall below the rim leans inwards more steeply than the rays lean
    outwards). Corners outside the rim get the rim plane's depth (not rendered). A pixel is in
    the mask when its 4 corners lie inside the bowl and its facet faces the camera (cosine above
    0.4, as the torus); the largest 4-connected part is kept. Only the mask is rendered: the
    inside of the bowl is all of the surface it sees.
    """
    rim, radius_rim, depth_bowl = DISTANCE_MM, 35.0, 20.0
    radius = (radius_rim**2 + depth_bowl**2) / (2 * depth_bowl)
    centre = np.array([0.0, 0.0, rim + depth_bowl - radius])
    x, y = vertex_rays(n)
    d = np.stack([x, y, np.ones_like(x)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ centre
    disc = b * b - centre @ centre + radius**2
    with np.errstate(invalid="ignore"):
        far = b + np.sqrt(disc)  # the far intersection along the unit ray
    depth = far * d[..., 2]
    inside = (disc > 0) & (depth >= rim)
    depth = np.where(inside, depth, rim)
    corners = np.stack([inside[:-1, :-1], inside[:-1, 1:], inside[1:, :-1], inside[1:, 1:]]).all(0)
    return depth, largest_part(corners & (facing(depth, n) > 0.4))


SHEET_MARGIN_MM = 25.0  # the corrugated sheet goes on this far past the image on every side


def sheet_depth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return the depth of the corrugated sheet on the rays (x, y) (at z = 1).

    A sine of period 20 mm and amplitude 5 mm (slopes up to 57 degrees) whose crests run at 15
    degrees from the image's columns, on a plane at 210 mm tilted by about 5 degrees (0.08 in x,
    0.04 in y); lateral positions are taken on the rays at the working distance, as
    ``make_scene`` does.
    """
    X, Y = x * DISTANCE_MM, y * DISTANCE_MM
    across = X * np.cos(np.radians(15.0)) + Y * np.sin(np.radians(15.0))
    return DISTANCE_MM + 10.0 + 0.08 * X + 0.04 * Y + 5.0 * np.sin(2 * np.pi * across / 20.0)


def sheet_margin(n: int) -> int:
    """Return the margin in pixels of the sheet's rendered mesh past the image."""
    return int(np.ceil(SHEET_MARGIN_MM / SIZE_MM * n))


def sheet_surface(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertex depths and mask of the corrugated sheet (``sheet_depth``).

    The mask keeps the facets that face the camera (cosine above 0.4, as the torus and the bowl)
    and the largest 4-connected part. The rendered mesh (``render_mesh``) is the whole sheet:
    every pixel of the image and a margin of 25 mm past it on every side, so that the border
    pixels get the light of the slopes beyond the image that face them, as on a real sheet
    larger than the view.
    """
    x, y = vertex_rays(n)
    depth = sheet_depth(x, y)
    return depth, largest_part(facing(depth, n) > 0.4)


def render_mesh(shape: str, depth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertices and triangles Mitsuba renders: the mask's pixels, or the whole sheet with its margin."""
    if shape != "sheet":
        return mesh_of(depth, mask)
    n = mask.shape[0]
    m = sheet_margin(n)
    x, y = vertex_rays(n, m)
    wide = sheet_depth(x, y)
    if not np.array_equal(wide[m : m + n + 1, m : m + n + 1], depth):
        raise SystemExit("the sheet's margin grid does not continue the image's")
    index = np.arange(wide.size).reshape(wide.shape)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    triangles = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    return np.stack([x * wide, y * wide, wide], -1).reshape(-1, 3), triangles


def largest_part(mask: np.ndarray) -> np.ndarray:
    """Return the largest 4-connected part of a mask (label propagation, numpy only).

    Each pixel's label is the index of a pixel of its part; a round takes the least label of the
    4-neighbourhood, then follows labels to the label they point at until none moves (pointer
    jumping), so a part of any diameter settles in far fewer rounds than one a pixel of
    its diameter (the 12 MP bowl of ``indirect.py --synthetic``). The labels end as each part's
    least index, as plain propagation's do."""
    big = mask.size
    labels = np.where(mask, np.arange(mask.size).reshape(mask.shape), big)
    while True:
        old = labels
        padded = np.pad(labels, 1, constant_values=big)
        neighbours = np.stack(
            [padded[1:-1, 1:-1], padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]]
        )
        pointers = np.append(np.where(mask, neighbours.min(0), big).ravel(), big)
        while True:
            jumped = pointers[pointers]
            if np.array_equal(jumped, pointers):
                break
            pointers = jumped
        labels = pointers[:-1].reshape(mask.shape)
        if np.array_equal(labels, old):
            break
    values, counts = np.unique(labels[mask], return_counts=True)
    return mask & (labels == values[np.argmax(counts)]) if len(values) else mask


def surface(shape: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the true vertex depths (n+1, n+1) and the mask (n, n) of a shape."""
    if shape in ("sphere", "bumps"):
        scene = nplps.make_scene(shape, n=n, size=SIZE_MM, distance=DISTANCE_MM, camera="pinhole")
        if not np.allclose(scene.rig.camera["K"], camera(n)["K"]):
            raise SystemExit("make_scene's pinhole camera is not the benchmark's")
        return scene.depth, scene.mask
    if shape == "shadows":
        return shadows_surface(n)
    if shape == "torus":
        return torus_surface(n)
    if shape == "bowl":
        return bowl_surface(n)
    if shape == "sheet":
        return sheet_surface(n)
    raise SystemExit(f"unknown shape {shape!r}: one of {', '.join(SHAPES + CONCAVE)}")


def vertices(depth: np.ndarray) -> np.ndarray:
    """Return the 3-D vertices (n+1, n+1, 3) of a vertex depth map (on the corner rays)."""
    x, y = vertex_rays(depth.shape[0] - 1)
    return np.stack([x * depth, y * depth, depth], -1)


def facet_normals(depth: np.ndarray, n: int) -> np.ndarray:
    """Return the unit facet normals (n, n, 3) of the mesh, facing the camera (nplps's quad normal).

    The normal of a quad is the cross product of its diagonals (as nplps's mesh normals).
    """
    p = vertices(depth)
    d1 = p[1:, 1:] - p[:-1, :-1]
    d2 = p[:-1, 1:] - p[1:, :-1]
    normal = np.cross(d1, d2)
    normal *= -np.sign(normal[..., 2:3])
    return normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def mean_depth(depth: np.ndarray, mask: np.ndarray) -> float:
    """Return the gauge of a pinhole scene: the geometric mean depth of the vertices the mask uses."""
    h, w = mask.shape
    used = np.zeros((h + 1, w + 1), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr : dr + h, dc : dc + w] |= mask
    return float(np.exp(np.log(depth[used]).mean()))


def mesh_of(depth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertices (N, 3) and triangles (M, 3) of the surface inside the mask.

    Each pixel's quad is split along its (r, c)-(r+1, c+1) diagonal; both triangles face the
    camera (-z), since Mitsuba's BSDFs are one-sided.
    """
    h, w = mask.shape
    index = np.arange((h + 1) * (w + 1)).reshape(h + 1, w + 1)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    keep = mask.ravel()
    triangles = np.concatenate([np.stack([a, c, b], 1)[keep], np.stack([a, d, c], 1)[keep]])
    return vertices(depth).reshape(-1, 3), triangles


def set_variant() -> str:
    """Choose the fast ``llvm_ad_rgb`` variant when DRJIT_LIBLLVM_PATH is set, else ``scalar_rgb``."""
    import mitsuba as mi

    if mi.variant() is None:
        fast = "llvm_ad_rgb" in mi.variants() and bool(os.environ.get("DRJIT_LIBLLVM_PATH"))
        mi.set_variant("llvm_ad_rgb" if fast else "scalar_rgb")
    return str(mi.variant())


def render(
    depth: np.ndarray,
    mask: np.ndarray,
    rig: nplps.Rig,
    material: str,
    spp: int,
    max_depth: int,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Render one image per light of the rig; return them (k, H, W), the cast shadows and the render seconds.

    One Mitsuba scene with one point emitter is built; the emitter is moved from light to
    light (image i with sampler seed ``seed * 1000 + i``). ``mesh`` (vertices, triangles) is the
    rendered surface, by default the mask's pixels (``mesh_of``).
    """
    import mitsuba as mi

    set_variant()
    K = np.asarray(rig.camera["K"], dtype=np.float64)
    h, w = mask.shape
    if abs(K[0, 2] - (w - 1) / 2) > 1e-9 or abs(K[1, 2] - (h - 1) / 2) > 1e-9 or K[0, 0] != K[1, 1] or h != w:
        raise SystemExit("the sensor needs square pixels and images and the principal point at the image centre")
    start = time.perf_counter()
    points, triangles = mesh_of(depth, mask) if mesh is None else mesh
    shape = mi.Mesh("surface", vertex_count=len(points), face_count=len(triangles))
    params = mi.traverse(shape)
    # The buffers' own types: mi.Float / mi.UInt32 (JIT variants) or dynamic arrays (scalar).
    params["vertex_positions"] = type(params["vertex_positions"])(points.astype(np.float32).ravel())
    params["faces"] = type(params["faces"])(triangles.astype(np.uint32).ravel())
    params.update()
    shape.set_bsdf(mi.load_dict(bsdf(material)))
    sensor = {
        "type": "perspective",
        # The film's full width, w pixels, spans tan(fov / 2) = (w / 2) / f on each side of the
        # principal point, which is the film centre: (w - 1) / 2 in nplps's pixel-centre units.
        "fov": float(np.degrees(2 * np.arctan(w / 2 / K[0, 0]))),
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }
    world = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": max_depth},
            "sensor": sensor,
            "surface": shape,
            "light": {"type": "point", "position": [0.0, 0.0, 0.0], "intensity": {"type": "uniform", "value": 1.0}},
        }
    )
    scene_params = mi.traverse(world)
    images = []
    for i, (position, intensity) in enumerate(zip(rig.positions, rig.intensities, strict=True)):
        if not np.allclose(intensity, intensity[0]):
            raise SystemExit("the benchmark renders grey lights only")
        scene_params["light.position"] = mi.Point3f(*(float(v) for v in position))
        scene_params["light.intensity.value"] = float(np.pi * intensity[0])
        scene_params.update()
        image = np.asarray(mi.render(world, seed=seed * 1000 + i, spp=spp))
        images.append(image[..., 0])
    seconds = time.perf_counter() - start
    return np.asarray(images, dtype=np.float32), cast_shadows(world, rig, mask), seconds


def cast_shadows(world: Any, rig: nplps.Rig, mask: np.ndarray, sub: int = 4) -> np.ndarray:
    """Return the share of each pixel in each light's cast shadow (k, H, W), from Mitsuba ray casts.

    The camera rays through ``sub`` x ``sub`` points of each pixel meet the mesh; a point that
    faces a light (its triangle's normal towards it) but whose ray to the light is blocked by the
    mesh is in that light's cast shadow. Attached shadows (facing away) are not counted: the
    image model has them. 0: no cast shadow in the pixel, 1: all of it; in between the pixel is
    partly shadowed (an edge crosses it).
    """
    import drjit as dr
    import mitsuba as mi

    K = np.asarray(rig.camera["K"], dtype=np.float64)
    h, w = mask.shape
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    rows, cols = np.nonzero(mask)
    u = (cols[:, None, None] + offsets[None, None, :]) * np.ones((1, sub, 1))
    v = (rows[:, None, None] + offsets[None, :, None]) * np.ones((1, 1, sub))
    x, y = ((u - K[0, 2]) / K[0, 0]).ravel(), ((v - K[1, 2]) / K[1, 1]).ravel()
    norm = np.sqrt(x * x + y * y + 1)
    shadow = np.zeros((len(rig.lights), h, w), dtype=np.float32)
    if str(mi.variant()).startswith("scalar"):
        # One ray at a time (slow: about a minute per light at 256 x 256).
        blocked = np.zeros((len(rig.lights), len(x)), dtype=bool)
        for j in range(len(x)):
            hit = world.ray_intersect(mi.Ray3f([0.0, 0.0, 0.0], [x[j] / norm[j], y[j] / norm[j], 1 / norm[j]]))
            if not hit.is_valid():
                continue
            for i, position in enumerate(rig.positions):
                target = mi.Point3f(*(float(c) for c in position))
                if dr.dot(hit.n, target - hit.p) > 0:
                    blocked[i, j] = world.ray_test(hit.spawn_ray_to(target))
        shadow[:, rows, cols] = blocked.reshape(len(rig.lights), -1, sub * sub).mean(2)
        return shadow
    zero = np.zeros_like(x)
    rays = mi.Ray3f(mi.Point3f(zero, zero, zero), mi.Vector3f(x / norm, y / norm, 1 / norm))
    hits = world.ray_intersect(rays)
    found = np.asarray(hits.is_valid())
    for i, position in enumerate(rig.positions):
        target = mi.Point3f(*(float(c) for c in position))
        facing = np.asarray(dr.dot(hits.n, target - hits.p)) > 0
        blocked = np.asarray(world.ray_test(hits.spawn_ray_to(target))) & facing & found
        shadow[i, rows, cols] = blocked.reshape(-1, sub * sub).mean(1)
    return shadow


def render_file(
    shape: str,
    material: str,
    n: int,
    spp: int,
    max_depth: int,
    out: Path,
    float16: bool,
    seed: int = 0,
    lights: int = 16,
) -> float:
    """Render one scene with a rig of ``lights`` lights and write its .npz; return the render seconds."""
    import mitsuba as mi

    depth, mask = surface(shape, n)
    rig = make_rig(n, lights).with_grid(n, n)
    images, shadow, seconds = render(
        depth, mask, rig, material, spp, max_depth, mesh=render_mesh(shape, depth, mask), seed=seed
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        images=images.astype(np.float16) if float16 else images,
        rig=json.dumps(rig.to_dict()),
        depth=depth,
        distance=mean_depth(depth, mask),
        normals=np.where(mask[..., None], facet_normals(depth, n), np.nan),
        mask=mask,
        shadow=shadow.astype(np.float16),
        shape=shape,
        material=material,
        reflectance=reflectance(material),
        spp=spp,
        seed=seed,
        max_depth=max_depth,
        variant=set_variant(),
        mitsuba=mi.__version__,
        seconds=seconds,
    )
    print(
        f"{shape} {material} {n}^2 x {len(images)} lights, {spp} spp, max depth {max_depth}: {seconds:.1f} s -> {out}",
        flush=True,
    )
    return seconds


def main() -> None:
    """Render one scene, or with ``--all`` every shape in every material, or with ``--gi`` the interreflection set."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("shape", nargs="?", choices=SHAPES + CONCAVE)
    parser.add_argument(
        "--material", default="diffuse", help=f"one of {', '.join(MATERIALS)}, diffuse-R (or another value)"
    )
    parser.add_argument("--size", type=int, default=64, help="image size n (n x n); the benchmark is 256")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument(
        "--max-depth", type=int, help="2 (the default): direct light only; with --gi the GI renders' depth (default 12)"
    )
    parser.add_argument("--seed", type=int, default=0, help="image i gets sampler seed 1000 * SEED + i")
    parser.add_argument(
        "--lights", type=int, default=16, help="16 (the benchmark), 24 or 32: rings of 8 (see make_rig)"
    )
    parser.add_argument("--float16", action="store_true", help="store the images as float16")
    parser.add_argument("--out", type=Path, help="the .npz of one scene")
    parser.add_argument("--all", action="store_true", help="render every shape in every material")
    parser.add_argument(
        "--gi",
        action="store_true",
        help="render the interreflection set (GI_SET) with global illumination (SHAPE-MATERIAL-gi-SIZE.npz) "
        "and the direct-only twins (SHAPE-MATERIAL-direct-SIZE.npz)",
    )
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=SHAPES + CONCAVE, help="with --all")
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS), help="with --all")
    parser.add_argument("--out-dir", type=Path, default=Path("/work/pbr-data"), help="with --all or --gi")
    args = parser.parse_args()
    print(f"variant {set_variant()}", flush=True)
    if args.gi:
        depth = 12 if args.max_depth is None else args.max_depth
        if depth <= 2:
            parser.error("--gi needs --max-depth above 2")
        total = {"gi": 0.0, "direct": 0.0}
        for shape, material in GI_SET:
            for kind, max_depth in (("gi", depth), ("direct", 2)):
                out = args.out_dir / f"{shape}-{material}-{kind}-{args.size}.npz"
                total[kind] += render_file(
                    shape, material, args.size, args.spp, max_depth, out, args.float16, args.seed, args.lights
                )
        print(f"total render time: {total['gi']:.1f} s GI, {total['direct']:.1f} s direct ({2 * len(GI_SET)} renders)")
        return
    max_depth = 2 if args.max_depth is None else args.max_depth
    if args.all:
        total = 0.0
        for shape in args.shapes:
            for material in args.materials:
                out = args.out_dir / f"{shape}-{material}-{args.size}.npz"
                total += render_file(
                    shape, material, args.size, args.spp, max_depth, out, args.float16, args.seed, args.lights
                )
        print(f"total render time: {total:.1f} s ({len(args.shapes) * len(args.materials)} renders)")
        return
    if args.shape is None or args.out is None:
        parser.error("give a shape and --out, or --all, or --gi")
    render_file(
        args.shape, args.material, args.size, args.spp, max_depth, args.out, args.float16, args.seed, args.lights
    )


if __name__ == "__main__":
    main()
