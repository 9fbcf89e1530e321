"""The moving Gaussians' seeds (engine/train/init_model.py): each frame's moving pixels
covered once before any is seeded twice, and a frame's own seeds opaque from the start."""

from __future__ import annotations

import torch

from engine.geometry.camera import project
from engine.train.config import preset_config
from engine.train.init_model import build_model, distinct_pixels, dynamic_gaussians

from .synthetic_training import make_nodes, make_scene


def test_distinct_pixels_covers_every_pixel_before_repeating_one():
    gen = torch.Generator().manual_seed(0)
    few = distinct_pixels(50, 20, gen)
    assert len(few) == 20 and len(torch.unique(few)) == 20
    exact = distinct_pixels(50, 50, gen)
    assert torch.equal(torch.sort(exact).values, torch.arange(50))
    more = distinct_pixels(50, 120, gen)  # two whole passes and 20 of a third
    counts = torch.bincount(more, minlength=50)
    assert int(counts.min()) == 2 and int(counts.max()) == 3 and int(counts.sum()) == 120
    assert torch.equal(torch.sort(more[:50]).values, torch.arange(50))


def _moving_pixels(data, cfg, f):
    m = data.fg[f] >= cfg.dynamic_threshold
    return m & (data.depth[f] > 0)


def test_a_frame_with_as_many_seeds_as_moving_pixels_has_one_on_each():
    """With the seed count equal to the moving area every moving pixel of every frame is
    seeded exactly once (independent draws leave ~37 % of them bare)."""
    data, _ = make_scene()
    probe = preset_config("preview")
    moving = torch.stack([_moving_pixels(data, probe, int(f)) for f in data.train_idx])
    area = int(moving.sum())
    cfg = preset_config("preview", dynamic_gaussians=area)
    pts, _, _, tms = dynamic_gaussians(data, cfg, torch.Generator().manual_seed(0), distinct=True)
    assert len(pts) >= area - len(data.train_idx)  # each frame's floor() share loses < 1 seed
    for k, f in enumerate(data.train_idx.tolist()):
        sel = tms == data.times[f]
        uv = project(data.K[f], data.w2c[f], pts[sel])[0]
        px = torch.floor(uv).long()
        flat = px[:, 1] * data.width + px[:, 0]
        assert len(torch.unique(flat)) == len(flat)  # no pixel twice
        hit = torch.zeros(data.height * data.width, dtype=torch.bool)
        hit[flat] = True
        assert bool(moving[k].flatten()[hit].all())  # only moving pixels
        assert int(moving[k].sum()) - int(hit.sum()) <= 1  # and all of them


def test_seeds_with_a_lifespan_cover_their_frame_and_start_opaque():
    """A frame's own seeds (lifespans on) cover its moving pixels evenly (no pixel seeded twice
    while another has none) and start at ``lifespan_seed_opacity``; without lifespans the moving
    seeds, shown at every time, start at 0.3 like the static ones."""
    data, truth = make_scene()
    kw = dict(gaussians_per_frame=800, init_keyframes=4, num_nodes=25, dynamic_gaussians=600,
              lifespan_seed_opacity=0.9)
    for lifespan, want in (("on", 0.9), ("off", 0.3)):
        cfg = preset_config("preview", lifespan=lifespan, **kw)
        model = build_model(data, make_nodes(truth), cfg, torch.Generator().manual_seed(0))
        assert model.is_split and bool((model.gauss_lifespan[model.gauss_dyn] > 0).all()) == (lifespan == "on")
        op = model.opacities()
        torch.testing.assert_close(op[model.gauss_dyn], torch.full((int(model.gauss_dyn.sum()),), want))
        torch.testing.assert_close(op[~model.gauss_dyn], torch.full((int((~model.gauss_dyn).sum()),), 0.3))
    # with lifespans the seeds, moved to their own time, sit on their seed pixels: count them per
    # moving pixel of each frame
    cfg = preset_config("preview", lifespan="on", **kw)
    model = build_model(data, make_nodes(truth), cfg, torch.Generator().manual_seed(0))
    dyn = torch.nonzero(model.gauss_dyn).squeeze(1)
    with torch.no_grad():
        for f in data.train_idx.tolist():
            t = float(data.times[f])
            rows = dyn[model.gauss_t_center[dyn] == t]
            uv = project(data.K[f], data.w2c[f], model.deform(t)[0][rows])[0]
            px = torch.floor(uv + 1e-3).long()
            counts = torch.bincount(px[:, 1] * data.width + px[:, 0], minlength=data.height * data.width)
            moving = _moving_pixels(data, cfg, f).flatten()
            assert int(counts[~moving].sum()) == 0
            assert int(counts[moving].max()) - int(counts[moving].min()) <= 1, (f, counts[moving].tolist())
