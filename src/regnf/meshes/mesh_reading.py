"""Reading a mesh file to distil: what it names, what it holds, what unit it is in.

:func:`load_mesh_file` reads a mesh with trimesh, but

- opens the files the mesh names (an OBJ's ``mtllib``, the textures an MTL names, a glTF's
  buffers and images) only if they are regular files inside the mesh's folder, symlinks
  resolved (:class:`FolderResolver`): a FIFO would block the reader for ever, a device could
  be read without end, and a path outside the folder is not the mesh's to hand out. Such a
  name is skipped and said in one warning line; a glTF whose buffer is skipped cannot be read;
- drops the faces that have a non-finite (NaN or inf) vertex and says how many (trimesh
  would drop them silently), and refuses a mesh with none left;
- and :func:`extent_warning` says when the mesh, in metres, is outside the sizes of
  furniture and objects (:data:`PLAUSIBLE_EXTENT`): a file in millimetres read as metres is
  1000 times too large.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from trimesh.resolvers import FilePathResolver

from regnf.core.preflight import input_file_problem, open_regular_file
from regnf.meshes.mesh_repair import MeshError

UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
"""Metres per unit of each unit a mesh file may be in (``regnf distill --units``)."""

PLAUSIBLE_EXTENT: tuple[float, float] = (0.01, 10.0)
"""Largest extent, in metres, of the things a library holds (1 cm to 10 m); outside it the
mesh's unit is probably not the one given."""


class FolderResolver(FilePathResolver):
    """A trimesh resolver that reads only regular files inside the mesh's folder.

    Names are tried as trimesh tries them (as given, without a leading ``/``, the bare file
    name); each is resolved with its symlinks, and one that leads outside the folder or to
    anything but a regular file is not opened. A name none of whose tries could be read, and
    that was skipped for one of those reasons, is recorded in :attr:`skipped`.

    Parameters
    ----------
    source : str or PathLike
        The mesh file.
    skipped : list of str, optional
        Shared list of skipped names (``"NAME is not a file (a FIFO)"``); a new one by default.
    """

    def __init__(self, source: str | os.PathLike, skipped: list[str] | None = None) -> None:
        super().__init__(str(source))
        self.skipped: list[str] = [] if skipped is None else skipped

    def namespaced(self, namespace: str) -> FolderResolver:
        """The same checks, from a subfolder (the skipped names still go to this list)."""
        folder = Path(self.parent, namespace).resolve()
        if not folder.is_relative_to(Path(self.parent).resolve()) or not folder.is_dir():
            raise FileNotFoundError(namespace)
        return FolderResolver(folder, self.skipped)

    def get(self, name: str) -> bytes:
        """The bytes of the regular file ``name`` inside the folder.

        Raises
        ------
        FileNotFoundError
            No try of ``name`` is a regular file inside the folder (trimesh then goes on
            without it where it can).
        """
        root = Path(self.parent).resolve()
        clean = name.strip()
        problem = ""
        for attempt in dict.fromkeys((clean, clean.lstrip("/"), os.path.basename(clean))):
            if not attempt:
                continue
            path = (root / attempt).resolve()
            if not path.is_relative_to(root):
                problem = problem or "is outside the mesh's folder"
                continue
            why = input_file_problem(path, missing="")
            if why is not None:
                problem = problem or why
                continue
            try:
                opened = open_regular_file(path)
            except OSError as exc:
                problem = problem or f"cannot be read ({exc.strerror or exc})"
                continue
            if opened is None:
                problem = problem or "is not a file"
                continue
            with opened[0] as f:
                return f.read()
        if problem and f"{clean} {problem}" not in self.skipped:
            self.skipped.append(f"{clean} {problem}")
        raise FileNotFoundError(name)


@dataclass
class MeshFile:
    """A mesh read by :func:`load_mesh_file`."""

    mesh: trimesh.Trimesh
    """The mesh as trimesh reads it (vertices merged), without faces at non-finite vertices."""
    warnings: list[str] = field(default_factory=list)
    """One line each, ``"FILE: what"``: files it names that were skipped, faces dropped."""


def drop_nonfinite_faces(mesh: trimesh.Trimesh, source: str) -> tuple[trimesh.Trimesh, int]:
    """``mesh`` without the faces that have a non-finite vertex, and how many there were.

    Faces with a vertex index out of range are left to the repair (degenerate faces).

    Raises
    ------
    MeshError
        Every face had one.
    """
    finite = np.isfinite(np.asarray(mesh.vertices)).all(axis=1)
    faces = np.asarray(mesh.faces)
    in_range = (faces >= 0) & (faces < len(finite))
    bad = in_range.all(axis=1) & ~finite[np.where(in_range, faces, 0)].all(axis=1)
    n_bad = int(bad.sum())
    if n_bad and n_bad == len(faces):
        which = "its one face has" if n_bad == 1 else f"each of its {n_bad} faces has"
        raise MeshError(source, f"{which} a non-finite (NaN or inf) vertex; nothing is left to distil")
    if n_bad:
        mesh.update_faces(~bad)
    return mesh, n_bad


def load_mesh_file(path: str | os.PathLike) -> MeshFile:
    """Read the mesh file ``path`` (any format trimesh reads; a scene is concatenated).

    Returns
    -------
    MeshFile

    Raises
    ------
    MeshError
        It cannot be read, or every face has a non-finite vertex.
    """
    source = str(path)
    resolver = FolderResolver(path)
    try:
        loaded = trimesh.load(source, force="mesh", process=False, resolver=resolver)
    except Exception as exc:  # trimesh raises many types for unreadable files
        skipped = f"; skipped {'; '.join(resolver.skipped)}" if resolver.skipped else ""
        raise MeshError(source, f"cannot read mesh ({exc}){skipped}") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(source, f"cannot read mesh (trimesh read a {type(loaded).__name__}, not triangles)")
    mesh, dropped = drop_nonfinite_faces(loaded, source)
    # What trimesh.load does by default (merge equal vertices), now that no face is at a NaN.
    mesh.process()
    warnings = []
    if resolver.skipped:
        warnings.append(f"{source}: skipped the files it names that are not regular files inside its folder: "
                        f"{'; '.join(resolver.skipped)}")
    if dropped:
        warnings.append(f"{source}: dropped {dropped} faces with non-finite vertices")
    return MeshFile(mesh=mesh, warnings=warnings)


def format_length(metres: float) -> str:
    """A length with a readable unit: ``400 m``, ``3.2 cm``, ``0.4 mm``."""
    if metres >= 1.0:
        return f"{metres:.3g} m"
    if metres >= 0.01:
        return f"{100 * metres:.3g} cm"
    return f"{1000 * metres:.3g} mm"


def extent_warning(mesh: trimesh.Trimesh, scale: float, source: str, units_given: bool) -> str | None:
    """One line when the mesh's largest extent times ``scale`` (metres) is implausible.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        As read.
    scale : float
        Metres per unit of the file.
    source : str
        The mesh's file.
    units_given : bool
        Whether the unit was given (``--units`` other than m, or ``--scale``).

    Returns
    -------
    str or None
        None when the size is within :data:`PLAUSIBLE_EXTENT`.
    """
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces).reshape(-1)]
    extent = float(np.ptp(corners, axis=0).max()) * scale if len(corners) else 0.0
    lo, hi = PLAUSIBLE_EXTENT
    if lo <= extent <= hi or extent == 0.0:
        return None
    size = f"{source}: the mesh is {format_length(extent)} across"
    if units_given:
        return f"{size} in the unit given, outside {format_length(lo)} to {format_length(hi)}; check --units or --scale"
    if extent > hi:
        return f"{size}; if its unit is not metres, pass --units mm or cm"
    return f"{size}; if its unit is not metres, pass --scale (metres per unit of the file)"
