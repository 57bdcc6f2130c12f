"""glTF 2.0 binary (.glb) export of the animated cloth, and reading its frames back.

Choice: ONE mesh whose base shape is frame 0 (quads split into triangles as QuadMesh.triangles), with one
morph target per frame (POSITION and NORMAL deltas from the base) driven by a `weights` animation channel
with one-hot keyframes at t = i·frame_dt and LINEAR interpolation (exactly frame i at its time, a blend of
neighbouring frames in between). Blender imports morph targets as shape keys with their animation, and
three.js / Babylon play them as morph animations; per-frame node visibility would import as N meshes.

The mesh data stay in saft's world frame (metres); a root node rotates that frame so that "up" (opposite
gravity, else the camera's image-up) becomes glTF's +Y. The working camera is exported as a glTF camera
(child of the root node). Material: metallic-roughness, baseColorTexture = material/diffuse.png (else
texture.png), metallicRoughnessTexture = roughness in G and metallic in B when those maps exist; every
image is embedded in the binary buffer; doubleSided. UVs: V flipped (glTF's origin is the top-left).
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import atomic_path
from saft.result import Result, read_result
from saft.scene.mesh import vertex_normals
from saft.io_utils import read_image

log = logging.getLogger("saft")

FLOAT, UINT16, UINT32 = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3×3) taking unit vector a onto unit vector b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: half turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _png_bytes(img: np.ndarray) -> bytes:
    from PIL import Image

    a = (np.clip(img, 0, 1) * 255.0 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(a[:, :, 0] if a.ndim == 3 and a.shape[2] == 1 else a).save(buf, format="PNG")
    return buf.getvalue()


def _gray(path: Path) -> np.ndarray:
    img = read_image(path)
    return img[:, :, :3].mean(axis=2) if img.shape[2] >= 3 else img[:, :, 0]


def _resize_gray(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if img.shape == shape:
        return img
    from PIL import Image

    im = Image.fromarray(img.astype(np.float32), mode="F").resize((shape[1], shape[0]), Image.BILINEAR)
    return np.asarray(im, dtype=np.float32)


def material_images(res: Result) -> tuple[bytes | None, bytes | None, dict]:
    """(base colour PNG, metallic-roughness PNG, which sources were used)."""
    used: dict = {}
    base = None
    diffuse = res.material_path("diffuse.png")
    if diffuse is not None:
        base, used["baseColor"] = diffuse.read_bytes(), "material/diffuse.png"
    elif (res.folder / "texture.png").is_file():
        base, used["baseColor"] = (res.folder / "texture.png").read_bytes(), "texture.png"
    rough_p, metal_p = res.material_path("roughness.png"), res.material_path("metallic.png")
    mr = None
    if rough_p is not None or metal_p is not None:
        rough = _gray(rough_p) if rough_p is not None else None
        metal = _gray(metal_p) if metal_p is not None else None
        shape = (rough if rough is not None else metal).shape
        rough = np.ones(shape, np.float32) if rough is None else rough
        metal = np.zeros(shape, np.float32) if metal is None else _resize_gray(metal, shape)
        packed = np.stack([np.zeros(shape, np.float32), rough, metal], axis=2)  # R unused (occlusion), G, B
        mr = _png_bytes(packed)
        used["metallicRoughness"] = {"G": "material/roughness.png" if rough_p else "1",
                                     "B": "material/metallic.png" if metal_p else "0"}
    return base, mr, used


class _Blob:
    def __init__(self):
        self.data = bytearray()
        self.views: list = []
        self.accessors: list = []

    def view(self, raw: bytes, target: int | None = None) -> int:
        import pygltflib as g

        while len(self.data) % 4:
            self.data += b"\0"
        self.views.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw), target=target))
        self.data += raw
        return len(self.views) - 1

    def accessor(self, arr: np.ndarray, kind: str, component: int, target: int | None = None,
                 minmax: bool = False) -> int:
        import pygltflib as g

        arr = np.ascontiguousarray(arr)
        view = self.view(arr.tobytes(), target)
        acc = g.Accessor(bufferView=view, componentType=component, count=int(arr.shape[0]), type=kind)
        if minmax:
            flat = arr.reshape(arr.shape[0], -1)
            acc.min = [float(x) for x in flat.min(axis=0)]
            acc.max = [float(x) for x in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def build_gltf(res: Result, y_up: bool = True, interpolation: str = "LINEAR"):
    """The pygltflib.GLTF2 document (binary blob set) of a result."""
    import pygltflib as g

    if interpolation not in ("LINEAR", "STEP"):
        raise ValueError("interpolation must be LINEAR or STEP")
    tris = res.template.triangles
    frames = res.vertices.astype(np.float32)
    n = frames.shape[0]
    base = frames[0]
    normals = np.stack([vertex_normals(f, tris) for f in res.vertices]).astype(np.float32)
    uv = res.template.uvs.astype(np.float32).copy()
    uv[:, 1] = 1.0 - uv[:, 1]

    blob = _Blob()
    idx_type = UINT16 if res.template.num_vertices < 65535 else UINT32
    idx = tris.astype(np.uint16 if idx_type == UINT16 else np.uint32).reshape(-1)
    a_idx = blob.accessor(idx, "SCALAR", idx_type, ELEMENT_ARRAY_BUFFER)
    a_pos = blob.accessor(base, "VEC3", FLOAT, ARRAY_BUFFER, minmax=True)
    a_nrm = blob.accessor(normals[0], "VEC3", FLOAT, ARRAY_BUFFER)
    a_uv = blob.accessor(uv, "VEC2", FLOAT, ARRAY_BUFFER)
    targets = []
    for i in range(n):
        # float32 deltas: base + delta reproduces frame i to float32 rounding
        dpos = (frames[i] - base).astype(np.float32)
        dnrm = (normals[i] - normals[0]).astype(np.float32)
        targets.append({"POSITION": blob.accessor(dpos, "VEC3", FLOAT, ARRAY_BUFFER, minmax=True),
                        "NORMAL": blob.accessor(dnrm, "VEC3", FLOAT, ARRAY_BUFFER)})

    # material and textures
    base_png, mr_png, used = material_images(res)
    images, textures = [], []

    def add_texture(png: bytes, name: str) -> int:
        images.append(g.Image(bufferView=blob.view(png), mimeType="image/png", name=name))
        textures.append(g.Texture(source=len(images) - 1, sampler=0))
        return len(textures) - 1

    pbr = g.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=0.9)
    if base_png is not None:
        pbr.baseColorTexture = g.TextureInfo(index=add_texture(base_png, "baseColor"))
    if mr_png is not None:
        pbr.metallicRoughnessTexture = g.TextureInfo(index=add_texture(mr_png, "metallicRoughness"))
        pbr.metallicFactor, pbr.roughnessFactor = 1.0, 1.0
    material = g.Material(name="cloth", pbrMetallicRoughness=pbr, doubleSided=True)

    # animation: one-hot weights, key i at t = i * frame_dt
    times = (np.arange(n, dtype=np.float64) * res.frame_dt).astype(np.float32)
    weights = np.eye(n, dtype=np.float32).reshape(-1, 1)
    a_time = blob.accessor(times, "SCALAR", FLOAT, minmax=True)
    a_w = blob.accessor(weights, "SCALAR", FLOAT)

    names = [f"frame_{i:03d}" for i in range(n)]
    mesh = g.Mesh(name="cloth", primitives=[g.Primitive(
        attributes=g.Attributes(POSITION=a_pos, NORMAL=a_nrm, TEXCOORD_0=a_uv), indices=a_idx, material=0,
        mode=4, targets=targets)], weights=[0.0] * n, extras={"targetNames": names})
    nodes = [g.Node(name="saft_world", children=[1]), g.Node(name="cloth", mesh=0)]
    up = res.up_direction() if y_up else None
    if up is not None:
        rot = rotation_between(up, np.array([0.0, 1.0, 0.0]))
        nodes[0].rotation = [float(x) for x in _quat_xyzw(rot)]
    cameras = []
    if res.camera is not None:
        cam = res.camera
        c2w = cam.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV → glTF camera (looks down −Z)
        cameras.append(g.Camera(type="perspective", name="working_camera", perspective=g.Perspective(
            yfov=float(2 * np.arctan(cam.height / (2 * cam.fy))), aspectRatio=float(cam.width / cam.height),
            znear=0.01)))
        nodes.append(g.Node(name="working_camera", camera=0, rotation=[float(x) for x in _quat_xyzw(c2w[:3, :3])],
                            translation=[float(x) for x in c2w[:3, 3]]))
        nodes[0].children.append(2)
    anim = g.Animation(name="cloth_motion", samplers=[g.AnimationSampler(input=a_time, output=a_w,
                                                                        interpolation=interpolation)],
                       channels=[g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=1, path="weights"))])
    doc = g.GLTF2(
        asset=g.Asset(version="2.0", generator="saft (saft.export.gltf)"),
        scene=0, scenes=[g.Scene(name=str(res.scene_info.get("name", "saft")), nodes=[0])], nodes=nodes,
        meshes=[mesh], materials=[material], textures=textures, images=images,
        samplers=[g.Sampler(magFilter=9729, minFilter=9987, wrapS=33071, wrapT=33071)] if textures else [],
        cameras=cameras, animations=[anim], accessors=blob.accessors, bufferViews=blob.views,
        buffers=[g.Buffer(byteLength=len(blob.data))],
        extras={"saft": {"frame_dt": res.frame_dt, "frames": n, "material": used,
                         "world_up": None if up is None else [float(x) for x in up]}},
    )
    if not textures:
        doc.samplers = []
    doc.set_binary_blob(bytes(blob.data))
    return doc


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    return q / np.linalg.norm(q)


def write_glb(result: str | Path | Result, out: str | Path, y_up: bool = True, interpolation: str = "LINEAR") -> Path:
    """Write the animated cloth of a result as a .glb (atomically); returns the path."""
    res = result if isinstance(result, Result) else read_result(result)
    out = Path(out)
    if out.suffix.lower() != ".glb":
        raise SaftInputError(out, "the glTF export is binary: give a file name ending in .glb")
    doc = build_gltf(res, y_up=y_up, interpolation=interpolation)
    with atomic_path(out) as tmp:
        doc.save_binary(str(tmp))
    log.info("wrote %s (%d frames as morph targets)", out, res.num_frames)
    return out


def _read_accessor(doc, blob: bytes, index: int) -> np.ndarray:
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    dtype = {FLOAT: np.float32, UINT16: np.uint16, UINT32: np.uint32, 5121: np.uint8}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    arr = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return arr.reshape(acc.count, width) if width > 1 else arr


def read_glb_frames(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a saft .glb back: (times (N,), vertices (N, V, 3) float32 = base + target deltas at each key,
    triangles (T, 3), uvs (V, 2) in glTF convention). Evaluates the weights animation at its keyframes."""
    import pygltflib as g

    doc = g.GLTF2().load_binary(str(path))
    blob = doc.binary_blob()
    prim = doc.meshes[0].primitives[0]
    base = _read_accessor(doc, blob, prim.attributes.POSITION)
    deltas = np.stack([_read_accessor(doc, blob, t["POSITION"]) for t in prim.targets])
    tris = _read_accessor(doc, blob, prim.indices).reshape(-1, 3).astype(np.int64)
    uvs = _read_accessor(doc, blob, prim.attributes.TEXCOORD_0)
    sampler = doc.animations[0].samplers[0]
    times = _read_accessor(doc, blob, sampler.input)
    weights = _read_accessor(doc, blob, sampler.output).reshape(len(times), len(prim.targets))
    verts = base[None] + np.einsum("kt,tvc->kvc", weights, deltas, dtype=np.float32)
    return times, verts, tris, uvs
