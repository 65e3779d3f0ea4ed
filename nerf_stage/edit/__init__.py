"""Editing a trained run without its network: weight renders recoloured by palettes
(``editing``), inside regions of the scene (``regions``), and scored with their edits
against the truth (``evaluation``). docs/selections.md."""
