"""``palette-studio``: edit a palette live in the browser, for a weight stack or a trained
weight NeRF."""

from __future__ import annotations

import sys
import threading
import webbrowser

from palette_core.cli import ArgumentParser, run_cli, show_warnings

PROG = "palette-studio"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Edit a palette live in the browser: "
                            "the images of a weight stack, or a trained weight NeRF.")
    parser.add_argument("target", help="a weight stack (.npz or .zarr) from palette-decompose, "
                        "a run folder from nerf-stage train, or a splat file (.ply, .spz, "
                        ".splat, .sog) or its splat stack")
    parser.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1: this machine only)")
    parser.add_argument("--no-browser", action="store_true",
                        help="print the address only; do not open a browser")
    parser.add_argument("--no-splats", action="store_true",
                        help="scene mode: let the network draw every view, without baking the "
                             "run into splats for the browser (docs/splats.md)")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    from .app import Studio, open_target

    studio = Studio(open_target(args.target, splats=not args.no_splats), args.host, args.port)
    print(studio.url, flush=True)
    print(f"editing {args.target} ({studio.target.mode}); Ctrl+C to stop", file=sys.stderr)
    show_warnings()  # started well: what was held back in case of a refusal
    if not args.no_browser:
        webbrowser.open(studio.url)
    try:
        threading.Event().wait()
    finally:
        studio.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
