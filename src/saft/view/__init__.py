"""saft.view — `saft view RESULT_DIR`: an interactive 3D viewer of a result in the browser (viser).

    serve(result_dir, host="127.0.0.1", port=8080, stop=None) -> int     serves until Ctrl-C; prints the URL
    load_view_data(result_dir) -> ViewData                                 what the viewer shows (no viser)

Modules: data (result folder → meshes, distances to the ground truth, camera pose, input frames),
server (viser scene and GUI; viser is imported only when serving).
"""

from saft.view.data import ViewData, load_view_data
from saft.view.server import serve

__all__ = ["ViewData", "load_view_data", "serve"]
