"""``palette-harmonize``: a weight stack -> the same weights with a harmonised palette."""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

from palette_core.cli import ArgumentParser, exit_without_teardown, run_cli
from palette_core.palette_file import palette_to_hex
from palette_core.stack import DEFAULT_STACK, default_stack, read_stack

from .batch import ALL, BEST, StackHarmonization, harmonize_stack
from .templates import TEMPLATES

PROG = "palette-harmonize"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog=PROG,
        description="Harmonise the palette of a weight stack with a hue template in HCL "
                    "(Tan, Echevarria and Gingold 2018); the weights stay as they are.",
    )
    parser.add_argument("stack", nargs="?", default=None,
                        help="weight stack (.npz) from palette-decompose (default "
                             f"./{DEFAULT_STACK}, where palette-decompose writes it)")
    parser.add_argument("--template", required=True, metavar="NAME",
                        help=f"one of {', '.join(TEMPLATES)}; '{BEST}' for the least cost; "
                             f"'{ALL}' for one result per template")
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


def run() -> NoReturn:
    """The console script: ``main``, then the process ends without Python's teardown."""
    exit_without_teardown(main())


def _run(args) -> int:
    if args.stack is None:
        args.stack = str(default_stack())
        print(f"using ./{args.stack}")
    from splat_files.stack import is_splat_stack

    if is_splat_stack(args.stack):
        from splat_files.commands import harmonize_command

        return harmonize_command(args)
    result = harmonize_stack(read_stack(args.stack), args.template, args.strength)
    written = result.write(args.stack, args.output, args.render, args.force)
    if args.template in (BEST, ALL):
        _print_fit_table(result)
    before = " ".join(palette_to_hex(result.stack.palette))
    for name, h in result.results.items():
        print(f"{name}: alpha {h.fit.alpha:.2f} deg, cost {h.fit.cost:.1f}\n"
              f"  palette {before}\n"
              f"       -> {' '.join(palette_to_hex(h.palette))}\n"
              f"  wrote {written[name]}")
    if args.render:
        sheet = f", contact sheet {Path(args.render) / 'contact_sheet.png'}" if result.many else ""
        print(f"renders in {Path(args.render)}{sheet}")
    return 0


def _print_fit_table(result: StackHarmonization) -> None:
    print(f"{'template':<14} {'alpha':>8} {'cost':>10}")
    for name, fit in result.fits.items():
        mark = " *" if name in result.results and not result.many else ""
        print(f"{name:<14} {fit.alpha:>8.2f} {fit.cost:>10.1f}{mark}")


if __name__ == "__main__":
    run()
