"""harmonize: hue-template harmonisation of palettes in HCL.

Convert the palette to HCL (``hcl``), fit one of seven hue templates
(``templates``) by the weighted hue-distance cost (``fit``), move each hue onto
its nearest axis keeping lightness and chroma (``project``), and draw hue wheels
(``render``); ``batch`` harmonises whole weight stacks. After Tan, Echevarria and
Gingold (2018), as used by PaletteNeRF.
"""

from .batch import StackHarmonization, harmonize_stack
from .fit import TemplateFit, fit_all_templates, fit_template, palette_shares, template_cost
from .hcl import hcl_to_srgb, hcl_to_srgb_in_gamut, in_srgb_gamut, srgb_to_hcl
from .project import Harmonization, harmonize_palette, harmonize_with_fit, project_palette
from .templates import TEMPLATES, Template, get_template
from .wheel import contact_sheet, hue_wheel

__all__ = [
    "TEMPLATES",
    "Harmonization",
    "StackHarmonization",
    "Template",
    "TemplateFit",
    "contact_sheet",
    "fit_all_templates",
    "fit_template",
    "get_template",
    "harmonize_palette",
    "harmonize_stack",
    "harmonize_with_fit",
    "hcl_to_srgb",
    "hcl_to_srgb_in_gamut",
    "hue_wheel",
    "in_srgb_gamut",
    "palette_shares",
    "project_palette",
    "srgb_to_hcl",
    "template_cost",
]
