"""The one home of the motion math (no imports here, so that Blender can import
`blender_camera` without torch): `hermite`, `quaternion`, `dualquat`, `binding`,
`camera` (torch) and `blender_camera` (pure Python)."""
