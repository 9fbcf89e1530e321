"""The extension registers and unregisters cleanly, twice, without leaking classes."""

import bpy


def _registered_names():
    names = set()
    for base in (bpy.types.Operator, bpy.types.Panel, bpy.types.AddonPreferences, bpy.types.PropertyGroup,
                 bpy.types.Menu, bpy.types.UIList):
        names |= {cls.__name__ for cls in base.__subclasses__() if getattr(cls, "is_registered", False)}
    return names


def test_register_unregister_twice(extension, empty_scene):
    before = _registered_names()
    types_before = set(dir(bpy.types))
    for _ in range(2):
        extension.register()
        added = _registered_names() - before
        for module in (extension.addon, extension.operators, extension.panels):
            for cls in module.CLASSES:
                assert cls.is_registered, cls
                assert cls.__name__ in added
        extension.unregister()
        assert _registered_names() == before
        assert set(dir(bpy.types)) == types_before
