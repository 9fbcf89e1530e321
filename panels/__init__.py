# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-side package `panels` (may import bpy)."""

import bpy

from . import build_panel, main_panel, reconstruct_panel

# Classes registered by this package, in dependency order. Modules of this package
# append their classes here when they are added to the product.
CLASSES: tuple = (*main_panel.CLASSES, *build_panel.CLASSES, *reconstruct_panel.CLASSES)

_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()


def unregister():
    _unregister()
