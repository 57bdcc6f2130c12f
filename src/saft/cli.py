"""The `saft` command.

    saft demo [--out DIR]                       synthetic scene → reconstruction → evaluation table
    saft reconstruct SCENE --out DIR            texture, shape (and appearance) of a scene's cloth
    saft evaluate RESULT_DIR --gt GT_OR_SCENE   CD2, CD1, p2s, depth δ per frame and mean; writes metrics.json
    saft report DIR                             self-contained HTML report of a result
    saft export DIR [--video] [--gltf F.glb] [--sequence obj|ply]
    saft view DIR [--port N] [--host H]         interactive 3D viewer of a result in the browser (viser)
    saft batch SCENE... --out DIR [--grid k=v1,v2 ...] [--address ADDR]   many runs as Ray tasks
    saft inspect SCENE                          check a scene and print what saft reads from it
    saft info                                   versions, devices and rendering backends available

Bad input ends with one line naming the file and the problem, exit code 2 (`--debug` shows the traceback).
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings
from pathlib import Path

from saft import __version__
from saft.backends import backend_lines
from saft.batch import parse_grid, plan_tasks, run_batch
from saft.demo import run_demo
from saft.device import plan_devices
from saft.errors import BackendUnavailableError, SaftInputError, SimulationError
from saft.evaluate import (evaluate_result_dir, format_metrics_table, ground_truth_files, ground_truth_spec_for,
                           ground_truth_spec_from_path)
from saft.evaluate.appearance_result import evaluate_appearance_result, format_appearance_table
from saft.export import export_command, report_command
from saft.reconstruct import reconstruct
from saft.reconstruct.checkpoint import checkpoint_path
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.scene.frames import check_all_frames
from saft.view import serve

log = logging.getLogger("saft")

EXIT_BAD_INPUT = 2


def _setup_logging(quiet: bool, debug: bool) -> None:
    from rich.logging import RichHandler

    level = logging.DEBUG if debug else (logging.WARNING if quiet else logging.INFO)
    handler = RichHandler(show_time=False, show_path=False, markup=False, rich_tracebacks=debug)
    logging.basicConfig(level=level, format="%(message)s", handlers=[handler], force=True)
    if not debug:
        warnings.showwarning = _warning_as_log_line


def _warning_as_log_line(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings (saft's own and its libraries') as one log line, without the source line."""
    log.warning("%s", message)


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars; warnings and results only")
    p.add_argument("--debug", action="store_true", help="show full tracebacks and debug logs")


# ---------------------------------------------------------------------------- subcommands
def cmd_evaluate(args: argparse.Namespace) -> int:
    spec = ground_truth_spec_from_path(args.gt, frame=args.gt_frame, flip_axes=args.flip, root=args.root)
    metrics = evaluate_result_dir(args.result_dir, spec, seed=args.seed, allow_partial=args.allow_partial)
    print(format_metrics_table(metrics))
    log.info("wrote %s", Path(args.result_dir) / "metrics.json")
    gt_path = Path(args.gt)
    scene_dir = gt_path.parent if gt_path.suffix.lower() == ".json" else gt_path
    appearance = evaluate_appearance_result(args.result_dir, scene_dir)
    if appearance is not None:
        print(format_appearance_table(appearance))
        log.info("wrote the appearance metrics into %s", Path(args.result_dir) / "material" / "appearance.json")
    return 0


def _load_config(args: argparse.Namespace):
    overrides = list(args.set or [])
    if getattr(args, "device", None):
        overrides.append(f'run.device="{args.device}"')
    return load_saft_config(args.config, overrides)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 2:
        raise SaftInputError("--frames", f"must be at least 2 (frame 0 is the template), got {args.frames}")
    if args.resume and args.overwrite:
        raise SaftInputError("--overwrite", "cannot be combined with --resume")
    cfg = _load_config(args)
    scene = load_scene(args.scene, root=args.root)
    if args.frames:
        if args.frames > scene.num_frames:
            log.warning("--frames %d: the scene has only %d frames; using all of them", args.frames, scene.num_frames)
        scene = scene.with_frames(min(args.frames, scene.num_frames))
    spec = None
    if args.gt is not None:   # checked now, not after the reconstruction
        spec = ground_truth_spec_for(scene, None if args.gt == "scene" else args.gt, root=args.root)
        count = len(ground_truth_files(spec))
        if count < scene.num_frames or (count > scene.num_frames and not args.frames):
            raise SaftInputError(spec.directory, f"has {count} ground-truth frames but the scene has "
                                                 f"{scene.num_frames} frames")
    try:
        outcome = reconstruct(scene, cfg, args.out, resume=args.resume, overwrite=args.overwrite, quiet=args.quiet)
    except KeyboardInterrupt as exc:
        if not str(exc) and checkpoint_path(args.out).is_file():
            raise KeyboardInterrupt(f"interrupted; continue with --resume (checkpoint in "
                                    f"{checkpoint_path(args.out).parent})") from None
        raise
    log.info("result written to %s", outcome.out_dir)
    if spec is not None:
        metrics = evaluate_result_dir(args.out, spec, allow_partial=bool(args.frames))
        print(format_metrics_table(metrics))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    run_demo(args.out, quiet=args.quiet, device=args.device)
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene, root=args.root)
    cam = scene.working_camera()
    print(f"scene {scene.name}: {scene.num_frames} frames of {scene.camera.width}x{scene.camera.height}"
          f"{' with masks' if scene.frames.has_masks else ' (masks derived from non-black pixels)'}")
    print(f"template: {scene.template.num_vertices} vertices, {len(scene.template.quads)} quads")
    print(f"camera: fx={cam.fx:.2f} fy={cam.fy:.2f} cx={cam.cx:.2f} cy={cam.cy:.2f}, working image "
          f"{cam.width}x{cam.height}{f' (crop {scene.crop.to_json()})' if scene.crop else ''}")
    print(f"frame_dt={scene.frame_dt:g}s  gravity={scene.gravity_or_default().round(3).tolist()}"
          f"{'' if scene.gravity is not None else ' (default: opposite the camera up)'}"
          f"  pinned={0 if scene.pinned is None else len(scene.pinned)}  texture={'yes' if scene.texture is not None else 'no'}"
          f"  ground truth={scene.ground_truth_dir or 'none'}")
    if args.all_frames:
        check_all_frames(scene.working_frames(), decode=True)
        print("all frames readable, of the same size, with non-empty masks")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    path = report_command(args.result_dir, args.out)
    print(f"wrote {path}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    for path in export_command(args.result_dir, video=args.video, gltf=args.gltf, sequence=args.sequence,
                               out_dir=args.out):
        print(f"wrote {path}")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    tasks = plan_tasks(args.scenes, args.out, args.set, parse_grid(args.grid),
                       {"gt": args.gt, "device": args.device, "frames": args.frames, "root": args.root})
    outcomes = run_batch(tasks, args.out, address=args.address, num_cpus=args.num_cpus, resources=args.resources,
                         quiet=args.quiet)
    failed = [o for o in outcomes if not o.ok]
    print(f"{len(outcomes) - len(failed)} of {len(outcomes)} tasks finished; summary in {args.out / 'summary.csv'} "
          f"and {args.out / 'summary.html'}")
    return 1 if failed else 0


def cmd_view(args: argparse.Namespace) -> int:
    return serve(args.result_dir, host=args.host, port=args.port)


def cmd_info(args: argparse.Namespace) -> int:
    import platform

    import torch

    print(f"saft {__version__}  python {platform.python_version()}  torch {torch.__version__}")
    print(f"torch threads: {torch.get_num_threads()}  CUDA available: {torch.cuda.is_available()}")
    print("backends:")
    for line in backend_lines():
        print(f"  {line}")
    print("--device auto puts each part of a run here:")
    for line in plan_devices("auto").lines():
        print(f"  {line}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="saft", description="Shape and appearance of fabrics from a template and one RGB video.")
    parser.add_argument("--version", action="version", version=f"saft {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("demo", help="reconstruct a built-in synthetic example and print its accuracy")
    p.add_argument("--out", type=Path, default=Path("saft-demo"), help="folder for the scene/ and the result/ (default ./saft-demo)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    _add_common(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("reconstruct", help="reconstruct the cloth's shape in every frame of a scene",
                       description="Texture mapping, physics-based shape from template (and appearance) "
                                   "of SCENE; writes the result folder OUT (see docs/result-layout in README).")
    p.add_argument("scene", type=Path, help="a native scene folder or a SAFT/PG-SfT scene .json")
    p.add_argument("--out", required=True, type=Path, help="result folder")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None, help="default: auto")
    p.add_argument("--config", type=Path, default=None, help="a TOML config (see a result's config.toml)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one config value, e.g. --set shape.lambda_force=0 (repeatable)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from OUT/checkpoint (same scene and config only)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the saft result already in OUT (without it saft refuses to write there)")
    p.add_argument("--gt", nargs="?", const="scene", default=None, type=str,
                   help="evaluate against ground truth afterwards (default: the scene's own)")
    p.add_argument("--frames", type=int, default=None, help="use only the first N frames")
    p.add_argument("--root", type=Path, default=None, help="dataset root for a SAFT/PG-SfT scene JSON")
    _add_common(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("evaluate", help="compare a result's meshes with ground-truth point clouds",
                       description="Per-frame and mean CD2 (1e-4 m²), CD1 (cm), p2s (mm) of RESULT_DIR/meshes/"
                                   "frame_*.obj against ground truth; writes RESULT_DIR/metrics.json.")
    p.add_argument("result_dir", type=Path, help="a result folder with meshes/frame_000.obj …")
    p.add_argument("--gt", required=True, type=Path,
                   help="ground-truth point clouds (.pt/.npy/.ply per frame) or a scene that names them")
    p.add_argument("--gt-frame", choices=["world", "camera"], default=None,
                   help="frame the point clouds are stored in (default: from the scene, else world)")
    p.add_argument("--flip", default=None, help="axes to negate in the ground truth, e.g. 'xy'")
    p.add_argument("--root", type=Path, default=None, help="dataset root for a SAFT/PG-SfT scene JSON")
    p.add_argument("--seed", type=int, default=0, help="seed of the surface sampling (default 0)")
    p.add_argument("--allow-partial", action="store_true",
                   help="evaluate the frames present when the result has fewer frames than the ground truth")
    _add_common(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("report", help="write a self-contained HTML report of a result folder")
    p.add_argument("result_dir", type=Path)
    p.add_argument("--out", type=Path, default=None, help="default RESULT_DIR/report.html")
    _add_common(p)
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("export", help="videos, an animated glTF (.glb) or a mesh sequence of a result",
                       description="Export a result folder: --video (mp4s of target | re-render and an orbit), "
                                   "--gltf FILE.glb (animated cloth with its material, opens in Blender), "
                                   "--sequence obj|ply (one mesh per frame).")
    p.add_argument("result_dir", type=Path)
    p.add_argument("--video", action="store_true", help="write comparison/appearance/orbit mp4 videos")
    p.add_argument("--gltf", type=Path, default=None, metavar="FILE.glb", help="write an animated glTF binary")
    p.add_argument("--sequence", choices=["obj", "ply"], default=None, help="write one mesh per frame")
    p.add_argument("--out", type=Path, default=None, help="folder for videos and sequences (default DIR/export)")
    _add_common(p)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("batch", help="reconstruct many scenes × settings as Ray tasks (local or a cluster)",
                       description="Run `saft reconstruct` for every SCENE and every combination of the --grid "
                                   "values, as Ray tasks, into OUT/<scene>[/<setting>]. Finished tasks are "
                                   "skipped and interrupted ones resume when the command is run again. Writes "
                                   "OUT/summary.csv and OUT/summary.html; logs in OUT/logs/.")
    p.add_argument("scenes", nargs="+", type=Path, metavar="SCENE", help="native scene folders or scene .json files")
    p.add_argument("--out", required=True, type=Path, help="batch folder")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override for every task (repeatable)")
    p.add_argument("--grid", action="append", metavar="KEY=V1,V2",
                   help="one row of settings per value (repeatable: the cartesian product), e.g. "
                        "--grid shape.lambda_force=0,1e-3")
    p.add_argument("--gt", action="store_true", help="evaluate every result against its scene's ground truth")
    p.add_argument("--address", default=None,
                   help="join this Ray cluster (e.g. auto, or HEAD_IP:6379) instead of starting Ray here")
    p.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    p.add_argument("--resources", action="append", metavar="NAME=AMOUNT",
                   help="what each task asks Ray for (default CPU=1, and GPU=1 when the cluster has GPUs)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None, help="default: auto")
    p.add_argument("--frames", type=int, default=None, help="use only the first N frames of every scene")
    p.add_argument("--root", type=Path, default=None, help="dataset root for SAFT/PG-SfT scene JSONs")
    _add_common(p)
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("view", help="interactive 3D viewer of a result in the browser",
                       description="Serve an interactive viewer of RESULT_DIR (viser): the cloth of every frame "
                                   "with a timeline, the camera with the input frame, the static template, the "
                                   "distance to the ground truth and the material maps. Serves until Ctrl-C.")
    p.add_argument("result_dir", type=Path)
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; the next free one if taken)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; 0.0.0.0 for all)")
    _add_common(p)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("inspect", help="check a scene and print what saft reads from it")
    p.add_argument("scene", type=Path, help="a native scene folder or a SAFT/PG-SfT scene .json")
    p.add_argument("--root", type=Path, default=None, help="dataset root for a SAFT/PG-SfT scene JSON")
    p.add_argument("--all-frames", action="store_true", help="also open every frame and mask")
    _add_common(p)
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("info", help="versions, devices and backends")
    _add_common(p)
    p.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    debug = getattr(args, "debug", False)
    _setup_logging(getattr(args, "quiet", False), debug)
    try:
        return int(args.func(args) or 0)
    except (SaftInputError, BackendUnavailableError) as exc:
        if debug:
            raise
        print(f"saft: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SimulationError as exc:
        if debug:
            raise
        print(f"saft: simulation failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        print(f"saft: {exc}" if str(exc) else "saft: interrupted", file=sys.stderr)
        return 130
