"""Exact analytic SDF fields: primitives, unions and similarity-transformed children.

They answer to the same :class:`~regnf.fields.field.Field` interface as neural fields, so
registration, compositing, meshing and rendering can be tested against closed forms. All
are differentiable in torch; parameters are float64 buffers (so ``.to(device)`` moves them
and closed-form tests are exact) and are cast to the dtype of the query points.

Distance formulas follow Inigo Quilez's catalogue of exact SDFs; every primitive here is an
exact Euclidean distance (gradient norm 1 almost everywhere) except :class:`SmoothUnion`,
which is only a bound near the blend.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from regnf.core.errors import RegnfError

from .field import Field, FieldInfo, check_points
from .similarity import decompose_similarity

Vec3 = Sequence[float]

BOUNDS_MARGIN = 0.02
"""Bounds padding of primitives, as a fraction of their largest extent (keeps surfaces inside)."""

DEFAULT_COLOR = (0.8, 0.8, 0.8)
"""Light grey."""


def _vec3(v: Vec3 | torch.Tensor | np.ndarray, what: str) -> torch.Tensor:
    t = (
        torch.as_tensor(
            np.asarray(v, dtype=np.float64) if not isinstance(v, torch.Tensor) else v,
            dtype=torch.float64,
        )
        .detach()
        .cpu()
    )
    if t.shape != (3,) or not bool(torch.isfinite(t).all()):
        raise RegnfError(f"{what} must be 3 finite numbers, got {t.tolist()}")
    return t


def _positive(v: float, what: str) -> float:
    v = float(v)
    if not np.isfinite(v) or v <= 0:
        raise RegnfError(f"{what} must be finite and > 0, got {v}")
    return v


def _padded(lo: torch.Tensor, hi: torch.Tensor, margin: float = BOUNDS_MARGIN) -> torch.Tensor:
    """(2, 3) AABB ``[lo, hi]`` grown by ``margin`` times its largest extent."""
    pad = margin * float((hi - lo).max())
    return torch.stack([lo - pad, hi + pad]).float()


def _info(label: str | None, name: str | None, default_name: str, kind: str) -> FieldInfo:
    return FieldInfo(
        label=label or "object",
        name=name if name is not None else default_name,
        provenance={"analytic": kind},
    )


class AnalyticField(Field):
    """A field with a closed-form SDF and one constant colour.

    Parameters
    ----------
    bounds : (2, 3) float
        AABB of the surface in the field frame, already padded.
    color : (3,) float in [0, 1]
        The colour everywhere.
    to_world : (4, 4) float, optional
        Field frame -> world similarity; identity by default.
    info : FieldInfo, optional
    """

    rgb: torch.Tensor

    def __init__(
        self,
        bounds: torch.Tensor,
        color: Vec3 = DEFAULT_COLOR,
        to_world: torch.Tensor | np.ndarray | None = None,
        info: FieldInfo | None = None,
    ) -> None:
        super().__init__(bounds=bounds, to_world=_as_to_world(to_world), info=info)
        rgb = _vec3(color, "color")
        if bool((rgb < 0).any() or (rgb > 1).any()):
            raise RegnfError(f"color must lie in [0, 1], got {rgb.tolist()}")
        self.register_buffer("rgb", rgb)

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """Constant colour: (n, 3) in [0, 1] for points ``x`` (n, 3); ``d`` is ignored."""
        check_points(x, self)
        return self.rgb.to(x.dtype).expand(x.shape[0], 3).clone()

    def _p(self, name: str, x: torch.Tensor) -> torch.Tensor:
        """Parameter buffer ``name`` in the dtype of ``x``."""
        return getattr(self, name).to(x.dtype)


def _as_to_world(m: torch.Tensor | np.ndarray | None) -> torch.Tensor | None:
    if m is None:
        return None
    mt = torch.as_tensor(
        np.asarray(m) if not isinstance(m, torch.Tensor) else m, dtype=torch.float64
    )
    decompose_similarity(mt)  # validates: to_world must be a similarity
    return mt


class Sphere(AnalyticField):
    """``|x - c| - r``.

    Parameters
    ----------
    radius : float
        > 0.
    center : (3,) float
    color : (3,) float in [0, 1]
    label, name : str, optional
        Stored in ``info``.
    to_world : (4, 4) float, optional
    """

    def __init__(
        self,
        radius: float = 1.0,
        center: Vec3 = (0.0, 0.0, 0.0),
        color: Vec3 = DEFAULT_COLOR,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        r = _positive(radius, "radius")
        c = _vec3(center, "center")
        super().__init__(
            _padded(c - r, c + r), color, to_world, _info(label, name, "sphere", "sphere")
        )
        self.register_buffer("radius", torch.tensor(r, dtype=torch.float64))
        self.register_buffer("center", c)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        return torch.linalg.vector_norm(x - self._p("center", x), dim=-1) - self._p("radius", x)


def _from_slab_distances(q: torch.Tensor) -> torch.Tensor:
    """Exact SDF (n,) of an intersection of slabs from signed per-axis distances ``q`` (n, k).

    Outside: the length of the positive part; inside: the largest (least negative) distance.
    """
    outside = torch.linalg.vector_norm(q.clamp(min=0.0), dim=-1)
    inside = q.max(dim=-1).values.clamp(max=0.0)
    return outside + inside


def box_sdf(p: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Exact SDF (n,) of the centred box with half extents ``b`` (3,) at points ``p`` (n, 3)."""
    return _from_slab_distances(p.abs() - b)


class Box(AnalyticField):
    """Axis-aligned box with half extents ``b`` centred at ``c``.

    Parameters
    ----------
    half_extents : (3,) float
        All > 0.
    center : (3,) float
    color, label, name, to_world
        As for :class:`Sphere`.
    """

    def __init__(
        self,
        half_extents: Vec3 = (1.0, 1.0, 1.0),
        center: Vec3 = (0.0, 0.0, 0.0),
        color: Vec3 = DEFAULT_COLOR,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        b = _vec3(half_extents, "half_extents")
        for v in b.tolist():
            _positive(v, "half_extents")
        c = _vec3(center, "center")
        super().__init__(_padded(c - b, c + b), color, to_world, _info(label, name, "box", "box"))
        self.register_buffer("half_extents", b)
        self.register_buffer("center", c)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        return box_sdf(x - self._p("center", x), self._p("half_extents", x))


class RoundedBox(AnalyticField):
    """Box with rounded edges: the inner box ``half_extents - radius`` dilated by ``radius``.

    Parameters
    ----------
    half_extents : (3,) float
        OUTER half size (the faces stay where a :class:`Box` of these extents has them).
    radius : float
        Edge radius, 0 < radius <= min(half_extents).
    center : (3,) float
    color, label, name, to_world
        As for :class:`Sphere`.
    """

    def __init__(
        self,
        half_extents: Vec3 = (1.0, 1.0, 1.0),
        radius: float = 0.1,
        center: Vec3 = (0.0, 0.0, 0.0),
        color: Vec3 = DEFAULT_COLOR,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        b = _vec3(half_extents, "half_extents")
        for v in b.tolist():
            _positive(v, "half_extents")
        r = _positive(radius, "radius")
        if r > float(b.min()):
            raise RegnfError(f"radius {r} exceeds the smallest half extent {float(b.min())}")
        c = _vec3(center, "center")
        info = _info(label, name, "rounded_box", "rounded_box")
        super().__init__(_padded(c - b, c + b), color, to_world, info)
        self.register_buffer("half_extents", b)
        self.register_buffer("radius", torch.tensor(r, dtype=torch.float64))
        self.register_buffer("center", c)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        r = self._p("radius", x)
        return box_sdf(x - self._p("center", x), self._p("half_extents", x) - r) - r


class Cylinder(AnalyticField):
    """Capped cylinder along +Z: radius ``r``, ``|z - c_z| <= half_height``.

    Parameters
    ----------
    radius, half_height : float
        > 0.
    center : (3,) float
    color, label, name, to_world
        As for :class:`Sphere`.
    """

    def __init__(
        self,
        radius: float = 1.0,
        half_height: float = 1.0,
        center: Vec3 = (0.0, 0.0, 0.0),
        color: Vec3 = DEFAULT_COLOR,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        r = _positive(radius, "radius")
        h = _positive(half_height, "half_height")
        c = _vec3(center, "center")
        ext = torch.tensor([r, r, h], dtype=torch.float64)
        info = _info(label, name, "cylinder", "cylinder")
        super().__init__(_padded(c - ext, c + ext), color, to_world, info)
        self.register_buffer("radius", torch.tensor(r, dtype=torch.float64))
        self.register_buffer("half_height", torch.tensor(h, dtype=torch.float64))
        self.register_buffer("center", c)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        p = x - self._p("center", x)
        # 2D box SDF in (radial distance, height): exact for a solid of revolution.
        q = torch.stack(
            [
                torch.linalg.vector_norm(p[:, :2], dim=-1) - self._p("radius", x),
                p[:, 2].abs() - self._p("half_height", x),
            ],
            dim=-1,
        )
        return _from_slab_distances(q)


class Capsule(AnalyticField):
    """All points within ``radius`` of the segment ``a``-``b`` (a sphere if ``a == b``).

    Parameters
    ----------
    a, b : (3,) float
        Segment end points.
    radius : float
        > 0.
    color, label, name, to_world
        As for :class:`Sphere`.
    """

    def __init__(
        self,
        a: Vec3 = (0.0, 0.0, -0.5),
        b: Vec3 = (0.0, 0.0, 0.5),
        radius: float = 0.5,
        color: Vec3 = DEFAULT_COLOR,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        pa, pb = _vec3(a, "a"), _vec3(b, "b")
        r = _positive(radius, "radius")
        lo, hi = torch.minimum(pa, pb) - r, torch.maximum(pa, pb) + r
        super().__init__(_padded(lo, hi), color, to_world, _info(label, name, "capsule", "capsule"))
        self.register_buffer("a", pa)
        self.register_buffer("b", pb)
        self.register_buffer("radius", torch.tensor(r, dtype=torch.float64))

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        a, b = self._p("a", x), self._p("b", x)
        pa, ba = x - a, b - a
        # Clamp the denominator so a degenerate segment (a == b) is a sphere, not a NaN.
        h = ((pa @ ba) / (ba @ ba).clamp(min=torch.finfo(x.dtype).tiny)).clamp(0.0, 1.0)
        return torch.linalg.vector_norm(pa - h[:, None] * ba, dim=-1) - self._p("radius", x)


def _children(fields: Sequence[Field], what: str) -> torch.nn.ModuleList:
    if len(fields) == 0:
        raise RegnfError(f"{what} needs at least one field")
    for f in fields:
        if not isinstance(f, Field):
            raise TypeError(f"{what} takes Field instances, got {type(f).__name__}")
    return torch.nn.ModuleList(fields)


def _union_bounds(fields: Sequence[Field], pad: float = 0.0) -> torch.Tensor:
    lo = torch.stack([f.bounds[0].detach().cpu() for f in fields]).min(dim=0).values
    hi = torch.stack([f.bounds[1].detach().cpu() for f in fields]).max(dim=0).values
    return torch.stack([lo - pad, hi + pad])


class Union(Field):
    """Hard union: ``min_i sdf_i``; the colour is the colour of the field that wins the min.

    Parameters
    ----------
    *fields : Field
        At least one; all on the same device.
    label, name : str, optional
    to_world : (4, 4) float, optional
        Identity by default: the children's frame is the union's frame.
    """

    def __init__(
        self,
        *fields: Field,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        children = _children(fields, "Union")
        super().__init__(
            _union_bounds(fields), _as_to_world(to_world), _info(label, name, "union", "union")
        )
        self.fields = children
        # Live where the children live, so that composites of moved fields work as built.
        self.to(fields[0].device)

    def _all_sdf(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([f.sdf(x) for f in self.fields])  # (k, n)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        return self._all_sdf(x).min(dim=0).values

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """Colour (n, 3) of the child with the smallest SDF at each point."""
        check_points(x, self)
        with torch.no_grad():
            winner = self._all_sdf(x).argmin(dim=0)  # (n,)
        cols = torch.stack([f.color(x, d) for f in self.fields])  # (k, n, 3)
        return cols.gather(0, winner[None, :, None].expand(1, -1, 3))[0]


class SmoothUnion(Union):
    """Polynomial smooth union of children, colour blended with the same weights.

    Folds ``smin(a, b) = mix(b, a, h) - k h (1 - h)``, ``h = clamp(0.5 + 0.5 (b - a) / k, 0, 1)``
    over the children in order (for more than two fields the result depends on the order;
    it is not associative). It is below the hard union by at most ``k / 4``, so the bounds
    are the union's grown by ``k / 4``. Not an exact distance inside the blend region.

    Parameters
    ----------
    *fields : Field
        At least one.
    k : float
        Blend radius in field units, > 0.
    label, name, to_world
        As for :class:`Union`.
    """

    def __init__(
        self,
        *fields: Field,
        k: float = 0.1,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        super().__init__(*fields, label=label, name=name, to_world=to_world)
        self.k = _positive(k, "k")
        self.info = _info(label, name, "smooth_union", "smooth_union")
        self.bounds.copy_(_union_bounds(fields, pad=self.k / 4.0).to(self.bounds.device))

    def _blend(
        self, x: torch.Tensor, d: torch.Tensor | None, with_color: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        # A loop over children (not points): each fold step is vectorised over all points.
        dist = self.fields[0].sdf(x)
        col = self.fields[0].color(x, d) if with_color else None
        for f in list(self.fields)[1:]:
            di = f.sdf(x)
            h = (0.5 + 0.5 * (di - dist) / self.k).clamp(0.0, 1.0)
            dist = di + (dist - di) * h - self.k * h * (1.0 - h)
            if with_color:
                ci = f.color(x, d)
                col = ci + (col - ci) * h[:, None]
        return dist, col

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Smooth-min signed distance (n,) of points ``x`` (n, 3)."""
        check_points(x, self)
        return self._blend(x, None, with_color=False)[0]

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """Children's colours (n, 3) blended by the smooth-min weights."""
        check_points(x, self)
        col = self._blend(x, d, with_color=True)[1]
        assert col is not None
        return col


class Transformed(Field):
    """A child field placed by a similarity ``M`` (child frame -> this field's frame).

    ``sdf(y) = s * child.sdf(M^-1 y)`` with ``M = [[s R, t], [0, 1]]``: distances scale with
    the geometry. Colours pass through, with view directions rotated into the child frame.

    Parameters
    ----------
    child : Field
    matrix : (4, 4) float
        Similarity: uniform scale ``s > 0``, rotation, translation. Anything else (shear,
        non-uniform or negative scale, reflection) raises ``ValueError``.
    label, name : str, optional
        Default to the child's.
    to_world : (4, 4) float, optional
        This field's own frame -> world; identity by default (the new frame is treated as
        the world, as when placing a primitive in a scene). It is not derived from the
        child's ``to_world``.
    """

    matrix: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    scale: torch.Tensor

    def __init__(
        self,
        child: Field,
        matrix: torch.Tensor | np.ndarray,
        label: str | None = None,
        name: str | None = None,
        to_world: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        if not isinstance(child, Field):
            raise TypeError(f"Transformed takes a Field, got {type(child).__name__}")
        M = (
            torch.as_tensor(
                np.asarray(matrix) if not isinstance(matrix, torch.Tensor) else matrix,
                dtype=torch.float64,
            )
            .detach()
            .cpu()
        )
        R, t, s = decompose_similarity(M)
        lo, hi = child.bounds.detach().cpu().double()
        # The 8 corners of the child's box, mapped: their AABB contains the mapped surface.
        corners = torch.stack(
            [
                torch.stack([(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]])
                for i in (0, 1)
                for j in (0, 1)
                for k in (0, 1)
            ]
        )
        mapped = corners @ (s * R).T + t
        bounds = torch.stack([mapped.min(dim=0).values, mapped.max(dim=0).values])
        info = FieldInfo(
            label=label or child.info.label,
            name=name if name is not None else child.info.name,
            symmetry=child.info.symmetry,
            provenance={"analytic": "transformed", "child": dict(child.info.provenance)},
        )
        super().__init__(bounds, _as_to_world(to_world), info)
        self.child = child
        self.register_buffer("matrix", M.clone())
        self.register_buffer("rotation", R)
        self.register_buffer("translation", t)
        self.register_buffer("scale", s.clone())
        self.to(child.device)  # live where the child lives

    def to_child(self, y: torch.Tensor) -> torch.Tensor:
        """Map points ``y`` (n, 3) of this frame into the child's frame: ``R^T (y - t) / s``."""
        R, t, s = (b.to(y.dtype) for b in (self.rotation, self.translation, self.scale))
        return ((y - t) @ R) / s

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance (n,) of points ``x`` (n, 3), in this frame's units."""
        check_points(x, self)
        return self.scale.to(x.dtype) * self.child.sdf(self.to_child(x))

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """The child's colour (n, 3) at the mapped points, seen along rotated directions."""
        check_points(x, self)
        dc = None if d is None else d @ self.rotation.to(d.dtype)  # R^T d, row-wise
        return self.child.color(self.to_child(x), dc)
