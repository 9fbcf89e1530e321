"""Training: the dynamic scene model, losses, optimisation loop and evaluation.

``config``   TrainConfig (+ presets), the one typed home of every hyper-parameter.
``data``     TrainingData, the tensors of one clip at training resolution.
``model``    DynamicScene: canonical Gaussians + nodes + node motion (spline/per_frame/mlp).
``losses``   photometric, SSIM, depth, mask, track, ARAP, spline regularisers.
``render``   the bridge to :mod:`engine.raster` (SH colours, backend choice).
``trainer``  Trainer: init, train, densify, checkpoint/resume, evaluate, export bundle.
"""
