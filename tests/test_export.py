"""Tests of nplps.export: PLY / OBJ meshes, normal maps, albedo and depth files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from nplps import export, io
from nplps.errors import InputError
from nplps.export import (
    read_ply,
    save_albedo,
    save_depth_npy,
    save_depth_tiff,
    save_normal_map,
    write_meshes,
    write_obj,
    write_ply,
    write_png,
)

H, W = 3, 4
DEPTH = 2.0


def _grid() -> tuple[np.ndarray, np.ndarray]:
    """A flat plane z = DEPTH seen by the camera, and a mask with a hole and a missing corner."""
    rows, cols = np.mgrid[0 : H + 1, 0 : W + 1].astype(np.float64)
    vertices = np.stack([0.1 * cols, 0.1 * rows + 0.05, np.full_like(rows, DEPTH)], axis=2)
    mask = np.ones((H, W), dtype=bool)
    mask[1, 1] = False  # a hole: its corners are still used by the neighbours
    mask[0, 3] = False  # vertex (0, 4) becomes unused
    return vertices, mask


def _expected_used(mask: np.ndarray) -> np.ndarray:
    """The vertices that are a corner of a masked facet, computed naively."""
    used = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=bool)
    for r, c in zip(*np.nonzero(mask), strict=True):
        used[r : r + 2, c : c + 2] = True
    return used


def _face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Right-hand geometric normals of the triangles."""
    a, b, c = (points[faces[:, i]] for i in range(3))
    return np.cross(b - a, c - a)


def _camera_normals() -> np.ndarray:
    """Per-vertex normals (0, 0, -1): facing the camera in the OpenCV frame."""
    normals = np.zeros((H + 1, W + 1, 3))
    normals[..., 2] = -1.0
    return normals


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------


def test_ply_counts_and_coordinates(tmp_path: Path) -> None:
    vertices, mask = _grid()
    path = tmp_path / "mesh.ply"
    write_ply(path, vertices, mask)

    mesh = read_ply(path)

    used = _expected_used(mask)
    assert len(mesh["vertices"]) == used.sum() == (H + 1) * (W + 1) - 1
    assert len(mesh["faces"]) == 2 * mask.sum()
    assert mesh["normals"] is None and mesh["colors"] is None
    assert "nplps" in mesh["comments"] and "frame opencv" in mesh["comments"]
    np.testing.assert_allclose(mesh["vertices"], vertices[used], rtol=1e-6)
    assert mesh["faces"].min() == 0 and mesh["faces"].max() == used.sum() - 1


def test_ply_triangle_layout(tmp_path: Path) -> None:
    vertices, mask = _grid()
    path = tmp_path / "mesh.ply"
    write_ply(path, vertices, mask)

    mesh = read_ply(path)

    points, faces = mesh["vertices"], mesh["faces"]
    for i, (r, c) in enumerate(zip(*np.nonzero(mask), strict=True)):  # row-major facet order
        first = vertices[[r, r + 1, r + 1], [c, c, c + 1]]  # (00, 10, 11)
        second = vertices[[r, r + 1, r], [c, c + 1, c + 1]]  # (00, 11, 01)
        np.testing.assert_allclose(points[faces[2 * i]], first, rtol=1e-6)
        np.testing.assert_allclose(points[faces[2 * i + 1]], second, rtol=1e-6)


def test_ply_faces_face_the_camera_opencv(tmp_path: Path) -> None:
    vertices, mask = _grid()
    path = tmp_path / "mesh.ply"
    write_ply(path, vertices, mask, normals=_camera_normals())

    mesh = read_ply(path)

    geometric = _face_normals(mesh["vertices"], mesh["faces"])
    assert np.all(geometric[:, 2] < 0)  # towards the camera at the origin (plane at z > 0)
    vertex_normals = mesh["normals"][mesh["faces"][:, 0]]
    assert np.all(np.einsum("ij,ij->i", geometric, vertex_normals) > 0)


def test_ply_opengl_frame(tmp_path: Path) -> None:
    vertices, mask = _grid()
    normals = _camera_normals()
    normals[..., 0] = 0.6
    normals[..., 2] = -0.8
    path = tmp_path / "mesh_gl.ply"
    write_ply(path, vertices, mask, normals=normals, opengl=True)

    mesh = read_ply(path)

    used = _expected_used(mask)
    assert "frame opengl" in mesh["comments"]
    np.testing.assert_allclose(mesh["vertices"], vertices[used] * [1, -1, -1], rtol=1e-6)
    np.testing.assert_allclose(mesh["normals"], normals[used] * [1, -1, -1], rtol=1e-6)
    assert np.all(mesh["vertices"][:, 2] < 0)  # in front of the viewer: z backwards
    geometric = _face_normals(mesh["vertices"], mesh["faces"])
    assert np.all(geometric[:, 2] > 0)  # front faces point at the viewer (+z)


def test_ply_colors(tmp_path: Path) -> None:
    vertices, mask = _grid()
    albedo = np.linspace(0.1, 0.9, (H + 1) * (W + 1)).reshape(H + 1, W + 1)
    albedo[2, 2] = np.nan
    path = tmp_path / "mesh.ply"
    write_ply(path, vertices, mask, albedo=albedo)

    colors = read_ply(path)["colors"]

    written = albedo[_expected_used(mask)]
    reference = np.percentile(written[np.isfinite(written)], 99)
    expected = np.nan_to_num(np.rint(np.clip(written / reference * 255, 0, 255)), nan=0)
    assert colors.dtype == np.uint8
    np.testing.assert_array_equal(colors[:, 0], colors[:, 1])
    np.testing.assert_array_equal(colors[:, 0], colors[:, 2])
    np.testing.assert_array_equal(colors[:, 0], expected.astype(np.uint8))
    assert colors.max() == 255


def test_ply_skips_facets_with_nan(tmp_path: Path) -> None:
    vertices, mask = _grid()
    vertices[3, 0] = np.nan  # only facet (2, 0) uses this vertex
    path = tmp_path / "mesh.ply"
    with pytest.warns(RuntimeWarning, match="skipped 1 masked facet"):
        write_ply(path, vertices, mask)

    mesh = read_ply(path)

    assert len(mesh["faces"]) == 2 * (mask.sum() - 1)
    assert np.isfinite(mesh["vertices"]).all()


def test_ply_rejects_bad_shapes(tmp_path: Path) -> None:
    vertices, mask = _grid()
    with pytest.raises(InputError, match="mask"):
        write_ply(tmp_path / "a.ply", vertices, mask[:, :-1])
    with pytest.raises(InputError, match="normals"):
        write_ply(tmp_path / "a.ply", vertices, mask, normals=np.zeros((H, W, 3)))
    with pytest.raises(InputError, match="no facet"):
        write_ply(tmp_path / "a.ply", vertices, np.zeros_like(mask))


def test_read_ply_rejects_other_files(tmp_path: Path) -> None:
    path = tmp_path / "ascii.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(InputError, match="binary_little_endian"):
        read_ply(path)


# --------------------------------------------------------------------------------------------------
# OBJ
# --------------------------------------------------------------------------------------------------


def _parse_obj(path: Path) -> dict[str, np.ndarray]:
    """Parse the v / vn / f lines of an OBJ file (f as (m, 3, 2) vertex // normal indices)."""
    records: dict[str, list] = {"v": [], "vn": [], "f": []}
    for line in path.read_text().splitlines():
        tag, *values = line.split()
        if tag == "v" or tag == "vn":
            records[tag].append([float(value) for value in values])
        elif tag == "f":
            records["f"].append([[int(i) for i in value.split("//")] for value in values])
    return {tag: np.array(values) for tag, values in records.items()}


def test_obj_with_normals_and_colors(tmp_path: Path) -> None:
    vertices, mask = _grid()
    albedo = np.linspace(0.0, 1.0, (H + 1) * (W + 1)).reshape(H + 1, W + 1)
    write_ply(tmp_path / "mesh.ply", vertices, mask, normals=_camera_normals(), albedo=albedo)
    path = tmp_path / "mesh.obj"
    write_obj(path, vertices, mask, normals=_camera_normals(), albedo=albedo)

    obj = _parse_obj(path)
    ply = read_ply(tmp_path / "mesh.ply")

    assert path.read_text().startswith("# nplps\n# frame opencv\n")
    n = _expected_used(mask).sum()
    assert obj["v"].shape == (n, 6) and obj["vn"].shape == (n, 3)
    assert obj["f"].shape == (2 * mask.sum(), 3, 2)
    assert obj["f"].min() == 1 and obj["f"].max() == n  # 1-based, in range
    np.testing.assert_array_equal(obj["f"][..., 0], obj["f"][..., 1])
    np.testing.assert_array_equal(obj["f"][..., 0] - 1, ply["faces"])
    np.testing.assert_allclose(obj["v"][:, :3], ply["vertices"], rtol=1e-6)
    np.testing.assert_allclose(obj["v"][:, 3:] * 255, ply["colors"], atol=1e-3)
    np.testing.assert_allclose(obj["vn"], ply["normals"])


def test_obj_without_normals(tmp_path: Path) -> None:
    vertices, mask = _grid()
    path = tmp_path / "mesh.obj"
    write_obj(path, vertices, mask, opengl=True)

    lines = path.read_text().splitlines()

    assert lines[1] == "# frame opengl"
    faces = np.array([[int(i) for i in line.split()[1:]] for line in lines if line[0] == "f"])
    points = np.array([[float(x) for x in line.split()[1:]] for line in lines if line[0] == "v"])
    assert points.shape == (_expected_used(mask).sum(), 3)
    assert faces.shape == (2 * mask.sum(), 3)
    assert faces.min() == 1 and faces.max() == len(points)
    assert np.all(_face_normals(points, faces - 1)[:, 2] > 0)
    assert not any(line.startswith("vn") for line in lines)


def _percent_obj(mesh: export._Mesh) -> bytes:
    """The OBJ text of ``mesh`` formatted with Python's % operator, line by line: what the
    vectorized writer must reproduce byte for byte."""
    lines = ["# nplps\n", f"# frame {mesh.frame}\n"]
    for i, (x, y, z) in enumerate(mesh.points.tolist()):
        if mesh.colors is None:
            lines.append("v %.9g %.9g %.9g\n" % (x, y, z))  # noqa: UP031 (the writer's %-formats are the spec)
        else:
            r, g, b = (mesh.colors[i].astype(np.float64) / 255.0).tolist()
            lines.append("v %.9g %.9g %.9g %.6g %.6g %.6g\n" % (x, y, z, r, g, b))  # noqa: UP031
    if mesh.normals is not None:
        lines += ["vn %.7g %.7g %.7g\n" % tuple(n) for n in mesh.normals.tolist()]  # noqa: UP031
        faces = (mesh.faces + 1).tolist()
        lines += ["f %d//%d %d//%d %d//%d\n" % (a, a, b, b, c, c) for a, b, c in faces]  # noqa: UP031
    else:
        lines += ["f %d %d %d\n" % tuple(f) for f in (mesh.faces + 1).tolist()]  # noqa: UP031
    return "".join(lines).encode("ascii")


def _wild_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, mask, normals and albedo with values that exercise every branch of %g: signs,
    zeros, -0, tiny and huge magnitudes, powers of ten, trailing zeros, holes in the mask."""
    rng = np.random.default_rng(7)
    vertices = rng.normal(0.0, 50.0, (h + 1, w + 1, 3))
    vertices[..., 2] += 200.0
    flat = vertices.reshape(-1)
    specials = [
        0.0,
        -0.0,
        1.0,
        -1.0,
        0.5,
        1e-4,
        1.5e-5,
        1e-12,
        -3e-20,
        1e9,
        123456789.0,
        1e20,
        -3.4e38,
        1e-40,
        100.0,
        0.1,
    ]
    flat[: len(specials)] = specials
    end = min(400, flat.size)
    flat[len(specials) : end] = 10.0 ** rng.integers(-30, 30, end - len(specials))
    normals = rng.normal(size=(h + 1, w + 1, 3))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals[::3, ::2, 0] = 0.0
    normals[1, :, 1] = -0.0
    albedo = rng.uniform(0.0, 1.0, (h + 1, w + 1))
    mask = rng.random((h, w)) < 0.9
    return vertices, mask, normals, albedo


@pytest.mark.parametrize("with_normals", [True, False])
@pytest.mark.parametrize("with_albedo", [True, False])
def test_obj_text_is_percent_formatting(tmp_path: Path, with_normals: bool, with_albedo: bool) -> None:
    vertices, mask, normals, albedo = _wild_grid(40, 30)
    normals = normals if with_normals else None
    albedo = albedo if with_albedo else None
    path = tmp_path / "mesh.obj"
    write_obj(path, vertices, mask, normals=normals, albedo=albedo)

    expected = _percent_obj(export._build_mesh(vertices, mask, normals, albedo, False))

    assert path.read_bytes() == expected


def test_obj_text_is_percent_formatting_across_chunks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    vertices, mask, normals, albedo = _wild_grid(60, 50)
    monkeypatch.setattr(export, "_OBJ_CHUNK_ROWS", 97)  # many chunks, some digit counts change inside one
    path = tmp_path / "mesh.obj"
    write_obj(path, vertices, mask, normals=normals, albedo=albedo, opengl=True)

    assert path.read_bytes() == _percent_obj(export._build_mesh(vertices, mask, normals, albedo, True))


@pytest.mark.parametrize("precision", [9, 7, 6, 2, 1])
def test_format_float32_is_percent_g(precision: int) -> None:
    rng = np.random.default_rng(precision)
    with np.errstate(all="ignore"):  # float32 overflow, signalling NaN bit patterns
        powers = np.float32(10.0 ** np.arange(-45, 39))
        values = _float32_cases(rng, powers)

    text = export._lines([export._format_float32(values, precision), b"\n"])

    assert text.decode("ascii").splitlines() == ["%.*g" % (precision, v) for v in values.tolist()]  # noqa: UP031


def _float32_cases(rng: np.random.Generator, powers: np.ndarray) -> np.ndarray:
    return np.concatenate(
        [
            rng.integers(0, 2**32, 50000, dtype=np.uint64)
            .astype(np.uint32)
            .view(np.float32)
            .astype(np.float64),  # any bits
            rng.normal(0.0, 100.0, 20000),
            rng.integers(-(10**6), 10**6, 20000) / 2.0 ** rng.integers(0, 24, 20000),  # exact ties
            powers,
            np.nextafter(powers, np.float32(0)),
            np.nextafter(powers, np.float32(np.inf)),
            [0.0, -0.0, np.inf, -np.inf, np.nan, 0.5, 0.25, 0.125, 9.5, 99999.995, 1e-4, 9.99999e-5],
        ]
    ).astype(np.float32)


@pytest.mark.parametrize(
    "values",
    [
        np.concatenate([np.arange(0, 20001), [99999999, 10**8, 10**9, 2**32 - 1], np.arange(10**7 - 5, 10**7 + 5)]),
        np.arange(10**6, 10**6 + 5000),  # all with 7 digits: no 0 bytes
    ],
)
def test_format_int_is_percent_d(values: np.ndarray) -> None:
    text, blanks = export._format_int(values)

    lines = export._lines([b"f ", text, b"\n"], compact=blanks)

    assert lines == "".join("f %d\n" % v for v in values.tolist()).encode("ascii")  # noqa: UP031


def test_write_meshes_is_write_ply_and_write_obj(tmp_path: Path) -> None:
    vertices, mask, normals, albedo = _wild_grid(12, 9)
    write_ply(tmp_path / "a.ply", vertices, mask, normals=normals, albedo=albedo)
    write_obj(tmp_path / "a.obj", vertices, mask, normals=normals, albedo=albedo)
    write_meshes(tmp_path / "b.ply", tmp_path / "b.obj", vertices, mask, normals=normals, albedo=albedo)

    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    assert (tmp_path / "a.obj").read_bytes() == (tmp_path / "b.obj").read_bytes()


# --------------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------------


def test_normal_map_encoding(tmp_path: Path) -> None:
    normals = np.zeros((2, 2, 3))
    normals[0, 0] = (0, 0, -1)
    normals[0, 1] = (1, 0, 0)
    normals[1, 0] = np.nan
    normals[1, 1] = (0, -1, 0)  # up in the image
    path = tmp_path / "normals.png"
    save_normal_map(path, normals, bits=8)  # 16 bits by default: tests/test_normal_maps.py

    image = io.read_image(path)

    assert image.dtype == np.uint8 and image.shape == (2, 2, 3)
    np.testing.assert_array_equal(image[0, 0], (128, 128, 255))
    np.testing.assert_array_equal(image[0, 1], (255, 128, 128))
    np.testing.assert_array_equal(image[1, 0], (0, 0, 0))
    np.testing.assert_array_equal(image[1, 1], (128, 255, 128))

    mask = np.array([[True, False], [True, True]])
    save_normal_map(path, normals, mask=mask, bits=8)
    np.testing.assert_array_equal(io.read_image(path)[0, 1], (0, 0, 0))


def test_albedo_png_is_16_bit(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    albedo = rng.random((8, 9)) * 0.7
    albedo[0, 0] = np.nan
    path = tmp_path / "albedo.png"

    scale = save_albedo(path, albedo)

    header = path.read_bytes()[:26]
    assert header[24] == 16  # PNG bit depth
    image = io.read_image(path)
    assert image.dtype == np.uint16 and image.shape == (8, 9)
    assert scale == pytest.approx(65535 / np.nanpercentile(albedo, 99.9))
    assert image[0, 0] == 0
    assert image.max() == 65535
    finite = np.isfinite(albedo)
    expected = np.clip(albedo[finite] * scale, 0, 65535)
    np.testing.assert_allclose(image[finite], expected, atol=0.5 + 1e-9)


@pytest.mark.parametrize("shape", [(7, 5), (6, 4, 3), (1, 1), (3, 200, 3)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_writer_round_trips(tmp_path: Path, shape: tuple[int, ...], dtype: type) -> None:
    """The Rust PNG writer's files read back bit for bit by the Rust reader, pypng and (8-bit) imageio."""
    import imageio.v3 as iio
    import png

    top = np.iinfo(dtype).max
    pixels = np.random.default_rng(1).integers(0, top + 1, shape).astype(dtype)
    pixels.flat[0], pixels.flat[-1] = 0, top
    path = tmp_path / "a.png"
    write_png(path, pixels)

    assert path.read_bytes()[24] == 8 * np.dtype(dtype).itemsize  # bit depth
    np.testing.assert_array_equal(io.read_image(path), pixels)
    w, h, rows, info = png.Reader(filename=str(path)).read()
    assert (w, h, info["bitdepth"], info["greyscale"]) == (shape[1], shape[0], 8 * pixels.itemsize, len(shape) == 2)
    np.testing.assert_array_equal(np.array([list(r) for r in rows]).reshape(shape), pixels)
    if dtype == np.uint8:
        np.testing.assert_array_equal(iio.imread(path), pixels)


def test_pngs_written_in_parallel_match_one_by_one(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    images = [rng.integers(0, 65536, (40, 30, 3)).astype(np.uint16), rng.integers(0, 256, (20, 50)).astype(np.uint8)]
    export.write_pngs([(tmp_path / f"{i}.png", image) for i, image in enumerate(images)])
    for i, image in enumerate(images):
        write_png(tmp_path / f"single{i}.png", image)
        assert (tmp_path / f"{i}.png").read_bytes() == (tmp_path / f"single{i}.png").read_bytes()
        np.testing.assert_array_equal(io.read_image(tmp_path / f"{i}.png"), image)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0.png", "1.png", "single0.png", "single1.png"]


def test_png_writer_errors_name_the_final_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="shape"):
        write_png(tmp_path / "a.png", np.zeros((2, 3, 4), dtype=np.uint8))
    with pytest.raises(InputError, match="shape"):
        write_png(tmp_path / "a.png", np.zeros((0, 3), dtype=np.uint8))
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a.png").mkdir()  # a directory where the file goes: refused, named
    with pytest.raises(OSError) as caught:
        export.write_pngs(
            [(tmp_path / "b.png", np.zeros((2, 2), np.uint8)), (tmp_path / "d" / "a.png", np.zeros((2, 2), np.uint8))]
        )
    assert caught.value.filename == str(tmp_path / "d" / "a.png")
    assert [p.name for p in tmp_path.iterdir() if p.is_file()] == []  # all or nothing: b.png removed too


def test_normal_map_in_bands_is_one_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    normals = np.random.default_rng(2).normal(size=(23, 17, 3))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals[3, 4] = np.nan
    mask = np.random.default_rng(3).random((23, 17)) < 0.8
    save_normal_map(tmp_path / "one.png", normals, mask=mask)
    monkeypatch.setattr(export, "_GATHER_CHUNK", 40)  # bands of 2 rows
    save_normal_map(tmp_path / "bands.png", normals, mask=mask)

    assert (tmp_path / "one.png").read_bytes() == (tmp_path / "bands.png").read_bytes()


def test_depth_npy_round_trip(tmp_path: Path) -> None:
    depth = np.array([[1.0, np.nan], [2.5, 1e-12]])
    path = tmp_path / "depth.bin"  # written exactly there, no .npy appended
    save_depth_npy(path, depth)

    loaded = np.load(path)

    assert loaded.dtype == np.float64
    np.testing.assert_array_equal(loaded, depth)


def test_depth_tiff_round_trip(tmp_path: Path) -> None:
    depth = np.array([[1.0, np.nan, 3.25], [2.5, 0.125, np.nan]])
    path = tmp_path / "depth.tif"
    save_depth_tiff(path, depth)

    loaded = tifffile.imread(path)

    assert loaded.dtype == np.float32
    np.testing.assert_array_equal(loaded, depth.astype(np.float32))
    np.testing.assert_array_equal(io.read_image(path), loaded)


def test_ply_written_in_blocks_is_one_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The PLY writers stream blocks of records: the bytes do not depend on the block size."""
    vertices, mask = _grid()
    normals = np.broadcast_to(np.array([0.0, 0.0, -1.0]), vertices.shape)
    albedo = np.linspace(0.1, 0.9, vertices.shape[0] * vertices.shape[1]).reshape(vertices.shape[:2])
    data = {"normals": normals, "albedo": albedo}
    write_ply(tmp_path / "one.ply", vertices, mask, **data)
    export.write_point_cloud(tmp_path / "one_points.ply", vertices, mask, **data)
    monkeypatch.setattr(export, "_PLY_BLOCK", 3)
    write_ply(tmp_path / "blocks.ply", vertices, mask, **data)
    export.write_point_cloud(tmp_path / "blocks_points.ply", vertices, mask, **data)

    assert (tmp_path / "one.ply").read_bytes() == (tmp_path / "blocks.ply").read_bytes()
    assert (tmp_path / "one_points.ply").read_bytes() == (tmp_path / "blocks_points.ply").read_bytes()
    ply = read_ply(tmp_path / "blocks.ply")
    assert len(ply["faces"]) == 2 * mask.sum()  # type: ignore[arg-type]
