"""The composite field: a scene with regions cut away and library objects added.

It lives in the SCENE FIELD frame (same ``to_world`` as the scene, bounds grown to hold the
placed objects) and is itself a :class:`~regnf.fields.field.Field`, so registration,
meshing and both renderers accept it::

    scene_masked(x) = max(S_scene(x), -M(x)),       M = min over removal regions
    composite(x)    = min(scene_masked(x), min_i s_i S_i(T_i^-1 x))

with ``T_i`` the similarity library field frame -> scene field frame and ``s_i`` its scale
(docs/design.md section 1.9 writes the same with the inverse map, scene -> library, and divides
by its scale ``1 / s_i``). Each placed field is culled to its oriented box (see
:mod:`regnf.compositor.placement`), and the scene to where it is not deeper than ``cull_pad``
inside a removal region (:meth:`CompositeField.scene_masked`): with culling, the composite keeps
the sign of the exact one everywhere, never exceeds it in magnitude, and equals it within
``cull_pad`` of the surface.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from regnf.core.errors import RegnfError
from regnf.fields.field import Field, FieldInfo, FieldSample, check_points
from regnf.fields.oriented_box import OrientedBoxes

from .placement import PlacedObject, Placement
from .regions import BoxRegionUnion, OrientedBoxRegion, RemovalRegion

SCENE_ID = 0
"""Winner id of the scene field."""
MAX_COMPONENTS = 1024
"""Most placed objects, and most removal regions, one composite takes. Every query loops over
its components (vectorised over the points), so a frame's cost grows with their number: at
1024 a 320 x 240 view already takes minutes on 2 CPU cores. A stage with more instances is
refused when the composite is built, before any rendering."""


@dataclass(frozen=True)
class CompositeConfig:
    """How a :class:`CompositeField` evaluates its components."""

    cull: bool = True
    """Evaluate placed fields only in their padded boxes, the scene only outside removals less ``cull_pad``."""
    cull_pad: float = 0.02
    """Culling margin in scene field units; must exceed the renderer's hit tolerance."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.cull_pad) and self.cull_pad > 0):
            raise RegnfError(f"cull_pad must be finite and > 0, got {self.cull_pad}")


class CompositeField(Field):
    """A scene field minus removal regions plus similarity-placed library fields.

    Parameters
    ----------
    scene : Field
        The scene field; the composite uses its frame, ``to_world`` and device.
    objects : sequence of PlacedObject
        Library fields with their library -> scene similarity, instance id (>= 1, unique)
        and optional tint.
    removals : sequence of RemovalRegion
        Regions cut out of the scene (their union).
    config : CompositeConfig
    info : FieldInfo, optional
        Defaults to the scene's label with name ``<scene>+composite``.

    Notes
    -----
    Colour comes from the component that wins the min at ``x``. A tint MULTIPLIES the
    library colour channel-wise (``(1, 1, 1)`` leaves it unchanged), which keeps the
    object's texture and shading visible under the tint.
    """

    def __init__(
        self,
        scene: Field,
        objects: Sequence[PlacedObject] = (),
        removals: Sequence[RemovalRegion] = (),
        config: CompositeConfig = CompositeConfig(),
        info: FieldInfo | None = None,
    ) -> None:
        if not isinstance(scene, Field):
            raise TypeError(f"the scene must be a Field, got {type(scene).__name__}")
        for what, items in (("placed objects", objects), ("removal regions", removals)):
            if len(items) > MAX_COMPONENTS:
                raise RegnfError(f"a composite takes at most {MAX_COMPONENTS} {what}, got {len(items)}")
        placements, ids, tints = _placements(scene, objects, config)
        for k, r in enumerate(removals):
            if not isinstance(r, RemovalRegion):
                raise TypeError(f"removals take RemovalRegion objects, got {type(r).__name__}")
            # Analytic shapes simply move with the composite; a field inside one must already
            # be where the scene is (moving a caller's field behind its back would surprise).
            for f in r.modules():
                if isinstance(f, Field) and f.device != scene.device:
                    raise RegnfError(
                        f"removals[{k}] holds field {f.name!r} on {f.device} but the scene is on "
                        f"{scene.device}; move them to one device"
                    )
        bounds = scene.bounds.detach().cpu().double()
        for p in placements:  # grow the bounds to hold objects that stick out of the scene
            box = p.aabb()
            bounds = torch.stack(
                [torch.minimum(bounds[0], box[0]), torch.maximum(bounds[1], box[1])]
            )
        info = info or FieldInfo(
            label=scene.info.label,
            name=f"{scene.info.name or 'scene'}+composite",
            provenance={"composite": {"instances": ids, "removals": len(removals)}},
        )
        super().__init__(bounds.float(), scene.to_world.detach().cpu(), info)
        self.scene = scene
        self.placements = torch.nn.ModuleList(placements)
        self.removals = torch.nn.ModuleList(removals)
        self.instance_ids: tuple[int, ...] = tuple(ids)
        self.tints: tuple[tuple[float, float, float] | None, ...] = tuple(tints)
        self.config = config
        # Every box distance of a query at once (see OrientedBoxes): the placed objects' culling
        # boxes, and the removal regions when they are all boxes (the usual case).
        self.placement_boxes = OrientedBoxes([p.box for p in placements]) if placements else None
        boxes_only = len(removals) > 0 and all(isinstance(r, OrientedBoxRegion) for r in removals)
        self.removal_union = BoxRegionUnion(list(removals)) if boxes_only else None
        self.to(scene.device)

    def scene_masked(self, x: torch.Tensor) -> FieldSample:
        """``max(S_scene, -M)`` (n,) at points ``x`` (n, 3); winner 0 everywhere.

        With ``config.cull``, the scene is evaluated only where ``-M <= cull_pad``: deeper
        inside a removal region ``-M`` itself stands in, a lower bound of the masked SDF of the
        same (positive) sign, as a placed object's box distance stands in for it (a third of a
        substitution view's samples lie there, where the scene's network was wasted).
        """
        check_points(x, self)
        if len(self.removals) == 0:
            # Through evaluate() so that a composite used as a scene reports its full cost.
            s, _, evals = self.scene.evaluate(x)
            return FieldSample(s, torch.zeros_like(evals), evals)
        if self.removal_union is not None:
            m, region_evals = self.removal_union.evaluate(x)
        else:
            # A running min, not a stack: memory stays one value per point however many regions.
            m, region_evals = None, None
            for region in self.removals:
                r = region.evaluate(x)
                m = r.sdf if m is None else torch.minimum(m, r.sdf.to(m.dtype))
                region_evals = r.evals if region_evals is None else region_evals + r.evals
        need = None
        if self.config.cull:
            need = (-m <= self.config.cull_pad).nonzero().squeeze(1)
            if need.numel() == x.shape[0]:
                need = None
        if need is None:
            s, _, evals = self.scene.evaluate(x)
            m = m.to(s.dtype)
        else:
            evals = torch.zeros_like(region_evals)
            s = -m
            if need.numel() > 0:
                sub = self.scene.evaluate(x[need])
                m = m.to(sub.sdf.dtype)
                # Out-of-place index_put keeps autograd through both the scene and the regions.
                s = (-m).index_put((need,), sub.sdf)
                evals = evals.index_put((need,), sub.evals.to(evals.dtype))
        return FieldSample(torch.maximum(s, -m), torch.zeros_like(region_evals), evals + region_evals)

    def evaluate(self, x: torch.Tensor) -> FieldSample:
        """Composite SDF (n,), winning component (n,) and evaluations (n,) at ``x`` (n, 3).

        Ties go to the scene (then to the earlier object), so a library object replaces the
        scene only where it is strictly closer.
        """
        best, winner, evals = self.scene_masked(x)
        boxes = self.placement_boxes.sdf(x) if self.placement_boxes is not None and self.config.cull else None
        # A loop over the handful of objects; each step is vectorised over all points.
        for k, (placement, iid) in enumerate(zip(self.placements, self.instance_ids, strict=True)):
            sample = placement.evaluate(x, None if boxes is None else boxes[k])
            v = sample.sdf.to(best.dtype)
            closer = v < best
            best = torch.where(closer, v, best)
            winner = torch.where(closer, torch.full_like(winner, iid), winner)
            evals = evals + sample.evals
        return FieldSample(best, winner, evals)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Composite signed distance (n,) in scene field units of points ``x`` (n, 3)."""
        return self.evaluate(x).sdf

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """RGB (n, 3) in [0, 1] of the component winning the min at each point ``x`` (n, 3).

        Library colours are queried in the library frame with the view directions ``d``
        (n, 3) rotated into it, then multiplied by the instance's tint if it has one.
        """
        check_points(x, self)
        with torch.no_grad():
            winner = self.evaluate(x).winner
        out = x.new_zeros(x.shape[0], 3)
        pick = (winner == SCENE_ID).nonzero().squeeze(1)
        if pick.numel() > 0:
            out[pick] = self.scene.color(x[pick], None if d is None else d[pick]).to(out.dtype)
        for k, (placement, iid) in enumerate(zip(self.placements, self.instance_ids, strict=True)):
            pick = (winner == iid).nonzero().squeeze(1)
            if pick.numel() == 0:
                continue
            c = placement.color(x[pick], None if d is None else d[pick]).to(out.dtype)
            tint = self.tints[k]
            out[pick] = (
                c if tint is None else c * torch.tensor(tint, dtype=c.dtype, device=c.device)
            )
        return out

    def placed(self) -> list[PlacedObject]:
        """The placed objects as given to the constructor: field, library -> scene similarity,
        instance id and tint (to build a composite of the same components with another config)."""
        return [PlacedObject(p.field, p.mapped.matrix.detach().cpu().numpy(), iid, tint)
                for p, iid, tint in zip(self.placements, self.instance_ids, self.tints, strict=True)]

    def scale_of(self, instance_id: int) -> float:
        """The library -> scene scale ``s`` of an instance."""
        return self._placement(instance_id).scale

    def _placement(self, instance_id: int) -> Placement:
        try:
            return self.placements[self.instance_ids.index(int(instance_id))]
        except ValueError:
            raise RegnfError(
                f"no instance {instance_id} in this composite (ids: {list(self.instance_ids)})"
            ) from None


def _placements(
    scene: Field, objects: Sequence[PlacedObject], config: CompositeConfig
) -> tuple[list[Placement], list[int], list[tuple[float, float, float] | None]]:
    placements, ids, tints = [], [], []
    for k, obj in enumerate(objects):
        if not isinstance(obj, PlacedObject):
            raise TypeError(f"objects[{k}] must be a PlacedObject, got {type(obj).__name__}")
        if not isinstance(obj.field, Field):
            raise TypeError(f"objects[{k}].field must be a Field, got {type(obj.field).__name__}")
        iid = obj.instance_id
        if isinstance(iid, bool) or int(iid) != iid or iid < 1:
            raise RegnfError(f"objects[{k}]: instance_id must be an integer >= 1, got {iid!r}")
        if int(iid) in ids:
            raise RegnfError(f"objects[{k}]: instance_id {iid} is used twice")
        if obj.field.device != scene.device:
            raise RegnfError(
                f"objects[{k}] ({obj.field.name!r}) is on {obj.field.device} but the scene is on "
                f"{scene.device}; move them to one device"
            )
        tint = None
        if obj.tint is not None:
            tint = tuple(float(v) for v in np.asarray(obj.tint, dtype=np.float64).reshape(-1))
            if len(tint) != 3 or not all(0.0 <= v <= 1.0 for v in tint):
                raise RegnfError(
                    f"objects[{k}]: tint must be 3 numbers in [0, 1], got {obj.tint!r}"
                )
        placements.append(Placement(obj.field, obj.library_to_scene, config.cull_pad, config.cull))
        ids.append(int(iid))
        tints.append(tint)
    return placements, ids, tints
