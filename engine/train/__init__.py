"""Training: the dynamic scene model, losses, optimisation loop and evaluation.

``config``   TrainConfig (+ presets), the one typed home of every hyper-parameter.
``data``     TrainingData, the tensors of one clip at training resolution.
``model``    DynamicScene: canonical Gaussians + nodes + node motion (spline/per_frame/mlp).
``losses``   photometric, SSIM, depth, mask, track, ARAP, spline regularisers.
``render``   the bridge to :mod:`engine.raster` (SH colours, backend choice).
``objective`` Objective: the loss terms of a step, the lifted tracks, the static-motion reference.
``strategy``  Gaussian and node densification as strategy objects (gsplat's manner).
``param_edit`` the Adam optimiser and its per-row surgery (densification).
``export``   the trained model and cameras as result-bundle arrays.
``trainer``  Trainer: init, train loop, lr schedule, checkpoint/resume, evaluate, export bundle.
"""
