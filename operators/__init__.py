# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-side package `operators` (may import bpy)."""

import bpy

from . import engine_ops, finetune_ops, import_ops, reconstruct_ops, result_ops

# Classes registered by this package, in dependency order. Modules of this package
# append their classes here when they are added to the product.
CLASSES: tuple = (*engine_ops.CLASSES, *result_ops.CLASSES, *reconstruct_ops.CLASSES, *import_ops.CLASSES,
                  *finetune_ops.CLASSES)

_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()


def unregister():
    _unregister()
