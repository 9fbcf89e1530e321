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


def _key_frames(empty):
    """Key frames of each of ``empty``'s 7 node F-curves."""
    curves = _curves(empty)
    out = []
    for path, size in (("location", 3), ("rotation_quaternion", 4)):
        for c in range(size):
            kp = curves.find(path, index=c).keyframe_points
            co = np.empty(2 * len(kp), np.float32)
            kp.foreach_get("co", co)
            out.append(co[0::2].tolist())
    return out


def _engine_curve(nodes, name, t):
    import torch

    from engine.geometry.hermite import hermite_eval

    inn = getattr(nodes, f"{name}_tangents_in")
    return hermite_eval(torch.tensor(nodes.key_times, dtype=torch.float64),
                        torch.tensor(getattr(nodes, f"{name}_keys"), dtype=torch.float64),
                        torch.tensor(getattr(nodes, f"{name}_tangents"), dtype=torch.float64),
                        torch.tensor(t), None if inn is None else torch.tensor(inn, dtype=torch.float64)).numpy()


def test_keying_one_empty_at_a_new_frame_edits_that_node_only(registered, tmp_path):
    """Issue #18.6: keying one Empty at a frame no node has a key on adds a knot to the
    shared key times, but every other node only gets an exact split of its curve there
    (key_mask False): its curve is the same, its keys in the file are the same bits, and
    Blender shows no new key on it, on this scene or after a re-import."""
    bdir = tmp_path / "bundle"
    make_bundle(bdir, n=12, g=100)
    nodes_file = bdir / bio.NODES_FILE
    b = bio.read_nodes(nodes_file)
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir)) == {"FINISHED"}
    build = registered.addon.build
    col = build.bundle_collection(bpy.context)
    empties = build.node_empties(col)
    before = [_key_frames(e) for e in empties]
    old_frames = sorted(set(before[0][0]))
    new_frame = 0.5 * (old_frames[1] + old_frames[2]) + 1.25  # between two keys, on no key
    scene = bpy.context.scene
    scene.frame_set(int(new_frame), subframe=new_frame - int(new_frame))
    e5 = empties[5]
    e5.location = (e5.location[0], e5.location[1], e5.location[2] + 0.4)  # the artist moves it up there
    e5.keyframe_insert("location", frame=new_frame)

    sent = registered.addon.exporters.send_edits(col)
    assert sent.edited == [5], sent.edited  # was every node
    assert sent.rekeyed
    n2 = bio.read_nodes(nodes_file)
    k = len(b.key_times)
    assert n2.key_times.shape == (k + 1,)
    new = int(np.flatnonzero(~np.isin(n2.key_times, b.key_times))[0])
    old = np.delete(np.arange(k + 1), new)
    assert np.array_equal(n2.key_times[old], b.key_times)
    others = np.arange(12) != 5
    assert n2.key_mask.shape == (12, k + 1) and n2.key_mask.dtype == np.bool_
    assert not n2.key_mask[others, new].any() and n2.key_mask[5].all()
    assert n2.key_mask[:, old].all()
    for name in ("pos", "rot"):
        for arr in ("keys", "tangents"):  # the other nodes' keys: the same bits
            assert np.array_equal(getattr(n2, f"{name}_{arr}")[others][:, old], getattr(b, f"{name}_{arr}")[others])
        # ... and the same curves everywhere (the new knot is an exact split)
        t = np.linspace(-0.05, 1.05, 221)
        np.testing.assert_allclose(_engine_curve(n2, name, t)[others], _engine_curve(b, name, t)[others],
                                   atol=1e-6, rtol=0)
    # node 5 moved up at the new frame
    z_new = float(n2.pos_keys[5, new, 2])
    z_old = float(_engine_curve(b, "pos", n2.key_times[new:new + 1].astype(np.float64))[5, 0, 2])
    assert z_new == pytest.approx(z_old + 0.4, abs=1e-3)

    # Blender: no new key on the untouched Empties; sending again finds nothing edited
    assert [_key_frames(e) for e in empties][:5] == before[:5]
    again = registered.addon.exporters.send_edits(col)
    assert again.path is None and again.edited == [], again.edited

    # a re-import keys each Empty only on its own keys, and the F-curves are the engine's curves
    saved = nodes_file.read_bytes()
    bpy.data.collections.remove(col)
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir)) == {"FINISHED"}
    col = build.bundle_collection(bpy.context)
    empties = build.node_empties(col)
    counts = [len(set(f for ch in _key_frames(e) for f in ch)) for e in empties]
    assert counts[5] == k + 1 and all(c == k for i, c in enumerate(counts) if i != 5), counts
    fs, fe = 1, 25
    frames = np.linspace(fs, fe, 97)
    engine = _engine_curve(n2, "pos", (frames - fs) / (fe - fs))
    for i in (0, 5, 11):
        fcs = _curves(empties[i])
        got = np.array([[fcs.find("location", index=c).evaluate(f) for c in range(3)] for f in frames])
        np.testing.assert_allclose(got, engine[i], atol=2e-5)
    again = registered.addon.exporters.send_edits(col)
    assert again.path is None and again.edited == [], again.edited
    assert nodes_file.read_bytes() == saved
