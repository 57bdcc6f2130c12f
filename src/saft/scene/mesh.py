"""QuadMesh: the cloth template (quads, one UV per vertex, metres) and its OBJ reading and writing.

OBJ is parsed here rather than with trimesh because trimesh triangulates quads on load, and the physics
needs the quads themselves (springs live on quad edges, hinges on pairs of quad-edge neighbours).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import atomic_write_text


@dataclass(frozen=True)
class QuadMesh:
    """A quad mesh with one UV per vertex.

    vertices: (V, 3) float64, metres, in the scene's world frame.
    quads:    (Q, 4) int64 vertex indices, counter-clockwise as in the file.
    uvs:      (V, 2) float64 texture coordinates in the OBJ convention: u right, v UP, (0, 0) is the
              bottom-left corner of the texture image (image row 0 is v = 1).
    """

    vertices: np.ndarray
    quads: np.ndarray
    uvs: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "vertices", np.ascontiguousarray(self.vertices, dtype=np.float64))
        object.__setattr__(self, "quads", np.ascontiguousarray(self.quads, dtype=np.int64))
        object.__setattr__(self, "uvs", np.ascontiguousarray(self.uvs, dtype=np.float64))

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def triangles(self) -> np.ndarray:
        """(2Q, 3) int64: each quad (a, b, c, d) split into (a, b, c) and (a, c, d) (quad_triangles)."""
        return quad_triangles(self.quads)

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) int64: the unique quad edges (no diagonals), each with i < j."""
        q = self.quads
        e = np.concatenate([q[:, [0, 1]], q[:, [1, 2]], q[:, [2, 3]], q[:, [3, 0]]], axis=0)
        e = np.sort(e, axis=1)
        return np.unique(e, axis=0)

    def with_vertices(self, vertices: np.ndarray) -> "QuadMesh":
        return QuadMesh(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), self.quads, self.uvs)


def quad_triangles(quads: np.ndarray) -> np.ndarray:
    """(2Q, 3): each quad (a, b, c, d) of (Q, 4) split into (a, b, c) and (a, c, d), first triangles first."""
    q = np.asarray(quads)
    return np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]], axis=0)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3) following the triangle winding; +Z where a vertex has no
    area. (saft.render.vertex_normals is the differentiable, batched torch version.)"""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 1e-20, n / np.maximum(length, 1e-20), np.array([0.0, 0.0, 1.0]))


def read_obj(path: str | Path) -> QuadMesh:
    """Read a quad OBJ with per-vertex UVs. Every problem raises SaftInputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise SaftInputError(path, "template mesh not found")
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise SaftInputError(path, f"cannot read the mesh ({exc})") from None

    positions: list[list[float]] = []
    texcoords: list[list[float]] = []
    faces_v: list[list[int]] = []
    faces_vt: list[list[int] | None] = []
    face_lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        tag = parts[0]
        try:
            if tag == "v":
                positions.append([float(x) for x in _fields(parts, 3)])
            elif tag == "vt":
                texcoords.append([float(x) for x in _fields(parts, 2)])
            elif tag == "f":
                fv, fvt = [], []
                for corner in parts[1:]:
                    fields = corner.split("/")
                    fv.append(_obj_index(int(fields[0]), len(positions)))
                    if len(fields) > 1 and fields[1]:
                        fvt.append(_obj_index(int(fields[1]), len(texcoords)))
                faces_v.append(fv)
                faces_vt.append(fvt if len(fvt) == len(fv) else None)
                face_lines.append(lineno)
        except (ValueError, IndexError):
            raise SaftInputError(path, f"line {lineno} is not valid OBJ: {line.strip()!r}") from None

    if not positions:
        raise SaftInputError(path, "the mesh has no vertices")
    if not faces_v:
        raise SaftInputError(path, "the mesh has no faces")
    bad = next((i for i, f in enumerate(faces_v) if len(f) != 4), None)
    if bad is not None:
        raise SaftInputError(
            path, f"face {bad + 1} has {len(faces_v[bad])} corners; the template must be a pure quad mesh"
        )
    vertices = np.asarray(positions, dtype=np.float64)
    if not np.isfinite(vertices).all():
        raise SaftInputError(path, "vertex positions contain NaN or inf")
    quads = np.asarray(faces_v, dtype=np.int64)
    if quads.min() < 0 or quads.max() >= len(vertices):
        bad = int(np.flatnonzero((quads < 0).any(axis=1) | (quads >= len(vertices)).any(axis=1))[0])
        raise SaftInputError(path, f"face {bad + 1} (line {face_lines[bad]}) refers to a vertex that does not exist")
    _check_quads(path, vertices, quads, face_lines)
    if not texcoords or any(f is None for f in faces_vt):
        raise SaftInputError(path, "the template has no texture coordinates (vt) on every face; UVs are required")
    quads_vt = np.asarray(faces_vt, dtype=np.int64)
    if quads_vt.min() < 0 or quads_vt.max() >= len(texcoords):
        raise SaftInputError(path, "a face refers to a texture coordinate that does not exist")
    texcoords_arr = np.asarray(texcoords, dtype=np.float64)

    uvs = np.full((len(vertices), 2), np.nan)
    corner_uv = texcoords_arr[quads_vt.reshape(-1)]
    corner_v = quads.reshape(-1)
    uvs[corner_v] = corner_uv
    if not np.allclose(uvs[corner_v], corner_uv, atol=1e-6):
        seam = corner_v[np.argmax(np.abs(uvs[corner_v] - corner_uv).max(axis=1))]
        raise SaftInputError(
            path, f"vertex {seam + 1} has several different UVs (a UV seam); saft needs one UV per vertex"
        )
    unused = np.isnan(uvs[:, 0])
    if unused.any():
        raise SaftInputError(path, f"{int(unused.sum())} vertices belong to no face; remove them from the template")
    if not np.isfinite(uvs).all():
        raise SaftInputError(path, "texture coordinates contain NaN or inf")
    return QuadMesh(vertices, quads, uvs)


# A quad counts as degenerate when one of its two triangles has less than this fraction of the area of a
# square with the template's median edge length (the physics divides by rest areas, the renderer by them).
DEGENERATE_AREA_FRACTION = 1e-8


def _fields(parts: list[str], count: int) -> list[str]:
    """The first `count` values after the tag of an OBJ line; ValueError when fewer are given."""
    if len(parts) < count + 1:
        raise ValueError(f"expected {count} numbers")
    return parts[1:count + 1]


def _check_quads(path: Path, vertices: np.ndarray, quads: np.ndarray, face_lines: list[int]) -> None:
    """Every quad has four different corners and a non-zero area in both of its triangles."""
    s = np.sort(quads, axis=1)
    repeated = (s[:, 1:] == s[:, :-1]).any(axis=1)
    if repeated.any():
        bad = int(np.flatnonzero(repeated)[0])
        raise SaftInputError(path, f"face {bad + 1} (line {face_lines[bad]}) uses a vertex twice: "
                                   "a degenerate quad; every face needs four different vertices")
    v = vertices[quads]                                            # (Q, 4, 3)
    tri1 = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    tri2 = 0.5 * np.linalg.norm(np.cross(v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]), axis=1)
    edge = np.median(np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2))
    flat = np.minimum(tri1, tri2) <= DEGENERATE_AREA_FRACTION * max(edge, 1e-300) ** 2
    if flat.any():
        bad = int(np.flatnonzero(flat)[0])
        raise SaftInputError(path, f"face {bad + 1} (line {face_lines[bad]}) has zero area "
                                   f"({int(flat.sum())} such quads); the template needs proper quads")


def _obj_index(index: int, count: int) -> int:
    """OBJ indices are 1-based; negative ones count back from the last element read so far."""
    if index > 0:
        return index - 1
    if index < 0:
        return count + index
    raise ValueError("OBJ index 0")


def obj_text(mesh: QuadMesh, vertices: np.ndarray | None = None, comment: str | None = None,
             mtllib: str | None = None) -> str:
    """OBJ text of the mesh (optionally with other vertex positions), quads kept, one vt per vertex."""
    verts = mesh.vertices if vertices is None else np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    lines = []
    if comment:
        lines.append(f"# {comment}")
    if mtllib:
        lines += [f"mtllib {mtllib}", "usemtl cloth"]
    lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in verts]
    lines += [f"vt {u:.7f} {v:.7f}" for u, v in mesh.uvs]
    q = mesh.quads + 1
    lines += [f"f {a}/{a} {b}/{b} {c}/{c} {d}/{d}" for a, b, c, d in q]
    return "\n".join(lines) + "\n"


def write_obj(path: str | Path, mesh: QuadMesh, vertices: np.ndarray | None = None,
              comment: str | None = None, mtllib: str | None = None) -> None:
    """Write the mesh (or the same topology with other vertex positions) as a quad OBJ, atomically."""
    atomic_write_text(path, obj_text(mesh, vertices, comment, mtllib))
