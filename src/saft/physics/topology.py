"""Cloth topology from a quad mesh: stretch springs, bend/shear hinges, lumped masses, and the fixed
sparsity pattern of the (3V x 3V) system matrix M + h^2 K.

Everything per element is stored elements-last (index arrays (n,), rest values (n,)), which is what the
closed-form kernels in ``saft.physics.energy`` consume.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from saft.scene.mesh import quad_triangles, vertex_normals

ARCCOS_GUARD = 0.99  # theta = arccos(0.99 * e1_hat . e2_hat) keeps arccos differentiable (REFERENCE.md)
BEND_THRESHOLD_RAD = math.pi / 4.0  # rest angle < 45 deg -> bending hinge, else shearing hinge
DEFAULT_DENSITY = 0.1  # kg / m^2 (paper, supplementary "Mass")
REST_SHAPES = ("template", "flat")


@dataclass(frozen=True)
class ClothTopology:
    """Springs, hinges, masses and the matrix pattern of one cloth template.

    Tensors (on ``device``, floating ones in ``dtype``):
      edges     (E, 2) int64   stretch springs on the unique quad edges (i < j)
      rest_len  (E,)           template edge lengths L0
      hinges    (H, 3) int64   (n1, v, n2): vertex v and a pair of its quad-edge neighbours
      rest_angle (H,)          theta0 = arccos(0.99 * e1_hat . e2_hat), e1 = v - n1, e2 = n2 - v; with
                               rest_shape="flat", e1, e2 projected on the plane normal to v's vertex normal
                               first (``flat_hinge_cosines``: the template flattened, its normal curvature
                               taken out, its in-surface angles kept)
      is_bend   (H,) bool      theta0 < 45 deg (bending, stiffness B), else shearing (stiffness S)
      bend_w    (H,)           1.0 for bending hinges, 0.0 for shearing hinges (same as is_bend, float)
      mass      (V,)           lumped masses: each triangle gives area/3 to its corners, times density
      triangles (T, 3) int64   the triangulation (a, b, c), (a, c, d) of the quads (air drag; None when
                               the topology was built without it)
    Host (numpy) data describing the scalar CSR pattern of the symmetric (3V x 3V) system matrix:
      csr_indptr, csr_indices  int32/int64 numpy arrays (rows sorted; the pattern is symmetric)
      spring_idx (4*9*E,), hinge_idx (9*9*H,), diag_idx (3V,): positions in the CSR data array of every
      element-Hessian entry, in the elements-last order the kernels produce (block, row, col, element).
      scatter_idx (2E + 3H,): vertex of every per-element vector entry (springs i, j; hinges n1, v, n2).
    Derived (computed on construction) for the fast kernels:
      gather_idx (3 * (2E + 3H),): flat index 3 * vertex + dim of every per-element vector entry, dim-major,
        so one 1-D gather of a (V, 3) field gives all element ends as (3, 2E + 3H).
      up_of (nnz,): for every CSR entry (r, c) the position of (min(r, c), max(r, c)) in the upper-triangle
        ("up") storage of the symmetric matrix (nnz_up entries, CSR order); full = up[up_of].
      spring_up_idx (21 E,), hinge_up_idx (45 H,): up positions of the unique (upper) entries of each
        spring's 6x6 and each hinge's 9x9 element Hessian, pair-major; spring_up_rows (21,) picks them from
        a spring's (Ks, -Ks) 18 rows, hinge_up_rows (2, 45) from a hinge's 9-vector G (rows a, b of G G^T);
        diag_up_idx (3V,): up positions of the diagonal.
    """

    num_vertices: int
    edges: torch.Tensor
    rest_len: torch.Tensor
    hinges: torch.Tensor
    rest_angle: torch.Tensor
    is_bend: torch.Tensor
    bend_w: torch.Tensor
    mass: torch.Tensor
    csr_indptr: np.ndarray = field(repr=False)
    csr_indices: np.ndarray = field(repr=False)
    spring_idx: torch.Tensor = field(repr=False)
    hinge_idx: torch.Tensor = field(repr=False)
    diag_idx: torch.Tensor = field(repr=False)
    scatter_idx: torch.Tensor = field(repr=False)
    template: torch.Tensor = field(repr=False)
    hinge_idx_outer: torch.Tensor = field(repr=False, default=None)
    gather_idx: torch.Tensor = field(repr=False, default=None)
    up_of: torch.Tensor = field(repr=False, default=None)
    spring_up_idx: torch.Tensor = field(repr=False, default=None)
    hinge_up_idx: torch.Tensor = field(repr=False, default=None)
    diag_up_idx: torch.Tensor = field(repr=False, default=None)
    spring_up_rows: torch.Tensor = field(repr=False, default=None)
    hinge_up_rows: torch.Tensor = field(repr=False, default=None)
    triangles: torch.Tensor | None = field(repr=False, default=None)

    def __post_init__(self):
        if self.hinge_idx_outer is None:
            # hinge_idx reordered (vertex r, dim i, vertex c, dim j, hinge) for outer-product kernels
            H = self.hinge_idx.numel() // 81
            perm = self.hinge_idx.view(3, 3, 3, 3, H).permute(0, 2, 1, 3, 4).reshape(-1)
            object.__setattr__(self, "hinge_idx_outer", perm)
        if self.up_of is None:
            for name, val in _fast_maps(self).items():
                object.__setattr__(self, name, val)

    @property
    def nnz_up(self) -> int:
        """Entries of the upper triangle (diagonal included) of the system matrix pattern."""
        return (self.nnz + 3 * self.num_vertices) // 2

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_quads(
        cls,
        vertices,
        quads,
        density: float = DEFAULT_DENSITY,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float64,
        rest_shape: str = "template",
    ) -> "ClothTopology":
        """Build the topology of any quad mesh (boundaries and irregular vertices included).

        ``rest_shape``: "template" (the rest angles are the template's own) or "flat" (the template's
        hinges flattened, ``flat_hinge_cosines``; rest lengths are the template's edge lengths either way).
        """
        if rest_shape not in REST_SHAPES:
            raise ValueError(f"rest_shape must be one of {REST_SHAPES}, not {rest_shape!r}")
        verts = _as_numpy(vertices).astype(np.float64).reshape(-1, 3)
        quads = _as_numpy(quads).astype(np.int64).reshape(-1, 4)
        V = verts.shape[0]
        if quads.size and (quads.min() < 0 or quads.max() >= V):
            raise ValueError("a quad refers to a vertex that does not exist")

        # springs: unique quad edges
        e = np.concatenate([quads[:, [0, 1]], quads[:, [1, 2]], quads[:, [2, 3]], quads[:, [3, 0]]], axis=0)
        e = np.unique(np.sort(e, axis=1), axis=0)
        e = e[e[:, 0] != e[:, 1]]
        rest_len = np.linalg.norm(verts[e[:, 1]] - verts[e[:, 0]], axis=1)

        # hinges: every vertex, every unordered pair of its quad-edge neighbours
        nbr_lists = [[] for _ in range(V)]
        for a, b in e:
            nbr_lists[a].append(b)
            nbr_lists[b].append(a)
        hinge_rows = []
        for v in range(V):
            nb = sorted(nbr_lists[v])
            for i in range(len(nb)):
                for j in range(i + 1, len(nb)):
                    hinge_rows.append((nb[i], v, nb[j]))
        hinges = np.asarray(hinge_rows, dtype=np.int64).reshape(-1, 3)
        if rest_shape == "flat":
            q = flat_hinge_cosines(verts, quads, hinges)
        else:
            q = _cosines(verts[hinges[:, 1]] - verts[hinges[:, 0]], verts[hinges[:, 2]] - verts[hinges[:, 1]])
        rest_angle = np.arccos(ARCCOS_GUARD * np.clip(q, -1.0, 1.0))
        is_bend = rest_angle < BEND_THRESHOLD_RAD

        # lumped masses from the triangulation (a,b,c), (a,c,d)
        tris = quad_triangles(quads)
        area = 0.5 * np.linalg.norm(
            np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]]), axis=1
        )
        mass = np.zeros(V)
        np.add.at(mass, tris.reshape(-1), np.repeat(area / 3.0, 3) * density)
        if np.any(mass <= 0):
            bad = int(np.flatnonzero(mass <= 0)[0])
            raise ValueError(f"vertex {bad} has no positive mass (isolated vertex or degenerate quads)")

        indptr, indices, spring_idx, hinge_idx, diag_idx = _csr_pattern(V, e, hinges)
        dev = torch.device(device) if device is not None else torch.device("cpu")
        f = dict(device=dev, dtype=dtype)
        i = dict(device=dev, dtype=torch.int64)
        return cls(
            num_vertices=V,
            edges=torch.as_tensor(e, **i),
            rest_len=torch.as_tensor(rest_len, **f),
            hinges=torch.as_tensor(hinges, **i),
            rest_angle=torch.as_tensor(rest_angle, **f),
            is_bend=torch.as_tensor(is_bend, device=dev),
            bend_w=torch.as_tensor(is_bend.astype(np.float64), **f),
            mass=torch.as_tensor(mass, **f),
            csr_indptr=indptr,
            csr_indices=indices,
            spring_idx=torch.as_tensor(spring_idx, **i),
            hinge_idx=torch.as_tensor(hinge_idx, **i),
            diag_idx=torch.as_tensor(diag_idx, **i),
            scatter_idx=torch.as_tensor(np.concatenate([e[:, 0], e[:, 1], hinges[:, 0], hinges[:, 1], hinges[:, 2]]), **i),
            template=torch.as_tensor(verts, **f),
            triangles=torch.as_tensor(tris, **i),
        )

    @classmethod
    def from_mesh(cls, mesh, density: float = DEFAULT_DENSITY, **kw) -> "ClothTopology":
        """From a ``saft.scene.mesh.QuadMesh``."""
        return cls.from_quads(mesh.vertices, mesh.quads, density, **kw)

    # ------------------------------------------------------------------ device / dtype
    def to(self, device=None, dtype: torch.dtype | None = None) -> "ClothTopology":
        """A copy with every tensor on ``device`` and floating tensors in ``dtype``."""
        changes = {}
        for name in ("edges", "hinges", "is_bend", "spring_idx", "hinge_idx", "diag_idx", "scatter_idx",
                     "hinge_idx_outer", *_FAST_MAP_FIELDS):
            changes[name] = getattr(self, name).to(device=device)
        if self.triangles is not None:
            changes["triangles"] = self.triangles.to(device=device)
        for name in ("rest_len", "rest_angle", "bend_w", "mass", "template"):
            changes[name] = getattr(self, name).to(device=device, dtype=dtype)
        return replace(self, **changes)

    @property
    def device(self) -> torch.device:
        return self.mass.device

    @property
    def dtype(self) -> torch.dtype:
        return self.mass.dtype

    @property
    def num_springs(self) -> int:
        return int(self.edges.shape[0])

    @property
    def num_hinges(self) -> int:
        return int(self.hinges.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.csr_indices.shape[0])


def _cosines(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", e1, e2) / np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)


def flat_hinge_cosines(verts: np.ndarray, quads: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    """cos of each hinge's angle in the template flattened: its edges e1 = v - n1, e2 = n2 - v projected on
    the tangent plane at v (normal to v's vertex normal). A curved template's bend hinges become straight (the
    normal curvature is what the projection removes), its shear hinges keep their in-surface angles; on a flat
    template nothing changes (up to rounding)."""
    n = vertex_normals(verts, quad_triangles(quads))[hinges[:, 1]]
    e1 = verts[hinges[:, 1]] - verts[hinges[:, 0]]
    e2 = verts[hinges[:, 2]] - verts[hinges[:, 1]]
    e1 = e1 - np.einsum("ij,ij->i", e1, n)[:, None] * n
    e2 = e2 - np.einsum("ij,ij->i", e2, n)[:, None] * n
    return _cosines(e1, e2)


def _as_numpy(a) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().numpy()
    return np.asarray(a)


_FAST_MAP_FIELDS = ("gather_idx", "up_of", "spring_up_idx", "hinge_up_idx", "diag_up_idx", "spring_up_rows",
                    "hinge_up_rows")


def _fast_maps(t: ClothTopology) -> dict:
    """The derived index tensors of the fast kernels (see the ClothTopology docstring)."""
    dev = t.spring_idx.device
    indptr, indices = t.csr_indptr, t.csr_indices
    n = len(indptr) - 1
    rows = np.repeat(np.arange(n), np.diff(indptr))
    upper = rows <= indices
    rank = np.cumsum(upper) - 1
    key = rows * n + indices  # ascending: rows sorted, columns sorted within a row
    tpos = np.searchsorted(key, indices * n + rows)
    up_of = np.where(upper, rank, rank[tpos])
    E = t.spring_idx.numel() // 36
    H = t.hinge_idx.numel() // 81
    # spring: local dof a = 3 r + d over its ends r in (i, j); block (r, c) is +Ks on the diagonal, -Ks off it
    sa, sb = np.triu_indices(6)
    spring_pos = t.spring_idx.cpu().numpy().reshape(4, 3, 3, E)[2 * (sa // 3) + sb // 3, sa % 3, sb % 3]
    spring_rows = np.where(sa // 3 == sb // 3, 0, 9) + 3 * (sa % 3) + sb % 3
    ha, hb = np.triu_indices(9)
    hinge_pos = t.hinge_idx_outer.cpu().numpy().reshape(9, 9, H)[ha, hb]
    si = t.scatter_idx.cpu().numpy()
    i = dict(device=dev, dtype=torch.int64)
    return dict(
        gather_idx=torch.as_tensor((3 * si[None, :] + np.arange(3)[:, None]).reshape(-1), **i),
        up_of=torch.as_tensor(up_of, **i),
        spring_up_idx=torch.as_tensor(up_of[spring_pos].reshape(-1), **i),
        hinge_up_idx=torch.as_tensor(up_of[hinge_pos].reshape(-1), **i),
        diag_up_idx=torch.as_tensor(up_of[t.diag_idx.cpu().numpy()], **i),
        spring_up_rows=torch.as_tensor(spring_rows, **i),
        hinge_up_rows=torch.as_tensor(np.stack([ha, hb]), **i),
    )


def _csr_pattern(V: int, edges: np.ndarray, hinges: np.ndarray):
    """Scalar CSR pattern of the 3x3-block sparse symmetric matrix touched by all elements, and the
    CSR-data position of every element-Hessian entry (elements-last order)."""
    # block pairs (a, b) touched by each element block, in kernel order
    sa = np.stack([edges[:, 0], edges[:, 0], edges[:, 1], edges[:, 1]])  # (4, E): ii, ij, ji, jj
    sb = np.stack([edges[:, 0], edges[:, 1], edges[:, 0], edges[:, 1]])
    hv = hinges.T  # (3, H): n1, v, n2
    ha = np.repeat(hv, 3, axis=0)  # (9, H): blocks (r, c) for r, c in (n1, v, n2), row-major
    hb = np.tile(hv, (3, 1))
    diag = np.arange(V)
    all_a = np.concatenate([sa.ravel(), ha.ravel(), diag])
    all_b = np.concatenate([sb.ravel(), hb.ravel(), diag])
    key = all_a * V + all_b
    ukey = np.unique(key)  # sorted by (row block, col block)
    brow, bcol = ukey // V, ukey % V
    cnt = np.bincount(brow, minlength=V)
    bptr = np.concatenate([[0], np.cumsum(cnt)])
    rank = np.arange(len(ukey)) - bptr[brow]

    # scalar CSR: row 3a+r holds, for each block col b of block row a (sorted), columns 3b, 3b+1, 3b+2
    row_len = np.repeat(3 * cnt, 3)
    indptr = np.concatenate([[0], np.cumsum(row_len)]).astype(np.int64)
    indices = np.empty(indptr[-1], dtype=np.int64)
    for r in range(3):
        # positions of (3a+r, 3b+c)
        for c in range(3):
            pos = 9 * bptr[brow] + 3 * r * cnt[brow] + 3 * rank + c
            indices[pos] = 3 * bcol + c

    def positions(a, b):
        # a, b: (nb, n) block rows/cols -> (nb, 3, 3, n) data positions
        k = np.searchsorted(ukey, a * V + b)
        ar = a
        base = 9 * bptr[ar] + 3 * rank[k]
        r = np.arange(3)[None, :, None, None]
        c = np.arange(3)[None, None, :, None]
        return base[:, None, None, :] + 3 * r * cnt[ar][:, None, None, :] + c

    spring_idx = positions(sa, sb).reshape(-1)
    hinge_idx = positions(ha, hb).reshape(-1)
    dpos = positions(diag[None, :], diag[None, :])[0]  # (3, 3, V)
    diag_idx = np.stack([dpos[0, 0], dpos[1, 1], dpos[2, 2]], axis=1).reshape(-1)  # (3V,) order v*3+k
    return indptr, indices, spring_idx, hinge_idx, diag_idx
