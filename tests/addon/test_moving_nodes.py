"""Issue #18.7 / #18.10: which nodes move is visible (moving / static sub-collections, distinct
Empties, Select Moving Nodes); with several results the operators act on the active one and
refuse when it is ambiguous; the Result panel says where the preview's colours show."""

from __future__ import annotations

import numpy as np
import pytest

import bpy
from engine import bundle as bio

from tests.addon.test_build_bundle import make_bundle
from tests.addon.test_build_ops import _Layout


@pytest.fixture()
def registered(extension, empty_scene):
    extension.register()
    try:
        yield extension
    finally:
        extension.unregister()


def _bundle_with_scores(path, scores):
    make_bundle(path, n=len(scores), g=60)
    nodes = bio.read_nodes(path / bio.NODES_FILE)
    arrays = nodes.to_dict()
    arrays["p_dyn"] = np.asarray(scores, np.float32)
    bio.write_nodes(path / bio.NODES_FILE, bio.NodeArrays.from_dict(arrays, path / bio.NODES_FILE))
    return path


def test_moving_nodes_are_grouped_and_selectable(registered, tmp_path):
    scores = [0.9, 0.1, 0.6, 0.0, 0.5, 0.2]
    bdir = _bundle_with_scores(tmp_path / "cups", scores)
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir)) == {"FINISHED"}
    build = registered.addon.build
    col = build.bundle_collection(bpy.context)
    subs = {c["ms_nodes"]: c for c in col.children if "ms_nodes" in c}
    assert set(subs) == {"moving", "static"}
    moving = sorted(int(o["ms_node"]) for o in subs["moving"].objects)
    assert moving == [0, 2, 4]
    assert sorted(int(o["ms_node"]) for o in subs["static"].objects) == [1, 3, 5]
    assert {o.empty_display_type for o in subs["moving"].objects} != {o.empty_display_type
                                                                      for o in subs["static"].objects}
    assert [int(e["ms_node"]) for e in build.node_empties(col)] == list(range(6))
    assert bpy.ops.motion_splats.select_moving_nodes() == {"FINISHED"}
    assert sorted(int(o["ms_node"]) for o in bpy.context.selected_objects) == [0, 2, 4]
    # an Empty in a sub-collection still identifies its result
    bpy.context.view_layer.objects.active = subs["static"].objects[0]
    assert build.bundle_collection(bpy.context) == col
    assert col.name == "MotionSplats_cups"


def test_several_results_act_on_the_active_one(registered, tmp_path):
    build = registered.addon.build
    a = _bundle_with_scores(tmp_path / "a", [0.9, 0.1, 0.8, 0.2])
    b = _bundle_with_scores(tmp_path / "b", [0.9, 0.1, 0.8, 0.2])
    assert bpy.ops.motion_splats.import_bundle(directory=str(a)) == {"FINISHED"}
    assert bpy.ops.motion_splats.import_bundle(directory=str(b)) == {"FINISHED"}
    col_a = next(c for c in build.result_collections() if c.name == "MotionSplats_a")
    bpy.context.view_layer.objects.active = None
    assert build.bundle_collection(bpy.context) is None  # not "the last one built"
    assert not bpy.ops.motion_splats.send_edits.poll()
    assert "2 results" in build.why_no_result(bpy.context)
    bpy.context.view_layer.objects.active = build.node_empties(col_a)[1]  # the artist edits result a
    assert build.bundle_collection(bpy.context) == col_a
    assert bpy.ops.motion_splats.send_edits.poll()
    cams = [o.name for o in bpy.data.objects if o.type == "CAMERA"]
    assert sorted(cams) == ["MotionSplats_a_Camera", "MotionSplats_b_Camera"]


def test_result_panel_says_where_colours_show(registered, tmp_path):
    from types import SimpleNamespace

    labels = []

    class Recording(_Layout):
        def __getattr__(self, name):
            def call(*args, **kwargs):
                if name == "label":
                    labels.append(kwargs.get("text", ""))
                return Recording()
            return call

    make_bundle(tmp_path / "b", n=4, g=40)
    assert bpy.ops.motion_splats.import_bundle(directory=str(tmp_path / "b")) == {"FINISHED"}
    registered.panels.build_panel.MOTIONSPLATS_PT_result.draw(SimpleNamespace(layout=Recording()), bpy.context)
    assert any("Material Preview" in t for t in labels), labels
