"""Harmonising a weight stack with one template, the best one, or all seven, and writing
the harmonised stacks with their renders (what ``palette-harmonize`` does)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from palette_core.basis import weights_to_rgb
from palette_core.errors import InputError
from palette_core.folders import inside
from palette_core.outputs import atomic_outputs, check_writable, save_image
from palette_core.palette_file import palette_to_hex
from palette_core.stack import WeightStack, is_zarr, write_stack
from palette_core.stack.zarr import check_store_output
from palette_core.swatch import palette_swatch

from .fit import TemplateFit, fit_all_templates, palette_shares
from .hcl import srgb_to_hcl
from .project import Harmonization, check_strength, harmonize_with_fit
from .templates import TEMPLATES, get_template
from .wheel import contact_sheet, hue_wheel

#: Template choices beyond the names: the least cost, or every template.
BEST, ALL = "best", "all"


@dataclass
class StackHarmonization:
    """A stack's palette harmonised by one or more templates.

    Attributes
    ----------
    stack : WeightStack
    shares : (K,) float64
        Each palette colour's share of the weights (``palette_shares``).
    fits : dict of str to TemplateFit
        Every template at its best rotation.
    results : dict of str to Harmonization
        The chosen templates' harmonisations.
    many : bool
        All templates were asked for (outputs get one name per template).
    """

    stack: WeightStack
    shares: np.ndarray
    fits: dict[str, TemplateFit]
    results: dict[str, Harmonization]
    many: bool

    def stack_paths(self, source: Path, output: str | Path | None) -> dict[str, Path]:
        """Per template, the stack to write: ``output``, or ``SOURCE_TEMPLATE.npz`` (``.zarr``
        for a Zarr source) beside the source; with all templates each name is appended to
        the stem."""
        names = list(self.results)
        if output is None:
            suffix = ".zarr" if is_zarr(source) else ".npz"
            return {name: source.with_name(f"{source.stem}_{name}{suffix}") for name in names}
        output = Path(output)
        if output.suffix not in (".npz", ".zarr"):
            raise InputError(f"output must end in .npz or .zarr, got {output}")
        if not self.many:
            return {names[0]: output}
        return {name: output.with_name(f"{output.stem}_{name}{output.suffix}") for name in names}

    def render_paths(self, folder: Path) -> dict[str, list[Path]]:
        """Per template: the recoloured images, then hue_wheel.png and palette.png (one
        subfolder per template when all were asked for)."""
        return {name: [inside(sub, n) for n in self.stack.names] + [sub / "hue_wheel.png",
                                                              sub / "palette.png"]
                for name in self.results
                for sub in [folder / name if self.many else folder]}

    def write(self, source: str | Path, output: str | Path | None = None,
              render: str | Path | None = None, force: bool = False) -> dict[str, Path]:
        """Write the harmonised stacks and, with ``render``, the recoloured images, hue wheels,
        swatches and (all templates) ``contact_sheet.png``. Zarr stacks are published
        first, each by its own rename (``stack.zarr``); then the NPZ stacks and the pictures
        together (``outputs.atomic_outputs``).

        Returns
        -------
        dict of str to Path
            The stack written per template.

        Raises
        ------
        InputError
            If an output exists (without ``force``), cannot be written, or ``output``
            does not end in .npz.
        """
        stacks = self.stack_paths(Path(source), output)
        renders = self.render_paths(Path(render)) if render else {}
        sheet = Path(render) / "contact_sheet.png" if render and self.many else None
        zarrs = {name: path for name, path in stacks.items() if is_zarr(path)}
        check_writable([*(p for p in stacks.values() if p not in zarrs.values()),
                        *(p for ps in renders.values() for p in ps),
                        *([sheet] if sheet else [])], force)
        for path in zarrs.values():
            check_store_output(path, force)
        for name, path in zarrs.items():
            write_stack(self.harmonized_stack(name), path, force=force)
        with atomic_outputs(force) as stage:
            for name, path in stacks.items():
                if name not in zarrs:
                    with open(stage(path), "wb") as f:
                        write_stack(self.harmonized_stack(name), f)
            if renders:
                self._write_renders(renders, stage)
            if sheet:
                self.contact_sheet().save(stage(sheet), format="PNG")
        return stacks

    def harmonized_stack(self, name: str) -> WeightStack:
        """The stack with template ``name``'s palette, the harmonisation recorded in its meta."""
        h = self.results[name]
        record = {"template": h.fit.template.name, "alpha": h.fit.alpha, "cost": h.fit.cost,
                  "strength": h.strength, "palette_before": palette_to_hex(self.stack.palette)}
        return replace(self.stack, palette=h.palette.astype(np.float32),
                       meta={**self.stack.meta, "harmonize": record})

    def wheel(self, name: str, title: str | None = None):
        """Hue wheel of template ``name``: palette hues before and after, with its axes."""
        h = self.results[name]
        if title is None:
            title = f"{h.fit.template.name}  alpha {h.fit.alpha:.1f}"
        return hue_wheel(h.hcl_before, self.shares, h.hcl_after, h.fit.axes, title)

    def contact_sheet(self):
        """The first image with the original palette, then recoloured by each template."""
        stack = self.stack
        first = stack.weights[0]
        original = weights_to_rgb(first, stack.palette, stack.basis, stack.order)
        cells = [("original", original, hue_wheel(srgb_to_hcl(stack.palette), self.shares))]
        for name, h in self.results.items():
            recoloured = weights_to_rgb(first, h.palette, stack.basis, stack.order)
            label = f"{name}  alpha {h.fit.alpha:.1f}  cost {h.fit.cost:.0f}"
            cells.append((label, recoloured, self.wheel(name, title="")))
        return contact_sheet(cells)

    def _write_renders(self, renders: dict[str, list[Path]], stage) -> None:
        stack = self.stack
        total = len(self.results) * len(stack.names)
        bar = tqdm(total=total, desc="recolouring", unit="img", disable=total < 8)
        for name, h in self.results.items():
            *images, wheel_path, swatch_path = renders[name]
            for path, weights in zip(images, stack.weights):
                save_image(stage(path), weights_to_rgb(weights, h.palette, stack.basis,
                                                       stack.order))
                bar.update()
            self.wheel(name).save(stage(wheel_path), format="PNG")
            palette_swatch(h.palette).save(stage(swatch_path), format="PNG")
        bar.close()


def harmonize_stack(stack: WeightStack, template: str = BEST,
                    strength: float = 1.0) -> StackHarmonization:
    """Fit every template to the stack's palette and harmonise with ``template``.

    Parameters
    ----------
    template : str
        A name in ``TEMPLATES``, ``"best"`` (least cost) or ``"all"``.
    strength : float in [0, 1]

    Raises
    ------
    InputError
        For an unknown template or a strength outside [0, 1].
    """
    if template not in (BEST, ALL):
        get_template(template)
    check_strength(strength)
    shares = palette_shares(stack)
    fits = fit_all_templates(srgb_to_hcl(stack.palette), shares)
    if template == ALL:
        names = list(TEMPLATES)
    elif template == BEST:
        names = [min(fits, key=lambda name: fits[name].cost)]
    else:
        names = [template]
    results = {name: harmonize_with_fit(stack.palette, fits[name], strength) for name in names}
    return StackHarmonization(stack, shares, fits, results, template == ALL)
