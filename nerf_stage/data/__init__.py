"""What a scene is read from: datasets and captures (``dataset``: Blender, nerfstudio and
COLMAP layouts; a stack joined to their frames), cameras (``cameras``), lenses
(``distortion``), COLMAP models (``colmap``), sparse points (``points``) and structure from
motion for photos without cameras (``sfm``). docs/capture.md, docs/formats.md."""
