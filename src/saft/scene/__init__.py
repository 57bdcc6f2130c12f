"""Scene model and readers: everything converted into saft's conventions once, here.

- `QuadMesh` (mesh.py): template quads + one UV per vertex, metres; `read_obj`, `write_obj`.
- `Camera`, `Crop` (camera.py): OpenCV intrinsics + world_to_camera; `.cropped()`, `.scaled()`, `.project()`;
  camera geometry: `look_at`, `orbit_camera` (the novel view), `orbit_cameras` (the orbit video), `up_direction`.
- `FrameSequence` (frames.py): lazily loaded RGB + mask frames, with a crop/scale view.
- `Scene` (scene.py): template, camera, frames, texture, pinned vertices, frame_dt, gravity, crop, ground truth.
- `load_scene(path)`: a native scene folder (native.py) or a SAFT/PG-SfT JSON (phi_sft.py).
"""

from __future__ import annotations

from pathlib import Path

from saft.errors import SaftInputError
from saft.scene.camera import Camera, Crop, look_at, orbit_camera, orbit_cameras, up_direction
from saft.scene.frames import Frame, FrameSequence
from saft.scene.mesh import QuadMesh, read_obj, write_obj
from saft.scene.native import read_native_scene
from saft.scene.phi_sft import read_phi_sft_scene
from saft.scene.scene import Scene

__all__ = ["Camera", "Crop", "Frame", "FrameSequence", "QuadMesh", "Scene", "load_scene", "look_at", "orbit_camera",
           "orbit_cameras", "read_native_scene", "read_obj", "read_phi_sft_scene", "up_direction", "write_obj"]


def load_scene(path: str | Path, root: str | Path | None = None) -> Scene:
    """Load a scene: a native scene folder, or a SAFT/PG-SfT scene JSON (`root`: its dataset root)."""
    path = Path(path)
    if path.is_dir():
        return read_native_scene(path)
    if path.suffix.lower() == ".json" and path.is_file():
        return read_phi_sft_scene(path, root)
    if not path.exists():
        raise SaftInputError(path, "scene not found (expected a scene folder or a SAFT/PG-SfT .json)")
    raise SaftInputError(path, "not a scene: expected a scene folder or a SAFT/PG-SfT .json file")
