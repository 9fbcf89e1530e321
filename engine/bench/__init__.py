"""Benchmarks: ``python -m engine.bench <name> [--json] ...``.

Each benchmark is ``engine/bench/<name>.py`` exposing ``HELP``, ``add_arguments`` and
``run(args) -> list[dict]`` (one dict per row). :func:`engine.bench.common.print_rows`
prints them as a table, or with ``--json`` one JSON object per line. Benchmarks print
what they measure; they never assert timings.
"""
