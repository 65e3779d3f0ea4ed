"""Editing a trained run without its network: weight renders recoloured by palettes
(``editing``), inside regions of the scene (``regions``). docs/selections.md."""
