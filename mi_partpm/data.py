"""Finding the data files of the built-in scenes (the Happy Buddha mesh).

The files ship with the package, in ``mi_partpm/scenes/data/`` (see the README there for their
provenance). A directory given by the caller (``data_dir=``, ``--data``), else the one named by
the ``PARTPM_DATA`` environment variable, overrides that: the file is then read from there,
and its absence there is an error, not a silent fallback.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

__all__ = ["DATA_ENV", "PACKAGE_DATA", "MissingDataError", "find_data_file", "DATA_FILES"]

#: Environment variable naming the data directory.
DATA_ENV = "PARTPM_DATA"

#: Where the package keeps its own copies of the data files.
PACKAGE_DATA = Path(__file__).resolve().parent / "scenes" / "data"

#: File name -> what it is and where to get another copy (shown when it is missing).
DATA_FILES = {
    "happy_buddha_20k.ply": (
        "the Stanford Happy Buddha decimated to about 20,000 triangles (the paper's 20,062). "
        "Get happy_recon.tar.gz from the Stanford 3D Scanning Repository "
        "(http://graphics.stanford.edu/data/3Dscanrep/), decimate happy_vrip_res3.ply or "
        "happy_vrip.ply to about 20k triangles (e.g. quadric decimation in MeshLab or "
        "Open3D) and save it as binary PLY named happy_buddha_20k.ply, in Stanford's "
        "coordinates (+Y up, base near y = 0.05)"),
}


class MissingDataError(FileNotFoundError):
    """A data file the scene needs is not where it was looked for."""


def find_data_file(name: str, data_dir: Optional[os.PathLike] = None) -> Path:
    """The path of data file ``name``: in ``data_dir`` or ``$PARTPM_DATA`` when one is given,
    else the package's own copy.

    Raises
    ------
    MissingDataError
        Not found; the message says where it looked, what the file is, where to get it and
        where to put it.
    """
    if data_dir is not None:
        label, directory = "data_dir", Path(data_dir)
    elif os.environ.get(DATA_ENV):
        label, directory = DATA_ENV, Path(os.environ[DATA_ENV])
    else:
        label, directory = "the package's data folder", PACKAGE_DATA
    if directory.is_file():
        # The file itself where its folder was meant: say so, not where to download it.
        raise MissingDataError(
            f"{label} must be a directory holding {name!r}, got the file {str(directory)!r}"
            + (f": give its folder, {str(directory.parent)!r}" if directory.name == name
               else ""))
    path = directory / name
    if path.is_file():
        return path
    where = f"looked in {label}={str(directory)!r}"
    about = DATA_FILES.get(name, "a data file of a built-in scene")
    raise MissingDataError(
        f"data file {name!r} not found: {where}. It is {about}. Put it in a directory and "
        f"set {DATA_ENV} to that directory (or pass --data DIR on the command line, "
        f"data_dir=DIR in Python).")
