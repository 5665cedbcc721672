"""Camera RAW input (nplps.raw): DNG files written here, read back through rawpy (LibRaw).

No real camera RAW samples are available to the tests: every RAW file is a DNG that these tests
write from a known uint16 sensor mosaic (Bayer pattern, black and white level, as-shot neutral,
exposure time and ISO), so that each decoded value can be checked against the sensor value it
came from. The files are written with pidng (``RAW2DNG``); where pidng is not installed (it has no
binary wheels: installing it compiles a C extension), with tifffile and the same DNG tags. Both
writers' files read back alike (``test_rawpy_reads_the_written_dng_bit_exact``).
"""

from __future__ import annotations

import io
import json
import os
import shlex
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import tifffile

rawpy = pytest.importorskip("rawpy")

from nplps import cli, export  # noqa: E402
from nplps.errors import InputError  # noqa: E402
from nplps.io import load_stack, read_image  # noqa: E402
from nplps.raw import (  # noqa: E402
    RawFile,
    RawOptions,
    exposures_from_metadata,
    is_raw,
    read_exposure,
    read_raw,
    sensor_levels,
)

try:
    import pidng.core  # noqa: F401

    WRITERS = ("pidng", "tifffile")
except ImportError:
    WRITERS = ("tifffile",)

#: A 14-bit-like sensor whose usable range (white - black) is 65535 / 5: a decoded value is
#: exactly 5 x (sensor value - black).
BLACK = 1024
WHITE = BLACK + 13107
SCALE = 65535 / (WHITE - BLACK)  # = 5

#: The 2 x 2 colour filter patterns (row-major; 0 red, 1 green, 2 blue), as DNG's CFAPattern tag.
PATTERNS = {"RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1), "GBRG": (1, 2, 0, 1)}


def write_dng(
    path: Path,
    mosaic: np.ndarray,
    *,
    black: int = BLACK,
    white: int = WHITE,
    neutral: tuple[float, float, float] = (1.0, 1.0, 1.0),
    shutter: tuple[int, int] | None = (1, 125),
    iso: int | None = 200,
    pattern: tuple[int, ...] = PATTERNS["RGGB"],
    writer: str | None = None,
) -> Path:
    """Write ``mosaic`` (uint16, a Bayer ``pattern``) as an uncompressed DNG with pidng (or tifffile); return its path.

    The camera's colour matrix is the identity (D65); ``neutral`` is the as-shot neutral (its
    inverse the camera's white balance multipliers); ``shutter`` (seconds, as a fraction) and
    ``iso`` go into the first directory's ExposureTime and ISO tags (None: left out).
    """
    writer = writer or WRITERS[0]
    name = os.fspath(path)
    assert name.endswith(".dng")
    mosaic = np.ascontiguousarray(mosaic, dtype=np.uint16)
    if writer == "tifffile":
        _write_dng_tifffile(name, mosaic, black, white, neutral, shutter, iso, pattern)
        return Path(name)
    from pidng.core import RAW2DNG
    from pidng.defs import CalibrationIlluminant, DNGVersion, PhotometricInterpretation
    from pidng.dng import DNGTags, Tag

    height, width = mosaic.shape
    tags = DNGTags()
    tags.set(Tag.ImageWidth, width)
    tags.set(Tag.ImageLength, height)
    tags.set(Tag.TileWidth, width)
    tags.set(Tag.TileLength, height)
    tags.set(Tag.Orientation, 1)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, 16)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, list(pattern))
    tags.set(Tag.BlackLevel, black)
    tags.set(Tag.WhiteLevel, white)
    identity = [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]]
    tags.set(Tag.ColorMatrix1, identity)
    tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    tags.set(Tag.AsShotNeutral, [[round(n * 1000), 1000] for n in neutral])
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.Make, "nplps")
    tags.set(Tag.Model, "test sensor")
    if shutter is not None:
        tags.set(Tag.ExposureTime, [list(shutter)])
    if iso is not None:
        tags.set(Tag.PhotographicSensitivity, [iso])
    dng = RAW2DNG()
    dng.options(tags, path="", compress=False)
    dng.convert(mosaic, filename=name[: -len(".dng")])
    return Path(name)


def _write_dng_tifffile(name, mosaic, black, white, neutral, shutter, iso, pattern) -> None:
    """The DNG of :func:`write_dng` written with tifffile: a CFA TIFF with the DNG tags."""
    identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)  # 9 signed rationals
    extratags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(pattern), True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 0, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "nplps test sensor", True),  # UniqueCameraModel
        (50714, "I", 1, (black,), True),  # BlackLevel
        (50717, "I", 1, (white,), True),  # WhiteLevel
        (50721, "2i", 9, identity, True),  # ColorMatrix1
        (50778, "H", 1, (21,), True),  # CalibrationIlluminant1: D65
        (50728, "2I", 3, tuple(v for n in neutral for v in (round(n * 1000), 1000)), True),  # AsShotNeutral
    ]
    if shutter is not None:
        extratags.append((33434, "2I", 1, tuple(shutter), True))  # ExposureTime
    if iso is not None:
        extratags.append((34855, "H", 1, (iso,), True))  # ISOSpeedRatings
    tifffile.imwrite(name, mosaic, photometric=32803, extratags=extratags, metadata=None)


def random_mosaic(rng: np.random.Generator, shape: tuple[int, int] = (40, 60)) -> np.ndarray:
    return rng.integers(BLACK, WHITE + 1, size=shape).astype(np.uint16)


def superpixels(values: np.ndarray) -> np.ndarray:
    """(H, W) values -> (2H, 2W) mosaic with every 2 x 2 cell equal."""
    return np.repeat(np.repeat(values, 2, axis=0), 2, axis=1)


# --------------------------------------------------------------------------------------------------
# The DNG files written here, as LibRaw reads them
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("writer", WRITERS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rawpy_reads_the_written_dng_bit_exact(tmp_path, seed, writer):
    mosaic = random_mosaic(np.random.default_rng(seed))
    path = write_dng(tmp_path / "a.dng", mosaic, writer=writer, neutral=(0.5, 1.0, 0.25))
    assert read_exposure(path) == pytest.approx((1 / 125, 200), rel=1e-6)
    assert np.array_equal(read_raw(path, half_size=True)[..., 0], 5 * (mosaic[0::2, 0::2].astype(np.int64) - BLACK))
    with rawpy.imread(os.fspath(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, mosaic)
        assert list(raw.black_level_per_channel) == [BLACK] * 4
        assert raw.white_level == WHITE
        assert raw.color_desc == b"RGBG"
        assert raw.raw_pattern.tolist() == [[0, 1], [3, 2]]  # R G / G2 B: RGGB
        assert (raw.sizes.raw_height, raw.sizes.raw_width) == mosaic.shape
        assert list(raw.camera_whitebalance[:3]) == pytest.approx([2.0, 1.0, 4.0], rel=1e-3)


# --------------------------------------------------------------------------------------------------
# Linearity
# --------------------------------------------------------------------------------------------------


def _fit_through_zero(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y = a x and the largest residual."""
    x = x.astype(np.float64).ravel()
    y = y.astype(np.float64).ravel()
    slope = float(x @ y / (x @ x))
    return slope, float(np.max(np.abs(y - slope * x)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_half_size_is_linear_in_the_sensor_values(tmp_path, seed):
    """Decoded = (sensor - black) x 65535 / (white - black): a line through zero, no residual."""
    mosaic = random_mosaic(np.random.default_rng(seed))
    image = read_raw(write_dng(tmp_path / "a.dng", mosaic), half_size=True)
    assert image.dtype == np.uint16 and image.shape == (20, 30, 3)
    signal = mosaic.astype(np.int64) - BLACK
    for channel, cell in ((0, signal[0::2, 0::2]), (2, signal[1::2, 1::2])):
        slope, residual = _fit_through_zero(cell, image[..., channel])
        assert slope == pytest.approx(SCALE, rel=1e-12)
        assert residual < 1e-6  # exact: the values are 5 x (sensor - black)
        assert np.array_equal(image[..., channel], cell * 5)
    # green: the mean of the two greens of the cell, rounded down
    greens = signal[0::2, 1::2] * 5 + signal[1::2, 0::2] * 5
    assert np.array_equal(image[..., 1], greens // 2)
    slope, residual = _fit_through_zero(greens / 2, image[..., 1])
    assert slope == pytest.approx(1.0, abs=1e-4) and residual <= 0.5 + 1e-6


@pytest.mark.parametrize("name", list(PATTERNS))
def test_half_size_follows_the_colour_filter_pattern(tmp_path, name):
    pattern = PATTERNS[name]
    mosaic = random_mosaic(np.random.default_rng(7))
    image = read_raw(write_dng(tmp_path / "a.dng", mosaic, pattern=pattern), half_size=True).astype(np.int64)
    signal = 5 * (mosaic.astype(np.int64) - BLACK)
    cells = {(r, c): signal[r::2, c::2] for r in (0, 1) for c in (0, 1)}
    where = {colour: [rc for rc, p in zip(cells, pattern, strict=True) if p == colour] for colour in (0, 1, 2)}
    assert np.array_equal(image[..., 0], cells[where[0][0]])
    assert np.array_equal(image[..., 2], cells[where[2][0]])
    assert np.array_equal(image[..., 1], (cells[where[1][0]] + cells[where[1][1]]) // 2)


@pytest.mark.parametrize("value", [0, 1, 7, 1000, 6553, 13106, 13107])
def test_demosaic_of_a_uniform_field_is_exact(tmp_path, value):
    mosaic = np.full((32, 48), BLACK + value, dtype=np.uint16)
    image = read_raw(write_dng(tmp_path / "a.dng", mosaic))
    assert image.shape == (32, 48, 3)
    assert np.all(image == 5 * value)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_demosaic_is_linear_in_the_exposure_to_a_few_levels(tmp_path, seed):
    """A smooth grey scene at exposures t = 1/8 .. 1: per pixel, decoded value against t is a line through zero.

    The scene is a multiple of 8 sensor levels, so every written mosaic is exactly t x scene: the
    residual is the decoder's own. Full-size demosaicing (LibRaw's AHD) is not exactly linear: its
    interpolation picks a direction per pixel from the values. Measured on these four seeds: largest
    residual 19 to 24 decoded levels (3.7e-4 of full scale), 99th percentile under 6 levels;
    half-size decoding has none (the test above).
    """
    rng = np.random.default_rng(seed)
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    a, b, c = rng.uniform(0.2, 1.0, 3)
    scene = 0.4 + 0.3 * np.sin(2 * a * xx + 3 * b * yy + c) + 0.2 * xx * yy  # 0.1 .. 0.9 of the range
    scene = 8 * np.rint(scene * (WHITE - BLACK) / 8)
    times = np.array([1, 2, 4, 6, 8]) / 8
    stack = np.stack(
        [
            read_raw(write_dng(tmp_path / f"t{i}.dng", (BLACK + t * scene).astype(np.uint16))).astype(np.float64)
            for i, t in enumerate(times)
        ]
    )  # (t, H, W, 3)
    slope = np.tensordot(times, stack, axes=(0, 0)) / (times @ times)
    residual = np.abs(stack - times[:, None, None, None] * slope)
    assert residual.max() < 40  # of 65535
    assert np.quantile(residual, 0.99) < 8
    # and the slope is the scene (in decoded units) in every colour: a grey field stays grey
    truth = scene[4:-4, 4:-4, None] * SCALE
    assert np.max(np.abs(slope[4:-4, 4:-4] - truth)) / truth.max() < 2e-3


def test_sensor_levels_from_the_header(tmp_path):
    path = write_dng(tmp_path / "a.dng", random_mosaic(np.random.default_rng(0)))
    assert sensor_levels(path) == WHITE - BLACK == 13107
    mosaic = np.random.default_rng(1).integers(64, 4096, size=(32, 32)).astype(np.uint16)
    other = write_dng(tmp_path / "b.dng", mosaic, black=64, white=4095)
    assert sensor_levels(other) == 4031


def test_float_output_is_uint16_over_65535(tmp_path):
    path = write_dng(tmp_path / "a.dng", random_mosaic(np.random.default_rng(5)))
    as_int = read_raw(path, half_size=True)
    as_float = read_raw(path, half_size=True, output="float")
    assert as_float.dtype == np.float32
    assert np.array_equal(as_float, as_int.astype(np.float32) / np.float32(65535))


# --------------------------------------------------------------------------------------------------
# White balance
# --------------------------------------------------------------------------------------------------


def test_white_balance_none_and_camera(tmp_path):
    """As shot neutral (0.5, 1, 0.25): camera multipliers (2, 1, 4); none: 1 for every channel."""
    rng = np.random.default_rng(3)
    mosaic = rng.integers(BLACK, BLACK + (WHITE - BLACK) // 4, size=(40, 60)).astype(np.uint16)  # no clipping
    path = write_dng(tmp_path / "a.dng", mosaic, neutral=(0.5, 1.0, 0.25))
    with rawpy.imread(os.fspath(path)) as raw:
        assert list(raw.camera_whitebalance[:3]) == pytest.approx([2.0, 1.0, 4.0], rel=1e-3)
    none = read_raw(path, half_size=True).astype(np.int64)
    camera = read_raw(path, half_size=True, white_balance="camera").astype(np.int64)
    signal = mosaic.astype(np.int64) - BLACK
    assert np.array_equal(none[..., 0], 5 * signal[0::2, 0::2])
    assert np.array_equal(camera[..., 1], none[..., 1])
    assert np.max(np.abs(camera[..., 0] - 2 * none[..., 0])) <= 1
    assert np.max(np.abs(camera[..., 2] - 4 * none[..., 2])) <= 2


def test_camera_white_balance_clips_at_the_top_level(tmp_path):
    mosaic = np.full((32, 32), WHITE - 10, dtype=np.uint16)
    path = write_dng(tmp_path / "a.dng", mosaic, neutral=(0.5, 1.0, 0.25))
    camera = read_raw(path, half_size=True, white_balance="camera")
    assert np.all(camera[..., 0] == 65535) and np.all(camera[..., 2] == 65535)
    assert np.all(camera[..., 1] == 5 * (WHITE - 10 - BLACK))


def test_options_are_checked():
    with pytest.raises(InputError, match="white balance"):
        RawOptions(white_balance="auto")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="output"):
        RawOptions(output="uint8")  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------------
# Where images are read
# --------------------------------------------------------------------------------------------------


def test_read_image_decodes_raw_files_by_name(tmp_path):
    mosaic = superpixels(np.random.default_rng(0).integers(0, 13108, size=(16, 16))) + BLACK
    path = write_dng(tmp_path / "A.DNG".lower(), mosaic.astype(np.uint16))
    image = read_image(path)  # default options: full size, no white balance
    assert image.shape == (32, 32, 3) and image.dtype == np.uint16
    half = read_image(RawFile(path, RawOptions(half_size=True)))
    assert np.array_equal(half, np.repeat((5 * (mosaic[::2, ::2].astype(np.int64) - BLACK))[..., None], 3, -1))
    assert is_raw("x.NEF") and is_raw(RawFile("x.bin")) and not is_raw("x.png")
    assert os.fspath(RawFile(path)) == os.fspath(path)


def test_load_stack_takes_raw_files(tmp_path):
    cells = np.random.default_rng(1).integers(0, 13108, size=(2, 16, 16))
    paths = [
        RawFile(
            write_dng(tmp_path / f"{i}.dng", (BLACK + superpixels(c)).astype(np.uint16)), RawOptions(half_size=True)
        )
        for i, c in enumerate(cells)
    ]
    stack, levels = load_stack(paths, color=False)
    assert levels == 65535 and stack.shape == (2, 16, 16)
    assert np.allclose(stack, cells * 5 / 65535, rtol=0, atol=1e-7)


def test_pixel_limit_refused_before_decoding(tmp_path, monkeypatch):
    path = write_dng(tmp_path / "a.dng", random_mosaic(np.random.default_rng(0)))  # 60 x 40
    calls = []
    real = rawpy.imread

    class Guard:
        def __init__(self, raw):
            self.raw = raw

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.raw.close()

        @property
        def sizes(self):
            return self.raw.sizes

        def postprocess(self, **kwargs):
            calls.append(kwargs)
            return self.raw.postprocess(**kwargs)

    monkeypatch.setattr(rawpy, "imread", lambda name: Guard(real(name)))
    with pytest.raises(InputError, match=r"60 x 40 sensor pixels is more than the limit of 2399 pixels"):
        read_image(path, max_pixels=2399)
    assert calls == []  # refused from the header: nothing was decoded
    assert read_image(path, max_pixels=2400).shape == (40, 60, 3)
    assert len(calls) == 1


def test_unreadable_raw_file_names_the_file(tmp_path):
    bad = tmp_path / "broken.nef"
    bad.write_bytes(b"not a raw file at all" * 10)
    with pytest.raises(InputError, match=r"cannot read camera RAW file '.*broken\.nef'"):
        read_image(bad)
    with pytest.raises(InputError, match="file not found"):
        read_image(tmp_path / "missing.cr2")


def test_missing_rawpy_says_which_extra(tmp_path, monkeypatch):
    path = write_dng(tmp_path / "a.dng", random_mosaic(np.random.default_rng(0)))
    monkeypatch.setitem(sys.modules, "rawpy", None)  # import rawpy raises ImportError
    with pytest.raises(InputError, match=r"a\.dng'.*rawpy is not installed.*nplps\[raw\]"):
        read_image(path)


# --------------------------------------------------------------------------------------------------
# Exposure metadata
# --------------------------------------------------------------------------------------------------


def test_exposure_metadata(tmp_path):
    mosaic = random_mosaic(np.random.default_rng(0))
    path = write_dng(tmp_path / "a.dng", mosaic, shutter=(1, 125), iso=200)
    exposure = read_exposure(path)
    assert exposure.shutter == pytest.approx(1 / 125, rel=1e-6)  # LibRaw's (float32)
    assert exposure.iso == 200  # from the DNG tag: LibRaw reads ISO from an EXIF directory only
    files = [
        write_dng(tmp_path / "b.dng", mosaic, shutter=(1, 250), iso=200),
        write_dng(tmp_path / "c.dng", mosaic, shutter=(1, 125), iso=400),
    ]
    assert exposures_from_metadata([path, *files]) == pytest.approx([1.0, 0.5, 2.0], rel=1e-6)
    no_iso = [write_dng(tmp_path / f"n{i}.dng", mosaic, shutter=(1, s), iso=None) for i, s in enumerate((10, 40))]
    assert read_exposure(no_iso[0]).iso is None
    assert exposures_from_metadata(no_iso) == pytest.approx([1.0, 0.25], rel=1e-6)
    with pytest.raises(InputError, match=r"n0\.dng' gives no ISO but other images do"):
        exposures_from_metadata([path, no_iso[0]])
    no_shutter = write_dng(tmp_path / "s.dng", mosaic, shutter=None)
    with pytest.raises(InputError, match=r"s\.dng' gives no shutter time.*--exposures E1,E2"):
        exposures_from_metadata([path, no_shutter])
    png = tmp_path / "p.png"
    export.write_png16(png, np.zeros((4, 4), np.uint16))
    with pytest.raises(InputError, match=r"p\.png' is not a camera RAW file"):
        exposures_from_metadata([path, png])


# --------------------------------------------------------------------------------------------------
# Through the command line: DNG captures reconstruct like the equivalent 16-bit PNGs
# --------------------------------------------------------------------------------------------------

SIZE = 32


@pytest.fixture(scope="module")
def twin_scenes(tmp_path_factory):
    """A synthetic scene as 16-bit PNGs and as DNG mosaics whose half-size decoding equals the PNGs.

    ``nplps synth`` writes the scene; its images are rounded to multiples of 5 (value 5 q), written
    again as PNG, and as DNGs whose every 2 x 2 cell holds BLACK + q (decoded: exactly 5 q).
    """
    root = tmp_path_factory.mktemp("raw_scene")
    synth = root / "synth"
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert cli.main(["synth", "bumps", "--size", str(SIZE), "--seed", "2", "--out", str(synth)]) == 0
    command = next(line.strip() for line in buf.getvalue().splitlines() if line.strip().startswith("nplps reconstruct"))
    depth = shlex.split(command)[shlex.split(command).index("--depth") + 1]
    pngs, dngs = root / "png", root / "dng"
    pngs.mkdir()
    dngs.mkdir()
    quantized = []
    for i, name in enumerate(sorted(synth.glob("image_*.png"))):
        q = np.rint(read_image(name).astype(np.float64) / 5).astype(np.int64)  # 0 .. 13107
        quantized.append(q)
        export.write_png16(pngs / name.name, (5 * q).astype(np.uint16))
        shutter = (1, 100) if i % 3 else (1, 50)  # for --exposures auto
        write_dng(dngs / (name.stem + ".dng"), (BLACK + superpixels(q)).astype(np.uint16), shutter=shutter)
    return synth, pngs, dngs, depth, np.stack(quantized)


def _reconstruct(capsys, images, synth, depth, out, *extra):
    argv = [str(images), "--rig", str(synth / "rig.json"), "--mask", str(synth / "mask.png"), "--depth", depth]
    rc = cli.main(["reconstruct", *argv, "--out", str(out), *map(str, extra)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    return {name: np.load(out / f"{name}.npy") for name in ("depth", "normals", "residual")}, captured.err


def test_dng_capture_reconstructs_like_the_16bit_pngs(twin_scenes, tmp_path, capsys):
    synth, pngs, dngs, depth, quantized = twin_scenes
    # linearity of what the command line reads: the decoded DNG equals 5 q = 65535 q / (white - black)
    decoded = read_raw(next(iter(sorted(dngs.glob("*.dng")))), half_size=True)
    assert np.array_equal(decoded, np.repeat((5 * quantized[0])[..., None], 3, -1).astype(np.uint16))

    # The DNGs' levels are the sensor's (white - black = 13107, 14-bit), the PNGs' 65535: the default
    # thresholds are one level of each; the PNG run is given the DNG's to compare like with like.
    from_dng, err = _reconstruct(capsys, dngs, synth, depth, tmp_path / "dng", "--raw-half-size", "--gray")
    assert f"using {len(quantized)} images" in err and "image_00.dng" in err
    assert "(grey, 14-bit)" in err and f"at or below {1 / 13107:.4g} (shadow)" in err
    same = ("--dark", 1 / 13107, "--saturation", 1 - 0.5 / 13107)
    from_png, err = _reconstruct(capsys, pngs, synth, depth, tmp_path / "png", *same)
    assert "(grey, 16-bit)" in err
    # The same input up to float32 rounding: the grey of three equal channels, (v + v + v) / 3, is
    # v or 1 ulp off (6e-8; 8407 of the 27 x 32 x 32 values on this scene). Measured: depth equal
    # to 3.7e-9 relative, normals to 1.3e-7, residuals to 1e-8 (they are ~2e-5).
    stack_png, _ = load_stack(sorted(pngs.glob("*.png")))
    stack_dng, _ = load_stack([RawFile(p, RawOptions(half_size=True)) for p in sorted(dngs.glob("*.dng"))])
    assert np.max(np.abs(stack_dng - stack_png)) <= 6e-8
    assert np.allclose(from_dng["depth"], from_png["depth"], rtol=1e-7, atol=0, equal_nan=True)
    assert np.allclose(from_dng["normals"], from_png["normals"], rtol=0, atol=1e-6, equal_nan=True)
    assert np.allclose(from_dng["residual"], from_png["residual"], rtol=0, atol=1e-7, equal_nan=True)


def test_exposures_auto_from_the_dng_metadata(twin_scenes, tmp_path, capsys):
    synth, _, dngs, depth, quantized = twin_scenes
    k = len(quantized)
    by_hand = ",".join("1" if i % 3 == 0 else "0.5" for i in range(k))  # 1/100 s relative to 1/50 s
    auto, err = _reconstruct(capsys, dngs, synth, depth, tmp_path / "auto", "--raw-half-size", "--exposures", "auto")
    assert "exposures from the RAW metadata (shutter x ISO, relative to the first image): 1, 0.5, 0.5, 1" in err
    summary = json.loads((tmp_path / "auto" / "summary.json").read_text())
    steps = summary["options"]["preprocessing"]
    assert steps[0] == "camera RAW decoded linearly: half size (2 x 2 superpixels), white balance none"
    assert steps[1].startswith("exposures from the RAW metadata") and "divided by the exposures" in steps
    hand, _ = _reconstruct(capsys, dngs, synth, depth, tmp_path / "hand", "--raw-half-size", "--exposures", by_hand)
    assert np.array_equal(auto["depth"], hand["depth"], equal_nan=True)


def test_exposures_auto_refuses_png_images(twin_scenes, tmp_path, capsys):
    synth, pngs, _, depth, _ = twin_scenes
    argv = [str(pngs), "--rig", str(synth / "rig.json"), "--depth", depth, "--exposures", "auto"]
    rc = cli.main(["reconstruct", *argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc != 0
    assert "--exposures auto:" in err and "is not a camera RAW file" in err


def test_exposures_auto_is_named_where_it_is_not_taken():
    from nplps.cli.parsers import parse_exposures

    with pytest.raises(InputError, match=r"--exposures auto .* is an option of nplps reconstruct and evaluate"):
        parse_exposures("auto", 3)
    assert parse_exposures("1,0.5,2", 3).tolist() == [1.0, 0.5, 2.0]


def test_white_balance_leaves_the_normals(twin_scenes, tmp_path, capsys, angular_error):
    """Camera white balance scales each channel by a constant: the RGB albedo absorbs it, the normals stay.

    The scene at a quarter of its level (no channel clips after x 4) with as-shot neutral
    (0.5, 1, 0.25); reconstructed in colour with --raw-wb none and camera. The sensor values here
    scale exactly (x 2, x 4); measured: normals equal to 1.6e-12 degrees, depth to 6e-16.
    """
    synth, _, _, depth, quantized = twin_scenes
    folder = tmp_path / "wb"
    folder.mkdir()
    for i, q in enumerate(quantized):
        mosaic = (BLACK + superpixels(q // 4)).astype(np.uint16)
        write_dng(folder / f"image_{i:02d}.dng", mosaic, neutral=(0.5, 1.0, 0.25))
    none, _ = _reconstruct(capsys, folder, synth, depth, tmp_path / "none", "--raw-half-size")
    camera, err = _reconstruct(capsys, folder, synth, depth, tmp_path / "cam", "--raw-half-size", "--raw-wb", "camera")
    assert "(RGB, 14-bit)" in err and "white balance camera" in err
    inside = np.isfinite(none["normals"][..., 0]) & np.isfinite(camera["normals"][..., 0])
    assert inside.sum() > 0.5 * inside.size
    angles = angular_error(none["normals"], camera["normals"], inside)
    assert angles.max() < 1e-6
    assert np.allclose(camera["depth"], none["depth"], rtol=1e-9, atol=0, equal_nan=True)
