"""Engine Hermite splines written as Blender F-curves evaluate to the same motion."""

import time

import numpy as np
import pytest
import torch

import bpy
from engine.geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_eval_quat
from engine.geometry.quaternion import quat_normalize


def _random_splines(n, k, seed=0):
    g = torch.Generator().manual_seed(seed)
    kt = torch.sort(torch.rand(k, generator=g, dtype=torch.float64)).values
    kt = (kt - kt[0]) / (kt[-1] - kt[0])  # engine time [0, 1], non-uniform
    loc = torch.randn(n, k, 3, generator=g, dtype=torch.float64)
    rot = quat_normalize(torch.tensor([1.0, 0, 0, 0], dtype=torch.float64) + 0.3 * torch.randn(n, k, 4, generator=g,
                                                                                              dtype=torch.float64))
    return kt, loc, catmull_rom_tangents(kt, loc), rot, catmull_rom_tangents(kt, rot)


def _empties(scene, n):
    objs = []
    for i in range(n):
        o = bpy.data.objects.new(f"node_{i}", None)
        scene.collection.objects.link(o)
        objs.append(o)
    return objs


def _write(extension, scene, n=6, k=7, start=1, end=48):
    fcurves = extension.addon.fcurves
    kt, loc, loc_t, rot, rot_t = _random_splines(n, k)
    frames, loc_tf = fcurves.engine_keys_to_frames(kt.numpy(), loc_t.numpy(), start, end)
    _, rot_tf = fcurves.engine_keys_to_frames(kt.numpy(), rot_t.numpy(), start, end)
    objs = _empties(scene, n)
    fcurves.write_node_fcurves(objs, frames, loc.numpy(), loc_tf, rot.numpy(), rot_tf)
    return objs, (kt, loc, loc_t, rot, rot_t), frames


def _engine_at_frames(spl, frames_query, start, end):
    kt, loc, loc_t, rot, rot_t = spl
    t = torch.tensor((np.asarray(frames_query) - start) / (end - start), dtype=torch.float64)
    return hermite_eval(kt, loc, loc_t, t).numpy(), hermite_eval_quat(kt, rot, rot_t, t).numpy()


def test_fcurves_evaluate_to_engine_spline(extension, empty_scene):
    objs, spl, _ = _write(extension, empty_scene)
    query = np.linspace(1, 48, 97) + 0.123
    query = query[query <= 48]
    loc_ref, rot_ref = _engine_at_frames(spl, query, 1, 48)
    for i, obj in enumerate(objs):
        bag = extension.addon.fcurves._fcurve_container(obj, create=False)
        for c in range(3):
            fc = bag.find("location", index=c)
            got = np.array([fc.evaluate(f) for f in query])
            np.testing.assert_allclose(got, loc_ref[i, :, c], rtol=1e-5, atol=1e-5 * np.abs(loc_ref).max())
    # evaluated object transforms after frame_set (Blender normalises quaternions too)
    scene = empty_scene
    for f in (1, 7, 20, 33, 48):
        scene.frame_set(f)
        loc_f, rot_f = _engine_at_frames(spl, [f], 1, 48)
        for i, obj in enumerate(objs):
            np.testing.assert_allclose(np.array(obj.location), loc_f[i, 0], atol=1e-5)
            q = np.array(obj.rotation_quaternion)
            q = q / np.linalg.norm(q)
            np.testing.assert_allclose(q, rot_f[i, 0], atol=1e-5)


def test_reader_returns_written_keys_and_tangents(extension, empty_scene, tmp_path):
    fcurves = extension.addon.fcurves
    objs, spl, frames = _write(extension, empty_scene)
    kt, loc, loc_t, rot, rot_t = spl

    def check(objects):
        back = fcurves.read_node_fcurves(objects)
        np.testing.assert_allclose(back["key_frames"], frames, atol=1e-4)
        np.testing.assert_allclose(back["loc_keys"], loc.numpy(), atol=1e-5)
        np.testing.assert_allclose(back["rot_keys"], rot.numpy(), atol=1e-5)
        times, loc_t_back = fcurves.frames_to_engine_keys(back["key_frames"], back["loc_tangents_out"], 1, 48)
        np.testing.assert_allclose(loc_t_back, loc_t.numpy(), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(back["loc_tangents_in"], back["loc_tangents_out"], rtol=1e-4, atol=1e-5)
        _, rot_t_back = fcurves.frames_to_engine_keys(back["key_frames"], back["rot_tangents_out"], 1, 48)
        np.testing.assert_allclose(rot_t_back, rot_t.numpy(), rtol=1e-4, atol=1e-4)

    check(objs)
    # survives save / reload of the .blend
    path = str(tmp_path / "nodes.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    check([bpy.data.objects[f"node_{i}"] for i in range(len(objs))])
    kp = fcurves._fcurve_container(bpy.data.objects["node_0"], False).find("location", index=0).keyframe_points
    assert {p.handle_left_type for p in kp} == {"FREE"} and {p.interpolation for p in kp} == {"BEZIER"}


def test_artist_edit_reads_back_and_mismatched_keys_are_reported(extension, empty_scene):
    fcurves = extension.addon.fcurves
    objs, spl, frames = _write(extension, empty_scene, n=3)
    fc = fcurves._fcurve_container(objs[1], False).find("location", index=2)
    kp = fc.keyframe_points[2]
    kp.co.y += 0.5
    kp.handle_left.y += 0.5
    kp.handle_right.y += 0.9  # broken tangent
    fc.update()
    back = fcurves.read_node_fcurves(objs)
    assert back["loc_keys"][1, 2, 2] == pytest.approx(float(spl[1][1, 2, 2]) + 0.5, abs=1e-5)
    assert back["loc_tangents_out"][1, 2, 2] != pytest.approx(back["loc_tangents_in"][1, 2, 2], abs=1e-3)
    # a key inserted on one node only
    objs[0].keyframe_insert("location", index=0, frame=5.5)
    with pytest.raises(fcurves.SplineMismatchError, match="node_0"):
        fcurves.read_node_fcurves(objs)
    res = fcurves.read_node_fcurves(objs, resample=True)
    assert len(res["key_frames"]) == len(frames) + 1
    # the finer Hermite spline reproduces every F-curve: exactly where the handles sit at
    # 1/3 spacing (nodes 1, 2), and at the keys for the edited node 0
    kf = torch.tensor(res["key_frames"])
    query = np.linspace(frames[0], frames[-1], 61)
    ev = hermite_eval(kf, torch.tensor(res["loc_keys"]), torch.tensor(res["loc_tangents_out"]),
                      torch.tensor(query), tangents_in=torch.tensor(res["loc_tangents_in"])).numpy()
    for i, obj in enumerate(objs):
        bag = fcurves._fcurve_container(obj, False)
        for c in range(3):
            fc = bag.find("location", index=c)
            if i == 0 and c == 0:
                got = np.array([fc.evaluate(f) for f in res["key_frames"]])
                np.testing.assert_allclose(res["loc_keys"][0, :, 0], got, atol=1e-5)
            else:
                got = np.array([fc.evaluate(f) for f in query])
                np.testing.assert_allclose(ev[i, :, c], got, atol=1e-5)


def test_write_speed_2000_nodes(extension, empty_scene, capsys):
    fcurves = extension.addon.fcurves
    n, k = 2000, 30
    kt, loc, loc_t, rot, rot_t = _random_splines(n, k, seed=1)
    frames, loc_tf = fcurves.engine_keys_to_frames(kt.numpy(), loc_t.numpy(), 1, 120)
    _, rot_tf = fcurves.engine_keys_to_frames(kt.numpy(), rot_t.numpy(), 1, 120)
    objs = _empties(empty_scene, n)
    t0 = time.perf_counter()
    fcurves.write_node_fcurves(objs, frames, loc.numpy(), loc_tf, rot.numpy(), rot_tf)
    elapsed = time.perf_counter() - t0
    t0 = time.perf_counter()
    back = fcurves.read_node_fcurves(objs)
    elapsed_read = time.perf_counter() - t0
    with capsys.disabled():
        print(f"\n[measured] 2000 nodes x 7 channels x 30 keys written in {elapsed:.2f} s, "
              f"read in {elapsed_read:.2f} s")
    assert back["rot_keys"].shape == (n, k, 4)
    np.testing.assert_allclose(back["rot_keys"], rot.numpy(), atol=1e-6)
    assert elapsed < 10 and elapsed_read < 10  # generous CI bounds; the figures above are what we report
