"""The field interface every SDF in regnf answers to.

A field lives in its own *field frame* (normalised, roughly [-1, 1]^3) and carries a
``to_world`` similarity (4x4, uniform scale) from that frame to metres. Registration,
compositing, meshing and rendering accept any :class:`Field`: neural fields, analytic
fields and composites alike.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import torch

from regnf.core.denormals import denormals_flushed
from regnf.core.errors import RegnfError

if TYPE_CHECKING:
    from regnf.observations.visibility import VisibilityGrid

DEFAULT_CHUNK = 65536
"""Points evaluated per batch by the chunked helpers (bounded memory, still vectorised)."""


class FieldSample(NamedTuple):
    """What one query of a field finds and costs, point by point (:meth:`Field.evaluate`)."""

    sdf: torch.Tensor
    """(n,) float: signed distance in field units."""
    winner: torch.Tensor
    """(n,) int64: component at the minimum, 0 for a plain field (a composite: its instance)."""
    evals: torch.Tensor
    """(n,) int64: evaluations of underlying neural or analytic fields spent on each point."""


@dataclass(frozen=True)
class Symmetry:
    """The rotational symmetries of an object about its canonical up axis (+Z).

    ``order = 1`` means no symmetry, ``order = k`` a k-fold symmetry (rotations by
    2 pi j / k about Z leave the shape unchanged) and ``order = 0`` a continuous one.
    """

    order: int = 1
    """1: none; k > 1: k-fold about +Z; 0: continuous about +Z."""

    def to_json(self) -> dict:
        return {"axis": "z", "order": int(self.order)}

    @staticmethod
    def from_json(data: dict | None) -> Symmetry:
        if not data:
            return Symmetry()
        if data.get("axis", "z") != "z":
            raise RegnfError(f"only symmetries about z are supported, got axis {data.get('axis')!r}")
        order = int(data.get("order", 1))
        if order < 0:
            raise RegnfError(f"symmetry order must be >= 0, got {order}")
        return Symmetry(order)


@dataclass
class FieldInfo:
    """Descriptive metadata of a field: what it is and where it came from."""

    label: str = "object"
    """Semantic class, for example ``chair`` or ``table``; ``scene`` for a room."""
    name: str = ""
    """Instance or library name, for example ``dc``."""
    symmetry: Symmetry = field(default_factory=Symmetry)
    """Declared rotational symmetry about the canonical up axis."""
    provenance: dict = field(default_factory=dict)
    """Free-form JSON-serialisable record of how the field was made."""


class Field(torch.nn.Module, metaclass=abc.ABCMeta):
    """Base class of all signed-distance fields.

    Subclasses implement :meth:`sdf` and :meth:`color` on batched points and set
    ``bounds`` (2, 3) and ``to_world`` (4, 4) as buffers. Everything else (gradients,
    chunked evaluation, devices) is shared.

    ``visibility`` is where the field's training views observed space
    (:class:`regnf.observations.visibility.VisibilityGrid`, in the field frame), or None: nothing
    recorded, every point counts as observed (analytic fields, fields distilled from a mesh,
    checkpoints saved before fields recorded it). A grid assigned to it becomes a submodule:
    ``to(device)`` moves it and ``state_dict()`` holds its counts.
    """

    bounds: torch.Tensor
    to_world: torch.Tensor
    visibility: VisibilityGrid | None

    def __init__(
        self,
        bounds: torch.Tensor | None = None,
        to_world: torch.Tensor | None = None,
        info: FieldInfo | None = None,
    ) -> None:
        super().__init__()
        if bounds is None:
            bounds = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], device="cpu")
        # An explicit device keeps validation possible inside a ``torch.device("meta")``
        # context (checkpoint loading builds a weightless skeleton that way).
        bounds = torch.as_tensor(bounds, dtype=torch.float32, device=_device_of(bounds))
        if bounds.shape != (2, 3) or not bool((bounds[1] > bounds[0]).all()):
            raise RegnfError(f"bounds must be (2, 3) with max > min, got {bounds.tolist()}")
        if to_world is None:
            to_world = torch.eye(4, device=_device_of(bounds))
        to_world = torch.as_tensor(to_world, dtype=torch.float64, device=_device_of(to_world))
        if to_world.shape != (4, 4):
            raise RegnfError(f"to_world must be 4x4, got shape {tuple(to_world.shape)}")
        self.register_buffer("bounds", bounds.clone())
        # float64 keeps chained similarity transforms exact to well below a micrometre.
        self.register_buffer("to_world", to_world.clone())
        self.info = info or FieldInfo()
        self.visibility = None

    # -- the two methods a field must provide -------------------------------------------
    @abc.abstractmethod
    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance in field-frame units.

        Parameters
        ----------
        x : (n, 3) float
            Points in the field frame.

        Returns
        -------
        (n,) float
        """
        ...

    @abc.abstractmethod
    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        """RGB in [0, 1] at points ``x`` (n, 3) seen along unit directions ``d`` (n, 3)."""
        ...

    # -- shared behaviour -----------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.bounds.device

    @property
    def label(self) -> str:
        return self.info.label

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def symmetry(self) -> Symmetry:
        return self.info.symmetry

    @property
    def world_scale(self) -> float:
        """Metres per field-frame unit (the uniform scale of ``to_world``)."""
        return float(torch.linalg.det(self.to_world[:3, :3]).abs() ** (1.0 / 3.0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.sdf(x)

    def evaluate(self, x: torch.Tensor) -> FieldSample:
        """SDF, winning component and cost at points ``x`` (n, 3): what a renderer traces.

        A plain field is one component (0) costing one evaluation per point; a composite
        (:class:`regnf.compositor.composite_field.CompositeField`) reports its own.
        """
        s = self.sdf(x)
        ones = torch.ones(x.shape[0], dtype=torch.long, device=s.device)
        return FieldSample(s, torch.zeros_like(ones), ones)

    def sdf_and_gradient(
        self, x: torch.Tensor, create_graph: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF (n,) and its spatial gradient (n, 3) by autograd.

        Works under ``torch.no_grad()`` too: gradients w.r.t. the points are always
        enabled inside. ``create_graph=True`` keeps the graph for losses on the gradient.
        """
        with torch.enable_grad(), denormals_flushed():  # the backward of a network too (core.denormals)
            xr = x.detach().requires_grad_(True) if not create_graph else x
            if not xr.requires_grad:
                xr = xr.requires_grad_(True)
            s = self.sdf(xr)
            (g,) = torch.autograd.grad(s.sum(), xr, create_graph=create_graph)
        if not create_graph:
            s, g = s.detach(), g.detach()
        return s, g

    def gradient(self, x: torch.Tensor) -> torch.Tensor:
        """Spatial SDF gradient (n, 3) by autograd (detached)."""
        return self.sdf_and_gradient(x)[1]

    def normal(self, x: torch.Tensor) -> torch.Tensor:
        """Unit outward normals (n, 3)."""
        return torch.nn.functional.normalize(self.gradient(x), dim=-1)

    @torch.no_grad()
    def sdf_chunked(
        self, x: torch.Tensor, chunk: int = DEFAULT_CHUNK, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """No-grad SDF of many points, ``chunk`` at a time, on ``device`` (default: the field's).

        The result is returned on the device of ``x``.
        """
        return _chunked(lambda p: self.sdf(p), x, chunk, device or self.device)

    @torch.no_grad()
    def color_chunked(
        self,
        x: torch.Tensor,
        d: torch.Tensor | None = None,
        chunk: int = DEFAULT_CHUNK,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """No-grad colour of many points (n, 3), ``chunk`` at a time."""
        dev = torch.device(device or self.device)
        if d is None:
            return _chunked(lambda p: self.color(p, None), x, chunk, dev)
        both = torch.cat([x, d], dim=-1)
        return _chunked(lambda pd: self.color(pd[:, :3], pd[:, 3:]), both, chunk, dev)

    def contains(self, x: torch.Tensor, pad: float = 0.0) -> torch.Tensor:
        """(n,) bool: points inside the field's bounds inflated by ``pad``."""
        lo, hi = self.bounds[0] - pad, self.bounds[1] + pad
        return ((x >= lo) & (x <= hi)).all(dim=-1)

    @property
    def diagonal(self) -> float:
        """Length of the bounds' diagonal in field-frame units."""
        return float(torch.linalg.norm(self.bounds[1] - self.bounds[0]))


def _device_of(x: object) -> torch.device:
    """The device of a tensor argument; CPU for lists and arrays."""
    return x.device if isinstance(x, torch.Tensor) else torch.device("cpu")


def _chunked(
    fn: Callable[[torch.Tensor], torch.Tensor],
    x: torch.Tensor,
    chunk: int,
    device: torch.device | str,
) -> torch.Tensor:
    if x.ndim != 2:
        raise RegnfError(f"expected points of shape (n, k), got {tuple(x.shape)}")
    out_device = x.device
    if x.shape[0] == 0:
        probe = fn(x[:1].to(device).new_zeros((1, x.shape[1])))
        return probe.new_zeros((0, *probe.shape[1:])).to(out_device)
    # A loop over chunks (not points) bounds the memory of huge queries.
    parts = [fn(x[i : i + chunk].to(device)).to(out_device) for i in range(0, x.shape[0], chunk)]
    return torch.cat(parts, dim=0)


def check_points(x: torch.Tensor, field: Field) -> None:
    """Raise a clear error if ``x`` is not an (n, 3) float tensor on the field's device."""
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[-1] != 3:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise RegnfError(f"points must be a (n, 3) tensor, got {shape}")
    if x.device != field.device:
        raise RegnfError(
            f"points are on {x.device} but field {field.name or type(field).__name__!r} is on "
            f"{field.device}; move one of them (field.to(device) or x.to(device))"
        )
