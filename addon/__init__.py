# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender-side package `addon` (may import bpy)."""

import bpy

from . import build, fcurves, preview, properties, render_setup, rig  # noqa: F401  (scene builders)
from . import bridge, env_setup, jobs, preferences  # noqa: F401  (engine bridge)

# Classes registered by this package, in dependency order. Modules of this package
# append their classes here when they are added to the product.
CLASSES: tuple = (*preferences.CLASSES, properties.MOTIONSPLATS_PG_result)

_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()
    properties.register_scene_props()
    jobs.register()


def unregister():
    jobs.unregister()
    properties.unregister_scene_props()
    _unregister()
