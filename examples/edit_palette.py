"""Edit a palette file: rotate every colour's hue, keeping greys as they are.

    python examples/edit_palette.py palette.json -o edited.json [--degrees 120] [--force]

This is what a user does by hand in any colour picker; the output is a palette
file for ``palette-recolor``.
"""

import argparse
import colorsys
import json
import sys
from pathlib import Path

from palette_core import read_palette_json, write_palette_json


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("palette")
    parser.add_argument("-o", "--output", required=True)
    parser.add_argument("--degrees", type=float, default=120.0)
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args()
    if Path(args.output).exists() and not args.force:
        print(f"error: {args.output} exists (use --force)", file=sys.stderr)
        return 2
    edited = []
    for r, g, b in read_palette_json(args.palette):
        h, s, v = colorsys.rgb_to_hsv(r, g, b)
        edited.append(colorsys.hsv_to_rgb((h + args.degrees / 360.0) % 1.0, s, v))
    write_palette_json(args.output, edited)
    print(f"wrote {args.output}: {json.loads(Path(args.output).read_text())['palette']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
