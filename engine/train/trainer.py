"""The optimisation loop: initialise, train, densify, checkpoint, resume, evaluate.

``Trainer(data, nodes, config, out_dir).run()`` turns :class:`TrainingData` and an
initial node set into a trained result bundle. Long runs are safe to interrupt:
checkpoints are written atomically every ``checkpoint_every`` steps and on SIGINT /
SIGTERM (the CLI turns both into ``KeyboardInterrupt``); ``resume=True`` continues from
the last checkpoint and reproduces the uninterrupted run (CPU, same seed).

The trainer keeps the loop, the learning-rate schedule, checkpoint / resume and export;
scoring its frames is :mod:`engine.train.evaluation`'s. The loss is
:class:`engine.train.objective.Objective`'s; densification is done by the strategies of
:mod:`engine.train.strategy`, called at fixed points of a step; the optimiser and its row
surgery are :mod:`engine.train.param_edit`'s.
"""

from __future__ import annotations

import math
import time
from functools import partial
from pathlib import Path

import torch

from .. import bundle as B
from ..errors import Cancelled, InputError
from ..fsutil import atomic_path
from ..protocol import Reporter
from . import checkpoint as CK
from .config import TrainConfig
from .data import TrainingData
from .export import bundle_arrays, bundle_cameras
from .evaluation import evaluate_frames, quality_lines, render_frame, spread_sample
from .frame_order import resolve_frame_order, step_frame
from .lifespan import camera_translates, clamp_lifespans_, shown_gaussians
from .objective import Objective
from .param_edit import make_optimizer  # noqa: F401  (re-exported)
from .phases import no_phase
from .render import render_scene, scene_colors
from .seed_anchor import canonical_view, deform_seed_frame, hold_seed_frame_
from .shot_detail import has_detail, stage_optimizer, train_detail
from .split import freeze_static_nodes
from .strategy import GaussianDensifyStrategy, NodeDensifyStrategy
from .warmup import warm_kernels

CHECKPOINT_NAME = "checkpoint.pt"

#: each step renders only the Gaussians its time can show (lifespan.shown_gaussians; tests
#: switch it off to compare)
CULL_HIDDEN = True

# build_model / initial_gaussians / trajectory_fg_score re-exported: the model's
# construction lives in init_model.py
from .init_model import build_model, canonicalise, initial_gaussians, trajectory_fg_score  # noqa: F401, E402


class Trainer:
    """Runs one reconstruction.

    Parameters
    ----------
    data : TrainingData
    nodes : bundle.NodeArrays
        Initial node set (from ``engine.nodes``).
    config : TrainConfig
    out_dir : path
        The result bundle folder (checkpoints go to ``out_dir/checkpoints``).
    reporter : Reporter, optional
    resume : bool
        Continue from ``out_dir/checkpoints/checkpoint.pt``.
    scene_extra : dict, optional
        Extra scene.json keys (source clip, priors, camera solve).
    still_plate : dict, optional
        ``{"train": dB, "val": dB}``: the still plate's PSNR, logged and recorded beside the
        run's own (``engine.pipeline.still_plate_psnr``).
    """

    def __init__(self, data: TrainingData, nodes: B.NodeArrays, config: TrainConfig, out_dir,
                 reporter: Reporter | None = None, resume: bool = False, scene_extra: dict | None = None,
                 still_plate: dict | None = None):
        self.data = data.validate()
        self.nodes = nodes
        self.cfg = config.validate()
        self.out_dir = Path(out_dir)
        self.ckpt_path = self.out_dir / "checkpoints" / CHECKPOINT_NAME
        self.reporter = reporter or Reporter(quiet=True)
        self.scene_extra = scene_extra or {}
        self.still_plate = still_plate
        self.device = data.images.device
        torch.manual_seed(self.cfg.seed)
        # bitwise resume on the CPU needs deterministic algorithms: a process-wide switch,
        # set where the process starts (engine/runtime.py), not here
        self.gen = torch.Generator(device="cpu")
        self.gen.manual_seed(self.cfg.seed)
        self.step = 0
        self._seed_frame = False  # moving Gaussians held in their seed frame (seed_anchor.py)
        self.history: list[dict] = []
        self.train_seconds = 0.0
        self.initial_eval: dict | None = None
        # the loss (and the track / static-motion state it keeps) and the densification
        # strategies; they share the run's generator, so the draws keep their order
        self.objective = Objective(self.data, self.cfg, self.gen)
        self.gaussian_strategy = GaussianDensifyStrategy(self.cfg, self.device, len(self.data.train_idx))
        self.node_strategy = NodeDensifyStrategy(self.cfg, self.data, self.device)
        # a PhaseTimer (engine/train/phases.py) when a bench profiles the step; None in runs
        self.phases = None
        # which run this is (data + config hashes): stored in checkpoints, checked on resume
        self.identity = CK.run_identity(self.data, self.cfg)
        if resume and self.ckpt_path.exists():
            self._load_checkpoint()
        else:
            if resume:
                B.refuse_finished_resume(self.out_dir)
                self.reporter.log(f"no checkpoint at {self.ckpt_path}; starting a new run", "warning")
            self.model = build_model(self.data, nodes, self.cfg, self.gen)  # sets node_fg too
            self.opt = make_optimizer(self.model, self.cfg)
            self.gaussian_strategy.reset_stats(self.model.num_gaussians)
            self.objective.prepare_tracks(self.model)
            if self.model.pos_keys is not None and self.cfg.loss.static_init > 0:
                self.static_ref = (self.model.pos_keys.detach().clone(), self.model.rot_keys.detach().clone())

    # ---------------------------------------------------------------- helpers
    def _rebind(self):
        """Refresh the binding of the Gaussians and of the lifted track points together.

        The track points are bound like Gaussians (canonical position -> K nearest nodes).
        Node densification renumbers the nodes (pruned ones leave gaps, spawned ones are
        appended), so a binding kept from before addresses the wrong nodes, or none: the
        fused deformation kernel does not bounds-check, and a run whose densification
        pruned a node crashed with heap corruption.
        """
        self.model.rebind()
        self.objective.rebind_tracks(self.model)

    def _lr_schedule(self):
        if self.cfg.steps <= 1:
            return
        frac = min(self.step / self.cfg.steps, 1.0)
        e = self.model.extent
        def decay(a, b):
            return math.exp((1 - frac) * math.log(a) + frac * math.log(b)) if a > 0 and b > 0 else (1 - frac) * a + frac * b

        # spline keys decay like the Gaussian means (log-linear): at a constant rate the
        # per-frame photometric noise keeps moving them (static nodes drifted ~3 px), which
        # blurs everything they carry in the held-out view
        lrs = {"means": decay(self.cfg.lr_means * e, self.cfg.lr_means_final * e),
               "pos_keys": decay(self.cfg.lr_node_keys * e, self.cfg.lr_node_keys_final * e),
               "rot_keys": decay(self.cfg.lr_node_rot, self.cfg.lr_node_rot_final),
               # the MLP baseline decays the same way (SC-GS decays its deformation lr too)
               "mlp": decay(self.cfg.lr_mlp, self.cfg.lr_mlp_final)}
        for group in self.opt.param_groups:
            if group["name"] in lrs:
                group["lr"] = lrs[group["name"]]

    # ---------------------------------------------------------------- one step
    def _loss(self, f: int):
        """One step's ``(loss, metrics, render, shown)`` on training frame ``f``: ``shown [L]``
        the model rows the render holds (None: all; :func:`shown_gaussians`)."""
        d, m, w = self.data, self.model, self.cfg.loss
        ph = self.phases or no_phase
        t = float(d.times[f])
        with ph("deform"):
            # only the Gaussians this time can show (None: all): with lifespans most moving ones
            # of a long clip are outside their window and would change no pixel (lifespan.py)
            shown = shown_gaussians(m, t) if CULL_HIDDEN else None
            # node state at t once per step: the deformation, the track term and ARAP share it
            pos_t, rot_t, dq_nodes = m.node_state_dq(t)
            if self._seed_frame:  # keys learn each held Gaussian's motion relative to its seed frame
                rows = shown if shown is not None else torch.arange(m.num_gaussians, device=m.means.device)
                means_t, quats_t = deform_seed_frame(m, t, dq_nodes, rows)
            else:
                means_t, quats_t = m.deform(t, dq_nodes=dq_nodes, index=shown)
        with ph("sh"):  # the colour raster.render would compute from sh=..., timed on its own
            colors = scene_colors(m, means_t, d.w2c[f], index=shown)
        # the mask term (every 4th step) renders the Gaussians' dynamic score as an extra
        # channel of the colour pass instead of a second render
        mask_now = w.mask > 0 and d.fg is not None and self.step % 4 == 0
        extra = None
        if mask_now:
            extra = self.objective.dynamic_score(m)
            extra = extra if shown is None else extra[shown]
        with ph("raster_fwd"):
            out = render_scene(m, means_t, quats_t, d.K[f], d.w2c[f], d.width, d.height, colors=colors,
                               backend=self.cfg.backend, extra=extra, time=t, index=shown)
        with ph("losses"):
            # the pull onto the moving pixels moves held rows too, the keys learning through B(t) alone
            held = partial(deform_seed_frame, m, relative=False) if self._seed_frame else None
            loss, metrics, out = self.objective.terms(m, self.step, f, t, out, means_t, quats_t,
                                                      (pos_t, rot_t, dq_nodes), shown=shown, deform=held)
            return loss, metrics, out, shown

    def _anchoring(self) -> bool:
        """Whether this step holds the moving Gaussians at their seed frames
        (``cfg.lifespan_anchor``; from the end of the static warm-up, when the keys train)."""
        return (self.cfg.lifespan_anchor and self.model.pos_keys is not None
                and self.step >= self.cfg.warmup_static_steps)

    def _sync_seed_frame(self, hold: bool | None = None) -> None:
        """Hold the moving Gaussians in their seed frame while :meth:`_anchoring` says so, or as
        ``hold`` says (``engine/train/seed_anchor.py``; a checkpoint stores which)."""
        self._seed_frame = hold_seed_frame_(self.model, self._seed_frame,
                                            self._anchoring() if hold is None else hold)

    def _static_motion(self, pos_t: torch.Tensor, rot_t: torch.Tensor, state_t1=None) -> torch.Tensor:
        """The static-motion term now (:meth:`Objective.static_motion`)."""
        return self.objective.static_motion(self.model, pos_t, rot_t, state_t1)

    # ---------------------------------------------------------------- densification
    def _densify(self):
        """Gaussian densification, rebinding, then node densification (``cfg.node_densify``)."""
        with torch.no_grad():
            self.gaussian_strategy.densify(self.model, self.opt, self.gen)  # the binding follows the rows
            with canonical_view(self.model, self._seed_frame):
                self._rebind()
                if self.cfg.node_densify:
                    self._densify_nodes()
            self.gaussian_strategy.reset_stats(self.model.num_gaussians)

    def _densify_nodes(self):
        """Spawn / prune nodes (:meth:`NodeDensifyStrategy.densify`), rebinding after."""
        self.static_ref = self.node_strategy.densify(self.model, self.opt, self.static_ref, self._rebind)

    # ---------------------------------------------------------------- checkpoints
    def _checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "identity": self.identity,
            "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
            "optimizer": self.opt.state_dict(),
            "seed_frame": self._seed_frame,  # which parametrisation the held rows are in (seed_anchor.py)
            "gen": self._gen_state if getattr(self, "_gen_state", None) is not None else self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            **self.gaussian_strategy.state_dict(),  # grad_accum, grad_count
            "history": [[h["step"], h["loss"], h["psnr"]] for h in self.history],
            "train_seconds": self.train_seconds,
            "initial_eval": {k: float(v) for k, v in (self.initial_eval or {}).items()},
            **self.objective.state_dict(),  # tracks, static_ref
        }

    def save_checkpoint(self) -> Path:
        with atomic_path(self.ckpt_path) as tmp:
            torch.save(self._checkpoint_state(), tmp)
        return self.ckpt_path

    def _load_checkpoint(self):
        state = CK.load_state(self.ckpt_path)
        CK.check_identity(state, self.identity, self.ckpt_path)
        try:
            self._restore(state)
        except (KeyError, RuntimeError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"checkpoint does not match this run's model ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0][:120]})", self.ckpt_path,
                             "delete the checkpoints folder to start over, or pass --overwrite") from None
        self.reporter.log(f"resumed from step {self.step} ({self.ckpt_path})")

    def _restore(self, state: dict) -> None:
        dev = self.device
        model = CK.model_from_state(state["model"], self.cfg, self.data.extent, dev)
        self.model = model
        # a checkpoint of the shot-detail stage holds its seeds and the stage's optimiser
        self.opt = stage_optimizer(model, self.cfg) if has_detail(model) else make_optimizer(model, self.cfg)
        self.opt.load_state_dict(CK.without_groups(state["optimizer"], ("node_log_radii",)))
        self.gen.set_state(state["gen"])
        torch.set_rng_state(state["torch_rng"])
        self.step = int(state["step"])
        self.gaussian_strategy.load_state_dict(state)
        self.history = [{"step": int(s), "loss": float(lo), "psnr": float(p)} for s, lo, p in state["history"]]
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.initial_eval = dict(state.get("initial_eval") or {}) or None
        self.objective.load_state_dict(state, dev)
        self._seed_frame = bool(state.get("seed_frame", False))

    # ---------------------------------------------------------------- main loop
    def train(self) -> None:
        cfg, d = self.cfg, self.data
        train_idx = d.train_idx.cpu()
        motion_groups = {"pos_keys", "rot_keys", "mlp"}
        frame_order = resolve_frame_order(cfg.frame_order, bool((self.model.gauss_lifespan > 0).any()))
        t_start = time.perf_counter()
        self._stop_requested = False
        previous = self._install_stop_handlers()
        # Deterministic mode NaN-fills every torch.empty (a debugging aid): a fill_ per
        # allocation, a sixth of the step at 240x180 before the fused kernels. The step
        # reads no uninitialised memory (torch.linalg.lstsq on the CPU does, so the depth
        # fit solves its 2x2 normal equations instead), so the loop runs without it; the
        # previous setting is restored on exit, for code outside the loop.
        previous_fill = torch.utils.deterministic.fill_uninitialized_memory
        torch.utils.deterministic.fill_uninitialized_memory = False
        if self.step < cfg.steps:  # starts the stage's clock: the first logged step has a measured ETA
            self.reporter.progress("train", self.step, cfg.steps)
        try:
            self._sync_seed_frame()
            while self.step < cfg.steps:
                if self._stop_requested:  # SIGINT/SIGTERM: stop at a step boundary
                    raise KeyboardInterrupt
                self._gen_state = self.gen.get_state()
                f = step_frame(frame_order, self.step, train_idx, cfg.seed, self.gen)
                self._lr_schedule()
                ph = self.phases or no_phase
                loss, metrics, out, shown = self._loss(f)
                self.opt.zero_grad(set_to_none=True)
                with ph("backward"):
                    loss.backward()
                if self.model.is_split and self.model.pos_keys is not None:
                    freeze_static_nodes(self.model.pos_keys, self.model.rot_keys, self.model.node_dyn)
                if self.step < cfg.warmup_static_steps:  # static warm-up: motion frozen
                    for group in self.opt.param_groups:
                        if group["name"] in motion_groups:
                            for p in group["params"]:
                                p.grad = None
                with ph("optimizer"):
                    self.opt.step()
                    clamp_lifespans_(self.model, cfg)
                with torch.no_grad(), ph("densify_stats"):
                    self.gaussian_strategy.step_post_backward(self.step, out, d.width, d.height, index=shown)
                self.step += 1
                self._sync_seed_frame()  # the step that starts the anchoring converts the model
                # the step's frame draw is done: a checkpoint from here on stores the sampler
                # state after it, so a resume draws the next step's frame, not this one again
                self._gen_state = None
                if cfg.densify_from <= self.step < cfg.densify_until and self.step % cfg.densify_every == 0:
                    self._densify()
                elif cfg.rebind_every and self.step % cfg.rebind_every == 0:
                    with torch.no_grad(), canonical_view(self.model, self._seed_frame):
                        self._rebind()
                if cfg.opacity_reset_every and self.step % cfg.opacity_reset_every == 0 and self.step < cfg.densify_until:
                    self.gaussian_strategy.reset_opacity(self.model, self.opt)
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    total = sum(v for k, v in metrics.items() if k != "psnr")
                    self.history.append({"step": self.step, "loss": total, "psnr": metrics["psnr"]})
                    self.reporter.progress("train", self.step, cfg.steps, loss=total, psnr=metrics["psnr"],
                                           gaussians=self.model.num_gaussians)
                if cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0 and self.step < cfg.steps:
                    self.train_seconds += time.perf_counter() - t_start
                    t_start = time.perf_counter()
                    self.save_checkpoint()
                self._gen_state = None
            # the shot-detail stage (engine/train/shot_detail.py; a no-op unless cfg.shot_detail),
            # on the canonical model, with its own clock
            self.train_seconds += time.perf_counter() - t_start
            self._sync_seed_frame(False)
            train_detail(self)
            t_start = time.perf_counter()
        except KeyboardInterrupt:
            # A KeyboardInterrupt raised mid-step (no handler installed, e.g. off the
            # main thread) loses that step's work; the sampler state is rewound to the
            # step's start so a resume replays it exactly.
            self.train_seconds += time.perf_counter() - t_start
            path = self.save_checkpoint()
            raise Cancelled(f"training stopped at step {self.step}; checkpoint saved to {path}") from None
        finally:
            self._sync_seed_frame(False)  # canonical again, after any checkpoint (evaluation, export)
            torch.utils.deterministic.fill_uninitialized_memory = previous_fill
            self._restore_stop_handlers(previous)
        self.train_seconds += time.perf_counter() - t_start

    def request_stop(self) -> None:
        """Ask the loop to checkpoint and stop after the current step (thread-safe)."""
        self._stop_requested = True

    def _install_stop_handlers(self):
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return None
        handler = lambda signum, frame: self.request_stop()  # noqa: E731
        return {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}

    @staticmethod
    def _restore_stop_handlers(previous):
        import signal

        for sig, old in (previous or {}).items():
            signal.signal(sig, old)

    # ---------------------------------------------------------------- evaluation
    def render_frame(self, f: int, t: float | None = None):
        """Frame ``f`` rendered now (:func:`engine.train.evaluation.render_frame`)."""
        with canonical_view(self.model, self._seed_frame):
            return render_frame(self.model, self.data, f, t, self.cfg.backend, cull=CULL_HIDDEN)

    def evaluate(self, idx: torch.Tensor | None = None) -> dict:
        """PSNR / SSIM (and masked PSNR where a fg prior exists) on frames ``idx`` (default: val)."""
        idx = self.data.val_idx if idx is None else idx
        with canonical_view(self.model, self._seed_frame):
            return evaluate_frames(self.model, self.data, idx, self.cfg.backend, cull=CULL_HIDDEN)

    # ---------------------------------------------------------------- export
    def export_bundle(self, metrics: dict | None = None) -> Path:
        m, d = self.model, self.data
        with torch.no_grad(), canonical_view(m, self._seed_frame):  # the bundle holds canonical poses
            nodes, gaussians = bundle_arrays(m)
        frames, cams = bundle_cameras(d)
        scene = B.new_scene(int(frames.min()), int(frames.max()), d.fps, cams, config=self.cfg.to_dict(),
                            stats={"steps": min(self.step, self.cfg.steps),
                                   # the shot-detail stage's steps after them (shot_detail.py)
                                   "detail_steps": max(self.step - self.cfg.steps, 0),
                                   "gaussians": m.num_gaussians, "nodes": m.num_nodes,
                                   "train_seconds": round(self.train_seconds, 2),
                                   "history": self.history, **(metrics or {})},
                            extent=d.extent, **self.scene_extra)
        return B.save_bundle(self.out_dir, scene, nodes, gaussians)

    def run(self) -> dict:
        """Train, evaluate on held-out frames, write the bundle; return a summary."""
        self.reporter.log(f"training {self.model.num_gaussians} Gaussians, {self.model.num_nodes} nodes, "
                          f"{self.cfg.steps} steps ({self.cfg.preset})")
        living = int((self.model.gauss_lifespan > 0).sum())
        if living:
            why = ""
            if self.cfg.lifespan == "auto":
                why = ("; lifespan auto: the camera does not translate"
                       if not camera_translates(self.data.w2c[self.data.train_idx], self.data.extent)
                       else "; lifespan auto: a moving camera with no held-out cameras (--lifespan off keeps "
                            "views away from the shot's path better)")
            self.reporter.log(f"moving Gaussians live around their own frame ({living} of them, lifespan "
                              f"{self.cfg.lifespan_frames:g} frame intervals{why})")
        # the Numba kernels load (or, on a first run, compile) as their own progress stage,
        # not inside the first render below
        warm_kernels(self.reporter, self.device, self.cfg.backend)
        # held-out quality of the initialisation, so every run reports its own gain
        initial = self.evaluate() if self.step == 0 else self.initial_eval
        self.initial_eval = initial
        self.train()
        metrics = {"eval_init": initial, "eval": self.evaluate(),
                   "eval_train": self.evaluate(spread_sample(self.data.train_idx))}
        metrics["iterations_per_s"] = round(self.step / max(self.train_seconds, 1e-9), 3)
        if self.still_plate is not None:
            metrics["still_plate"] = self.still_plate
        for line in quality_lines(metrics):
            self.reporter.log(line)
        path = self.export_bundle(metrics)
        CK.discard(self.ckpt_path)  # finished: a later --resume must not retrain over the bundle
        return {"bundle": str(path), "steps": min(self.step, self.cfg.steps),
                "detail_steps": max(self.step - self.cfg.steps, 0), "gaussians": self.model.num_gaussians,
                "nodes": self.model.num_nodes, **metrics}


def _objective_attribute(name: str) -> property:
    return property(lambda self: getattr(self.objective, name), lambda self, v: setattr(self.objective, name, v),
                    doc=f"The objective's ``{name}`` (:class:`Objective`).")


# the objective's state, under the names the trainer has always had
for _name in ("static_ref", "track_canon", "track_ids", "track_idx", "track_w", "track_vis"):
    setattr(Trainer, _name, _objective_attribute(_name))
