"""The input options that ``reconstruct`` and ``evaluate`` share, and reading them.

Images or a capture folder, rig, mask, depth, pre-processing, binning and the solver options.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._checks import MAX_THREADS, _memory_limit
from ..errors import InputError
from ..progress import PipelineProgress, aborting
from .console import PROG, _hint_ctrl_c, _note, describe_rig
from .imagefiles import _is_dir_input, resolve_images
from .options import NEAR_SOLVER, add_option_groups, add_options, api_options
from .parsers import _parse_list, parse_depth, parse_exposures

#: Capture folder layouts of ``--capture``: two general layouts and presets for published captures.
CAPTURE_LAYOUTS = ("near_ps", "diligent", "luces", "hehe12", "queau_human1")

#: The layouts that take only the folder (their images, sRGB decoding and grid are fixed).
_PRESETS = ("diligent", "luces", "hehe12", "queau_human1")

CONVENTIONS = (
    "Conventions: camera frame as in OpenCV (x right, y down, z forward into the scene, depth = z); "
    "the rig file gives the camera (orthographic pixel footprint, or pinhole K) and the lights in "
    "one length unit (mm typical), and depths are in that unit too."
)

INPUT_NOTES = """\
Input: IMAGES (one file per light in the rig's order, or one directory) and --rig; or a capture
folder: --capture near_ps FOLDER (camera.mat, light.mat, the images, a mask and an ambient
image found by name; the ambient image is subtracted and cos^4 vignetting compensated by
default) or --capture diligent FOLDER (a DiLiGenT object folder with filenames.txt: directional
lights, orthographic camera with 1-unit pixels) or --capture luces FOLDER (a LUCES object
folder with led_params.txt: 52 LEDs with RGB Phi and mu; no vignetting correction by default).
Presets of published near_ps captures: --capture hehe12 FOLDER (its 8 raw images, ambient and
mask) and --capture queau_human1 FOLDER (the 7 JPEG renders: sRGB decoded, grey, 2 x 2 averaged
and padded to the RAW grid of camera.mat, LED rows 0,1,2,3,5,6,7). --lights (evaluate:
--use-lights) picks rows of the rig's (or the capture's) lights for the images, in the images'
order; --grid-shape pads or crops the images to the calibration grid. The rig and the options
are checked before any image is read. A .npy --depth map must match the images after --bin.

Thresholds: by default, for integer images, observations at the top level (raw values, before
any pre-processing) are saturated and left out, and values at or below one level above black
are shadowed (0 after pre-processing, whose subtractions and scalings move the levels).
"""


def add_input_options(p: argparse.ArgumentParser, lights_flag: str = "--lights") -> None:
    """Add the options that ``reconstruct`` and ``evaluate`` share.

    Input, thresholds, pre-processing, solver (read back by :func:`build_inputs` and
    :func:`near_options`). ``lights_flag`` names the light selection (``evaluate`` uses
    ``--lights`` for the held-out lights).
    """
    p.add_argument(
        "images",
        nargs="*",
        metavar="IMAGES",
        help="one image file per light, in the rig's light order; or one directory (all its image "
        "files sorted by name, except those with 'mask' or 'ambient' in the name); with --capture: "
        "the capture folder [and, for near_ps, a glob pattern of its image files]",
    )
    p.add_argument("--rig", metavar="RIG.json", help="rig file: camera and lights (required unless --capture)")
    p.add_argument(
        "--capture",
        choices=CAPTURE_LAYOUTS,
        help="read IMAGES as one capture folder in this layout instead of image files + --rig "
        "(hehe12, queau_human1: presets of the near_ps layout for these published captures)",
    )
    p.add_argument(
        lights_flag,
        dest="select_lights",
        metavar="I,J,...",
        help="the rows of the rig's lights (with --capture: of light.mat / the capture's lights) that "
        "the images are, in the images' order, 0-based, e.g. 0,1,2,3,5,6,7 (default: all)",
    )
    p.set_defaults(lights_flag=lights_flag)
    p.add_argument(
        "--grid-shape",
        metavar="H,W",
        help="pad (zeros, at the bottom/right) or crop the images and the ambient image to H x W "
        "pixels, the calibration's grid, before any other step (the mask must be on that grid)",
    )
    add_options(p, ("--depth", "--depth-range", "--depth-prior", "--prior-weight"))
    p.add_argument(
        "--mask",
        metavar="M",
        help="mask image, non-zero = reconstruct (default: every pixel, or the capture's mask)",
    )

    add_option_groups(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


class Inputs(NamedTuple):
    """What :func:`build_inputs` makes of the input options."""

    #: Pre-processed float32 images (k, H, W) or (k, H, W, 3).
    images: np.ndarray
    #: The rig (camera adjusted to --bin).
    rig: Any
    #: (H, W) bool mask, or None for every pixel.
    mask: np.ndarray | None
    #: (k, H, W) bool, False where an observation is saturated; None if none is.
    valid: np.ndarray | None
    #: Keyword arguments for reconstruct, reconstruct_parallel and held_out: depth, dark, robust, threads.
    options: dict[str, Any]
    #: The files read (images, rig, mask, ambient image): a result written beside them never removes them.
    sources: tuple[str, ...] = ()
    #: The pre-processing steps applied, in the words the command line prints (recorded in summary.json).
    steps: tuple[str, ...] = ()


class _Source(NamedTuple):
    """Where the images come from, before anything is read.

    Image files, rig, mask, ambient image, K for cos^4 and the default vignetting correction.
    """

    files: list[str]
    rig: Any
    mask: Any
    ambient: Any
    K: np.ndarray | None
    vignetting: str
    #: For a capture loaded by its loader (queau_human1): reads it, returning a loaded Capture.
    load: Callable[[Any], Any] | None = None


#: The pipeline's parameter names at the start of its messages, in the command line's words.
_OPTION_WORDS = (
    ("bin_factor ", "--bin "),
    ("vignetting 'cos4'", "--vignetting cos4"),
    ("vignetting and flat", "--vignetting and --flat"),
    ("ambient ", "--ambient "),
    ("flat ", "--flat "),
    ("exposures", "--exposures"),
)


def build_inputs(args: argparse.Namespace) -> Inputs:
    """Read and pre-process the input that :func:`add_input_options` describes.

    This runs :func:`nplps.pipeline.prepare`.
    """
    check_input_args(args)
    depth = parse_depth(args.depth)
    source = _capture_source(args) if args.capture else _file_source(args)
    exposures = _exposures(args, source)
    vignetting = args.vignetting or source.vignetting
    _check_rig_options(args, source, depth, vignetting)  # before any image is read
    _hint_ctrl_c(args)  # the long work starts here
    display = None if args.quiet else PipelineProgress()
    with aborting(display):
        prepared, by_loader = _read_and_prepare(args, source, exposures, vignetting, display)
    if display is not None:
        display.finish()
    # The first steps are the capture loader's (e.g. queau_human1's 2 x 2 binning), the rest the pipeline's.
    steps = [
        _step_text(step, args, source, prepared.images, by_loader=i < len(by_loader))
        for i, step in enumerate(prepared.steps)
    ]
    steps = _raw_steps(args, source, exposures) + steps
    if not args.quiet:
        _note_inputs(prepared.images, prepared.rig, prepared.valid, steps, prepared.dark, prepared.levels)
    options = {"depth": depth, "dark": prepared.dark, **api_options(args, ("--robust", "--threads", "--max-memory"))}
    side = (source.mask, source.ambient, getattr(args, "rig", None))
    sources = [*source.files, *(os.fspath(f) for f in side if isinstance(f, (str, os.PathLike)))]
    return Inputs(prepared.images, prepared.rig, prepared.mask, prepared.valid, options, tuple(sources), tuple(steps))


def _exposures(args: argparse.Namespace, source: _Source) -> np.ndarray | None:
    """Return the ``--exposures`` values: the numbers given, or ``auto``: from the RAW files' metadata."""
    if not args.exposures:
        return None
    if args.exposures.strip().lower() != "auto":
        return parse_exposures(args.exposures, len(source.files))
    from ..raw import exposures_from_metadata

    try:
        return exposures_from_metadata(source.files)  # listed with the pre-processing steps
    except InputError as exc:
        raise InputError(f"--exposures auto: {str(exc).removeprefix('exposures from metadata: ')}") from None


def _raw_steps(args: argparse.Namespace, source: _Source, exposures: np.ndarray | None) -> list[str]:
    """Say how camera RAW images were decoded and which exposures their metadata gave (for the summary)."""
    from ..raw import is_raw

    if source.load is not None or not any(is_raw(f) for f in source.files):
        return []
    options = _raw_options(args)
    size = "half size (2 x 2 superpixels)" if options.half_size else "demosaiced at full size"
    steps = [f"camera RAW decoded linearly: {size}, white balance {options.white_balance}"]
    if exposures is not None and args.exposures.strip().lower() == "auto":
        steps.append(
            f"exposures from the RAW metadata (shutter x ISO, relative to the first image): {_listed(exposures)}"
        )
    return steps


def _listed(values: np.ndarray) -> str:
    """``1, 0.5, 2``: the values, shortly."""
    return ", ".join(f"{v:.4g}" for v in values)


def _raw_options(args: argparse.Namespace) -> Any:
    """Return the :class:`nplps.raw.RawOptions` of ``--raw-wb`` and ``--raw-half-size``."""
    from ..raw import RawOptions

    return RawOptions(
        white_balance=getattr(args, "raw_wb", None) or "none", half_size=bool(getattr(args, "raw_half_size", False))
    )


def _with_raw_options(args: argparse.Namespace, path: Any) -> Any:
    """Return ``path`` as a :class:`nplps.raw.RawFile` with the RAW options if it is a RAW file, else as it is."""
    from ..raw import RawFile, is_raw

    if isinstance(path, (str, os.PathLike)) and is_raw(path):
        return RawFile(path, _raw_options(args))
    return path


def _read_and_prepare(
    args: argparse.Namespace, source: _Source, exposures: Any, vignetting: str, display: PipelineProgress | None
) -> tuple[Any, tuple[str, ...]]:
    """Read the images and run :func:`nplps.pipeline.prepare`, reporting to ``display``.

    Return the prepared inputs and the steps a capture loader ran before the pipeline.
    """
    from .. import pipeline

    images, levels, preprocessed, ambient = _read_images(args, source, display)
    rig = source.rig
    if args.grid_shape is not None and getattr(rig, "grid", None) is not None:
        # Padding or cropping at the bottom and right keeps K: the images are on the grid asked for.
        height, width = parse_grid_shape(args.grid_shape)
        rig = rig.with_grid(width, height)
    try:
        prepared = pipeline.prepare(
            images,
            rig=rig,
            K=source.K,
            mask=source.mask,
            color=False if args.gray else None,
            levels=levels,
            preprocessed=preprocessed,
            saturation=args.saturation,
            dark=args.dark,
            srgb=args.srgb,
            ambient=ambient,
            exposures=exposures,
            vignetting="cos4" if vignetting == "cos4" and not args.flat else None,
            flat=_with_raw_options(args, args.flat),
            bin_factor=args.bin,
            overwrite=True,
            progress=display,
            uint16=True,
        )
    except InputError as exc:
        raise _in_option_words(exc) from None
    return prepared, tuple(preprocessed)


def _check_rig_options(args: argparse.Namespace, source: _Source, depth: Any, vignetting: str) -> None:
    """Check what the rig and the options decide before any image is read."""
    rig = source.rig
    if isinstance(depth, str):  # "auto"
        if not np.any(~np.asarray(rig.directional)):
            raise InputError(
                "--depth auto: the working distance cannot be estimated with directional lights only "
                "(they light every distance alike): give --depth D"
            )
        if rig.n_lights <= 3:
            raise InputError(
                f"--depth auto: the working distance cannot be estimated from {rig.n_lights} lights "
                "(with 3 lights every distance fits the images exactly): use at least 4 lights or give --depth D"
            )
    if vignetting == "cos4" and not args.flat and source.K is None:
        raise InputError(
            "--vignetting cos4 needs a pinhole camera (K), but the camera is orthographic: "
            "use a flat field or no vignetting correction"
        )


def _read_images(
    args: argparse.Namespace, source: _Source, display: PipelineProgress | None = None
) -> tuple[Any, int | None, tuple[str, ...], Any]:
    """Return the images (file names or a stack), their levels, the steps already run and the ambient image.

    A capture with a loader is read by it; with --grid-shape the images and the ambient image are
    read and padded or cropped to the grid here.
    """
    from .. import pipeline, preprocess
    from ..io import read_image, to_float

    if source.load is not None:
        capture = source.load(None if display is None else (lambda i, k, name: display("load", i, k, name)))
        return capture.images, capture.levels, tuple(capture.preprocessed), capture.ambient
    files = [_with_raw_options(args, os.fspath(f)) for f in source.files]
    sensor = _sensor_levels(files)
    if args.grid_shape is None:
        return files, sensor, (), _with_raw_options(args, source.ambient)
    grid = parse_grid_shape(args.grid_shape)
    try:
        loaded = None if display is None else (lambda i, k, name: display("load", i, k, name))
        stack, levels = pipeline.load_images(files, progress=loaded)
    except InputError as exc:
        raise _in_option_words(exc) from None
    stack = preprocess.pad_or_crop(stack, grid)
    ambient = source.ambient
    if ambient is not None:
        image = (
            np.asarray(ambient)
            if isinstance(ambient, np.ndarray)
            else to_float(read_image(_with_raw_options(args, ambient)))
        )
        ambient = preprocess.pad_or_crop(image, grid, stack=False)
    return stack, sensor or levels, (), ambient


def _sensor_levels(files: list[Any]) -> int | None:
    """Return the levels of camera RAW images: the largest white - black of their sensors (None unless all are RAW).

    Decoded RAW images are 16-bit, but their levels are the sensor's: the default thresholds
    (shadows one level above black, saturation at the top level) are then one sensor level.
    """
    from ..raw import stack_levels

    return stack_levels(files)


def _in_option_words(exc: InputError) -> InputError:
    """Return the pipeline's error with its parameter name replaced by the command-line option."""
    text = str(exc)
    for word, option in _OPTION_WORDS:
        if text.startswith(word):
            return InputError(option + text[len(word) :])
    return exc


def _step_text(
    step: str, args: argparse.Namespace, source: _Source, images: np.ndarray, *, by_loader: bool = False
) -> str:
    """How the summary names a pre-processing step (``by_loader``: one the capture's loader ran)."""
    if by_loader and step in ("bin", "pad"):
        return {"bin": "binned by the capture preset", "pad": "padded to the calibration grid"}[step]
    if step == "ambient":
        return f"ambient '{args.ambient or Path(source.ambient).name}' subtracted"
    if step == "bin":
        return f"binned {args.bin} x {args.bin} to {images.shape[2]} x {images.shape[1]} pixels"
    if step == "flat":
        return f"divided by the flat field '{args.flat}'"
    texts = {
        "srgb": "sRGB decoded",
        "exposures": "divided by the exposures",
        "vignetting": "divided by the cos^4 vignetting map",
    }
    return texts.get(step, step)


def near_options(args: argparse.Namespace) -> dict[str, Any]:
    """Return the options of the near-light solver only (not of the parallel-light baseline)."""
    options: dict[str, Any] = api_options(args, NEAR_SOLVER)
    if args.depth_range is not None:
        near_far = _parse_list(args.depth_range, float, "--depth-range", "NEAR,FAR, e.g. 150,400")
        if len(near_far) != 2:
            raise InputError(f"--depth-range needs two numbers NEAR,FAR, got {args.depth_range}")
        if str(getattr(args, "depth", "")).strip().lower() == "auto":
            options["depth_range"] = tuple(near_far)
        # else: ignored, as the warning below says (a reversed range must not fail the run then)
    if args.depth_prior is not None:
        options["depth_prior"] = parse_depth(args.depth_prior, "--depth-prior")
        options["prior_weight"] = 1.0 if args.prior_weight is None else args.prior_weight
    for given, needed in _no_effect(args):
        _note(f"{PROG}: warning: {given} has no effect without {needed}; it is ignored")
    return options


def _no_effect(args: argparse.Namespace) -> list[tuple[str, str]]:
    """Return the options given that do nothing with the others given: ``(option, what it needs)``."""
    found = []
    if getattr(args, "light_prior_weight", None) is not None and getattr(args, "refine_lights", None) not in (
        "position",
        "both",
    ):
        found.append(("--light-prior-weight", "--refine-lights position or both"))
    # (1.0 is the default: nplps batch sets it without a --prior-weight option)
    if getattr(args, "prior_weight", None) not in (None, 1.0) and getattr(args, "depth_prior", None) is None:
        found.append(("--prior-weight", "--depth-prior"))
    if getattr(args, "depth_range", None) is not None and str(getattr(args, "depth", "")).strip().lower() != "auto":
        found.append(("--depth-range", "--depth auto"))
    return found


def _estimated(result: Any, options: dict[str, Any]) -> dict[str, Any]:
    """Return the options with ``depth="auto"`` replaced by the depth map that ``result`` estimated."""
    if not isinstance(options.get("depth"), str):
        return options
    return dict(options, depth=result.depth)


def check_input_args(args: argparse.Namespace) -> None:
    """Check the input options before anything is read.

    It checks numbers, which options go together, and that the named side files exist.
    """
    _check_numbers(args)
    if args.select_lights is not None:
        parse_light_rows(args.select_lights, args.lights_flag)
    if args.grid_shape is not None:
        parse_grid_shape(args.grid_shape)
    if args.capture:
        given = [f"--{name}" for name in ("rig", "ambient", "exposures") if getattr(args, name)]
        given += ["--srgb"] if args.srgb and args.capture != "near_ps" else []
        given += ["--grid-shape"] if args.grid_shape and args.capture == "queau_human1" else []
        if given:
            raise InputError(
                f"--capture {args.capture} takes the rig, the ambient image and its decoding from the folder: "
                f"{', '.join(given)} cannot be combined with it"
            )
    elif not args.images:
        raise InputError("no input: give IMAGES (image files or one directory) and --rig, or --capture LAYOUT FOLDER")
    elif args.rig is None:
        raise InputError("--rig is required with IMAGES (or read a capture folder with --capture LAYOUT FOLDER)")
    for option in ("mask", "ambient", "flat"):
        path = getattr(args, option)
        if path is not None and not os.path.isfile(path):
            raise InputError(f"--{option} file '{path}' not found")


def _check_numbers(args: argparse.Namespace) -> None:
    if args.iterations < 1:
        raise InputError(f"--iterations must be at least 1, got {args.iterations}")
    if getattr(args, "levels", None) is not None and args.levels < 1:
        raise InputError(f"--levels must be at least 1, got {args.levels}")
    if getattr(args, "max_memory", None) is not None:
        args.max_memory = _memory_limit(args.max_memory, "--max-memory")
    if args.threads is not None and not 1 <= args.threads <= MAX_THREADS:
        raise InputError(f"--threads must be from 1 to {MAX_THREADS}, got {args.threads}")
    if not np.isfinite(args.tol) or args.tol < 0:
        raise InputError(f"--tol must be a non-negative number, got {args.tol}")
    if args.bin < 1:
        raise InputError(f"--bin must be a positive integer (the block size in pixels), got {args.bin}")
    if args.dark is not None and not np.isfinite(args.dark):
        raise InputError(f"--dark must be a finite number, got {args.dark}")
    if args.saturation is not None and not (np.isfinite(args.saturation) and args.saturation > 0):
        raise InputError(f"--saturation must be a positive number (0..1 scale), got {args.saturation}")
    _check_reflectance(args)


def _check_reflectance(args: argparse.Namespace) -> None:
    """Check --reflectance, --roughness and --eta: the lobe is glossy's, given whole or not at all."""
    roughness, eta = getattr(args, "roughness", None), getattr(args, "eta", None)
    given = [flag for flag, value in (("--roughness", roughness), ("--eta", eta)) if value is not None]
    if not given:
        return
    if getattr(args, "reflectance", None) != "glossy":
        raise InputError(
            f"{' and '.join(given)} {'is an option' if len(given) == 1 else 'are options'} of the glossy model: "
            "add --reflectance glossy (the lambertian model has no specular lobe)"
        )
    if len(given) == 1:
        missing = "--eta" if given[0] == "--roughness" else "--roughness"
        raise InputError(
            f"{given[0]} needs {missing} too: give both (a fixed lobe) or neither (the lobe is then "
            "estimated from the images)"
        )
    assert roughness is not None and eta is not None  # both given (checked above)
    if not (np.isfinite(roughness) and 0 < roughness <= 1):
        raise InputError(f"--roughness (the GGX alpha) must be a number in (0, 1], got {roughness}")
    if not (np.isfinite(eta) and 1 <= eta <= 3):
        raise InputError(f"--eta (the relative index of refraction) must be a number from 1 to 3, got {eta}")


def parse_light_rows(text: str, flag: str = "--lights", k: int | None = None) -> list[int]:
    """Parse the light selection ``I,J,...``: distinct 0-based rows (below ``k`` if given)."""
    expected = "comma-separated 0-based light indices, e.g. 0,1,2,3,5,6,7"
    try:
        rows = [int(part) for part in text.split(",")]
    except ValueError:
        raise InputError(f"{flag} must be {expected}, got '{text}'") from None
    negative = [i for i in rows if i < 0]
    if negative:
        raise InputError(f"{flag}: {negative[0]} is negative; give {expected}")
    twice = sorted({i for i in rows if rows.count(i) > 1})
    if twice:
        raise InputError(f"{flag}: light {twice[0]} is given twice; each light can be one image only")
    if k is not None and max(rows) >= k:
        raise InputError(f"{flag}: {max(rows)} is not a light of the rig (0 .. {k - 1})")
    return rows


def parse_grid_shape(text: str) -> tuple[int, int]:
    """Parse ``--grid-shape H,W``: two positive whole numbers."""
    try:
        h, w = (int(part) for part in text.split(","))
    except ValueError:
        raise InputError(
            f"--grid-shape must be two whole numbers H,W (rows, columns), e.g. 1732,2601; got '{text}'"
        ) from None
    if h < 1 or w < 1:
        raise InputError(f"--grid-shape must be positive numbers of rows and columns, got {text}")
    return h, w


def _file_source(args: argparse.Namespace) -> _Source:
    """IMAGES + --rig: the image files, the rig (its --lights rows), --mask and --ambient."""
    rig = load_rig(args.rig)
    if args.select_lights is not None:
        rig = rig.subset(parse_light_rows(args.select_lights, args.lights_flag, rig.n_lights))
    exclude = [f for f in (args.ambient, args.flat) if f]
    files = resolve_images(args.images, args.mask, quiet=args.quiet, exclude=exclude, ambient=args.ambient)
    if len(files) != rig.n_lights:
        source = f"found in '{args.images[0]}'" if _is_dir_input(args.images) else "given"
        lights = (
            f"{rig.n_lights} lights selected by {args.lights_flag}" if args.select_lights else f"{rig.n_lights} lights"
        )
        raise InputError(
            f"{len(files)} images {source} but the rig file '{args.rig}' has {lights}: "
            "there must be exactly one image per light, in the rig's light order"
        )
    return _Source(list(files), rig, args.mask, args.ambient, rig.K, "none")


def _capture_source(args: argparse.Namespace) -> _Source:
    """Return the sources of ``--capture LAYOUT FOLDER [PATTERN]``.

    The capture's image files, rig, mask (or --mask) and ambient image; cos^4 vignetting by default
    when the capture has K. Only calibration files (and the mask) are read here.
    """
    capture = _read_capture(args)
    mask = capture.mask if args.mask is None else args.mask
    # LUCES's own code does not correct vignetting (docs/luces.md); --vignetting cos4 asks for it.
    vignetting = "cos4" if capture.K is not None and args.capture != "luces" else "none"
    load = None
    if args.capture == "queau_human1":
        load = _queau_loader(args, capture)
    return _Source(
        [os.fspath(f) for f in capture.files], capture.rig(), mask, capture.ambient, capture.K, vignetting, load
    )


def _read_capture(args: argparse.Namespace) -> Any:
    from .. import captures

    items = args.images
    if not 1 <= len(items) <= (1 if args.capture in _PRESETS else 2) or not os.path.isdir(items[0]):
        what = "the object folder" if args.capture == "diligent" else "the capture folder"
        if args.capture == "near_ps":
            what = "the capture folder and optionally a glob pattern of its images"
        raise InputError(f"--capture {args.capture} takes {what}, got {' '.join(items) or 'nothing'}")
    rows = None if args.select_lights is None else parse_light_rows(args.select_lights, args.lights_flag)
    try:
        if args.capture == "diligent":
            capture = captures.load_diligent(items[0], normals=False, lights=rows)
        elif args.capture == "luces":
            capture = captures.load_luces(items[0], normals=False, depth=False, lights=rows)
        elif args.capture in ("hehe12", "queau_human1"):
            capture = _led_capture(args.capture, items[0], rows)
        else:
            try:
                capture = captures.load_near_ps(items[0], items[1] if len(items) > 1 else None, lights=rows)
            except InputError as e:
                if "lights selected" not in str(e):
                    raise
                head = str(e).split(": pass images=")[0]
                hint = "give a glob pattern of the image files after the folder, e.g. 'img_[0-9]*.png'"
                if rows is not None:
                    hint = f"give a glob pattern of the image files after the folder or fix {args.lights_flag}"
                raise InputError(f"{head}: {hint}") from None
    except InputError as e:
        if str(e).startswith("lights: "):  # an index the loader's light file does not have
            raise InputError(f"{args.lights_flag}: {str(e)[len('lights: ') :]}") from None
        raise
    if not args.quiet:
        _note(f"capture '{capture.name}' ({args.capture}): {capture.num_images} images")
        distance = getattr(capture, "mean_distance", None)
        if distance is not None:
            _note(f"its mean distance is {distance:.6g} mm ({captures.luces.LED_PARAMS}): a --depth to start from")
    return capture


#: The image files of the near_ps presets (the LED row of each is the number in its name, minus 1).
_LED_IMAGES = {"hehe12": "photometric_sample_raw_[0-9]*.png", "queau_human1": "photometric_sample_jpg_[0-9]*.png"}


def _led_capture(layout: str, folder: str, rows: list[int] | None) -> Any:
    """Describe a near_ps preset capture (files, calibration, mask, ambient) without reading its images.

    ``rows``: the LED rows to use (default: every image of the folder); each image's LED row is
    the number in its file name, minus 1.
    """
    from .. import captures
    from ..captures.near_ps import _led_rows_from_names

    if layout == "hehe12":
        capture = captures.load_hehe12(folder)
    else:  # the files and calibration as load_queau_human1 reads them; the images come later
        files = captures.find_images(folder, _LED_IMAGES[layout])
        capture = captures.load_near_ps(
            folder,
            files,
            lights=_led_rows_from_names(files),
            mask="photometric_sample_mask_raw.png",
            ambient="photometric_sample_jpg_ambient.png",
            color=None,
            name=layout,
        )
        if capture.intensities is not None and capture.intensities.ndim == 2:
            capture.intensities = capture.intensities.mean(axis=1)  # as loaded: grey, Phi averaged
    if rows is None:
        return capture
    available = _led_rows_from_names(capture.files)
    missing = [i for i in rows if i not in available]
    if missing:
        raise InputError(
            f"--capture {layout}: no image of LED row(s) {missing} in '{folder}' (available rows: {sorted(available)})"
        )
    return capture.select([available.index(i) for i in rows])


def _queau_loader(args: argparse.Namespace, capture: Any) -> Callable[[Any], Any]:
    """Return the reader of --capture queau_human1: :func:`nplps.captures.load_queau_human1`.

    The reader takes the load progress callback (or None).
    """
    from .. import captures
    from ..captures.near_ps import _led_rows_from_names

    rows = _led_rows_from_names(capture.files)

    def load(progress: Any) -> Any:
        return captures.load_queau_human1(args.images[0], lights=rows, progress=progress)

    return load


def load_rig(path: str) -> Any:
    """Read the rig file; every failure becomes a :class:`~nplps.RigError` naming the file."""
    from ..errors import RigError
    from ..rig import Rig

    if os.path.isdir(path):
        raise RigError(f"rig file '{path}' is a directory")
    return Rig.load(path)


def _note_inputs(
    images: np.ndarray, rig: Any, valid: np.ndarray | None, steps: list[str], dark: float, levels: int | None
) -> None:
    k, h, w = images.shape[:3]
    depth = f", {levels.bit_length()}-bit" if levels else ""
    colour = "RGB" if images.ndim == 4 else "grey"
    _note(f"{k} images of {w} x {h} pixels ({colour}{depth}); rig: {describe_rig(rig)}")
    if steps:
        _note(f"pre-processing: {', '.join(steps)}")
    saturated = 0 if valid is None else int(np.count_nonzero(~valid))
    _note(f"left out: observations at or below {dark:.4g} (shadow), {saturated} saturated")
