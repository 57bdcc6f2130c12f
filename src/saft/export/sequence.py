"""OBJ or PLY mesh sequences of a result: one file per frame, quads kept, UVs included.

OBJ: OUT/frame_000.obj … with `mtllib cloth.mtl`; cloth.mtl and texture.png (material/diffuse.png when the
appearance phase ran, else texture.png) are copied beside them, so the folder is self-contained.
PLY: binary little-endian, per vertex x y z nx ny nz (float32) and s t (float32, OBJ convention: v up),
quad faces as `vertex_indices` lists — what Blender, MeshLab and Open3D read.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.scene.mesh import vertex_normals
from saft.io_utils import atomic_path, atomic_write_bytes, atomic_write_text
from saft.result import Result, mtl_text, read_result
from saft.scene.mesh import write_obj

log = logging.getLogger("saft")

FORMATS = ("obj", "ply")


def ply_bytes(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray, quads: np.ndarray, comment: str = "") -> bytes:
    v = len(vertices)
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header += [f"element vertex {v}", "property float x", "property float y", "property float z",
               "property float nx", "property float ny", "property float nz", "property float s", "property float t",
               f"element face {len(quads)}", "property list uchar int vertex_indices", "end_header"]
    vdt = np.dtype([(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz", "s", "t")])
    vert = np.empty(v, dtype=vdt)
    for k, n in enumerate(("x", "y", "z")):
        vert[n] = vertices[:, k]
        vert["n" + n] = normals[:, k]
    vert["s"], vert["t"] = uvs[:, 0], uvs[:, 1]
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (4,))])
    face = np.empty(len(quads), dtype=fdt)
    face["n"] = 4
    face["i"] = quads
    return ("\n".join(header) + "\n").encode("ascii") + vert.tobytes() + face.tobytes()


def write_sequence(result: str | Path | Result, out_dir: str | Path, fmt: str = "obj") -> list[Path]:
    """Write every frame of a result as OUT_DIR/frame_XXX.obj|ply; returns the files written."""
    if fmt not in FORMATS:
        raise SaftInputError(None, f"--sequence must be one of {', '.join(FORMATS)}, got {fmt!r}")
    res = result if isinstance(result, Result) else read_result(result)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if fmt == "obj":
        tex = res.material_path("diffuse.png") or (res.folder / "texture.png")
        if tex.is_file():
            with atomic_path(out_dir / "texture.png") as tmp:
                tmp.write_bytes(tex.read_bytes())
            written.append(out_dir / "texture.png")
        atomic_write_text(out_dir / "cloth.mtl", mtl_text("texture.png"))
        written.append(out_dir / "cloth.mtl")
        for i, verts in enumerate(res.vertices):
            p = out_dir / f"frame_{i:03d}.obj"
            write_obj(p, res.template, verts, comment=f"saft frame {i}, t = {i * res.frame_dt:.6g} s",
                      mtllib="cloth.mtl")
            written.append(p)
    else:
        tris = res.template.triangles
        for i, verts in enumerate(res.vertices):
            p = out_dir / f"frame_{i:03d}.ply"
            atomic_write_bytes(p, ply_bytes(verts, vertex_normals(verts, tris), res.template.uvs, res.template.quads,
                                            comment=f"saft frame {i} t={i * res.frame_dt:.6g}s"))
            written.append(p)
    log.info("wrote %d %s frames to %s", res.num_frames, fmt.upper(), out_dir)
    return written
