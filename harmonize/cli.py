"""``palette-harmonize``: a weight stack -> the same weights with a harmonised palette."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from palette_core.cli import ArgumentParser, run_cli
from palette_core.errors import InputError
from palette_core.io import atomic_outputs, check_writable, save_image
from palette_core.recolor import palette_to_hex, weights_to_rgb
from palette_core.render import palette_swatch
from palette_core.stack import WeightStack, read_stack, write_stack

from .fit import fit_all_templates, palette_shares
from .hcl import srgb_to_hcl
from .project import Harmonization, harmonize_with_fit
from .render import contact_sheet, hue_wheel
from .templates import TEMPLATES, get_template

PROG = "palette-harmonize"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog=PROG,
        description="Harmonise the palette of a weight stack with a hue template in HCL "
                    "(Tan, Echevarria and Gingold 2018); the weights stay as they are.",
    )
    parser.add_argument("stack", help="weight stack (.npz) from palette-decompose")
    parser.add_argument("--template", required=True, metavar="NAME",
                        help=f"one of {', '.join(TEMPLATES)}; 'best' for the least cost; "
                             "'all' for one result per template")
    parser.add_argument("--strength", type=float, default=1.0, metavar="B",
                        help="0 keeps the palette, 1 puts every hue on its axis (default 1)")
    parser.add_argument("-o", "--output", default=None,
                        help="stack to write (default: STACK_TEMPLATE.npz beside the input); "
                             "with 'all', each template's name is appended to its stem")
    parser.add_argument("--render", metavar="DIR", default=None,
                        help="also write the recoloured images, a hue wheel and a palette "
                             "swatch here (one subfolder per template with 'all', plus "
                             "contact_sheet.png)")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    if args.template not in ("best", "all"):
        get_template(args.template)
    if not 0.0 <= args.strength <= 1.0:
        raise InputError(f"--strength must lie in [0, 1], got {args.strength}")
    source = Path(args.stack)
    if args.output is not None and Path(args.output).suffix != ".npz":
        raise InputError(f"output must end in .npz, got {args.output}")
    stack = read_stack(source)
    shares = palette_shares(stack)
    fits = fit_all_templates(srgb_to_hcl(stack.palette), shares)
    if args.template == "all":
        names = list(TEMPLATES)
    elif args.template == "best":
        names = [min(fits, key=lambda name: fits[name].cost)]
    else:
        names = [args.template]

    results = {name: harmonize_with_fit(stack.palette, fits[name], args.strength)
               for name in names}
    outputs = _output_paths(source, args.output, names, args.template == "all")
    render = Path(args.render) if args.render else None
    renders, sheet = {}, None
    if render:
        many = args.template == "all"
        renders = _render_paths(stack, {name: render / name if many else render
                                        for name in names})
        sheet = render / "contact_sheet.png" if many else None
    check_writable([*outputs.values(), *(p for ps in renders.values() for p in ps),
                    *([sheet] if sheet else [])], args.force)

    dtype = str(stack.weights[0].dtype)
    with atomic_outputs() as stage:
        for name in names:
            with open(stage(outputs[name]), "wb") as f:
                write_stack(_harmonized_stack(stack, results[name]), f, dtype)
        if render:
            _write_renders(stack, results, shares, renders, stage)
        if sheet:
            _contact_sheet(stack, results, shares).save(stage(sheet), format="PNG")

    if args.template in ("best", "all"):
        _print_fit_table(fits, names)
    before = " ".join(palette_to_hex(stack.palette))
    for name in names:
        h = results[name]
        print(f"{name}: alpha {h.fit.alpha:.2f} deg, cost {h.fit.cost:.1f}\n"
              f"  palette {before}\n"
              f"       -> {' '.join(palette_to_hex(h.palette))}\n"
              f"  wrote {outputs[name]}")
    if render:
        print(f"renders in {render}" + (f", contact sheet {sheet}" if sheet else ""))
    return 0


def _print_fit_table(fits: dict, chosen: list[str]) -> None:
    print(f"{'template':<14} {'alpha':>8} {'cost':>10}")
    for name, fit in fits.items():
        mark = " *" if name in chosen and len(chosen) == 1 else ""
        print(f"{name:<14} {fit.alpha:>8.2f} {fit.cost:>10.1f}{mark}")


def _output_paths(source: Path, output: str | None, names: list[str], many: bool) -> dict:
    if output is None:
        return {name: source.with_name(f"{source.stem}_{name}.npz") for name in names}
    output = Path(output)
    if not many:
        return {names[0]: output}
    return {name: output.with_name(f"{output.stem}_{name}.npz") for name in names}


def _render_paths(stack: WeightStack, folders: dict[str, Path]) -> dict[str, list[Path]]:
    """Per template: the recoloured images, then hue_wheel.png and palette.png."""
    return {name: [folder / n for n in stack.names]
            + [folder / "hue_wheel.png", folder / "palette.png"]
            for name, folder in folders.items()}


def _harmonized_stack(stack: WeightStack, h: Harmonization) -> WeightStack:
    record = {"template": h.fit.template.name, "alpha": h.fit.alpha, "cost": h.fit.cost,
              "strength": h.strength, "palette_before": palette_to_hex(stack.palette)}
    return replace(stack, palette=h.palette.astype(np.float32),
                   meta={**stack.meta, "harmonize": record})


def _wheel(h: Harmonization, shares: np.ndarray, title: str | None = None):
    if title is None:
        title = f"{h.fit.template.name}  alpha {h.fit.alpha:.1f}"
    return hue_wheel(h.hcl_before, shares, h.hcl_after, h.fit.axes, title)


def _write_renders(stack, results, shares, renders, stage) -> None:
    total = len(results) * len(stack.names)
    bar = tqdm(total=total, desc="recolouring", unit="img", disable=total < 8)
    for name, h in results.items():
        *images, wheel_path, swatch_path = renders[name]
        for path, weights in zip(images, stack.weights):
            save_image(stage(path), weights_to_rgb(weights, h.palette, stack.basis, stack.order))
            bar.update()
        _wheel(h, shares).save(stage(wheel_path), format="PNG")
        palette_swatch(h.palette).save(stage(swatch_path), format="PNG")
    bar.close()


def _contact_sheet(stack: WeightStack, results: dict[str, Harmonization], shares: np.ndarray):
    """The first image with the original palette, then recoloured by each template."""
    first = stack.weights[0]
    original = weights_to_rgb(first, stack.palette, stack.basis, stack.order)
    hcl = srgb_to_hcl(stack.palette)
    cells = [("original", original, hue_wheel(hcl, shares))]
    for name, h in results.items():
        recoloured = weights_to_rgb(first, h.palette, stack.basis, stack.order)
        label = f"{name}  alpha {h.fit.alpha:.1f}  cost {h.fit.cost:.0f}"
        cells.append((label, recoloured, _wheel(h, shares, title="")))
    return contact_sheet(cells)


if __name__ == "__main__":
    sys.exit(main())
