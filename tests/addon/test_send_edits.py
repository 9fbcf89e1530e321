"""Issue #18.6: Send Edits touches only the edited nodes (the others stay bit-exact, no in-tangents
made up from float32 noise), backs the old nodes.npz up like Fine-tune does, is an undo step,
and the README names the button as the panel does."""

from __future__ import annotations

import numpy as np
import pytest

import bpy
from engine import bundle as bio

from tests.addon._support import fcurves_of, REPO
from tests.addon.test_build_bundle import make_bundle


@pytest.fixture()
def registered(extension, empty_scene):
    extension.register()
    try:
        yield extension
    finally:
        extension.unregister()


def _curves(empty):
    return fcurves_of(empty)


def test_send_edits_touches_only_edited_nodes(registered, tmp_path):
    bdir = tmp_path / "bundle"
    make_bundle(bdir, n=12, g=100)
    nodes_file = bdir / bio.NODES_FILE
    b = bio.read_nodes(nodes_file)  # what the bundle holds (float32 on disk)
    original = nodes_file.read_bytes()
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir)) == {"FINISHED"}
    col = registered.addon.build.bundle_collection(bpy.context)
    empties = registered.addon.build.node_empties(col)

    # nothing edited: nothing written, no backup
    assert bpy.ops.motion_splats.send_edits() == {"FINISHED"}
    assert nodes_file.read_bytes() == original
    assert not (bdir / "backups").exists()

    # move node 3's z key 2 (value and both handles) by 0.5
    kp = _curves(empties[3]).find("location", index=2).keyframe_points[2]
    for attr in ("co", "handle_left", "handle_right"):
        v = getattr(kp, attr)
        setattr(kp, attr, (v[0], v[1] + 0.5))
    assert bpy.ops.motion_splats.send_edits() == {"FINISHED"}
    n2 = bio.read_nodes(nodes_file)
    others = np.arange(12) != 3
    for name in ("pos_keys", "pos_tangents", "rot_keys", "rot_tangents"):
        assert np.array_equal(getattr(n2, name)[others], getattr(b, name)[others]), name
    assert np.array_equal(n2.key_times, b.key_times)
    assert n2.pos_keys[3, 2, 2] == pytest.approx(b.pos_keys[3, 2, 2] + 0.5, abs=1e-5)
    assert n2.pos_tangents_in is None and n2.rot_tangents_in is None  # no handle was broken
    backups = list((bdir / "backups").glob("edits-*/nodes.npz"))
    assert len(backups) == 1 and backups[0].read_bytes() == original


def test_send_edits_is_an_undo_step_named_as_in_the_readme(registered):
    op = registered.operators.result_ops.MOTIONSPLATS_OT_send_edits
    assert "UNDO" in op.bl_options
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert op.bl_label in readme
    assert "Send edits to engine" not in readme
