"""``palette-studio``: edit a palette live in the browser, for a weight stack or a trained
weight NeRF."""

from __future__ import annotations

import sys
import threading
import webbrowser
from pathlib import Path

from palette_core.cli import ArgumentParser, run_cli
from palette_core.errors import InputError

PROG = "palette-studio"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Edit a palette live in the browser: "
                            "the images of a weight stack, or a trained weight NeRF.")
    parser.add_argument("target", help="a weight stack (.npz or .zarr) from palette-decompose, "
                        "or a run folder from nerf-stage train")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1: this machine only)")
    parser.add_argument("--no-browser", action="store_true",
                        help="print the address only; do not open a browser")
    return parser


def open_target(path: str):
    """A ``PhotoTarget`` for a weight stack, a ``SceneTarget`` for a run folder.

    Raises
    ------
    InputError
        If ``path`` is neither.
    """
    from nerf_stage.run import CHECKPOINT

    from .photos import PhotoTarget

    target = Path(path)
    if target.is_dir() and (target / CHECKPOINT).is_file():
        from .scene import SceneTarget

        return SceneTarget.open(target)
    if target.suffix in (".npz", ".zarr"):
        return PhotoTarget.open(target)
    if not target.exists():
        raise InputError(f"{path} does not exist")
    raise InputError(f"{path} is neither a weight stack (.npz, .zarr) nor a run folder "
                     f"(a folder with {CHECKPOINT})")


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    from .app import Studio

    if not 0 <= args.port <= 65535:
        raise InputError(f"--port must be in [0, 65535], got {args.port}")
    studio = Studio(open_target(args.target), args.host, args.port)
    print(studio.url, flush=True)
    print(f"editing {args.target} ({studio.target.mode}); Ctrl+C to stop", file=sys.stderr)
    if not args.no_browser:
        webbrowser.open(studio.url)
    try:
        threading.Event().wait()
    finally:
        studio.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
