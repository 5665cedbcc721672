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
  :func:`make_scene`, :func:`light_changes`; calibrating: :func:`calibrate_spheres`,
  :func:`calibrate_intensities`;
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

from . import calibrate, captures, evaluation, export, io, pipeline, preprocess, report, types, viewer, views
from ._core import __version__
from .api import reconstruct, reconstruct_parallel, render
from .calibrate import (
    IntensityCalibration,
    LightReport,
    SphereCalibration,
    SphereReport,
    calibrate_intensities,
    calibrate_spheres,
)
from .errors import InputError, MemoryLimitError, NplpsError, OutputExistsError, RigError, SolverError
from .evaluation import HeldOut
from .reconstruction import DistanceCheck, DistanceEstimate, Iteration, LightRefinement, Reconstruction, light_changes
from .rig import LED, DirectionalLight, PointLight, Rig, RigGrid
from .synth import Scene, make_scene

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
