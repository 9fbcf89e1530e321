"""Each step's track term scores the rendered frame and a few other training frames, so the
keys far from the rendered frame's time are held by their tracks too."""

import torch

from engine.train.config import preset_config
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene


def _track_grad_and_times(tmp_path, data, truth, track_frames):
    cfg = preset_config("preview", steps=1, gaussians_per_frame=400, init_keyframes=4, num_nodes=25,
                        checkpoint_every=0, warmup_static_steps=0, track_frames=track_frames)
    tr = Trainer(data, make_nodes(truth), cfg, tmp_path / f"k{track_frames}")
    m, o = tr.model, tr.objective
    with torch.no_grad():  # off the true motion, so every track pulls
        m.pos_keys.add_(0.05 * torch.randn(m.pos_keys.shape, generator=torch.Generator().manual_seed(0)))
    asked = []
    state_dq = m.node_state_dq
    m.node_state_dq = lambda t: (asked.append(float(t)), state_dq(t))[1]
    f = int(data.train_idx[0])  # time 0: its spline support is the first keys only
    t = float(data.times[f])
    term = o.track_terms(m, f, t, state_dq(t)[2])
    term.backward()
    return term, m.pos_keys.grad.clone(), asked


def test_the_track_term_reaches_keys_far_from_the_rendered_frame(tmp_path):
    data, truth = make_scene()
    one, grad_one, asked_one = _track_grad_and_times(tmp_path, data, truth, 1)
    many, grad_many, asked = _track_grad_and_times(tmp_path, data, truth, 8)
    assert asked_one == [] and len(asked) == 7
    # the other frames are training frames, never held-out ones
    train_times = {float(data.times[i]) for i in data.train_idx}
    assert set(asked) <= train_times and max(asked) > 0.7
    # the rendered frame's term alone moves only the keys near time 0 ...
    last = grad_one[:, -1].abs().sum()
    assert float(last) == 0.0 and float(grad_one[:, 0].abs().sum()) > 0
    # ... the frames drawn beside it reach the last key, and add their own terms to it
    assert float(grad_many[:, -1].abs().sum()) > 0
    assert float(many) > float(one) > 0
