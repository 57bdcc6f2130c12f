"""`saft view RESULT_DIR`: the interactive 3D viewer of a result, served by viser in the browser.

Scene: the cloth of the current frame (one double-sided glTF mesh per frame and colouring, made when first
shown and then only hidden and shown again), the working camera as a frustum holding the current input
frame, the static template (toggle) and, with ground truth, its point cloud (toggle). GUI: a timeline slider
with play/pause at the video's frame rate, the colouring (phase-1 texture, phase-3 material, distance to the
ground truth with its colour bar), the material maps, and the run's metrics of the current frame.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation
from PIL import Image
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial

from saft.errors import BackendUnavailableError
from saft.evaluate import CD1, CD2, DEPTH, METRIC_LABELS, P2S_L1
from saft.io_utils import read_image
from saft.view.data import (
    ViewData,
    colormap_strip,
    colour_bar,
    distance_scale,
    distance_uvs,
    frustum_pose,
    load_view_data,
    target_image,
)

log = logging.getLogger("saft")

COLOUR_TEXTURE = "texture (phase 1)"
COLOUR_MATERIAL = "material (phase 3)"
COLOUR_DISTANCE = "distance to ground truth"
VIEW_METRICS = (CD2, CD1, P2S_L1, DEPTH)


def _import_viser():
    try:
        import viser
    except ImportError as exc:
        raise BackendUnavailableError(f"saft view needs the viser package ({exc}); pip install viser") from None
    return viser


def _uint8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 2:
        img = img[:, :, None]
    return np.ascontiguousarray(np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[:, :, :3])


def _pbr(base: np.ndarray, metallic_roughness: np.ndarray | None = None):
    mr = None if metallic_roughness is None else Image.fromarray(metallic_roughness)
    return PBRMaterial(baseColorTexture=Image.fromarray(base), metallicRoughnessTexture=mr, doubleSided=True,
                       metallicFactor=1.0 if mr is not None else 0.0, roughnessFactor=1.0)


class ClothViewer:
    """The viser scene and GUI of one result; `frame` and `colouring` select what is shown."""

    def __init__(self, server, data: ViewData):
        self.server, self.data = server, data
        res = data.result
        self.triangles = res.template.triangles
        self.meshes: dict[tuple[str, int], object] = {}
        self.clouds: dict[int, object] = {}
        self.frame = 0
        self.lock = threading.Lock()
        self.materials = self._materials()
        self.scale = distance_scale(data.distances) if data.distances is not None else None
        server.scene.set_up_direction(tuple(float(v) for v in data.up))
        server.scene.configure_environment_map(hdri="studio", environment_intensity=0.6)
        self._camera()
        self.template = server.scene.add_mesh_simple(
            "/template", res.template.vertices.astype(np.float32), self.triangles, color=(150, 150, 150),
            wireframe=True, visible=False)
        self._gui()
        self.show(0)

    # ------------------------------------------------------------------ content
    def _materials(self) -> dict[str, object]:
        res, data = self.data.result, self.data
        out = {}
        if res.texture is not None:
            out[COLOUR_TEXTURE] = _pbr(_uint8(res.texture))
        if "diffuse" in data.material:
            diffuse = _uint8(read_image(data.material["diffuse"]))
            h, w = diffuse.shape[:2]
            mr = np.zeros((h, w, 3), np.uint8)   # glTF: green = roughness, blue = metallic
            for channel, name in ((1, "roughness"), (2, "metallic")):
                if name in data.material:
                    m = Image.fromarray(_uint8(read_image(data.material[name]))[:, :, 0]).resize((w, h))
                    mr[:, :, channel] = np.asarray(m)
                else:
                    mr[:, :, channel] = 255 if name == "roughness" else 0
            out[COLOUR_MATERIAL] = _pbr(diffuse, mr)
        if data.distances is not None:
            out[COLOUR_DISTANCE] = _pbr(colormap_strip())
        if not out:  # a result without any texture: plain grey
            out[COLOUR_TEXTURE] = _pbr(np.full((4, 4, 3), 180, np.uint8))
        return out

    def _mesh(self, colouring: str, k: int):
        key = (colouring, k)
        if key not in self.meshes:
            res = self.data.result
            uvs = (distance_uvs(self.data.distances[k], self.scale) if colouring == COLOUR_DISTANCE
                   else res.template.uvs)
            mesh = trimesh.Trimesh(res.vertices[k], self.triangles, process=False,
                                   visual=TextureVisuals(uv=uvs, material=self.materials[colouring]))
            self.meshes[key] = self.server.scene.add_mesh_trimesh(
                f"/cloth/{colouring.split()[0]}/frame_{k:03d}", mesh, visible=False)
        return self.meshes[key]

    def _cloud(self, k: int):
        if k not in self.clouds:
            pts = self.data.gt_frames[k].astype(np.float32)
            self.clouds[k] = self.server.scene.add_point_cloud(
                f"/ground_truth/frame_{k:03d}", pts, colors=(230, 60, 40), point_size=0.004 * self.data.radius / 0.2,
                visible=False)
        return self.clouds[k]

    def _camera(self) -> None:
        cam = self.data.result.camera
        self.frustum = None
        if cam is None:
            return
        wxyz, position, fov, aspect = frustum_pose(cam)
        dist = float(np.linalg.norm(position - self.data.centre))
        self.frustum = self.server.scene.add_camera_frustum(
            "/camera", fov=fov, aspect=aspect, scale=0.15 * dist, wxyz=wxyz, position=position,
            color=(40, 90, 200), thickness=0.003 * dist)
        # the browser opens looking at the cloth from 35° beside the input camera, close enough to fill the view
        side = Rotation.from_rotvec(np.radians(35.0) * self.data.up).apply(position - self.data.centre)
        eye = self.data.centre + side / np.linalg.norm(side) * 4.0 * self.data.radius
        self.server.initial_camera.position = tuple(float(v) for v in eye)
        self.server.initial_camera.look_at = tuple(float(v) for v in self.data.centre)

    # ------------------------------------------------------------------ GUI
    def _gui(self) -> None:
        gui, data = self.server.gui, self.data
        n = data.num_frames
        gui.add_markdown(f"**{data.result.scene_info.get('name', data.result.folder.name)}** — {n} frames at "
                         f"{data.fps:.4g} fps")
        with gui.add_folder("Timeline"):
            self.slider = gui.add_slider("frame", min=0, max=max(n - 1, 1), step=1, initial_value=0,
                                         disabled=n < 2)
            self.play = gui.add_checkbox("play", initial_value=False, disabled=n < 2)
            self.time_text = gui.add_markdown("")
        with gui.add_folder("Show"):
            self.colouring = gui.add_dropdown("cloth colour", tuple(self.materials), initial_value=next(iter(self.materials)))
            self.show_template = gui.add_checkbox("static template", initial_value=False)
            self.show_camera = gui.add_checkbox("camera and input frame", initial_value=self.frustum is not None,
                                                disabled=self.frustum is None)
            self.show_gt = gui.add_checkbox("ground-truth points", initial_value=False,
                                            disabled=data.gt_frames is None)
            gui.add_markdown(data.gt_note)
        if self.scale is not None:
            with gui.add_folder("Distance to ground truth"):
                gui.add_image(colour_bar(self.scale), label="per-vertex distance (mm); top = 98th percentile")
        self.metrics_text = gui.add_markdown("")
        if data.material:
            with gui.add_folder("Material maps (phase 3)", expand_by_default=False):
                for name, path in data.material.items():
                    gui.add_image(_uint8(read_image(path)), label=f"material/{path.name}")
        self.slider.on_update(lambda _: self.show(int(self.slider.value)))
        self.colouring.on_update(lambda _: self.show(self.frame))
        self.show_template.on_update(lambda _: setattr(self.template, "visible", self.show_template.value))
        self.show_camera.on_update(lambda _: self.frustum is not None
                                   and setattr(self.frustum, "visible", self.show_camera.value))
        self.show_gt.on_update(lambda _: self.show(self.frame))

    def _metrics_line(self, k: int) -> str:
        per = (self.data.result.metrics or {}).get("per_frame")
        if not isinstance(per, dict):
            return ""
        vals = []
        for key in VIEW_METRICS:
            label = METRIC_LABELS[key]
            seq = per.get(key)
            if isinstance(seq, list) and k < len(seq) and isinstance(seq[k], (int, float)):
                vals.append(f"{label} {seq[k]:.3g}")
        return f"frame {k}: " + ", ".join(vals) if vals else ""

    def show(self, k: int) -> None:
        """Show frame k with the selected colouring (hides what was shown before)."""
        with self.lock:
            k = int(np.clip(k, 0, self.data.num_frames - 1))
            want = self.colouring.value
            current = self._mesh(want, k)
            current.visible = True
            for key, handle in self.meshes.items():
                if key != (want, k) and handle.visible:
                    handle.visible = False
            if self.data.gt_frames is not None:
                for handle in self.clouds.values():
                    handle.visible = False
                if self.show_gt.value and k < len(self.data.gt_frames):
                    self._cloud(k).visible = True
            if self.frustum is not None and k < len(self.data.render_files):
                img = target_image(self.data.render_files[k], self.data.result.camera)
                if img is not None:
                    self.frustum.image = img
            self.frame = k
            self.time_text.content = f"t = {k * self.data.result.frame_dt:.3f} s"
            self.metrics_text.content = self._metrics_line(k)

    def step(self) -> None:
        """Advance one frame while playing (wraps around); called at the video's frame rate."""
        if self.play.value and self.data.num_frames > 1:
            self.slider.value = (self.frame + 1) % self.data.num_frames


def serve(result_dir: str | Path, host: str = "127.0.0.1", port: int = 8080,
          stop: threading.Event | None = None) -> int:
    """Serve the viewer of a result until Ctrl-C (or `stop` is set); prints the URL. Returns 0."""
    data = load_view_data(result_dir)
    viser = _import_viser()
    logging.getLogger("websockets").setLevel(logging.WARNING)  # no INFO lines for every connection
    server = viser.ViserServer(host=host, port=port, label=f"saft — {data.result.folder.name}", verbose=False)
    try:
        viewer = ClothViewer(server, data)
        shown = "localhost" if host in ("127.0.0.1", "0.0.0.0", "::") else host
        print(f"saft view: {data.result.folder} at http://{shown}:{server.get_port()}  (Ctrl-C stops)", flush=True)
        period = 1.0 / data.fps
        stop = stop or threading.Event()
        next_tick = time.perf_counter()
        while not stop.is_set():
            next_tick += period
            viewer.step()
            time.sleep(max(0.0, next_tick - time.perf_counter()))
            if time.perf_counter() - next_tick > 1.0:  # fell far behind (a slow browser): do not race
                next_tick = time.perf_counter()
    except KeyboardInterrupt:
        print("saft view: stopped", flush=True)
    finally:
        server.stop()
    return 0
