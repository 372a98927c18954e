"""A terrain's triangulated grid as a mesh file for viewing (``warptan terrain export``; .ply, .glb, .obj, .stl)."""

from __future__ import annotations

import contextlib
import os
import tempfile

import numpy as np

from warptan.outputs import current_umask
from warptan.terrain.raster import TerrainError

MESH_FORMATS = (".ply", ".glb", ".obj", ".stl")
"""File types :meth:`~warptan.terrain.grid.Terrain.export` writes."""


def check_export_path(path: str | os.PathLike, overwrite: bool = False, formats: tuple = MESH_FORMATS,
                      what: str = "mesh", inputs: tuple = ()) -> str:
    """``path`` as text when a ``what`` file (one of ``formats``; default :meth:`~warptan.terrain.grid.Terrain.
    export`'s meshes) may be written there (a known format, an existing folder, not an existing file unless
    ``overwrite``, never one of ``inputs``: the files the command reads, whatever ``overwrite`` says), else a
    TerrainError naming the problem."""
    path = os.fspath(path)
    for source in inputs:
        if source is not None and os.path.lexists(path) and os.path.exists(source) and os.path.samefile(path, source):
            raise TerrainError(f"{path} is the input {source}; nothing was written (--overwrite never replaces an "
                               "input: give another file name)")
    ext = os.path.splitext(path)[1].lower()
    if ext not in formats:
        raise TerrainError(f"{path}: unsupported {what} format {ext!r}; use {', '.join(formats)}")
    if os.path.isdir(path):
        raise TerrainError(f"{path}: is a folder; give a file name")
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise TerrainError(f"{path}: its folder {folder} does not exist; create it first")
    if os.path.lexists(path) and not overwrite:
        raise TerrainError(f"{path} exists; nothing was written (pass --overwrite, or overwrite=True, to replace it)")
    return path


def to_trimesh(terrain, frame: str = "ned"):
    """``terrain``'s triangulated grid as a ``trimesh.Trimesh`` in NED (default) or ENU (x east, y north, z up)."""
    import trimesh

    verts, faces = terrain.mesh_arrays()
    if frame == "enu":
        verts = np.stack([verts[:, 1], verts[:, 0], -verts[:, 2]], axis=1)
    elif frame != "ned":
        raise ValueError(f"frame must be 'ned' or 'enu', got {frame!r}")
    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return trimesh.Trimesh(vertices=verts[used], faces=remap[faces], process=False)

def export_mesh(terrain, path: str | os.PathLike, frame: str = "enu", overwrite: bool = False) -> None:
    """Write ``terrain``'s mesh for viewing (.ply, .glb, .obj, .stl; ENU with z up by default). An existing file is
    replaced only with ``overwrite=True`` (whole or not at all); a failed write names the file and leaves
    it as it was."""
    path = check_export_path(path, overwrite)
    ext = os.path.splitext(path)[1].lower()
    mesh = to_trimesh(terrain, frame)
    folder = os.path.dirname(path) or "."
    # Written beside the target and renamed over it: an existing file is replaced whole or not at all.
    try:
        fd, tmp = tempfile.mkstemp(prefix=".warptan-export-", suffix=ext, dir=folder)
    except OSError as err:
        raise TerrainError(f"{path}: cannot create a file in {folder} ({err.strerror or err})") from None
    try:
        with os.fdopen(fd, "wb") as f:
            mesh.export(f, file_type=ext[1:])
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise TerrainError(f"writing {path} failed: {err.strerror or err}; nothing was written") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
