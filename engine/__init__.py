"""Motion Splats reconstruction engine.

Runs in its own Python process (``python -m engine ...``), never imports bpy. This
module stays import-light (no torch) so that bpy-free helpers such as
:mod:`engine.bundle` and :mod:`engine.protocol` can also be used from Blender's Python.
Inside the package every import is relative, so it works both as the top-level
``engine`` package and as ``<extension>.engine`` inside Blender.
"""

__version__ = "0.1.0"
