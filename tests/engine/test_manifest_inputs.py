"""A clip manifest's own priors are used, and the clip path a bundle records is absolute."""

from pathlib import Path

from engine.cli import build_parser
from engine.commands._train_options import prior_config_from_args
from engine.io import load_clip

from . import _bad_input_fixtures as fx


def test_manifest_priors_feed_the_prior_config(tmp_path):
    clip = fx.manifest(tmp_path / "m", priors={"depth": "depth.npy", "tracks": "../elsewhere/tracks.npz"})
    args = build_parser().parse_args(["train", str(clip), "--out", str(tmp_path / "o"), "--no-models"])
    cfg = prior_config_from_args(args)
    assert Path(cfg.depth_path) == (tmp_path / "m" / "depth.npy").resolve()
    assert Path(cfg.tracks_path) == (tmp_path / "elsewhere" / "tracks.npz").resolve()  # a .npz may live outside
    assert cfg.mask_path is None
    args = build_parser().parse_args(["train", str(clip), "--out", "o", "--no-models", "--depth-path", "mine.npy"])
    assert prior_config_from_args(args).depth_path == "mine.npy"  # the option wins


def test_clip_source_is_absolute(tmp_path, monkeypatch):
    fx.manifest(tmp_path / "m")
    monkeypatch.chdir(tmp_path)
    clip = load_clip("m/clip.json")
    assert clip.source == (tmp_path / "m" / "clip.json").resolve() and clip.source.is_absolute()


def test_training_width_beyond_the_clip_is_said(tmp_path, capsys):
    from engine.pipeline import load_frames_at_width
    from engine.protocol import Reporter

    clip = load_clip(fx.manifest(tmp_path / "m"))
    frames, _, _ = load_frames_at_width(clip, 500, Reporter(jsonl=True))
    assert frames.shape[2] == fx.W
    assert "wider than the clip (64 px)" in capsys.readouterr().out


def test_depth_sidecar_option_feeds_the_prior_config(tmp_path):
    clip = fx.manifest(tmp_path / "m")
    base = ["train", str(clip), "--out", str(tmp_path / "o"), "--depth-model", "pydnet.onnx"]
    args = build_parser().parse_args(base + ["--depth-sidecar", '{"size_multiple": 64, "std": [1, 1, 1]}'])
    cfg = prior_config_from_args(args)
    assert cfg.depth_backend == "onnx" and cfg.depth_sidecar == {"size_multiple": 64, "std": [1, 1, 1]}
    assert prior_config_from_args(build_parser().parse_args(base)).depth_sidecar is None
