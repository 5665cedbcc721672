"""Loaders for photometric-stereo captures in published layouts.

Each loader returns a plain :class:`Capture`: images (file names or a float32 stack), mask,
camera matrix, lights and, when the dataset has them, ground-truth normals, all converted to
the conventions of nplps:

* camera frame (OpenCV): origin at the optical centre, x right (increasing column), y down
  (increasing row), z forward along the optical axis into the scene; millimetres;
* pinhole matrix ``K`` in the 0-based pixel-centre convention: pixel ``(r, c)`` has its centre
  at ``(u, v) = (c, r)``;
* normals face the camera (``n_z < 0``);
* directional lights are unit vectors from the surface towards the light.

Supported layouts:

* :func:`load_near_ps` -- the near-light toolbox of Quéau et al. (``camera.mat`` with ``K``,
  ``light.mat`` with ``S``, ``Dir``, ``Phi``, ``mu``, image files and a mask), with the helpers
  :func:`load_hehe12` and :func:`load_queau_human1` for two published captures;
* :func:`load_diligent` -- DiLiGenT's ``*PNG`` folders (directional lights, ground-truth normals);
* :func:`load_luces` -- LUCES object folders (``led_params.txt``, 52 LEDs, ground-truth normals and
  depth; see ``docs/luces.md``);
* :func:`load_folder` -- a plain folder with ``rig.json`` (nplps's own rig format), images, an
  optional mask and an optional ambient image.

The loaders only convert units and frames; radiometric corrections (ambient subtraction,
vignetting, binning) are :func:`prepare`'s, which runs :func:`nplps.pipeline.prepare` -- the
command line's pipeline -- and records what ran (``levels``, ``preprocessed``, ``valid``), so
that ``capture.options()`` gives :func:`nplps.reconstruct` the command line's ``dark`` default
and saturation flags. Grey or colour is ``color=``.
MATLAB files are read by :func:`nplps.captures.matlab.read_mat` (version 5 / v7 MAT-files; no scipy).

The light intensities are part of the rig: :meth:`Capture.rig` builds the lights with
``Capture.intensities`` (DiLiGenT's ``light_intensities.txt``, near_ps's ``Phi``), and the image
model multiplies by them. Pass the images as loaded: do **not** divide them by the intensities
too (that divides twice, and on DiLiGenT's ball gives about 16 degrees of mean normal error
instead of about 4, without any warning).

Examples
--------
DiLiGenT's ball (directional lights, so the distance only sets the gauge); run from the folder
that holds ``diligent_ball/ballPNG``::

    import nplps
    from nplps import captures

    ball = captures.load_diligent("diligent_ball", load=True)
    result = nplps.reconstruct(ball.images, ball.rig(), depth=1000.0, **ball.options())
    # result.normals against ball.normals_gt (inside ball.mask): about 4 degrees mean error
"""

from .capture import Capture, prepare
from .diligent import load_diligent
from .files import IMAGE_EXTENSIONS, find_images
from .folder import load_folder
from .luces import LucesCapture, load_luces
from .matlab import load_matlab_intrinsics, standardize_K
from .near_ps import load_hehe12, load_near_ps, load_queau_human1

__all__ = [
    "IMAGE_EXTENSIONS",
    "Capture",
    "LucesCapture",
    "find_images",
    "load_diligent",
    "load_folder",
    "load_hehe12",
    "load_luces",
    "load_matlab_intrinsics",
    "load_near_ps",
    "load_queau_human1",
    "prepare",
    "standardize_K",
]
