"""The solver, input and output options of the command line, declared once.

:data:`OPTIONS` holds each option's flag, type, default, help and the keyword of the Python API
it becomes; ``nplps reconstruct`` and ``nplps evaluate`` (:func:`nplps.cli.inputs.add_input_options`)
and ``nplps batch`` (:mod:`nplps.cli.batch`) add them from here (:func:`add_options`) and read
them back by their API keywords (:func:`api_options`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, get_args

from .. import types
from .._checks import MAX_THREADS


@dataclass(frozen=True)
class Option:
    """One command-line option and the API keyword it becomes."""

    #: The flags, the first one naming the attribute of the parsed arguments.
    flags: tuple[str, ...]
    #: The keyword of :func:`nplps.reconstruct`, :func:`nplps.pipeline.prepare` or
    #: :func:`nplps.batch.run` that the option's value is passed as.
    keyword: str
    #: The help text (or a function making it when the parser is made).
    help: str | Callable[[], str]
    type: Callable[[str], Any] | None = None
    default: Any = None
    metavar: str | None = None
    choices: tuple[Any, ...] | None = None
    #: A flag without a value (``store_true``).
    switch: bool = False
    #: ``"?"``: the value may be left out, and then it is `const`.
    nargs: str | None = None
    const: Any = None
    required: bool = False
    #: Options of one name here are mutually exclusive (added next to each other).
    exclusive: str | None = None
    #: The help of ``nplps batch`` where the option means more there (default: `help`).
    batch_help: str | None = None
    #: The option's value -> the API's value (default: as parsed).
    to_api: Callable[[Any], Any] | None = None

    @property
    def dest(self) -> str:
        """The attribute of the parsed arguments."""
        return self.flags[0].lstrip("-").replace("-", "_")


_OPTIONS = (
    Option(
        ("--depth",),
        "depth",
        "working distance (the object's mean depth, in the rig's unit), a .npy file "
        "with an (H+1, W+1) initial vertex depth map (NaN allowed outside the mask), or 'auto' to "
        "estimate it from the images (needs 4+ lights, some of them point lights)",
        required=True,
        metavar="D",
    ),
    Option(
        ("--depth-range",),
        "depth_range",
        "with --depth auto: where to search (default: derived from the light positions)",
        metavar="NEAR,FAR",
    ),
    Option(
        ("--depth-prior",),
        "depth_prior",
        "(H+1, W+1) prior depth map (e.g. from a coarse scan; NaN where unknown) fused in the global step",
        metavar="PRIOR.npy",
    ),
    Option(
        ("--prior-weight",),
        "prior_weight",
        "weight of --depth-prior relative to the facet terms (default 1)",
        type=float,
        metavar="W",
    ),
    # shadows, saturation, colour
    Option(
        ("--dark",),
        "dark",
        "values (0..1 scale, after pre-processing) at or below X count as shadowed and are "
        "left out (default: one level above black for integer images, 0 after pre-processing)",
        type=float,
        metavar="X",
    ),
    Option(
        ("--saturation",),
        "saturation",
        "raw values (0..1 scale, before pre-processing; any channel) at or above X count as "
        "saturated and are left out (default: the top level of integer images, none for float)",
        type=float,
        metavar="X",
    ),
    Option(
        ("--robust",),
        "robust",
        "reweight each pixel's fit so that highlights and cast shadows do not bend the normals",
        choices=get_args(types.Robust),
    ),
    Option(
        ("--shadows",),
        "shadows",
        "cast shadows predicted from the current mesh, whose hidden observations are left out of "
        "the fits (steps, pockets, deep relief): auto (default) marches every pixel to every "
        "light only where a probe of about 1024 pixels finds 0.5 %% or more of its observations "
        "hidden; on (or --shadows alone) always marches (a march per pixel and light at a few "
        "iterations: about 2x the time at 256 x 256, more at camera resolution); off never",
        choices=("auto", "on", "off"),
        nargs="?",
        const="on",
        metavar="{auto,on,off}",
        to_api=lambda value: {"on": True, "off": False}.get(value, "auto"),
    ),
    Option(
        ("--interreflections",),
        "interreflections",
        "model the light the surface sends to itself (concave objects: bowls, grooves, folds): "
        "after convergence, gather each pixel's indirect light from the images over the mesh and "
        "iterate again (for real captures only: direct-only renders get worse; 2-6x the time; "
        "with --reflectance glossy the modelled diffuse part emits)",
        switch=True,
        to_api=bool,
    ),
    # reflectance
    Option(
        ("--reflectance",),
        "reflectance",
        "the image model of each pixel's fit: lambertian (default; matte surfaces) or glossy: a "
        "diffuse part with Fresnel transmittance plus a GGX specular lobe (Smith masking, Fresnel "
        "shape; grey specular albedo, the light's colour), for plastics, glazes, coated or polished "
        "parts. The lobe (--roughness, --eta) is shared by the whole object: one material; "
        "highlights must not be saturated (saturated values are left out). Writes specular.npy "
        "and specular.png (the specular albedo); albedo.png is then the diffuse albedo. Several "
        "times slower than lambertian",
        choices=get_args(types.Reflectance),
    ),
    Option(
        ("--roughness",),
        "roughness",
        "with --reflectance glossy and --eta: the lobe's GGX roughness alpha, 0 < A <= 1 (about 0.05 "
        "polished, 0.3 satin, 0.6 rough; default: estimated from the images)",
        type=float,
        metavar="A",
    ),
    Option(
        ("--eta",),
        "eta",
        "with --reflectance glossy and --roughness: the relative index of refraction of the surface "
        "layer, 1 <= E <= 3 (1.5 for most plastics; default: estimated from the images)",
        type=float,
        metavar="E",
    ),
    Option(
        ("--gray", "--grey"),
        "color",
        "average RGB images to grey (default: keep colour)",
        switch=True,
        to_api=lambda gray: False if gray else None,
    ),
    # pre-processing
    Option(
        ("--srgb",),
        "srgb",
        "decode sRGB to linear (camera JPEGs); also --ambient/--flat",
        switch=True,
        batch_help="decode sRGB to linear (camera JPEGs); also the ambient image and --flat",
    ),
    Option(("--ambient",), "ambient", "subtract this image taken with every light off (clip at 0)", metavar="FILE"),
    Option(
        ("--exposures",),
        "exposures",
        "divide image i by Ei (exposure times, gains); auto: shutter time x ISO from camera RAW files, "
        "relative to the first image",
        metavar="E1,E2,...",
        batch_help="divide image i of every capture by Ei (exposure times, gains); auto: each capture's "
        "shutter time x ISO from its camera RAW files, relative to its first image",
    ),
    # camera RAW files
    Option(
        ("--raw-wb",),
        "white_balance",
        "white balance of camera RAW files (.dng .cr2 .nef .arw ...): none (the sensor's response, default) "
        "or camera (the as-shot multipliers); RAW files are always decoded linearly, black level subtracted",
        choices=("none", "camera"),
        default="none",
    ),
    Option(
        ("--raw-half-size",),
        "half_size",
        "decode camera RAW files at half size: each 2 x 2 colour filter cell becomes one pixel (no "
        "interpolation, exactly linear); the rig must then be the sensor's rig binned 2 x 2",
        switch=True,
    ),
    Option(
        ("--vignetting",),
        "vignetting",
        "cos4: divide by the cos^4 fall-off map of the pinhole K (default: none; cos4 for --capture near_ps)",
        choices=("cos4", "none"),
        exclusive="vignetting",
        batch_help="cos4: divide by the cos^4 fall-off map of the pinhole K (default: none)",
        to_api=lambda v: "cos4" if v == "cos4" else None,
    ),
    Option(
        ("--flat",),
        "flat",
        "divide by this flat-field image, normalized to maximum 1",
        metavar="FILE",
        exclusive="vignetting",
    ),
    Option(
        ("--bin",),
        "bin_factor",
        "average N x N pixel blocks (mask: whole blocks only; K or the pixel size adjusted)",
        type=int,
        default=1,
        metavar="N",
    ),
    # solver
    Option(
        ("--iterations",),
        "iterations",
        "maximum iterations (default 10)",
        type=int,
        default=10,
        metavar="N",
    ),
    Option(
        ("--tol",),
        "tol",
        "stop when the largest depth change is at most tol x the image footprint (default 1e-6)",
        type=float,
        default=1e-6,
    ),
    Option(
        ("--solver",),
        "solver",
        "global step: sparse Cholesky (direct), multigrid-preconditioned conjugate gradients "
        "(multigrid: linear time and memory) or direct up to ~200 x 200 pixels, multigrid above (auto)",
        choices=get_args(types.Solver),
        default="auto",
    ),
    Option(
        ("--levels",),
        "levels",
        "coarse-to-fine pyramid levels (1: full resolution only; default: halve while the "
        "longer side keeps at least 128 pixels); --iterations and --tol apply per level",
        type=int,
        metavar="N",
    ),
    Option(
        ("--weighting",),
        "weighting",
        "local fit: least squares in image units (image, default) or the paper's Eq. 6 (paper)",
        choices=get_args(types.Weighting),
        default="image",
    ),
    Option(
        ("--threads",),
        "threads",
        f"worker threads, 1 to {MAX_THREADS} (default: all cores)",
        type=int,
        metavar="N",
        batch_help=f"threads per reconstruction, 1 to {MAX_THREADS} (default: cores / workers locally)",
    ),
    Option(
        ("--max-memory",),
        "max_memory",
        'refuse a reconstruction whose estimated peak memory is above SIZE (bytes, or e.g. "8GB", '
        '"512MiB"; default 80%% of the memory available)',
        metavar="SIZE",
    ),
    # light self-calibration
    Option(
        ("--refine-lights",),
        "refine_lights",
        "refine the lights from the images: each light's intensity (their geometric mean stays "
        "the rig's), each point light's position (held toward the rig's), or both; the refined rig is "
        "written to rig_refined.json",
        choices=get_args(types.RefineLights),
    ),
    Option(
        ("--light-prior-weight",),
        "light_prior_weight",
        "weight of the prior toward the rig's light positions: a standard deviation of D/sqrt(W) "
        "per coordinate, D the working distance (default 1000, about 3%% of D)",
        type=float,
        metavar="W",
    ),
    # output (what nplps reconstruct and nplps batch write: see OUTPUT)
    Option(
        ("--opengl",),
        "opengl",
        "write meshes in the OpenGL frame (x right, y up, z towards the viewer)",
        switch=True,
    ),
    Option(
        ("--formats",),
        "formats",
        lambda: f"also write these formats, comma-separated: {_formats_help()}",
        type=lambda text: _parse_formats(text),
        default=[],
        metavar="LIST",
    ),
    Option(
        ("--normal-map",),
        "normal_map",
        "convention of normals.png and normals.exr: opengl = x right, y up, z towards the viewer "
        "(Blender, Unity; the default), directx = y down (Unreal Engine), opencv = the camera frame "
        "as is (y down, z forward); recorded in summary.json",
        choices=("opengl", "directx", "opencv"),
        default="opengl",
    ),
    Option(
        ("--normal-map-bits",),
        "normal_map_bits",
        "bits per channel of normals.png (default 16: 0.0015° at most of quantisation, 8: 0.39°)",
        type=int,
        choices=(16, 8),
        default=16,
    ),
    Option(
        ("--exr",),
        "formats",
        "also write depth.exr, normals.exr and albedo.exr (32-bit float; the same as --formats exr; "
        'needs OpenEXR: pip install "nplps[exr]")',
        switch=True,
        batch_help="also write depth.exr, normals.exr and albedo.exr for every capture (32-bit float; "
        'needs OpenEXR: pip install "nplps[exr]")',
        to_api=lambda exr: ["exr"] if exr else [],
    ),
    Option(
        ("--obj",),
        "formats",
        "write mesh.obj whatever the size (by default only up to 4 million masked pixels: a 12 MP "
        "result's OBJ file is 2.4 GB of text; the same as --formats obj)",
        switch=True,
        to_api=lambda obj: ["obj"] if obj else [],
    ),
    Option(
        ("--units",),
        "units",
        "the rig's length unit (e.g. mm), recorded in summary.json and shown with the scale bars "
        "of the report and the viewer (default: 'rig units')",
        metavar="UNIT",
    ),
)

#: The options by their first flag.
OPTIONS: dict[str, Option] = {o.flags[0]: o for o in _OPTIONS}

#: The option groups of ``nplps reconstruct`` and ``nplps evaluate``, in their order.
GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "shadows, saturation, colour",
        (
            "--dark",
            "--saturation",
            "--robust",
            "--shadows",
            "--interreflections",
            "--gray",
        ),
    ),
    ("reflectance", ("--reflectance", "--roughness", "--eta")),
    ("camera RAW files", ("--raw-wb", "--raw-half-size")),
    (
        "pre-processing (applied in this order)",
        ("--srgb", "--ambient", "--exposures", "--vignetting", "--flat", "--bin"),
    ),
    ("solver", ("--iterations", "--tol", "--solver", "--levels", "--weighting", "--threads", "--max-memory")),
    ("light self-calibration", ("--refine-lights", "--light-prior-weight")),
)

#: The options of what a result directory holds (:meth:`nplps.Reconstruction.save`'s ``opengl``,
#: ``formats``, ``normal_map``, ``normal_map_bits`` and ``units``), of ``nplps reconstruct`` and
#: ``nplps batch``, in their order. ``--formats``, ``--exr`` and ``--obj`` add to one list of formats
#: (:func:`api_options`).
OUTPUT = ("--opengl", "--formats", "--normal-map", "--normal-map-bits", "--exr", "--obj", "--units")

#: The options of the near-light solver only (not of the parallel-light baseline).
NEAR_SOLVER = (
    "--shadows",
    "--interreflections",
    "--reflectance",
    "--roughness",
    "--eta",
    "--iterations",
    "--tol",
    "--weighting",
    "--solver",
    "--levels",
    "--refine-lights",
    "--light-prior-weight",
)


def add_options(parser: Any, flags: Sequence[str], *, batch: bool = False) -> None:
    """Add the options `flags` (first flags of :data:`OPTIONS`) to `parser` (or an argument group), in order.

    With `batch`, each option's ``batch_help`` where it has one.
    """
    exclusive: tuple[str, Any] | None = None
    for flag in flags:
        o = OPTIONS[flag]
        target = parser
        if o.exclusive is not None:
            if exclusive is None or exclusive[0] != o.exclusive:
                exclusive = (o.exclusive, parser.add_mutually_exclusive_group())
            target = exclusive[1]
        else:
            exclusive = None
        text = o.batch_help if batch and o.batch_help else o.help
        kwargs: dict[str, Any] = {"help": text() if callable(text) else text}
        if o.switch:
            kwargs["action"] = "store_true"
        else:
            kwargs.update(type=o.type, default=o.default, metavar=o.metavar, choices=o.choices)
            kwargs.update(nargs=o.nargs, const=o.const)
        if o.required:
            kwargs["required"] = True
        target.add_argument(*o.flags, **{k: v for k, v in kwargs.items() if v is not None})


def add_option_groups(parser: argparse.ArgumentParser) -> None:
    """Add the option groups of :data:`GROUPS` to `parser`."""
    for title, flags in GROUPS:
        add_options(parser.add_argument_group(title), flags)


def api_options(args: argparse.Namespace, flags: Sequence[str]) -> dict[str, Any]:
    """Return the values of the options `flags` by their API keywords (None for one not in `args`).

    Options that become the same keyword with list values (``--formats``, ``--exr``, ``--obj``:
    ``formats``) add to one list, in the order of `flags`, without repeats.
    """
    out: dict[str, Any] = {}
    for flag in flags:
        o = OPTIONS[flag]
        value = getattr(args, o.dest, None)
        value = o.to_api(value) if o.to_api is not None else value
        if isinstance(value, list) and isinstance(out.get(o.keyword), list):
            value = list(dict.fromkeys([*out[o.keyword], *value]))
        out[o.keyword] = value
    return out


def _parse_formats(text: str) -> list[str]:
    from .outputs import parse_formats  # a usage error for an unknown name

    return parse_formats(text)


def _formats_help() -> str:
    from ..export import formats_help  # the format registry (imported when a parser is made)

    return formats_help()
