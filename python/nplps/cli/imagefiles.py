"""The image files that the IMAGES arguments name.

A list of files, or the image files of one directory in natural order.
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence

from ..errors import InputError
from ..pipeline import natural_key
from ..raw import RAW_SUFFIXES
from .console import _note

#: File name endings taken as images when IMAGES is a directory.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".pnm", ".webp", *RAW_SUFFIXES)

#: Words that keep a file of an IMAGES directory out of the image list.
SKIPPED_WORDS = ("mask", "ambient")


def resolve_images(
    items: Sequence[str],
    mask: str | None = None,
    quiet: bool = False,
    exclude: Sequence[str] = (),
    ambient: str | None = None,
) -> list[str]:
    """Return the image files named by the IMAGES arguments.

    These are the files themselves, or the image files of a single directory sorted by name (numbers
    in names compare by value; names containing ``mask`` or ``ambient`` and the files ``exclude``
    are skipped). Announces on stderr which files a directory gave.
    """
    if not _is_dir_input(items):
        return _check_files(items)
    folder = items[0]
    skip = {os.path.realpath(f) for f in exclude}
    names = sorted(
        (
            n
            for n in os.listdir(folder)
            if _is_image_name(n)
            and not any(word in n.lower() for word in SKIPPED_WORDS)
            and os.path.isfile(os.path.join(folder, n))
            and os.path.realpath(os.path.join(folder, n)) not in skip
        ),
        key=natural_key,
    )
    if not names:
        raise InputError(
            f"no image files in directory '{folder}' (looked for {', '.join(IMAGE_SUFFIXES)}; "
            "names containing 'mask' or 'ambient' are skipped)"
        )
    if not quiet:
        _note_directory(folder, names, mask, ambient)
    return [os.path.join(folder, n) for n in names]


def _is_dir_input(items: Sequence[str]) -> bool:
    return len(items) == 1 and os.path.isdir(items[0])


def _is_image_name(name: str) -> bool:
    return name.lower().endswith(IMAGE_SUFFIXES) and not name.startswith(".")


def _check_files(items: Sequence[str]) -> list[str]:
    dirs = [i for i in items if os.path.isdir(i)]
    if dirs:
        raise InputError(f"'{dirs[0]}' is a directory: give either one directory or a list of image files, not both")
    missing = [i for i in items if not os.path.exists(i)]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise InputError(f"image file '{missing[0]}' not found{more}")
    return list(items)


def _note_directory(folder: str, names: list[str], mask: str | None, ambient: str | None) -> None:
    listing = textwrap.fill(
        ", ".join(names), width=95, initial_indent="  ", subsequent_indent="  ", break_on_hyphens=False
    )
    _note(f"using {len(names)} images from '{folder}' in this order (light 0 first):\n{listing}")
    for word, given, option in (("mask", mask, "--mask"), ("ambient", ambient, "--ambient")):
        skipped = sorted(n for n in os.listdir(folder) if word in n.lower() and _is_image_name(n))
        if given is None and skipped:
            _note(f"note: {', '.join(skipped)} in '{folder}' was skipped; pass {option} to use it")
