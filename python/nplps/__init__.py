"""nplps: photometric stereo with near point lighting.

From k images of a still object, each lit by one LED close to it, nplps recovers a metric 3-D
mesh, normals and albedo by the mesh-deformation method of Xie, Dai & Wang (CVPR 2015). The
numerics run in Rust (``nplps._core``); this package holds the rig model, image I/O, export and
the command line.

Quick start::

    import nplps
    rig = nplps.Rig.load("rig.json")
    result = nplps.reconstruct(["img01.png", ...], rig, mask="mask.png", depth=200.0)
    result.save("out/")
"""

from . import captures, evaluation, export, io, preprocess
from ._core import __version__
from .api import reconstruct, reconstruct_parallel, render
from .errors import InputError, MemoryLimitError, NplpsError, OutputExistsError, RigError, SolverError
from .reconstruction import Iteration, LightRefinement, Reconstruction, light_changes
from .rig import LED, DirectionalLight, PointLight, Rig
from .synth import Scene, make_scene
from . import calibrate
from .calibrate import IntensityCalibration, SphereCalibration, calibrate_intensities, calibrate_spheres

__all__ = [
    "__version__",
    "Rig",
    "PointLight", "LED", "DirectionalLight",
    "Reconstruction",
    "LightRefinement",
    "light_changes",
    "Iteration",
    "Scene",
    "make_scene",
    "reconstruct",
    "reconstruct_parallel",
    "render",
    "NplpsError",
    "InputError",
    "RigError",
    "SolverError",
    "MemoryLimitError",
    "OutputExistsError",
    "io",
    "export",
    "preprocess",
    "captures",
    "evaluation",
    "calibrate",
    "calibrate_spheres",
    "calibrate_intensities",
    "SphereCalibration",
    "IntensityCalibration",
]
