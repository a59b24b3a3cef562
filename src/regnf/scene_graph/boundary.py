"""The trust boundary of a stage: every file it names lies inside its folder (or its package).

A stage is a folder (or a ``.usdz`` package) that can be copied, shared and exported as a
whole; a stage whose layers reach outside it is not, and opening one would read whatever the
path names (another user's field, a system file handed to USD's parsers). So before a stage is
opened, every composition arc of every layer (sublayers, references, payloads, in variants
too) is resolved and checked, layer by layer, before the layer it names is opened; the regnf
tables and attributes (library and slot layers, checkpoints, ``replacementOf``) are checked by
:func:`Boundary.resolve` before they are used.

The check is on real paths: symlinks are resolved (a link inside the folder that points out of
it is outside), and for a package member ``/a/pkg.usdz[fields/b.usdc]`` the package file
itself must be inside (and, when the stage is a package, be that package), with a member path
that is relative and does not climb with ``..``. ``allow_outside=True`` switches the checks
off, for a user who means it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from pxr import Ar, Sdf, Tf, Usd

from .errors import StageError

OUTSIDE_HINT = "(pass allow_outside=True, or --allow-outside, to open it anyway)"
"""How a refusal says that it can be overridden."""


def split_package(identifier: str) -> tuple[str, list[str]]:
    """The outermost file of an identifier and its package members, outermost first.

    ``/a/p.usdz[inner.usdz[x.usdc]]`` -> ``("/a/p.usdz", ["inner.usdz", "x.usdc"])``; a plain
    path gives ``(path, [])``.
    """
    members: list[str] = []
    outer = identifier
    if Ar.IsPackageRelativePath(identifier):
        outer, inner = Ar.SplitPackageRelativePathOuter(identifier)
        while Ar.IsPackageRelativePath(inner):
            head, inner = Ar.SplitPackageRelativePathOuter(inner)
            members.append(head)
        members.append(inner)
    return outer, members


@dataclass(frozen=True)
class Boundary:
    """Where the files of one stage may lie.

    Parameters
    ----------
    stage : Path
        The stage's root layer (named in messages).
    folder : Path
        Real path of the stage's folder.
    package : Path or None
        Real path of the stage when it is a ``.usdz`` package: then everything must be inside
        that package.
    allow_outside : bool
        Accept any path (no checks).
    """

    stage: Path
    folder: Path
    package: Path | None
    allow_outside: bool = False

    @classmethod
    def of(cls, stage_path: str | os.PathLike, allow_outside: bool = False,
           folder: str | os.PathLike | None = None) -> Boundary:
        """The boundary of the stage (or package) at ``stage_path``.

        ``folder`` overrides the stage's own folder (an asset layer opened on its own belongs
        to the stage one folder up); it is ignored for a package.
        """
        path = Path(stage_path).absolute()
        package = Path(os.path.realpath(path)) if path.suffix == ".usdz" else None
        root = path.parent if folder is None or package is not None else Path(folder)
        return cls(path, Path(os.path.realpath(root)), package, allow_outside)

    def where(self) -> str:
        """The boundary in words: ``the stage's folder /x`` or ``the package /x/p.usdz``."""
        return f"the package {self.package}" if self.package else f"the stage's folder {self.folder}"

    def problem(self, identifier: str) -> str | None:
        """Why a resolved identifier lies outside (a clause for the message), or None when inside."""
        outer, members = split_package(identifier)
        for m in members:
            p = PurePosixPath(m)
            if p.is_absolute() or ".." in p.parts:
                return f"its package member path {m!r} climbs out of its package"
        if not os.path.isabs(outer):
            return f"it does not resolve to a file path (resolved: {identifier!r})"
        real = Path(os.path.realpath(outer))
        kind = "the package it names" if members else "it"
        if self.package is not None:
            return None if real == self.package else f"{kind} resolves to {real}"
        return None if real.is_relative_to(self.folder) else f"{kind} resolves to {real}"

    def resolve(self, layer: Sdf.Layer, asset: str, owner: str, what: str) -> str:
        """Resolve ``asset`` (as authored in ``layer``) to an identifier, refusing an escape.

        Parameters
        ----------
        layer : Sdf.Layer
            The layer that holds the path (relative paths are anchored to it).
        asset : str
            The authored path.
        owner : str
            Prim path holding it (``/`` for layer metadata), for the message.
        what : str
            What the path is (``"checkpoint path"``), for the message.

        Returns
        -------
        str
            The anchored identifier (a file path, or ``pkg.usdz[member]``).

        Raises
        ------
        StageError
            Naming the layer's file, ``owner`` and ``asset``: an empty path, an absolute one, or
            one that resolves outside the boundary (unless ``allow_outside``).
        """
        file = layer.realPath or layer.identifier
        if not asset:
            raise StageError(file, owner, f"{what} is empty")
        ident = layer.ComputeAbsolutePath(asset)
        if self.allow_outside:
            return ident
        if os.path.isabs(split_package(asset)[0]):
            raise StageError(file, owner, f"{what} {asset!r} is absolute: a stage's paths are relative to "
                             f"its folder, so it escapes {self.where()} {OUTSIDE_HINT}")
        why = self.problem(ident)
        if why is not None:
            raise StageError(file, owner, f"{what} {asset!r} escapes {self.where()}: {why} {OUTSIDE_HINT}")
        return ident


ARC = "composition arc (sublayer, reference or payload)"


def _arc_owner(layer: Sdf.Layer, asset: str) -> str:
    """The prim of ``layer`` whose reference or payload names ``asset`` (``/`` for a sublayer)."""
    if asset in layer.subLayerPaths:
        return "/"
    found: list[str] = []

    def visit(path: Sdf.Path) -> None:
        if found or not (path.IsPrimPath() or path.IsPrimVariantSelectionPath()):
            return
        spec = layer.GetPrimAtPath(path)
        if spec is None:
            return
        arcs = [*spec.referenceList.GetAddedOrExplicitItems(), *spec.payloadList.GetAddedOrExplicitItems()]
        if any(a.assetPath == asset for a in arcs):
            found.append(str(path))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found[0] if found else "/"


def open_composed(identifier: str, boundary: Boundary, fresh: set[str] | None = None) -> Usd.Stage:
    """Open the stage whose root layer is ``identifier``, every layer checked before it is opened.

    Layers that were already in memory are reloaded from disk once (``fresh`` collects the
    identifiers reloaded so far in this read), so that an edit made by another process is seen.

    Parameters
    ----------
    identifier : str
        The root layer: a file path or a package member.
    boundary : Boundary
    fresh : set of str, optional
        Identifiers already reloaded by this read (updated).

    Raises
    ------
    StageError
        A layer that USD cannot open, or an arc that leaves the boundary (naming the layer
        holding it, its prim and its path).
    """
    fresh = set() if fresh is None else fresh
    loaded = {layer.identifier for layer in Sdf.Layer.GetLoadedLayers()}
    held: list[Sdf.Layer] = []  # keep every layer alive until the stage holds it
    todo, seen = [identifier], set()
    while todo:
        ident = todo.pop()
        if ident in seen:
            continue
        seen.add(ident)
        try:
            layer = Sdf.Layer.FindOrOpen(ident)
        except Tf.ErrorException as exc:
            raise StageError(ident, "/", f"USD cannot open it: {' '.join(str(exc).split())}") from exc
        if layer is None:
            if ident == identifier:
                raise StageError(ident, "/", "USD cannot open it")
            continue  # a missing asset: composition reports it, and read_stage names what is missing
        if ident in loaded and ident not in fresh and not layer.anonymous:
            layer.Reload(force=True)
        fresh.add(ident)
        held.append(layer)
        for asset in layer.GetCompositionAssetDependencies():
            try:
                todo.append(boundary.resolve(layer, asset, "/", ARC))
            except StageError:
                # Refused: find the prim that holds the arc for the message (a walk of the layer).
                boundary.resolve(layer, asset, _arc_owner(layer, asset), ARC)
                raise
    try:
        stage = Usd.Stage.Open(held[0])
    except Tf.ErrorException as exc:
        raise StageError(identifier, "/", f"USD cannot open it: {' '.join(str(exc).split())}") from exc
    if stage is None:
        raise StageError(identifier, "/", "USD cannot open it")
    return stage
