# SPDX-License-Identifier: GPL-3.0-or-later
"""Motion Splats: a Blender extension that turns a monocular clip into a dynamic
Gaussian-splat scene driven by editable control nodes.

This file only wires the three bpy sub-packages together. The reconstruction engine
(``engine/``) never imports bpy and runs in its own Python process.
"""

try:
    import bpy  # noqa: F401
except ImportError:  # imported outside Blender (e.g. engine tests on a machine without bpy)
    bpy = None

if bpy is not None:
    from . import addon, operators, panels

    _MODULES = (addon, operators, panels)
else:
    _MODULES = ()


def register():
    for module in _MODULES:
        module.register()


def unregister():
    for module in reversed(_MODULES):
        module.unregister()
