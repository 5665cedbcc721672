"""nplps: photometric stereo with near point lighting.

From k images of a still object, each lit by one LED close to it, nplps recovers a metric 3-D
mesh, normals and albedo by the mesh-deformation method of Xie, Dai & Wang (CVPR 2015). The
numerics run in Rust (``nplps._core``); this package holds the rig model, image I/O, export and
the command line.

Quick start::

    import nplps
    rig = nplps.Rig.load("rig.json")
    result = nplps.reconstruct(["img01.png", ...], rig, depth=200.0, mask="mask.png")
    result.save("out/")

The public names, by layer:

- reconstructing: :func:`reconstruct`, :func:`reconstruct_parallel`, :func:`render`,
  :func:`cast_shadows`, :func:`estimate_noise`, :func:`make_scene`, :func:`light_changes`;
  calibrating: :func:`calibrate_spheres`, :func:`calibrate_intensities`;
- what they return: :class:`Reconstruction` (with :class:`Iteration`,
  :class:`DistanceEstimate`, :class:`DistanceCheck`, :class:`LightRefinement`), :class:`Scene`,
  :class:`~nplps.evaluation.HeldOut`, :class:`SphereCalibration` and :class:`IntensityCalibration`
  (with :class:`SphereReport`, :class:`LightReport`);
- the rig: :class:`Rig`;
- errors: :class:`NplpsError` and its subclasses;
- submodules: :mod:`~nplps.io`, :mod:`~nplps.preprocess`, :mod:`~nplps.captures`,
  :mod:`~nplps.export`, :mod:`~nplps.evaluation`, :mod:`~nplps.calibrate` and
  :mod:`~nplps.types` (the ``Literal`` aliases of the string options, such as ``Status``).
"""

from typing import TYPE_CHECKING, Any

from .errors import InputError, MemoryLimitError, NplpsError, OutputExistsError, RigError, SolverError

# The other public names are imported when first used (PEP 562), so that ``import nplps`` does
# not import numpy (through the native core), imageio and tifffile for a caller that needs only a part of the package:
# the name -> the submodule that defines it.
_LAZY = {
    "__version__": "_core",
    "cast_shadows": "api",
    "estimate_noise": "api",
    "reconstruct": "api",
    "reconstruct_parallel": "api",
    "render": "api",
    "IntensityCalibration": "calibrate",
    "LightReport": "calibrate",
    "SphereCalibration": "calibrate",
    "SphereReport": "calibrate",
    "calibrate_intensities": "calibrate",
    "calibrate_spheres": "calibrate",
    "HeldOut": "evaluation",
    "DistanceCheck": "reconstruction",
    "DistanceEstimate": "reconstruction",
    "Iteration": "reconstruction",
    "LightRefinement": "reconstruction",
    "Lobe": "reconstruction",
    "LobeCheck": "reconstruction",
    "Reconstruction": "reconstruction",
    "light_changes": "reconstruction",
    "LED": "rig",
    "DirectionalLight": "rig",
    "PointLight": "rig",
    "Rig": "rig",
    "RigGrid": "rig",
    "Scene": "synth",
    "make_scene": "synth",
}

if TYPE_CHECKING:
    from . import calibrate, captures, evaluation, export, io, pipeline, preprocess, report, types, viewer, views
    from ._core import __version__
    from .api import cast_shadows, estimate_noise, reconstruct, reconstruct_parallel, render
    from .calibrate import (
        IntensityCalibration,
        LightReport,
        SphereCalibration,
        SphereReport,
        calibrate_intensities,
        calibrate_spheres,
    )
    from .evaluation import HeldOut
    from .reconstruction import (
        DistanceCheck,
        DistanceEstimate,
        Iteration,
        LightRefinement,
        Lobe,
        LobeCheck,
        Reconstruction,
        light_changes,
    )
    from .rig import LED, DirectionalLight, PointLight, Rig, RigGrid
    from .synth import Scene, make_scene


def __getattr__(name: str) -> Any:
    """Import a public name's submodule (or a submodule) when it is first used."""
    import importlib

    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
        globals()[name] = value
        return value
    if not name.startswith("_"):
        try:
            return importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "LED",
    "DirectionalLight",
    "DistanceCheck",
    "DistanceEstimate",
    "HeldOut",
    "InputError",
    "IntensityCalibration",
    "Iteration",
    "LightRefinement",
    "LightReport",
    "Lobe",
    "LobeCheck",
    "MemoryLimitError",
    "NplpsError",
    "OutputExistsError",
    "PointLight",
    "Reconstruction",
    "Rig",
    "RigError",
    "RigGrid",
    "Scene",
    "SolverError",
    "SphereCalibration",
    "SphereReport",
    "__version__",
    "calibrate",
    "calibrate_intensities",
    "calibrate_spheres",
    "captures",
    "cast_shadows",
    "estimate_noise",
    "evaluation",
    "export",
    "io",
    "light_changes",
    "make_scene",
    "pipeline",
    "preprocess",
    "reconstruct",
    "reconstruct_parallel",
    "render",
    "report",
    "types",
    "viewer",
    "views",
]
