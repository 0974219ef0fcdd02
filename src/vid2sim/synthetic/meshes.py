"""Textured triangle meshes: the :class:`TexturedMesh` container, watertightness checks and repair,
loading of user meshes (OBJ + MTL + texture, GLB/GLTF, PLY) and OBJ export.

Conventions
-----------
* ``faces`` index a single, position-merged vertex array, so a mesh whose UV seams split its
  vertices in the file becomes one closed surface here; texture coordinates live on the face
  corners instead (``uvs: (Nf, 3, 2)``), so seams cost nothing.
* UVs follow the OBJ / OpenGL convention: ``u`` to the right, ``v`` up, ``(0, 0)`` at the
  bottom-left corner of the texture image (row 0 of the image is its top). trimesh already flips
  glTF's v-down coordinates into this convention when it loads a GLB.
* Faces are wound counter-clockwise seen from outside, so ``(v1 - v0) × (v2 - v0)`` points out of
  the solid and every connected component encloses a positive volume.
* ``to_canonical`` is the 4×4 similarity transform taking the source frame (the file, or the
  procedural generator's frame) to the frame the ``vertices`` are stored in: ``x_stored =
  s·x_source + t``. After :func:`normalize_to_canonical` the stored frame is vid2sim's canonical
  object frame (bounding box centred at the origin, half its diagonal 0.5).

Textures are used as stored (sRGB values, no linearisation). For OBJ materials a diffuse texture
(``map_Kd``) is used on its own — as Blender and most viewers do — and ``Kd`` only when there is no
texture; for glTF PBR materials the base-colour texture is multiplied by ``baseColorFactor`` as the
glTF specification asks. Meshes with several textured materials are packed into one texture atlas
by trimesh (which wraps each vertex's UVs into [0, 1] on its own, so a face that spans a texture
repeat in such a multi-material file can get stretched texture). Vertex or face colours (typical
for PLY scans) are baked into a texture with one 2×2 texel block per face, which reproduces the
linear interpolation of the corner colours exactly under bilinear lookup (up to clamping into
[0, 1] of the block's fourth texel).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError

SUPPORTED_MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply")
DEFAULT_FLAT_COLOR = (0.7, 0.7, 0.7)


def _identity4() -> Tensor:
    return torch.eye(4, dtype=torch.float64)


@dataclass
class TexturedMesh:
    """A closed, outward-oriented triangle surface with a texture.

    Attributes:
        vertices: (Nv, 3) float vertex positions.
        faces: (Nf, 3) long vertex indices, counter-clockwise seen from outside.
        uvs: (Nf, 3, 2) float texture coordinates per face corner (OBJ convention, v up).
        texture: (Ht, Wt, 3) float32 RGB image in [0, 1]; row 0 is the top of the image.
        to_canonical: (4, 4) float64 similarity transform from the source frame to the frame of
            ``vertices`` (identity when nothing was normalised).
        name: where the mesh came from (a file name or ``procedural-<seed>``), used in messages.
    """

    vertices: Tensor
    faces: Tensor
    uvs: Tensor
    texture: Tensor
    to_canonical: Tensor = field(default_factory=_identity4)
    name: str = ""

    def __post_init__(self) -> None:
        label = self.name or "TexturedMesh"
        self.vertices = torch.as_tensor(self.vertices)
        if not self.vertices.is_floating_point():
            self.vertices = self.vertices.to(torch.float32)
        self.faces = torch.as_tensor(self.faces).to(torch.long)
        self.uvs = torch.as_tensor(self.uvs).to(self.vertices.dtype)
        self.texture = torch.as_tensor(self.texture).to(torch.float32)
        self.to_canonical = torch.as_tensor(self.to_canonical, dtype=torch.float64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ConfigError(f"{label}: vertices must have shape (Nv, 3), got {tuple(self.vertices.shape)}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ConfigError(f"{label}: faces must have shape (Nf, 3), got {tuple(self.faces.shape)}")
        nf = self.faces.shape[0]
        if nf == 0:
            raise ConfigError(f"{label}: the mesh has no faces")
        if self.uvs.shape != (nf, 3, 2):
            raise ConfigError(f"{label}: uvs must have shape (Nf, 3, 2) = ({nf}, 3, 2), got {tuple(self.uvs.shape)}")
        if self.texture.ndim != 3 or self.texture.shape[2] != 3 or min(self.texture.shape[:2]) < 1:
            raise ConfigError(f"{label}: texture must have shape (Ht, Wt, 3), got {tuple(self.texture.shape)}")
        if self.to_canonical.shape != (4, 4):
            raise ConfigError(f"{label}: to_canonical must be a 4x4 matrix, got {tuple(self.to_canonical.shape)}")
        lo, hi = int(self.faces.min()), int(self.faces.max())
        if lo < 0 or hi >= self.vertices.shape[0]:
            raise ConfigError(
                f"{label}: faces index vertices in [{lo}, {hi}] but there are {self.vertices.shape[0]} vertices"
            )
        if not torch.isfinite(self.vertices).all() or not torch.isfinite(self.uvs).all():
            raise ConfigError(f"{label}: vertices or uvs contain NaN or infinite values")
        tmin, tmax = float(self.texture.min()), float(self.texture.max())
        if not (tmin >= 0.0 and tmax <= 1.0):
            raise ConfigError(f"{label}: texture values must lie in [0, 1], got range [{tmin}, {tmax}]")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def face_normals(self) -> Tensor:
        """(Nf, 3) unit outward face normals."""
        tri = self.vertices[self.faces]
        n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)

    def volume(self) -> float:
        """Enclosed volume (divergence theorem; positive for an outward-oriented closed surface)."""
        return signed_volume(self.vertices.detach().cpu().double().numpy(), self.faces.cpu().numpy())

    def to(self, device: torch.device | str) -> "TexturedMesh":
        return TexturedMesh(
            self.vertices.to(device), self.faces.to(device), self.uvs.to(device), self.texture.to(device),
            self.to_canonical, self.name,
        )


# ---------------------------------------------------------------------------------------------
# topology
# ---------------------------------------------------------------------------------------------
@dataclass
class SurfaceReport:
    """Topological facts about a triangle surface (see :func:`surface_report`)."""

    num_vertices: int
    num_faces: int
    boundary_edges: int  # undirected edges used by exactly one face (holes)
    nonmanifold_edges: int  # undirected edges used by three faces or more
    inconsistent_edges: int  # manifold edges traversed in the same direction by both faces
    num_components: int
    signed_volume: float

    @property
    def watertight(self) -> bool:
        return self.boundary_edges == 0 and self.nonmanifold_edges == 0

    @property
    def consistently_wound(self) -> bool:
        return self.watertight and self.inconsistent_edges == 0


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by triangles ``faces`` (Nf, 3) over ``vertices`` (Nv, 3)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def _edge_table(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edge ids of every face corner.

    Returns (edge_id (3Nf,), counts (Ne,), direction (3Nf,) = +1 if the corner's directed edge runs
    from the smaller to the larger index, else -1, face_of_corner (3Nf,)).
    """
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys = lo.astype(np.int64) * (int(faces.max()) + 1) + hi
    _, edge_id, counts = np.unique(keys, return_inverse=True, return_counts=True)
    direction = np.where(a < b, 1, -1)
    face_of = np.repeat(np.arange(faces.shape[0]), 3)
    return edge_id, counts, direction, face_of


def _face_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For a surface whose edges all have two faces: (face_a, face_b, same_direction) per edge."""
    edge_id, counts, direction, face_of = _edge_table(faces)
    order = np.argsort(edge_id, kind="stable")
    first, second = order[0::2], order[1::2]
    same = direction[first] == direction[second]
    return face_of[first], face_of[second], same


def _components(num_faces: int, fa: np.ndarray, fb: np.ndarray) -> tuple[int, np.ndarray]:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(num_faces, num_faces))
    return connected_components(graph, directed=False)


def surface_report(vertices: np.ndarray, faces: np.ndarray) -> SurfaceReport:
    """Count holes, non-manifold edges, winding inconsistencies and components of a surface.

    Args:
        vertices: (Nv, 3) positions.
        faces: (Nf, 3) vertex indices.
    """
    faces = np.asarray(faces, dtype=np.int64)
    edge_id, counts, direction, _ = _edge_table(faces)
    boundary = int((counts == 1).sum())
    nonmanifold = int((counts > 2).sum())
    inconsistent = 0
    ncomp = 0
    if boundary == 0 and nonmanifold == 0:
        fa, fb, same = _face_pairs(faces)
        inconsistent = int(same.sum())
        ncomp, _ = _components(faces.shape[0], fa, fb)
    return SurfaceReport(
        num_vertices=int(np.asarray(vertices).shape[0]), num_faces=int(faces.shape[0]), boundary_edges=boundary,
        nonmanifold_edges=nonmanifold, inconsistent_edges=inconsistent, num_components=int(ncomp),
        signed_volume=signed_volume(vertices, faces),
    )


def merge_vertices(
    vertices: np.ndarray, faces: np.ndarray, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than ``tolerance`` (absolute, transitive) and drop unused vertices.

    Args:
        vertices: (Nv, 3) positions.
        faces: (Nf, 3) indices.
        tolerance: merge distance in the units of ``vertices``.

    Returns:
        (vertices (Nv', 3), faces (Nf, 3)) — faces are re-indexed, not removed (degenerate faces
        that this creates are removed by :func:`prepare_surface`).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, dtype=np.float64)
    pairs = cKDTree(vertices).query_pairs(r=tolerance, output_type="ndarray")
    n = vertices.shape[0]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else None
    if graph is None:
        labels = np.arange(n)
    else:
        _, labels = connected_components(graph, directed=False)
    # representative of each cluster: its lowest-index vertex
    rep = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(rep, labels, np.arange(n))
    faces = labels[np.asarray(faces, dtype=np.int64)]
    used = np.unique(faces)
    remap = np.full(labels.max() + 1, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[rep[used]], remap[faces]


def _orient_components(
    faces: np.ndarray, uvs: np.ndarray | None, fa: np.ndarray, fb: np.ndarray, same: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """Make winding consistent inside each component by flipping faces (BFS over face adjacency).

    Returns (faces, uvs, orientable).
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order

    nf = faces.shape[0]
    ones = np.ones(2 * len(fa))
    graph = csr_matrix((ones, (np.concatenate([fa, fb]), np.concatenate([fb, fa]))), shape=(nf, nf))
    # a BFS spanning forest; each face's flip is the XOR of the relations on its path to the root
    anc = np.arange(nf)
    seen = np.zeros(nf, dtype=bool)
    for start in range(nf):
        if seen[start]:
            continue
        order, pred = breadth_first_order(graph, start, directed=False, return_predecessors=True)
        seen[order] = True
        anc[order[1:]] = pred[order[1:]]
    keys = np.minimum(fa, fb) * nf + np.maximum(fa, fb)
    sort = np.argsort(keys)
    child = np.arange(nf)
    is_child = anc != child
    ckeys = np.minimum(anc, child) * nf + np.maximum(anc, child)
    pos = np.searchsorted(keys[sort], ckeys[is_child])
    parity = np.zeros(nf, dtype=bool)
    parity[is_child] = same[sort][pos]
    # pointer jumping: parity[n] = XOR of relations on the path from n to anc[n]
    while True:
        nxt = anc[anc]
        if np.array_equal(nxt, anc):
            break
        parity = parity ^ parity[anc]
        anc = nxt
    flip = parity
    orientable = bool(np.all((flip[fa] ^ flip[fb]) == same))
    faces = faces.copy()
    faces[flip] = faces[flip][:, [0, 2, 1]]
    if uvs is not None:
        uvs = uvs.copy()
        uvs[flip] = uvs[flip][:, [0, 2, 1]]
    return faces, uvs, orientable


def prepare_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray | None,
    name: str,
    merge_tolerance: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Turn a triangle soup into a closed, consistently and outwardly wound surface, or raise.

    Steps: merge vertices within ``merge_tolerance × bounding-box diagonal`` (so UV seams and
    per-face vertex copies are welded); drop faces that collapsed onto an edge or point and exact
    duplicate faces (with a warning giving their number); check that every edge has exactly two
    faces; make the winding consistent per connected component; flip every component whose
    enclosed volume is negative. Each component is treated as a separate solid.

    Args:
        vertices: (Nv, 3) positions.
        faces: (Nf, 3) indices.
        uvs: optional (Nf, 3, 2) per-corner UVs, permuted along with the faces.
        name: the mesh's name for error messages (a file path, say).
        merge_tolerance: relative merge distance (fraction of the bounding-box diagonal).

    Returns:
        (vertices (Nv', 3) float64, faces (Nf', 3) int64, uvs (Nf', 3, 2) or None).

    Raises:
        ValueError: the surface has holes or non-manifold edges after merging, is not orientable,
            or a component encloses no volume.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < 4:
        raise ValueError(f"{name}: need at least 4 vertices of shape (Nv, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 4:
        raise ValueError(f"{name}: need at least 4 triangles of shape (Nf, 3), got {faces.shape}")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{name}: vertex positions contain NaN or infinite values")
    if uvs is not None:
        uvs = np.asarray(uvs, dtype=np.float64)
    diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    if diag <= 0:
        raise ValueError(f"{name}: all vertices coincide")
    tol = merge_tolerance * diag
    vertices, faces = merge_vertices(vertices, faces, tol)

    degenerate = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    duplicate = np.ones(faces.shape[0], dtype=bool)
    duplicate[first] = False
    duplicate &= ~degenerate
    drop = degenerate | duplicate
    if drop.any():
        warnings.warn(
            f"{name}: dropped {int(degenerate.sum())} faces that collapsed when merging vertices within "
            f"{tol:.3g} and {int(duplicate.sum())} duplicate faces",
            stacklevel=2,
        )
        faces = faces[~drop]
        if uvs is not None:
            uvs = uvs[~drop]
        used = np.unique(faces)
        remap = np.full(vertices.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = vertices[used], remap[faces]

    rep = surface_report(vertices, faces)
    if not rep.watertight:
        raise ValueError(
            f"{name}: the mesh is not watertight after merging vertices closer than {tol:.3g} "
            f"({merge_tolerance:g} of the bounding-box diagonal): {rep.boundary_edges} boundary edges (holes) and "
            f"{rep.nonmanifold_edges} non-manifold edges (shared by more than two faces); vid2sim needs a closed "
            f"surface to tetrahedralize. Close the holes (e.g. in Blender or with a remesher) and try again."
        )
    fa, fb, same = _face_pairs(faces)
    if rep.inconsistent_edges:
        faces, uvs, orientable = _orient_components(faces, uvs, fa, fb, same)
        if not orientable:
            raise ValueError(
                f"{name}: the surface is not orientable (e.g. a Möbius-like strip); cannot define an inside"
            )
    ncomp, labels = _components(faces.shape[0], fa, fb)
    tri = vertices[faces]
    per_face = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    vols = np.bincount(labels, weights=per_face, minlength=ncomp)
    tiny = np.abs(vols) <= 1e-12 * diag**3
    if tiny.any():
        raise ValueError(f"{name}: {int(tiny.sum())} of {ncomp} closed components enclose zero volume (flat shells)")
    flip = vols[labels] < 0
    if flip.any():
        faces = faces.copy()
        faces[flip] = faces[flip][:, [0, 2, 1]]
        if uvs is not None:
            uvs = uvs.copy()
            uvs[flip] = uvs[flip][:, [0, 2, 1]]
    return vertices, faces, uvs


def normalize_to_canonical(vertices: Tensor | np.ndarray) -> tuple[Tensor, Tensor]:
    """Centre the bounding box at the origin and scale so half its diagonal is 0.5.

    Args:
        vertices: (Nv, 3) positions in the source frame.

    Returns:
        (canonical vertices (Nv, 3) in the input's float dtype (float64 for numpy input),
        to_canonical (4, 4) float64 with ``x_canonical = s·x_source + t``).
    """
    v = torch.as_tensor(vertices)
    v64 = v.detach().to(torch.float64)
    lo, hi = v64.min(0).values, v64.max(0).values
    half_diag = 0.5 * float((hi - lo).norm())
    if half_diag <= 0:
        raise ValueError("normalize_to_canonical: all vertices coincide (zero bounding box)")
    scale = 0.5 / half_diag
    center = 0.5 * (lo + hi)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] *= scale
    m[:3, 3] = -scale * center
    out = (v64 - center) * scale
    return out.to(v.dtype if v.is_floating_point() else torch.float64), m


# ---------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------
def _image_to_array(image, max_size: int) -> np.ndarray:
    from PIL import Image

    img = image.convert("RGB")
    if max(img.size) > max_size:
        s = max_size / max(img.size)
        img = img.resize((max(1, round(img.size[0] * s)), max(1, round(img.size[1] * s))), Image.Resampling.LANCZOS)
    return np.asarray(img, dtype=np.float32) / 255.0


def _material_color_and_image(material) -> tuple[np.ndarray, object | None]:
    """(RGB colour factor in [0, 1], PIL image or None) of a trimesh material."""
    from trimesh.visual.material import PBRMaterial

    if isinstance(material, PBRMaterial):
        factor = material.baseColorFactor
        color = np.ones(3) if factor is None else np.asarray(factor, dtype=np.float64)[:3] / 255.0
        return color, material.baseColorTexture
    image = getattr(material, "image", None)
    if image is not None:
        return np.ones(3), image  # OBJ: map_Kd replaces Kd (see module docstring)
    diffuse = getattr(material, "diffuse", None)
    color = np.asarray(DEFAULT_FLAT_COLOR) if diffuse is None else np.asarray(diffuse, dtype=np.float64)[:3] / 255.0
    return color, None


def bake_corner_colors(corner_colors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bake per-corner colours into a texture with one 2×2 texel block per face.

    Corner 0, 1, 2 of face f sit at the centres of texels (0, 0), (0, 1), (1, 0) of its block; the
    fourth texel holds c1 + c2 − c0 (clamped to [0, 1]) so that bilinear lookup inside the triangle
    reproduces linear interpolation of the corner colours.

    Args:
        corner_colors: (Nf, 3, 3) RGB in [0, 1] per face corner.

    Returns:
        (uvs (Nf, 3, 2), texture (Ht, Wt, 3) float32).
    """
    c = np.clip(np.asarray(corner_colors, dtype=np.float64), 0.0, 1.0)
    nf = c.shape[0]
    cols = int(math.ceil(math.sqrt(nf)))
    rows = int(math.ceil(nf / cols))
    h, w = 2 * rows, 2 * cols
    tex = np.ones((h, w, 3), dtype=np.float64)
    r, q = np.divmod(np.arange(nf), cols)
    y0, x0 = 2 * r, 2 * q
    tex[y0, x0] = c[:, 0]
    tex[y0, x0 + 1] = c[:, 1]
    tex[y0 + 1, x0] = c[:, 2]
    tex[y0 + 1, x0 + 1] = np.clip(c[:, 1] + c[:, 2] - c[:, 0], 0.0, 1.0)
    px = np.stack([x0 + 0.5, x0 + 1.5, x0 + 0.5], axis=1)
    py = np.stack([y0 + 0.5, y0 + 0.5, y0 + 1.5], axis=1)
    uvs = np.stack([px / w, 1.0 - py / h], axis=-1)
    return uvs, tex.astype(np.float32)


def _visual_to_uvs_texture(mesh, max_texture_size: int) -> tuple[np.ndarray, np.ndarray]:
    """(uvs (Nf, 3, 2), texture) from a trimesh mesh's visual (texture, colours, or flat grey)."""
    faces = np.asarray(mesh.faces)
    nf = faces.shape[0]
    visual = mesh.visual
    kind = getattr(visual, "kind", None)
    if kind == "texture":
        color, image = _material_color_and_image(visual.material)
        uv = getattr(visual, "uv", None)
        if image is not None and uv is not None and len(uv) == len(mesh.vertices):
            tex = _image_to_array(image, max_texture_size) * color[None, None, :].astype(np.float32)
            return np.asarray(uv, dtype=np.float64)[faces], np.clip(tex, 0.0, 1.0)
        return np.full((nf, 3, 2), 0.5), np.tile(color.astype(np.float32), (2, 2, 1))
    if kind == "vertex":
        vc = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        return bake_corner_colors(vc[faces])
    if kind == "face":
        fc = np.asarray(visual.face_colors, dtype=np.float64)[:, :3] / 255.0
        return bake_corner_colors(np.repeat(fc[:, None, :], 3, axis=1))
    return np.full((nf, 3, 2), 0.5), np.tile(np.asarray(DEFAULT_FLAT_COLOR, dtype=np.float32), (2, 2, 1))


def load_user_mesh(
    path: str | Path,
    normalize: bool = True,
    merge_tolerance: float = 1e-6,
    max_texture_size: int = 2048,
) -> TexturedMesh:
    """Load an OBJ (with MTL + texture), GLB/GLTF or PLY file as a closed :class:`TexturedMesh`.

    Vertices are merged by position (within ``merge_tolerance`` × bounding-box diagonal) so that
    UV seams do not split the surface; the result must then be watertight (every edge shared by
    exactly two faces), its winding is made consistent and outward. Scenes with several parts
    are flattened with their transforms. Meshes without a texture get a flat texture (the
    material colour, or grey 0.7) or a texture baked from vertex/face colours.

    Args:
        path: mesh file; the suffix picks the format (.obj, .glb, .gltf, .ply).
        normalize: map into the canonical frame (centred, half bounding-box diagonal 0.5) and
            record the transform in ``to_canonical``; otherwise keep file coordinates.
        merge_tolerance: relative vertex-merge distance.
        max_texture_size: textures larger than this (either side) are downscaled.

    Returns:
        the mesh, float32, on the CPU.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: unsupported suffix, no triangles, or a surface that cannot be made watertight
            (the message names the file and the number of boundary / non-manifold edges).
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() not in SUPPORTED_MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {path.suffix!r}; expected one of {SUPPORTED_MESH_SUFFIXES}")
    try:
        scene = trimesh.load_scene(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds of errors for broken files
        raise ValueError(f"{path}: could not read the mesh file: {exc}") from exc
    if len(scene.geometry) == 0:
        raise ValueError(f"{path}: the file contains no geometry")
    meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not meshes:
        raise ValueError(f"{path}: the file contains no triangles (point clouds and lines cannot be simulated)")
    mesh = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    uvs, texture = _visual_to_uvs_texture(mesh, max_texture_size)
    vertices, faces, uvs = prepare_surface(
        np.asarray(mesh.vertices), np.asarray(mesh.faces), uvs, str(path), merge_tolerance
    )
    v = torch.from_numpy(vertices)
    to_canonical = torch.eye(4, dtype=torch.float64)
    if normalize:
        v, to_canonical = normalize_to_canonical(v)
    return TexturedMesh(
        v.to(torch.float32), torch.from_numpy(faces), torch.from_numpy(uvs).to(torch.float32),
        torch.from_numpy(np.ascontiguousarray(texture)), to_canonical, path.name,
    )


def save_obj(mesh: TexturedMesh, path: str | Path) -> Path:
    """Write ``mesh`` as OBJ + MTL + PNG texture (``<stem>.mtl``, ``<stem>.png`` beside it).

    One ``vt`` per face corner, so :func:`load_user_mesh` reads it back to the same surface.
    The texture is quantised to 8 bits.

    Returns:
        the OBJ path.
    """
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"save_obj: path must end in .obj, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.stem
    tex = (mesh.texture.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    Image.fromarray(tex).save(path.with_suffix(".png"))
    path.with_suffix(".mtl").write_text(f"newmtl material0\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nmap_Kd {stem}.png\n")
    v = mesh.vertices.detach().cpu().double().numpy()
    f = mesh.faces.cpu().numpy() + 1
    uv = mesh.uvs.detach().cpu().double().numpy().reshape(-1, 2)
    nf = f.shape[0]
    t = np.arange(1, 3 * nf + 1).reshape(nf, 3)
    lines = [f"mtllib {stem}.mtl", "usemtl material0"]
    lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
    lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv]
    lines += [f"f {f0}/{t0} {f1}/{t1} {f2}/{t2}" for (f0, f1, f2), (t0, t1, t2) in zip(f, t)]
    path.write_text("\n".join(lines) + "\n")
    return path
