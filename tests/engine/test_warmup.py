"""Issue #18.5: a run reports loading / compiling its Numba kernels as the progress stage
``compile`` (engine/train/warmup.py), and every stage's ETA is measured, never a made-up 0."""

from __future__ import annotations

import io
import json
import time

import pytest

from engine.protocol import Reporter, parse_event

numba = pytest.importorskip("numba")


def _events(stream: io.StringIO) -> list[dict]:
    return [parse_event(line) for line in stream.getvalue().splitlines()]


def test_eta_is_measured_from_the_stages_own_rate():
    stream = io.StringIO()
    rep = Reporter(jsonl=True, stream=stream)
    rep.progress("load frames", 1, 10)  # the stage's start was not reported: no rate yet
    time.sleep(0.2)
    rep.progress("load frames", 3, 10)  # 2 steps in 0.2 s: 7 left take ~0.7 s
    rep.progress("tracks", 0, 4)
    time.sleep(0.1)
    rep.progress("tracks", 1, 4)
    rep.progress("tracks", 4, 4)
    first, second, t0, t1, t4 = _events(stream)
    assert "eta_s" not in first, first  # was 0.0: "ETA 0:00" on every stage's first report
    assert 0.6 <= second["eta_s"] <= 2.0, second
    assert "eta_s" not in t0
    assert 0.25 <= t1["eta_s"] <= 1.0, t1
    assert t4["eta_s"] == 0.0  # finished
    # a stage name used again restarts its clock (a lower step)
    rep.progress("tracks", 1, 4)
    assert "eta_s" not in _events(stream)[-1]


def _dispatchers():
    from numba.core.dispatcher import Dispatcher

    from engine.raster import cpu_numba
    from engine.train import fused, fused_image, fused_nodes, fused_points, fused_reg, fused_sh, fused_ssim

    return {(m.__name__, name): d for m in (cpu_numba, fused, fused_image, fused_nodes, fused_points, fused_reg,
                                                   fused_sh, fused_ssim)
            for name, d in vars(m).items() if isinstance(d, Dispatcher)}


class _Recorder(Reporter):
    """A JSON-lines reporter that notes which kernel signatures were loaded when the
    compile stage logged its summary."""

    def __init__(self):
        super().__init__(jsonl=True, stream=io.StringIO())
        self.after_compile = None

    def log(self, message, level="info"):
        if message.startswith("engine kernels"):
            self.after_compile = {k: set(d.signatures) for k, d in _dispatchers().items()}
        super().log(message, level)


def test_training_reports_a_compile_stage_that_loads_every_kernel_it_uses(tmp_path):
    """The compile stage comes before the first render (the held-out evaluation of the
    initialisation) and training after it needs no kernel signature it did not load: the
    first step does not stall on a compilation that the box shows as training."""
    from engine.train.config import preset_config
    from engine.train.trainer import Trainer

    from .synthetic_training import make_nodes, make_scene

    data, truth = make_scene(frames=8, width=48, height=36)
    cfg = preset_config("preview", steps=24, gaussians_per_frame=300, init_keyframes=4, num_nodes=16,
                        densify_from=6, densify_until=20, densify_every=6, rebind_every=8, checkpoint_every=0,
                        log_every=4, warmup_static_steps=4, device="cpu")
    rep = _Recorder()
    Trainer(data, make_nodes(truth), cfg, tmp_path / "run", rep).run()
    events = _events(rep.stream)
    stages = [e["stage"] for e in events if e["event"] == "progress"]
    assert "compile" in stages and "train" in stages
    assert stages.index("compile") < stages.index("train")
    compile_steps = [e for e in events if e["event"] == "progress" and e["stage"] == "compile"]
    assert compile_steps[0]["step"] == 0 and compile_steps[-1]["step"] == compile_steps[-1]["total"]
    assert len(compile_steps) >= 5 and all("eta_s" in e for e in compile_steps[1:]), compile_steps
    summary = [e["message"] for e in events if e["event"] == "log" and e["message"].startswith("engine kernels")]
    assert len(summary) == 1 and (" compiled " in summary[0] or "loaded from the cache" in summary[0]), summary
    # nothing the compile stage left out was loaded (or compiled) during training
    after_run = {k: set(d.signatures) for k, d in _dispatchers().items()}
    missed = {k: sorted(map(str, after_run[k] - rep.after_compile.get(k, set()))) for k in after_run}
    assert not {k: v for k, v in missed.items() if v}, json.dumps({str(k): v for k, v in missed.items() if v})
    # the first logged training step already has a measured ETA (the stage's clock starts at step 0)
    train = [e for e in events if e["event"] == "progress" and e["stage"] == "train"]
    assert train[0]["step"] == 0 and train[1].get("eta_s", 0) > 0, train[:2]


def test_no_compile_stage_where_no_numba_kernel_runs():
    from engine.train.warmup import kernel_groups, warm_kernels

    stream = io.StringIO()
    assert warm_kernels(Reporter(jsonl=True, stream=stream), "meta") is None
    assert stream.getvalue() == ""
    assert "rasteriser" not in [g[0] for g in kernel_groups("cpu", "reference")]
    assert "rasteriser" in [g[0] for g in kernel_groups("cpu", "cpu")]
