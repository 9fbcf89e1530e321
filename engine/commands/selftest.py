"""Check that the engine's dependencies import, and print their versions as JSON.

Exit status 0 when every required package imports; 1 otherwise (the JSON then names
what is missing). Used by the add-on's "Check engine" button.
"""

HELP = "check the engine's dependencies and print their versions as JSON"

REQUIRED = ("numpy", "torch", "cv2", "onnxruntime", "pycolmap", "scipy", "numba")
OPTIONAL = ("gsplat", "onnx")


def add_arguments(parser):
    pass


def _probe(name):
    import importlib

    try:
        module = importlib.import_module(name)
    except Exception as exc:  # ImportError, or a broken binary wheel
        return None, f"{type(exc).__name__}: {exc}"
    return getattr(module, "__version__", "unknown"), None


def run(args, reporter):
    import platform
    import sys

    from .. import __version__

    versions, problems = {}, {}
    for name in REQUIRED + OPTIONAL:
        version, problem = _probe(name)
        versions[name] = version
        if problem and name in REQUIRED:
            problems[name] = problem
    cuda = False
    if versions.get("torch"):
        import torch

        cuda = bool(torch.cuda.is_available())
    reporter.result(ok=not problems, engine=__version__, python=sys.version.split()[0],
                    platform=platform.platform(), cuda=cuda, versions=versions, problems=problems)
    return 0 if not problems else 1
