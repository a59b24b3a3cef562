"""The neural SDF field: multi-resolution features + a small MLP with SDF and colour heads."""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F

from regnf.core.box_grid import grid_shape
from regnf.core.denormals import denormals_flushed
from regnf.core.errors import RegnfError
from regnf.fields.dense_grid import DenseGridEncoding, level_resolutions
from regnf.fields.field import Field, FieldInfo
from regnf.fields.hash_grid import HashGridEncoding

ARCHITECTURE = "regnf.neural_sdf.v1"
"""Name written into checkpoints; loading refuses any other architecture."""


@dataclass
class NeuralSDFConfig:
    """Architecture of a :class:`NeuralSDF` (saved in every checkpoint)."""

    encoding: str = "dense"
    """Feature encoding: ``dense`` (grid_sample pyramid, default) or ``hash``."""
    levels: int = 6
    """Number of grid levels."""
    features_per_level: int = 4
    """Feature channels per level."""
    base_resolution: int = 16
    """Cells along the longest bounds axis at the coarsest level."""
    finest_resolution: int = 128
    """Cells along the longest bounds axis at the finest level."""
    hash_table_size_log2: int = 18
    """Hash encoding only: at most 2**k entries per level."""
    hidden_dim: int = 64
    """Width of the SDF MLP."""
    hidden_layers: int = 2
    """Hidden layers of the SDF MLP."""
    geo_feature_dim: int = 15
    """Extra outputs of the SDF MLP passed to the colour head."""
    color_hidden_dim: int = 64
    """Width of the colour MLP."""
    view_dependent: bool = False
    """Feed the viewing direction to the colour head (off: our captures are Lambertian)."""
    color_grid_features: bool = False
    """Feed the grid features to the colour head too, beside the SDF MLP's (docs/decisions/field-training.md)."""
    init_radius: float = 0.5
    """Radius of the sphere the SDF starts as (geometric initialisation), field units."""
    inside_out: bool = False
    """Start with positive SDF inside the init sphere (rooms seen from inside)."""

    def __post_init__(self) -> None:
        self.validate()

    def to_json(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_json(data: dict) -> NeuralSDFConfig:
        """Parse a checkpoint's ``config`` block, strictly: every value of its field's type.

        Raises
        ------
        TypeError
            ``data`` is not an object.
        ValueError
            Unknown keys, a value of the wrong type (``"3"`` or ``16.5`` for an
            integer, ``1`` for a flag), a non-finite float, or a value out of its range (see
            :meth:`validate`). Size LIMITS are the checkpoint reader's business
            (:class:`regnf.io.checkpoint.ArchitectureLimits`).
        """
        if not isinstance(data, dict):
            raise TypeError(f"the architecture config must be an object, got {type(data).__name__}")
        defaults = {f.name: f.default for f in fields(NeuralSDFConfig)}
        unknown = sorted(set(data) - set(defaults))
        if unknown:
            raise RegnfError(f"unknown architecture keys {unknown}")
        for name, value in data.items():
            kind = type(defaults[name])
            if not _is_a(value, kind):
                raise RegnfError(f"'{name}' must be {_TYPE_WORDS[kind]}, got {value!r}")
        # The constructor validates the values.
        return NeuralSDFConfig(**{k: float(v) if type(defaults[k]) is float else v for k, v in data.items()})

    def validate(self) -> None:
        """Refuse values no network can have (ValueError naming the key).

        The grid pyramid itself (``levels >= 1``, ``2 <= base <= finest``) is checked where
        it is built, by :func:`regnf.fields.dense_grid.level_resolutions`.
        """
        if self.encoding not in ("dense", "hash"):
            raise RegnfError(f"unknown encoding {self.encoding!r} (expected 'dense' or 'hash')")
        for name in ("features_per_level", "hash_table_size_log2", "hidden_dim", "color_hidden_dim"):
            if getattr(self, name) < 1:
                raise RegnfError(f"'{name}' must be >= 1, got {getattr(self, name)}")
        for name in ("hidden_layers", "geo_feature_dim"):
            if getattr(self, name) < 0:
                raise RegnfError(f"'{name}' must be >= 0, got {getattr(self, name)}")
        if not self.init_radius > 0:
            raise RegnfError(f"'init_radius' must be > 0, got {self.init_radius}")


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}
"""How a config type reads in an error message."""


def _is_a(value: object, kind: type) -> bool:
    """``value`` is a JSON value of config type ``kind`` (bool, int, float or str)."""
    # bool is an int subclass: True is not a number of levels, 3 is not a flag.
    if kind is bool or isinstance(value, bool):
        return kind is bool and isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and math.isfinite(value)
    return isinstance(value, kind)


def parameter_count(config: NeuralSDFConfig, extent: torch.Tensor) -> int:
    """Number of trainable values of a :class:`NeuralSDF`, without building it.

    Parameters
    ----------
    config : NeuralSDFConfig
    extent : (3,) float
        Size of the bounds box (only its aspect ratio matters).

    Returns
    -------
    int
        Exactly ``sum(p.numel() for p in NeuralSDF(config, bounds).parameters())``.
        Costs one step per level: bound ``config.levels`` first.
    """
    cfg = config
    extent = torch.as_tensor(extent, dtype=torch.float32, device="cpu")
    cells = 0
    for res in level_resolutions(cfg.levels, cfg.base_resolution, cfg.finest_resolution):
        nx, ny, nz = grid_shape(res, extent)
        # A dense level holds nx * ny * nz samples; a hash level one row per cell corner,
        # at most 2**k of them (see HashGridEncoding).
        cells += nx * ny * nz if cfg.encoding == "dense" else min(
            (nx + 1) * (ny + 1) * (nz + 1), 2**cfg.hash_table_size_log2
        )
    total = cells * cfg.features_per_level
    dims = [3 + cfg.levels * cfg.features_per_level] + [cfg.hidden_dim] * cfg.hidden_layers
    dims.append(1 + cfg.geo_feature_dim)
    total += sum(a * b + b for a, b in itertools.pairwise(dims))
    color_in = color_input_dim(cfg, cfg.levels * cfg.features_per_level)
    ch = cfg.color_hidden_dim
    total += (color_in * ch + ch) + (ch * ch + ch) + (ch * 3 + 3)
    return total


def color_input_dim(config: NeuralSDFConfig, encoding_dim: int) -> int:
    """Inputs of the colour head: geometry features, the normal, the view direction if used,
    and the grid features if :attr:`NeuralSDFConfig.color_grid_features`."""
    return (config.geo_feature_dim + 3 + (3 if config.view_dependent else 0)
            + (encoding_dim if config.color_grid_features else 0))


class NeuralSDF(Field):
    """A trainable SDF field.

    Parameters
    ----------
    config : NeuralSDFConfig
    bounds : (2, 3) float
        AABB of the field in its own frame; the grids cover exactly this box.
    to_world : (4, 4) float
        Field frame -> metres.
    """

    def __init__(
        self,
        config: NeuralSDFConfig | None = None,
        bounds: torch.Tensor | None = None,
        to_world: torch.Tensor | None = None,
        info: FieldInfo | None = None,
    ) -> None:
        super().__init__(bounds=bounds, to_world=to_world, info=info)
        self.config = cfg = config or NeuralSDFConfig()
        extent = self.bounds[1] - self.bounds[0]
        if cfg.encoding == "dense":
            self.encoding: torch.nn.Module = DenseGridEncoding(
                extent, cfg.levels, cfg.features_per_level, cfg.base_resolution, cfg.finest_resolution
            )
        elif cfg.encoding == "hash":
            self.encoding = HashGridEncoding(
                extent, cfg.levels, cfg.features_per_level, cfg.base_resolution,
                cfg.finest_resolution, cfg.hash_table_size_log2,
            )
        else:
            raise RegnfError(f"unknown encoding {cfg.encoding!r}")
        enc_dim = self.encoding.output_dim
        dims = [3 + enc_dim] + [cfg.hidden_dim] * cfg.hidden_layers + [1 + cfg.geo_feature_dim]
        self.sdf_layers = torch.nn.ModuleList(
            torch.nn.Linear(a, b) for a, b in itertools.pairwise(dims)
        )
        color_in = color_input_dim(cfg, enc_dim)
        self.color_net = torch.nn.Sequential(
            torch.nn.Linear(color_in, cfg.color_hidden_dim),
            torch.nn.ReLU(),
            torch.nn.Linear(cfg.color_hidden_dim, cfg.color_hidden_dim),
            torch.nn.ReLU(),
            torch.nn.Linear(cfg.color_hidden_dim, 3),
        )
        self._geometric_init(enc_dim)

    @torch.no_grad()
    def _geometric_init(self, enc_dim: int) -> None:
        # SAL-style initialisation: the MLP starts as the SDF of a sphere in field coordinates
        # (features start near zero and their input weights at zero), so early training is
        # already a valid distance field and the eikonal term is satisfied from step 0.
        cfg = self.config
        if self.sdf_layers[0].weight.is_meta:
            return  # a skeleton: its weights will be loaded (see dense_grid.initial_values)
        for i, layer in enumerate(self.sdf_layers):
            out_dim, in_dim = layer.weight.shape
            if i == len(self.sdf_layers) - 1:
                torch.nn.init.normal_(layer.weight, mean=math.sqrt(math.pi) / math.sqrt(in_dim), std=1e-4)
                torch.nn.init.constant_(layer.bias, -cfg.init_radius)
                if cfg.inside_out:
                    layer.weight.neg_()
                    layer.bias.neg_()
            elif i == 0:
                torch.nn.init.constant_(layer.bias, 0.0)
                torch.nn.init.normal_(layer.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
                layer.weight[:, 3:].zero_()
            else:
                torch.nn.init.constant_(layer.bias, 0.0)
                torch.nn.init.normal_(layer.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))

    # -- evaluation ----------------------------------------------------------------------
    def box_coordinates(self, x: torch.Tensor) -> torch.Tensor:
        """Map field-frame points (n, 3) to [-1, 1]^3 over the bounds."""
        lo, hi = self.bounds[0], self.bounds[1]
        return (x - lo) / (hi - lo) * 2.0 - 1.0

    def _forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The SDF MLP's outputs (n, 1 + geo_feature_dim) and the grid features (n, k) at ``x``."""
        with denormals_flushed():  # the softplus is many times faster (core.denormals)
            enc = self.encoding(self.box_coordinates(x))
            h = torch.cat([x, enc], dim=-1)
            last = len(self.sdf_layers) - 1
            for i, layer in enumerate(self.sdf_layers):
                h = layer(h)
                if i < last:
                    h = F.softplus(h, beta=100.0)
        return h, enc

    def sdf_and_features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SDF (n,) and the colour head's features (n, k) at field-frame points (n, 3): the
        geometry features, then the grid features if ``config.color_grid_features``."""
        h, enc = self._forward(x)
        if self.config.color_grid_features:
            return h[:, 0], torch.cat([h[:, 1:], enc], dim=-1)
        return h[:, 0], h[:, 1:]

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return self._forward(x)[0][:, 0]

    def color_from(self, features: torch.Tensor, normals: torch.Tensor, d: torch.Tensor | None) -> torch.Tensor:
        """Colour head on precomputed geometry features (n, k), unit normals (n, 3), dirs (n, 3)."""
        parts = [features, normals]
        if self.config.view_dependent:
            if d is None:
                d = -normals
            parts.append(d)
        return torch.sigmoid(self.color_net(torch.cat(parts, dim=-1)))

    def color(self, x: torch.Tensor, d: torch.Tensor | None = None) -> torch.Tensor:
        with torch.enable_grad(), denormals_flushed():  # its backward too
            xr = x.detach().requires_grad_(True)
            s, feat = self.sdf_and_features(xr)
            (g,) = torch.autograd.grad(s.sum(), xr)
        n = F.normalize(g, dim=-1)
        return self.color_from(feat.detach(), n, d)


TETRAHEDRON = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))
"""Offsets of the 4-sample tetrahedral finite difference."""


def tetrahedral_points(x: torch.Tensor, h: float) -> torch.Tensor:
    """The 4 sample points (4n, 3) around each of ``x`` (n, 3) at step ``h`` (point-major)."""
    k = torch.tensor(TETRAHEDRON, device=x.device, dtype=x.dtype)
    return (x[:, None, :] + h * k[None]).reshape(-1, 3)


def tetrahedral_combine(values: torch.Tensor, h: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradient (n, 3) and mean value (n,) from the SDF (4n,) at :func:`tetrahedral_points`."""
    k = torch.tensor(TETRAHEDRON, device=values.device, dtype=values.dtype)
    v = values.view(-1, 4)
    return (v[..., None] * k[None]).sum(dim=1) / (4.0 * h), v.mean(dim=1)


def tetrahedral_gradient(
    sdf_fn, x: torch.Tensor, h: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Finite-difference SDF gradient (n, 3) from 4 tetrahedral samples at step ``h``.

    ``grid_sample`` has no second derivative, so training losses on the gradient (eikonal,
    normals) use this differentiable estimate; it also smooths over sub-voxel noise. Also
    returns the SDF estimate at ``x`` (n,) (the mean of the four samples). Training batches
    the sample points with everything else through :func:`tetrahedral_points` and
    :func:`tetrahedral_combine` instead, to query the network once per step.
    """
    return tetrahedral_combine(sdf_fn(tetrahedral_points(x, h)), h)
