"""A library object's source mesh in its asset layer: a ``Mesh`` with ``UsdPreviewSurface`` materials.

Under the library object's prim::

    Source           Mesh, purpose render, proxyPrim -> Proxy; normals face-varying
                     (a face's own normal at a corner sharper than CREASE_DEGREES)
        color_<k>    GeomSubset (familyName materialBind) of the faces of one colour
    Looks/
        color_<k>    Material: UsdPreviewSurface, constant diffuseColor
        texture      Material: UsdPreviewSurface <- UsdUVTexture (library/textures/<name>.png,
                     scaled by the base colour) <- UsdPrimvarReader_float2 ("st")
        base         Material: the base colour alone (a mesh without colours)

Face colours are 8-bit sRGB in the source; ``diffuseColor`` and ``displayColor`` (uniform, per
face) hold them linear, as USD's renderers expect. More than :data:`MAX_SUBSETS` colours (a
vertex-coloured scan) make one material whose diffuse colour reads ``displayColor``.
"""

from __future__ import annotations

import numpy as np
from pxr import Ar, Gf, Sdf, Usd, UsdGeom, Vt

from regnf.core.errors import RegnfError
from regnf.core.srgb import linear_to_srgb, srgb_to_linear
from regnf.meshes.source_mesh import SourceMesh

from . import layout as L
from .boundary import Boundary
from .errors import StageError

MAX_SUBSETS = 64
"""Most distinct face colours given a material each."""

CREASE_DEGREES = 30.0
"""A corner whose vertex normal is further than this from its face's normal shows the face's."""

ROUGHNESS = 0.6
"""``roughness`` of every source material (the files carry no more than a colour)."""


def corner_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f * 3, 3) float32 face-varying normals: the smooth vertex normal at a corner, or the face's
    own where the two are more than :data:`CREASE_DEGREES` apart (a box stays a box)."""
    p = np.asarray(points, np.float64)
    f = np.asarray(faces, np.int64)
    tri = p[f]
    area_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n = area_n / np.maximum(np.linalg.norm(area_n, axis=1, keepdims=True), 1e-30)
    vert_n = np.zeros_like(p)
    for corner in range(3):  # a loop over the three corners of every face
        np.add.at(vert_n, f[:, corner], area_n)
    vert_n /= np.maximum(np.linalg.norm(vert_n, axis=1, keepdims=True), 1e-30)
    at_corner = vert_n[f]  # (f, 3, 3)
    smooth = (at_corner * face_n[:, None]).sum(-1) >= np.cos(np.radians(CREASE_DEGREES))
    out = np.where(smooth[..., None], at_corner, face_n[:, None])
    return out.reshape(-1, 3).astype(np.float32)


def _attr(spec: Sdf.PrimSpec, name: str, type_name: Sdf.ValueTypeName, value: object,
          uniform: bool = False) -> Sdf.AttributeSpec:
    a = Sdf.AttributeSpec(spec, name, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    a.default = value
    return a


def _shader(material: Sdf.PrimSpec, name: str, shader_id: str) -> Sdf.PrimSpec:
    s = Sdf.PrimSpec(material, name, Sdf.SpecifierDef, "Shader")
    _attr(s, "info:id", Sdf.ValueTypeNames.Token, shader_id, uniform=True)
    return s


def _connect(attr: Sdf.AttributeSpec, source: Sdf.Path) -> None:
    attr.connectionPathList.Prepend(source)


def _material(looks: Sdf.PrimSpec, name: str, diffuse: np.ndarray | None = None,
              texture: tuple[str, np.ndarray] | None = None, from_display_color: bool = False) -> Sdf.Path:
    """A ``UsdPreviewSurface`` material: a constant diffuse colour, a scaled texture, or ``displayColor``."""
    T = Sdf.ValueTypeNames
    mat = Sdf.PrimSpec(looks, name, Sdf.SpecifierDef, "Material")
    surface = _shader(mat, "PreviewSurface", "UsdPreviewSurface")
    _attr(surface, "inputs:roughness", T.Float, ROUGHNESS)
    _attr(surface, "inputs:metallic", T.Float, 0.0)
    diffuse_in = _attr(surface, "inputs:diffuseColor", T.Color3f,
                       Gf.Vec3f(*(diffuse if diffuse is not None else (0.5, 0.5, 0.5))))
    out = Sdf.AttributeSpec(surface, "outputs:surface", T.Token)
    mat_out = Sdf.AttributeSpec(mat, "outputs:surface", T.Token)
    _connect(mat_out, out.path)
    if texture is not None:
        file, scale = texture
        reader = _shader(mat, "StReader", "UsdPrimvarReader_float2")
        _attr(reader, "inputs:varname", T.String, "st")
        reader_out = Sdf.AttributeSpec(reader, "outputs:result", T.Float2)
        tex = _shader(mat, "BaseColorTexture", "UsdUVTexture")
        _attr(tex, "inputs:file", T.Asset, Sdf.AssetPath(file))
        _attr(tex, "inputs:sourceColorSpace", T.Token, "sRGB")
        _attr(tex, "inputs:wrapS", T.Token, "repeat")
        _attr(tex, "inputs:wrapT", T.Token, "repeat")
        _attr(tex, "inputs:scale", T.Float4, Gf.Vec4f(*np.asarray(scale, float).tolist(), 1.0))
        _connect(_attr(tex, "inputs:st", T.Float2, Gf.Vec2f(0, 0)), reader_out.path)
        rgb = Sdf.AttributeSpec(tex, "outputs:rgb", T.Float3)
        _connect(diffuse_in, rgb.path)
    elif from_display_color:
        reader = _shader(mat, "DisplayColorReader", "UsdPrimvarReader_float3")
        _attr(reader, "inputs:varname", T.String, "displayColor")
        _connect(diffuse_in, Sdf.AttributeSpec(reader, "outputs:result", T.Float3).path)
    return mat.path


def _bind(spec: Sdf.PrimSpec, material: Sdf.Path) -> None:
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=["MaterialBindingAPI"]))
    rel = Sdf.RelationshipSpec(spec, "material:binding", custom=False)
    rel.targetPathList.Prepend(material)


def author_source_mesh(parent: Sdf.PrimSpec, mesh: SourceMesh, texture_rel: str | None) -> Sdf.PrimSpec:
    """Author ``mesh`` as ``Source`` under ``parent`` with its materials in ``Looks``.

    ``texture_rel`` is the texture's path relative to the layer (its bytes are written by the
    caller); required when the mesh has a texture.
    """
    T = Sdf.ValueTypeNames
    pts = np.ascontiguousarray(mesh.points, np.float32)
    faces = np.ascontiguousarray(mesh.faces, np.int32)
    spec = Sdf.PrimSpec(parent, L.SOURCE, Sdf.SpecifierDef, "Mesh")
    _attr(spec, "points", T.Point3fArray, Vt.Vec3fArray.FromNumpy(pts))
    _attr(spec, "faceVertexCounts", T.IntArray, Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    _attr(spec, "faceVertexIndices", T.IntArray, Vt.IntArray.FromNumpy(faces.reshape(-1)))
    extent = np.stack([pts.min(0), pts.max(0)])
    _attr(spec, "extent", T.Float3Array, Vt.Vec3fArray.FromNumpy(extent))
    _attr(spec, "subdivisionScheme", T.Token, "none", uniform=True)
    _attr(spec, "normals", T.Normal3fArray, Vt.Vec3fArray.FromNumpy(corner_normals(pts, faces))).SetInfo(
        "interpolation", "faceVarying")
    _attr(spec, "purpose", T.Token, "render", uniform=True)
    proxy = Sdf.RelationshipSpec(spec, "proxyPrim", custom=False)
    proxy.targetPathList.Prepend(parent.path.AppendChild(L.PROXY))
    looks = Sdf.PrimSpec(parent, L.LOOKS, Sdf.SpecifierDef, "Scope")
    if mesh.uv is not None and mesh.texture is not None:
        if texture_rel is None:
            raise RegnfError("a textured source mesh needs the texture's path")
        _attr(spec, "primvars:st", T.TexCoord2fArray,
              Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(mesh.uv, np.float32))).SetInfo("interpolation", "vertex")
        _bind(spec, _material(looks, "texture", texture=(texture_rel, srgb_to_linear(mesh.base_color))))
    elif mesh.face_colors is not None:
        linear = srgb_to_linear(mesh.face_colors).astype(np.float32)
        _attr(spec, "primvars:displayColor", T.Color3fArray, Vt.Vec3fArray.FromNumpy(linear)).SetInfo(
            "interpolation", "uniform")
        codes = np.round(np.asarray(mesh.face_colors) * 255).astype(np.int64)
        colours, which = np.unique(codes, axis=0, return_inverse=True)
        which = which.reshape(-1)
        if len(colours) > MAX_SUBSETS:
            _bind(spec, _material(looks, "display_color", from_display_color=True))
        else:
            _attr(spec, "subsetFamily:materialBind:familyType", T.Token, "partition", uniform=True)
            for k, code in enumerate(colours):  # a loop over distinct colours (at most MAX_SUBSETS)
                subset = Sdf.PrimSpec(spec, f"color_{k}", Sdf.SpecifierDef, "GeomSubset")
                _attr(subset, "elementType", T.Token, "face", uniform=True)
                _attr(subset, "familyName", T.Token, "materialBind", uniform=True)
                _attr(subset, "indices", T.IntArray, Vt.IntArray.FromNumpy(np.flatnonzero(which == k).astype(np.int32)))
                _bind(subset, _material(looks, f"color_{k}", diffuse=srgb_to_linear(code / 255.0)))
    else:
        _bind(spec, _material(looks, "base", diffuse=srgb_to_linear(mesh.base_color)))
    return spec


def _texture_bytes(prim: Usd.Prim, file: str, boundary: Boundary, where: str) -> bytes:
    """The PNG bytes of the source mesh's texture (from a package too)."""
    shader = prim.GetParent().GetChild(L.LOOKS).GetChild("texture").GetChild("BaseColorTexture")
    attr = shader.GetAttribute("inputs:file") if shader else None
    asset = attr.Get() if attr else None
    if not asset or not asset.path:
        raise StageError(file, where, "a textured source mesh needs its texture's file")
    spec = attr.GetPropertyStack(Usd.TimeCode.Default())[0]
    ident = boundary.resolve(spec.layer, asset.path, where, "texture path")
    resolved = Ar.GetResolver().Resolve(ident)
    data = Ar.GetResolver().OpenAsset(resolved) if resolved else None
    if data is None:
        raise StageError(file, where, f"texture {asset.path!r} does not exist")
    return bytes(memoryview(data.GetBuffer())[:data.GetSize()])


def read_source_mesh(prim: Usd.Prim, file: str, boundary: Boundary) -> SourceMesh | None:
    """The source mesh under a library object's prim, or None when it has none."""
    child = prim.GetChild(L.SOURCE)
    if not child:
        return None
    where = str(child.GetPath())
    if not child.IsA(UsdGeom.Mesh):
        raise StageError(file, where, "a library object's source mesh must be a Mesh")
    m = UsdGeom.Mesh(child)
    pts = np.asarray(m.GetPointsAttr().Get(), np.float32).reshape(-1, 3)
    counts = np.asarray(m.GetFaceVertexCountsAttr().Get(), np.int32)
    idx = np.asarray(m.GetFaceVertexIndicesAttr().Get(), np.int32)
    if len(pts) == 0 or not (counts == 3).all() or idx.size != 3 * counts.size or not np.isfinite(pts).all():
        raise StageError(file, where, "the source mesh must be a non-empty triangle mesh with finite points")
    faces = idx.reshape(-1, 3)
    if faces.min() < 0 or faces.max() >= len(pts):
        raise StageError(file, where, "the source mesh's face indices are out of range")
    pv = UsdGeom.PrimvarsAPI(child)
    st, colour = pv.GetPrimvar("st"), pv.GetPrimvar("displayColor")
    looks = prim.GetChild(L.LOOKS)
    if st and st.HasAuthoredValue():
        uv = np.asarray(st.Get(), np.float32).reshape(-1, 2)
        if len(uv) != len(pts):
            raise StageError(file, where, "the source mesh's st must have one value per point")
        scale = looks.GetChild("texture").GetChild("BaseColorTexture").GetAttribute("inputs:scale").Get()
        base = linear_to_srgb(np.asarray(scale, np.float64)[:3]).astype(np.float32)
        return SourceMesh(pts, faces, base, None, uv, _texture_bytes(child, file, boundary, where))
    if colour and colour.HasAuthoredValue():
        fc = np.asarray(colour.Get(), np.float64).reshape(-1, 3)
        if len(fc) != len(faces):
            raise StageError(file, where, "the source mesh's displayColor must have one value per face")
        return SourceMesh(pts, faces, np.ones(3, np.float32), linear_to_srgb(fc).astype(np.float32))
    diffuse = looks.GetChild("base").GetChild("PreviewSurface").GetAttribute("inputs:diffuseColor").Get() \
        if looks and looks.GetChild("base") else None
    if diffuse is None:
        raise StageError(file, where, "the source mesh has no colours, texture or base material")
    return SourceMesh(pts, faces, linear_to_srgb(np.asarray(diffuse, np.float64)).astype(np.float32))
