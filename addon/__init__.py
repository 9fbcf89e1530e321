# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-side package `addon` (may import bpy)."""

import bpy

from . import fcurves, rig  # noqa: F401  (scene builders; no classes to register)

# Classes registered by this package, in dependency order. Modules of this package
# append their classes here when they are added to the product.
CLASSES: tuple = ()

_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()


def unregister():
    _unregister()
