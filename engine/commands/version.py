"""Print the engine and protocol versions."""

HELP = "print the engine and protocol versions"


def add_arguments(parser):
    pass


def run(args, reporter):
    from .. import __version__
    from ..protocol import PROTOCOL_VERSION

    reporter.result(engine=__version__, protocol=PROTOCOL_VERSION)
    return 0
